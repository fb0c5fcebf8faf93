"""The process's C allocator (glibc's malloc) around the pipeline's stages: one arena for the resin job
(:func:`one_malloc_arena`), the first working memory of a command faulted in ahead on an idle core
(:func:`prefault`), and otherwise the heap's free pages handed back after slicing (:func:`trim_heap`).

Imports nothing heavy (no numpy), so the command line can call these first thing, before any other thread starts.
Only the command line calls the first two (its batch workers the first): the library leaves its caller's process
alone.
"""

from __future__ import annotations

import os

__all__ = ["on_glibc", "one_malloc_arena", "one_arena", "trim_heap", "prefault", "user_tuned_malloc", "PREFAULT_CHUNK"]

#: set by :func:`one_malloc_arena`
_ONE_ARENA = False


def on_glibc() -> bool:
    """Whether this process's C library is glibc (``os.confstr``: absent on Windows, refused on macOS and musl)."""
    try:
        return (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc")
    except (AttributeError, ValueError, OSError):
        return False


def one_malloc_arena() -> bool:
    """Make the threads of this process allocate from glibc's main arena (``mallopt(M_ARENA_MAX, 1)``), and say
    whether that was done (False off glibc, or when glibc refused). Call it before any other thread has allocated:
    an arena a thread already had (or left behind when it ended) is still handed out afterwards.

    For a process that slices and then writes resin layers (``gpuslice raster``, a batch's local workers for resin
    outputs): glibc gives each new thread an arena of its own, so the layers' threads (the runs' lanes, the
    encoders) never reuse the ~200 MB the slicer freed on the main thread, and every page they touch is fresh:
    zeroed by the kernel, and on a virtual machine perhaps first backed by the host (``docs/BENCHMARKS.md``,
    twentieth session: the armadillo job at 12K faulted 26k pages in its raster stage, 2.3–2.7k with one arena, and
    ``--z-samples 4`` ran in 0.93× the time at 0.89× the peak). Not done by the library, whose caller owns the
    process, nor by ``check``: GEOS's many small allocations on two threads contend for one arena (the nefertiti
    check 1.07× slower)."""
    global _ONE_ARENA
    if not on_glibc():
        return False
    try:
        import ctypes

        _ONE_ARENA = ctypes.CDLL(None).mallopt(-8, 1) == 1  # M_ARENA_MAX (malloc.h)
    except (OSError, AttributeError):  # no mallopt after all
        return False
    return _ONE_ARENA


def one_arena() -> bool:
    """Whether :func:`one_malloc_arena` was done in this process."""
    return _ONE_ARENA


def trim_heap() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``, as Dask's workers do: numpy's freed
    temporaries otherwise stay in the process), unless this process's threads share one arena
    (:func:`one_malloc_arena`): then the next stage's threads allocate where that memory was freed, and it stays to
    be reused. Nothing off glibc."""
    if _ONE_ARENA or not on_glibc():
        return
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # no malloc_trim after all
        pass


#: the blocks :func:`prefault` grows the heap by (below glibc's largest mmap threshold, 32 MiB: from the heap)
PREFAULT_CHUNK = 8 << 20
_MADV_POPULATE_WRITE = 23  # Linux 5.14 and later


def prefault(nbytes: int) -> bool:
    """Grow the main heap's free top by about ``nbytes`` and fault its pages in on a thread of its own, and say
    whether that was started: False off glibc, on a kernel older than Linux 5.14, for less than one
    :data:`PREFAULT_CHUNK`, where the user tuned glibc's malloc (:func:`user_tuned_malloc`), where glibc refuses the
    thresholds (a 32-bit process), where the blocks are not one stretch at the heap's top, or where memory or a
    thread cannot be had (nothing raises).

    A command's first touch of each page of its working memory costs a page fault and the page's zeroing by the
    kernel, and on a virtual machine often the host's backing of it too: a cold ``gpuslice slice`` spent ~15 % of its
    CPU in ``clear_page`` (``docs/BENCHMARKS.md``, twentieth session). Called first thing by the command line (no
    other thread yet), this moves that work onto the core the start-up leaves idle (the imports run on one):

    * glibc is told to keep freed memory: its mmap threshold raised to 32 MiB (blocks up to that size come from the
      heap) and its trim threshold to 1 GiB (no heap is shrunk before that much of it is free: the main one's top,
      and the other threads' arenas too);
    * blocks are allocated from the top of the heap, one after the other, and freed at once, so the heap's free top
      chunk now spans them;
    * the thread asks the kernel to populate that range (``madvise(MADV_POPULATE_WRITE)``: pages allocated and
      zeroed as a write would, but nothing written, so the main thread carving allocations out of the same range
      meanwhile is safe; a part unmapped meanwhile ends it with ENOMEM).

    The job's later allocations from the main arena (numpy's arrays and PoCL's buffers made on the main thread;
    with :func:`one_malloc_arena`, every thread's) are then carved from pages already there. Arrays over 32 MiB are
    still mapped fresh. The thread makes one system call (ctypes releases the GIL) and is not waited for."""
    if nbytes < PREFAULT_CHUNK or not on_glibc() or user_tuned_malloc():
        return False
    try:
        import _thread
        import ctypes
        import mmap

        libc = ctypes.CDLL(None, use_errno=True)
        malloc, free, madvise, sbrk = libc.malloc, libc.free, libc.madvise, libc.sbrk
        malloc.restype, malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
        free.restype, free.argtypes = None, [ctypes.c_void_p]
        madvise.restype, madvise.argtypes = ctypes.c_int, [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
        sbrk.restype, sbrk.argtypes = ctypes.c_void_p, [ctypes.c_ssize_t]
        if madvise(0, 0, _MADV_POPULATE_WRITE) != 0:  # (an empty range: EINVAL where the kernel lacks the advice)
            return False
        if libc.mallopt(-3, 32 << 20) != 1 or libc.mallopt(-1, 1 << 30) != 1:  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
            return False
        blocks = [malloc(PREFAULT_CHUNK) for _ in range(int(nbytes) // PREFAULT_CHUNK)]
        for b in reversed(blocks):  # (the last first: each joins the top chunk as it is freed; free(NULL): nothing)
            free(b)
        if None in blocks:  # (malloc failed: no memory to spare; c_void_p gives None for NULL)
            return False
        order = sorted(blocks)
        gaps = [b - a for a, b in zip(order[:-1], order[1:], strict=True)]
        lo, hi = order[0], order[-1] + PREFAULT_CHUNK
        # one stretch at the heap's top, below the break: not a heap that fell back to separate mappings
        if any(not PREFAULT_CHUNK <= g <= PREFAULT_CHUNK + 64 for g in gaps) or hi > (sbrk(0) or 0):
            return False  # (the thresholds stay: they only keep freed memory in the process)
        page = mmap.PAGESIZE
        start = (lo + page - 1) // page * page
        length = (hi - start) // page * page

        def populate() -> None:
            madvise(start, length, _MADV_POPULATE_WRITE)

        _thread.start_new_thread(populate, ())
    except (OSError, AttributeError, RuntimeError, MemoryError):  # no such functions after all; no thread to be had
        return False
    return True


#: environment variables by which a user tunes glibc's malloc: then :func:`prefault` leaves it alone
_MALLOC_VARIABLES = ("MALLOC_ARENA_MAX", "MALLOC_ARENA_TEST", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_",
                     "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_", "MALLOC_PERTURB_", "MALLOC_CHECK_")


def user_tuned_malloc() -> bool:
    """Whether the environment tunes glibc's malloc (a ``MALLOC_*`` variable, or ``GLIBC_TUNABLES`` naming
    ``glibc.malloc``): the user's settings are kept as given."""
    return any(os.environ.get(v) for v in _MALLOC_VARIABLES) or "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", "")
