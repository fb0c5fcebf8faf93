"""OpenCL devices: which one is used, and kernel programs built once per context.

The default device is the first GPU of any platform, else the first CPU device of a PoCL platform that can build
for this CPU (see :func:`cpu_unknown_to_pocl`), else any device. ``--device`` or the ``GPUSLICE_DEVICE`` environment
variable override it with PyOpenCL's ``PYOPENCL_CTX`` syntax: ``"P"`` or ``"P:D"`` (platform and device indices as
``gpuslice devices`` lists them), or a case-insensitive piece of the device's or platform's name or version
(``"pocl"``, ``"nvidia"``). Nothing here prompts.

Programs are built from ``kernels/*.cl`` (shipped inside the package as ``gpuslice.kernels``) with
``-D LOCAL_SIZE=…`` and memoised per (context, file, options). Later processes load the program's binary instead
of handing the source to the driver again: PyOpenCL leaves caching to drivers with a source cache of their own, such
as PoCL and NVIDIA's, but PoCL's still preprocesses and hashes the whole source each time (≈ 35–45 ms against ≈ 5 ms
for the binary). The binaries live in :func:`_cache_dir`, one file per (source, options, device and driver:
``pyopencl.cache.get_device_cache_id``), written whole or not at all (temporary file + rename) and checked by a
SHA-256 before use, so a killed process leaves neither a partial binary nor a lock; an unreadable, unwritable or
refused cache falls back to the source build. ``PYOPENCL_NO_CACHE=1`` builds from source every time.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import threading
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np

from .errors import DeviceError

__all__ = ["Device", "KernelDriver", "aligned_empty", "get_device", "list_devices", "release_scratch", "ENV_VAR"]

ENV_VAR = "GPUSLICE_DEVICE"

STRIPES = 16  #: counters neighbouring work-groups would share, kept once per stripe of them (a build option)


@dataclass(eq=False)
class Device:
    """A chosen OpenCL device with its context and an in-order queue (``origin``: for a :meth:`lane`, the device it
    is a lane of)."""

    context: object
    queue: object
    device: object
    platform_index: int
    device_index: int
    origin: Device | None = field(default=None, repr=False)
    _lanes: dict = field(default_factory=dict, repr=False)
    _lock: threading.RLock = field(default_factory=threading.RLock, repr=False)
    _pid: int = field(default_factory=os.getpid, repr=False)  # the process that made the context
    _name: str = field(init=False, repr=False)  # read once: a forked child may not ask NVIDIA's driver anything

    def __post_init__(self) -> None:
        self._name = f"{self.device.platform.name.strip()} / {self.device.name.strip()}"

    def lane(self, k: int) -> Device:
        """This device with in-order queue number ``k`` of its own (``k`` = 0: this device itself), made once: work
        enqueued on two lanes may overlap (one lane's kernels run while the host waits for or prepares the
        other's). Lanes share the context and the built program; each has its own kernel drivers, so its own reused
        buffers."""
        if k == 0 or self.origin is not None:
            return self if k == 0 else self.origin.lane(k)
        with _DRIVERS_LOCK:
            if k not in self._lanes:
                import pyopencl as cl

                self._lanes[k] = Device(self.context, cl.CommandQueue(self.context, self.device), self.device,
                                        self.platform_index, self.device_index, origin=self)
            return self._lanes[k]

    @property
    def name(self) -> str:
        return self._name

    def exclusive(self) -> threading.RLock:
        """The lock of this device (and its lanes) for one job's use of the kernel drivers that keep no lock of
        their own (:data:`SHARED_DRIVERS`): re-entrant; held by :func:`~gpuslice.slicing.slicer.slice_mesh`, by the
        mesh's weld and by the adaptive schedules on a device, so that two threads slicing at once
        take turns instead of overwriting each other's buffers (segfaults, wrong layers: found with two batch tasks
        on one Dask worker's threads). Also checks that the context belongs to this process (:meth:`check_process`)."""
        self.check_process()
        return (self.origin or self)._lock

    def check_process(self) -> None:
        """A :class:`DeviceError` when this device's context was made by another process: OpenCL contexts do not
        survive ``fork`` (a forked child's first kernel waits forever on PoCL's threads, which were not forked)."""
        if self._pid != os.getpid():
            raise DeviceError(f"{self.name}: this OpenCL context was made before the process forked and does not work "
                              "in the child; use the 'spawn' or 'forkserver' start method of multiprocessing")

    @property
    def is_gpu(self) -> bool:
        import pyopencl as cl

        return bool(self.device.type & cl.device_type.GPU)

    @property
    def is_cpu(self) -> bool:
        """A CPU device (PoCL, Intel's CPU runtime), whose buffers can be the host's own memory (``USE_HOST_PTR``);
        not a device that also says GPU (Oclgrind says every type, and its uninitialised-value check takes a
        ``USE_HOST_PTR`` buffer's contents for uninitialised: it gets copies, as a GPU does)."""
        import pyopencl as cl

        t = self.device.type
        return bool(t & cl.device_type.CPU) and not t & cl.device_type.GPU

    @property
    def local_size(self) -> int:
        """The work-group size used by every kernel: 64 (a multiple of the warp/wavefront, good for PoCL too)."""
        return int(min(64, self.device.max_work_group_size))

    def program(self, filename: str):
        """The built program holding the kernels of ``kernels/<filename>``, memoised for this context.

        All ``kernels/*.cl`` files are built together as one program: one lookup in PyOpenCL's binary cache per
        process (about 25 ms each on PoCL) instead of one per file. Each file keeps its own driver module.
        """
        if not resources.files("gpuslice.kernels").joinpath(filename).is_file():
            raise DeviceError(f"{filename}: no such kernel file")
        self.check_process()
        return _build(self.origin or self, self.local_size)


#: How the drivers transfer: never by dropping a non-blocking transfer's event before it is done. PyOpenCL's event of
#: a non-blocking ``enqueue_copy`` waits for its transfer when it is dropped, and waits holding the GIL: every other
#: Python thread of the process stops until the queue has reached the transfer (behind its kernels, and on PoCL
#: behind other queues' kernels too), whereas ``Event.wait``, ``finish`` and a blocking transfer wait with the GIL
#: released (``python scripts/probe_transfers.py``; BENCHMARKS, "The GIL"). Uploads keep their events until done
#: (:meth:`KernelDriver._put`), reads wait for all of theirs at once (:meth:`KernelDriver._read`).
TRANSFERS = "events kept until done"

_DRIVERS_LOCK = threading.RLock()  # (a driver made inside another one's construction)

#: The kernel drivers whose buffers one job's stages hand on to each other (the crossings' segments to chaining) or
#: that keep no lock of their own: a thread uses them inside :meth:`Device.exclusive`. The runs (``RunsKernel``: a
#: lock per driver) and the run-length encoders (``RunKernels``: a queue per thread) may run beside them.
SHARED_DRIVERS = ("CrossingsKernel", "ChainKernels", "WeldKernel", "AdaptiveKernel", "SegmentEdgesKernel",
                  "RasterKernel")


def locked(method):
    """Decorator of a driver method of :data:`SHARED_DRIVERS` that is a whole use of it (uploads, kernels, read-back):
    it runs inside its device's :meth:`Device.exclusive`."""

    @functools.wraps(method)
    def run(self, *args, **kwargs):
        with self.device.exclusive():
            return method(self, *args, **kwargs)

    return run


#: a CPU device's reused buffers of at least this many bytes live in numpy's memory (``USE_HOST_PTR``), which numpy
#: asks the kernel to back with huge pages (arrays of 4 MiB and more): a cold process touching its first segment
#: buffers faults them in 2 MiB pages, not 4 KiB ones (PoCL's own allocations): 1/3 fewer page faults, 0.91-0.94x
#: the whole process of a contour or resin job (docs/BENCHMARKS.md, fourteenth session)
HOST_BACKED_BYTES = 4 << 20


class KernelDriver:
    """Base of the thin drivers of ``kernels/*.cl``: named device buffers grown geometrically and reused across
    calls, uploads, fills, and launch grids rounded up to the explicit local size."""

    _instances: dict[tuple[type, int], KernelDriver] = {}

    def __init__(self, device: Device) -> None:
        self.device = device
        self._buffers: dict[str, tuple[object, int]] = {}
        self._events: list = []  # uploads' transfer events, held until done (TRANSFERS)

    @classmethod
    def of(cls, device: Device):
        """The driver of this class for ``device``, made (and its kernels looked up) once per process, also when
        several threads ask at once (the archive writers' encoder threads)."""
        key = (cls, id(device))
        drv = KernelDriver._instances.get(key)
        if drv is None:
            with _DRIVERS_LOCK:
                drv = KernelDriver._instances.get(key)
                if drv is None:
                    drv = KernelDriver._instances[key] = cls(device)
        return drv

    def _buffer(self, name: str, nbytes: int):
        """The buffer ``name`` with at least ``nbytes`` bytes (contents undefined when it had to grow; the drivers
        use their buffers on the device's queue, which a host-backed buffer waits for before it is let go)."""
        import pyopencl as cl

        buf, size = self._buffers.get(name, (None, 0))
        if size < nbytes:
            size = max(nbytes, int(size * 1.5), 64)
            if size >= HOST_BACKED_BYTES and self.device.is_cpu:  # (pyopencl holds ``hostbuf`` with it)
                if buf is not None:  # numpy frees the old memory with its buffer: no command may still use it
                    self.device.queue.finish()
                flags = cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR
                buf = cl.Buffer(self.device.context, flags, hostbuf=aligned_empty(size, np.uint8))
            else:
                buf = cl.Buffer(self.device.context, cl.mem_flags.READ_WRITE, size)
            self._buffers[name] = (buf, size)
        return buf

    def buffer(self, name: str):
        """The buffer ``name`` as the last call left it (e.g. for a later stage's kernels)."""
        return self._buffers[name][0]

    def _put(self, name: str, array: np.ndarray):
        """Upload ``array`` into the buffer ``name``, asynchronously (its event held until done: :data:`TRANSFERS`;
        the array must not change before the queue has passed the upload, e.g. a later :meth:`_read`)."""
        import pyopencl as cl

        buf = self._buffer(name, max(array.nbytes, 4))
        if array.nbytes:
            event = cl.enqueue_copy(self.device.queue, buf, np.ascontiguousarray(array), is_blocking=False)
            self._keep(event)
        return buf

    def _keep(self, event) -> None:
        """Hold a non-blocking transfer's ``event`` until it is done (dropped before, it would wait holding the GIL);
        the done ones are let go here."""
        import pyopencl as cl

        done = cl.command_execution_status.COMPLETE
        self._events = [e for e in self._events if e.command_execution_status != done]
        self._events.append(event)

    def _read(self, *pairs, queue=None) -> None:
        """Copy each ``(host array, device buffer)`` of ``pairs`` to the host, returning when all are done: one wait
        for ``queue`` (default: the device's), with the GIL released (:data:`TRANSFERS`)."""
        import pyopencl as cl

        q = self.device.queue if queue is None else queue
        events = []
        for host, buf in pairs:
            event = cl.enqueue_copy(q, host, buf, is_blocking=False)
            events.append(event)
        q.finish()  # (every event above is done: dropping them costs nothing)
        if q is self.device.queue:
            self._events.clear()

    def _fill(self, name: str, nbytes: int, value):
        """The buffer ``name`` with its first ``nbytes`` bytes set to the repeated scalar ``value``."""
        import pyopencl as cl

        buf = self._buffer(name, max(nbytes, 4))
        cl.enqueue_fill_buffer(self.device.queue, buf, value, 0, max(nbytes, 4))
        return buf

    def _grid(self, n: int) -> tuple[tuple[int], tuple[int]]:
        """(global size, local size) covering ``n`` work-items with the device's explicit local size."""
        ls = self.device.local_size
        return (max(ls, ((n + ls - 1) // ls) * ls),), (ls,)


def aligned_empty(n: int, dtype) -> np.ndarray:
    """An uninitialised (n,) array whose data start on a 4 KiB boundary (usable in place by a CPU device)."""
    dtype = np.dtype(dtype)
    raw = np.empty(n * dtype.itemsize + 4096, np.uint8)
    k = -raw.ctypes.data % 4096
    return raw[k : k + n * dtype.itemsize].view(dtype)


def release_scratch(device: Device | None = None) -> None:
    """Give the memory of a finished stage back to the system before a memory-heavy one (the resin layers): every
    kernel driver's reused buffers of ``device`` and of its lanes (default: every device) are dropped (made again,
    at the size needed, on next use), the young generations of the garbage collector are collected (a full
    collection took ~20 ms of a resin job and found no array), and on glibc the heap's free pages are returned
    (:func:`gpuslice.allocator.trim_heap`, as Dask's workers do: numpy's freed temporaries otherwise stay in the
    process), unless the process's threads share one arena (:func:`gpuslice.allocator.one_malloc_arena`), where they
    are the next stage's. Measured on the 346k-facet armadillo job: the resident memory after slicing falls from
    ~330 MB to ~130 MB."""
    import gc

    for (_, dev_id), drv in list(KernelDriver._instances.items()):
        if device is None or dev_id == id(device) or drv.device.origin is device:  # (and the device's lanes)
            own = getattr(drv, "_lock", None)  # (a driver with a lock of its own: the runs, between two batches)
            with drv.device.exclusive(), own if own is not None else contextlib.nullcontext():
                # first the queue: a kernel left running (e.g. the loops' screen) may use a buffer whose memory is
                # numpy's (HOST_BACKED_BYTES), freed with it; and the uploads' events hold their host arrays
                drv.device.queue.finish()
                drv._buffers.clear()
                drv._events.clear()
    gc.collect(1)  # (the young generations: the stage's own cycles; a full collection took ~20 ms and found none)
    from .allocator import trim_heap

    trim_heap()


def _cache_dir() -> Path:
    """Where built kernel binaries are kept: ``GPUSLICE_CACHE_DIR``, else ``$XDG_CACHE_HOME/gpuslice/kernels``, else
    ``~/.cache/gpuslice/kernels``."""
    if os.environ.get("GPUSLICE_CACHE_DIR"):
        return Path(os.environ["GPUSLICE_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "gpuslice" / "kernels"


def _cache_off() -> bool:
    """``PYOPENCL_NO_CACHE`` read as PyOpenCL reads it (a true value: 1, yes, true, on)."""
    return os.environ.get("PYOPENCL_NO_CACHE", "").strip().lower() in ("1", "yes", "y", "true", "t", "on")


def _cache_path(dev: Device, source: str, options: list[str]) -> Path:
    from pyopencl.cache import get_device_cache_id

    key = repr((get_device_cache_id(dev.device), options, source)).encode()
    return _cache_dir() / f"{hashlib.sha256(key).hexdigest()}.bin"


def _cached_binary(path: Path) -> bytes | None:
    """The binary stored at ``path`` if it is there whole (its first 32 bytes are the SHA-256 of the rest)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    return data[32:] if len(data) > 32 and hashlib.sha256(data[32:]).digest() == data[:32] else None


def _store_binary(path: Path, prg) -> None:
    """Keep ``prg``'s binary at ``path`` (written whole or not at all; the oldest entries beyond
    :data:`CACHE_ENTRIES` removed). Best effort: a cache that cannot be written only costs the next process a build."""
    import pyopencl as cl

    from .io.atomic import atomic_write_bytes

    try:
        (binary,) = prg.get_info(cl.program_info.BINARIES)
        if not binary:
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, hashlib.sha256(binary).digest() + bytes(binary))
        for f in sorted(path.parent.glob("*.bin"), key=lambda f: f.stat().st_mtime)[:-CACHE_ENTRIES]:  # the oldest
            f.unlink(missing_ok=True)
    except Exception:  # noqa: BLE001 - an unwritable or full cache directory, a driver without binaries
        pass


#: built kernel binaries kept in the cache directory (one per kernel-source version, device and local size)
CACHE_ENTRIES = 16


@cache
def _build(dev: Device, local_size: int):
    """Every ``kernels/*.cl`` built as one program for ``dev``: from the binary a previous process kept (see the
    module docstring), else from source (then the binary is kept)."""
    import pyopencl as cl

    files = sorted(p for p in resources.files("gpuslice.kernels").iterdir() if p.name.endswith(".cl"))
    source = "\n".join(f"// ---- {p.name}\n{p.read_text()}" for p in files)
    options = [f"-DLOCAL_SIZE={local_size}", f"-DSTRIPES={STRIPES}", "-cl-std=CL1.2",
               "-cl-fp32-correctly-rounded-divide-sqrt"]
    path = None if _cache_off() else _cache_path(dev, source, options)
    binary = _cached_binary(path) if path is not None else None
    if binary is not None:
        try:
            return cl.Program(dev.context, [dev.device], [binary]).build(options=options)
        except Exception:  # noqa: BLE001 - a binary the driver refuses: built from source below, and kept again
            pass
    try:
        prg = cl.Program(dev.context, source).build(options=options)
    except cl.RuntimeError as exc:  # pragma: no cover - a broken kernel or driver
        first = str(exc).splitlines()[0]
        names = ", ".join(p.name for p in files)
        if "unknown target CPU" in str(exc):  # see cpu_unknown_to_pocl
            first = ("this PoCL's LLVM does not know this CPU (unknown target CPU 'generic'); install a newer PoCL, "
                     "e.g. Debian's pocl-opencl-icd (scripts/setup-system.sh), and it is chosen by default")
        raise DeviceError(f"kernels ({names}): OpenCL build failed on {dev.name}: {first}") from None
    if path is not None:
        _store_binary(path, prg)
    return prg


def _platforms():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover
        raise DeviceError(f"pyopencl is not installed ({exc})") from None
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:
        raise DeviceError(f"no OpenCL platform found ({exc}); pip install pocl-binary-distribution") from None
    _reclaim_signal_handlers()
    return platforms


def _reclaim_signal_handlers() -> None:
    """Put back the handlers Python installed for SIGINT, SIGTERM and SIGHUP (Ctrl-C's KeyboardInterrupt, a program's
    own), in the main thread: PoCL loads LLVM, whose handlers (``SA_RESETHAND``) pass a signal on once and leave the
    default action meanwhile, so two Ctrl-C a few ms apart (``timeout -s INT`` sends two) killed the process with no
    word and an output's temporary file left (4 runs in 16)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    for signum in (getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)):
        handler = signal.getsignal(signum)
        if callable(handler):  # (not SIG_DFL, SIG_IGN, or None: a handler Python did not install)
            signal.signal(signum, handler)


def list_devices() -> list[dict]:
    """Every OpenCL device: platform and device index, names, type, compute units, memory (MiB)."""
    import pyopencl as cl

    out = []
    for pi, p in enumerate(_platforms()):
        try:
            devices = p.get_devices()
        except cl.Error:
            continue
        for di, d in enumerate(devices):
            out.append(
                {
                    "id": f"{pi}:{di}",
                    "platform": p.name.strip(),
                    "platform_version": p.version.strip(),
                    "device": d.name.strip(),
                    "type": cl.device_type.to_string(d.type),
                    "compute_units": int(d.max_compute_units),
                    "global_mem_mib": int(d.global_mem_size // 2**20),
                    "driver": d.driver_version.strip(),
                    "version": d.version.strip(),
                }
            )
    return out


def cpu_unknown_to_pocl(entry: dict) -> bool:
    """Whether ``entry`` (from :func:`list_devices`) is a PoCL CPU device whose LLVM does not know the host CPU: its
    version string's target is ``generic``, which PoCL 3.0 (and older) passes to clang as the target CPU and x86 clang
    refuses, so every kernel build fails with "unknown target CPU 'generic'" (pocl/pocl#1049). Seen with the PoCL 3.0
    (LLVM 14) that PyOpenCL's wheels bundle on AMD Zen 5; Debian's PoCL 3.1 picks a CPU by its features instead."""
    return "portable computing language" in entry["platform"].lower() and entry.get("version", "").endswith("-generic")


def _first_usable(entries: list[dict]) -> dict:
    """The first of ``entries`` (not empty) that can build for this CPU (:func:`cpu_unknown_to_pocl`), else the
    first."""
    return next((d for d in entries if not cpu_unknown_to_pocl(d)), entries[0])


def _default_choice(devices: list[dict]) -> dict:
    gpus = [d for d in devices if "GPU" in d["type"]]
    if gpus:
        return gpus[0]
    pocl = [d for d in devices if "portable computing language" in d["platform"].lower() and "CPU" in d["type"]]
    return _first_usable(pocl) if pocl else devices[0]


def resolve(spec: str | None) -> dict:
    """The device entry (from :func:`list_devices`) that ``spec`` (or the environment, or the default) names."""
    if not isinstance(spec, str | None):  # (cusp_schedule(device=0): an AttributeError on .split below)
        raise DeviceError(f"device must be text such as '0:0' or a piece of its name, got {spec!r}")
    devices = list_devices()
    if not devices:
        raise DeviceError("no OpenCL device found; pip install pocl-binary-distribution for the PoCL CPU device")
    spec = spec if spec not in (None, "") else os.environ.get(ENV_VAR) or None
    if spec is None:
        return _default_choice(devices)
    parts = spec.split(":")
    if all(x.isdigit() for x in parts) and 1 <= len(parts) <= 2:
        want = f"{parts[0]}:{parts[1] if len(parts) == 2 else 0}"
        for d in devices:
            if d["id"] == want:
                return d
        raise DeviceError(f"device '{spec}' not found (see gpuslice devices)")
    needle = spec.lower()
    named = [d for d in devices if any(needle in d.get(key, "").lower()
                                       for key in ("device", "platform", "platform_version", "version"))]
    if named:  # ("pocl" with two PoCLs installed: the one that can build)
        return _first_usable(named)
    raise DeviceError(f"device '{spec}' not found (see gpuslice devices)")


_DEVICES: dict[str, Device] = {}


def get_device(spec: str | Device | None = None) -> Device:
    """The :class:`Device` named by ``spec`` (see the module docstring; a :class:`Device` is returned as it is, so
    ``slice_mesh(mesh, device=get_device())`` works too); contexts are created once per process."""
    import pyopencl as cl

    if isinstance(spec, Device):
        spec.check_process()
        return spec
    for made in _DEVICES.values():  # (before asking the platforms: a forked child's driver may not answer)
        made.check_process()
    entry = resolve(spec)
    key = entry["id"]
    if key not in _DEVICES:
        pi, di = (int(x) for x in key.split(":"))
        dev = _platforms()[pi].get_devices()[di]
        ctx = cl.Context([dev])
        _DEVICES[key] = Device(ctx, cl.CommandQueue(ctx), dev, pi, di)
    return _DEVICES[key]
