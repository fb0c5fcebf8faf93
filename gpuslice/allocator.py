"""The process's C allocator (glibc's malloc) around the pipeline's stages: one arena for the resin job
(:func:`one_malloc_arena`), and otherwise the heap's free pages handed back after slicing (:func:`trim_heap`).

Imports nothing heavy (no numpy), so the command line can call :func:`one_malloc_arena` first thing, before any other
thread starts. Only the command line and its batch workers call it: the library leaves its caller's process alone.
"""

from __future__ import annotations

import os

__all__ = ["on_glibc", "one_malloc_arena", "resin_arena", "keep_freed_memory", "slice_heap", "one_arena", "trim_heap",
           "user_tuned_malloc"]

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
    ``--z-samples 4`` ran in 0.94× the time at 0.89× the peak). Not done by the library, whose caller owns the
    process, nor by ``check``: GEOS's many small allocations on two threads contend for one arena (the nefertiti
    check 1.07× slower)."""
    global _ONE_ARENA
    _ONE_ARENA = on_glibc() and _mallopt(-8, 1)  # M_ARENA_MAX (malloc.h)
    return _ONE_ARENA


def _mallopt(option: int, value: int) -> bool:
    """glibc's ``mallopt(option, value)`` (options as numbered in malloc.h); whether glibc took it."""
    try:
        import ctypes

        return ctypes.CDLL(None).mallopt(option, value) == 1
    except (OSError, AttributeError):  # no mallopt after all
        return False


def resin_arena() -> bool:
    """:func:`one_malloc_arena` for a process that writes resin layers (``gpuslice raster``, a batch's resin workers),
    unless the user tunes malloc (:func:`user_tuned_malloc`); whether it was done."""
    return not user_tuned_malloc() and one_malloc_arena()


def keep_freed_memory() -> bool:
    """:func:`one_malloc_arena`, and every block from the heap, where what is freed stays for the next allocation:
    ``mallopt(M_MMAP_MAX, 0)`` (no block mapped on its own: glibc maps each one over 32 MB apart, and frees it back
    to the system, so every large numpy array of a big slice was fresh pages the kernel zeroes first) and
    ``mallopt(M_TRIM_THRESHOLD, 2**31 - 1)`` (the heap's free top kept). Whether it was done (False off glibc, or
    when glibc refused).

    For ``gpuslice slice`` and ``view`` (:func:`slice_heap`): nefertiti after 2 Loop subdivisions (1.6M facets) at
    0.02 mm spent 18 % of its CPU samples in the kernel's ``clear_page`` (perf); with this, its whole process ran
    in 0.93–0.95× the time with ~0.2 s less system time and a median peak 15–37 MiB lower (``docs/BENCHMARKS.md``,
    thirty-first session; its ``view`` at 0.05 mm 0.86×); benchy, the plate of 12 benchies and the resin job alike
    within noise. The process keeps its peak's memory until it ends."""
    return one_malloc_arena() and _mallopt(-4, 0) and _mallopt(-1, 2**31 - 1)  # M_MMAP_MAX, M_TRIM_THRESHOLD


def slice_heap() -> bool:
    """:func:`keep_freed_memory` for ``gpuslice slice`` and ``view``, unless the user tunes malloc
    (:func:`user_tuned_malloc`); whether it was done."""
    return not user_tuned_malloc() and keep_freed_memory()


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


#: environment variables by which a user tunes glibc's malloc (:func:`user_tuned_malloc`)
_MALLOC_VARIABLES = ("MALLOC_ARENA_MAX", "MALLOC_ARENA_TEST", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_",
                     "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_", "MALLOC_PERTURB_", "MALLOC_CHECK_")


def user_tuned_malloc() -> bool:
    """Whether the environment tunes glibc's malloc (a ``MALLOC_*`` variable, or ``GLIBC_TUNABLES`` naming
    ``glibc.malloc``) or asks for it as it is (``GPUSLICE_PLAIN_MALLOC``, any non-empty value): the command line and
    its batch workers then keep the user's settings as given."""
    env = os.environ
    return (bool(env.get("GPUSLICE_PLAIN_MALLOC")) or any(env.get(v) for v in _MALLOC_VARIABLES)
            or "glibc.malloc" in env.get("GLIBC_TUNABLES", ""))
