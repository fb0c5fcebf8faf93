"""The batch task: one model read, sliced and written through the one pipeline (:func:`gpuslice.pipeline.run_job`),
in whatever process runs it (this one, a local worker, a Dask worker). :func:`run_model` never raises: it returns a
JSON-able record. Outputs are written atomically and their bytes depend only on the model and the options (no
timings, device names or paths of the machine in the file), so a task can be re-run anywhere: tasks are idempotent.
How many worker processes and PoCL threads a machine gets by default: :func:`default_workers`.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import socket
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from ..errors import BatchError, GpusliceError, MeshFileError, ParameterError, flatten, one_line
from .discover import Model
from .options import BatchOptions, check_path

__all__ = ["check_summary", "connect", "default_workers", "init_worker", "pocl_thread_env", "run_model"]

_WORKER: dict[str, Any] = {}


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def default_workers(n_models: int, device: str | None = None, backend: str = "opencl") -> tuple[int, int]:
    """The default (worker processes, PoCL threads per worker) for ``n_models`` models on this machine.

    On a CPU device (PoCL) one worker per core, each with ``cores // workers`` PoCL threads: the cores are
    shared out instead of every process starting one thread per core (oversubscription). Fewer models than cores
    get fewer workers with more threads each. On a GPU, ``min(cores, 4)`` workers share the GPU (the host-side
    stages of one model overlap the kernels of another); PoCL's thread count does not matter there.
    """
    cores = _cores()
    n = max(1, min(cores, n_models))
    if backend == "opencl":
        with contextlib.suppress(Exception):
            from ..device import resolve

            if "GPU" in resolve(device)["type"]:
                n = max(1, min(4, cores, n_models))
    return n, max(1, cores // n)


def pocl_thread_env(threads: int) -> dict[str, str]:
    """Environment that limits PoCL's CPU driver to ``threads`` threads in a process (PoCL 3 reads
    ``POCL_MAX_PTHREAD_COUNT``; PoCL 4+ ``POCL_CPU_MAX_CU_COUNT``; both are set)."""
    n = str(max(1, int(threads)))
    return {"POCL_MAX_PTHREAD_COUNT": n, "POCL_CPU_MAX_CU_COUNT": n}


def _worker_device(spec: str | None):
    """The OpenCL device of this process with every kernel built, made once per process; (device, seconds)."""
    key = ("device", spec)
    if key not in _WORKER:
        from ..device import get_device

        t = time.perf_counter()
        dev = get_device(spec)
        dev.program("crossings.cl")  # builds every kernels/*.cl (one program)
        _WORKER[key] = dev
        _WORKER["init_s"] = _WORKER.get("init_s", 0.0) + time.perf_counter() - t
    return _WORKER[key]


#: errors writing an output that no other worker would escape: a full disk or quota, a read-only file system, a file
#: over the size limit (retrying each model on another worker only doubled the failures)
_OUTPUT_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG}


def init_worker(env: dict[str, str] | None = None, device: str | None = None, backend: str = "opencl",
                one_arena: bool = False, driver: int | None = None) -> None:
    """Initializer of a local worker process: PoCL threads, signals, the OpenCL device and kernels (built once);
    ``one_arena``: its threads share one malloc arena (a batch of resin outputs: as ``gpuslice raster``,
    :func:`gpuslice.allocator.one_malloc_arena`).

    Ctrl-C and a closed terminal (SIGHUP) go to the whole process group; the workers ignore both (the driver stops
    them). SIGTERM unwinds the worker's model (``SystemExit``) so a half-written temporary output is removed, then
    ends the process (:func:`run_model`): the pool would take the ``SystemExit`` for the model's result and wait for
    the next, so a SIGTERM sent to the whole group (a service manager's stop) left the workers running for ever. A
    worker whose ``driver`` (its pid) is gone (killed: SIGKILL, the OOM killer) sends itself SIGTERM within a second
    (:func:`_watch_driver`): the forkserver between them outlives the driver while its workers hold its pipe.

    A signal sent to the process may be taken by any of its threads, and Python runs its handler in the main thread
    only when that thread next runs: an idle worker's main thread, blocked reading its next task, never did (about
    one group SIGTERM in 20 on a loaded machine left a worker alive, holding the caller's pipes). So the signals'
    wake-up pipe (:func:`signal.set_wakeup_fd`) tells the watching thread of each SIGTERM, and it pokes the main
    thread with SIGUSR1 (a no-op handler), whose interrupted read then runs the SIGTERM handler.
    """
    os.environ.update(env or {})
    if one_arena:  # (before the device's threads start)
        from ..allocator import resin_arena

        resin_arena()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _terminated)
    signal.signal(signal.SIGUSR1, lambda *_: None)  # (the watching thread's poke: see above)
    _WORKER["local"] = True
    import threading

    woken_r, woken_w = os.pipe()
    os.set_blocking(woken_w, False)
    signal.set_wakeup_fd(woken_w, warn_on_full_buffer=False)
    threading.Thread(target=_watch_driver, args=(driver, woken_r, threading.main_thread().ident),
                     name="gpuslice-driver-watch", daemon=True).start()
    t = time.perf_counter()
    if backend == "opencl":
        with contextlib.suppress(GpusliceError):  # reported by the first task instead
            _worker_device(device)
    _WORKER["started"] = time.perf_counter() - t


def _terminated(*_) -> None:
    """A worker's SIGTERM handler: the model unwinds (``SystemExit``), once; a worker between models (waiting for
    the next, or handing its last result back) ends at once: there, the pool's own code takes a ``SystemExit`` for a
    result to send back and waits for the next task, SIGTERM ignored from then on (one group SIGTERM in about 12 on
    a loaded machine left a worker so, holding the caller's pipes); should the pool's code take the ``SystemExit`` of a
    model's unwinding so, the watching thread ends the worker once it is out of the model (:func:`_watch_driver`).
    Later SIGTERMs (the driver stops its workers too, a moment after the group's) are ignored: raised again inside the
    unwinding they cut its cleanup short and printed tracebacks (a review, 6 runs in 70)."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if not _WORKER.get("in_model"):
        _exit_now()
    _WORKER["stopping"] = True
    sys.exit(143)


def _exit_now() -> None:
    """End this worker process now, exit status 143 (SIGTERM's)."""
    with contextlib.suppress(Exception):
        sys.stdout.flush()
    os._exit(143)


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended: no such process, or a zombie (ended, not yet reaped: a caller that reads
    the driver's output to its end before it reaps it, as ``subprocess.run(capture_output=True)`` does)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # (exists, but not ours to signal: still there)
        return False
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] == b"Z"
    except (OSError, IndexError):  # (no /proc: not Linux)
        return False


def _watch_driver(pid: int | None, woken: int, main: int, every: float = 1.0) -> None:
    """The worker's watching thread: on each SIGTERM the process takes (a byte on the signals' wake-up pipe
    ``woken``), poke the ``main`` thread (SIGUSR1) so that its handler runs there even when that thread is blocked
    in a read; and once the process ``pid`` (the batch's driver) no longer exists (polled every ``every`` seconds),
    send this worker SIGTERM (its own handling then removes its temporaries and ends it); and end the process when
    it is out of its model after a SIGTERM and still running (:func:`_terminated`)."""
    import select

    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM, signal.SIGUSR1})  # (this thread takes neither)
    while True:
        ready, _, _ = select.select([woken], [], [], every)
        if _WORKER.get("stopping") and not _WORKER.get("in_model"):  # (a model's unwinding is never cut short)
            _exit_now()
        if ready and signal.SIGTERM in os.read(woken, 256):
            signal.pthread_kill(main, signal.SIGUSR1)
            continue
        if pid is not None and _gone(pid):
            os.kill(os.getpid(), signal.SIGTERM)
            pid = None  # (once: the poke above makes sure it is seen)


def connect(address: str):
    """A ``distributed.Client`` for the Dask scheduler at ``address``; one-line :class:`BatchError` otherwise."""
    try:
        from distributed import Client
    except ImportError:
        raise BatchError("--scheduler needs Dask: pip install 'gpuslice[batch]'") from None
    try:
        return Client(address, timeout="10s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise BatchError(f"{address}: cannot reach the Dask scheduler ({one_line(exc)})") from None


def _collect(path: Path) -> bytes | dict[str, bytes]:
    if path.is_dir():
        return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}
    return path.read_bytes()


def _remove_written(paths: list[Path], since_ns: int) -> None:
    """Remove those of a failed model's files that this attempt put in place (at or after ``since_ns``): its check
    report is written before its archive, and its contour file before its checks, so a model that failed half way
    left one without the other. Files from before (an earlier run's) are left."""
    from ..io.atomic import remove_path

    for p in paths:
        with contextlib.suppress(OSError):
            if p.stat().st_mtime_ns >= since_ns:  # (through a link: the file written, not the user's link)
                remove_path(Path(os.path.realpath(p)) if p.is_symlink() else p)


def check_summary(report) -> dict[str, Any]:
    """A model's pre-print checks in its batch record: the counts (``islands``, ``island_layers``, ``traps``,
    ``suction_cups``), the largest unsupported area of a layer (mm²) and the print time (s) and resin (ml)."""
    unsup = report.islands.unsupported
    worst = float(max((v for v in unsup.tolist() if v == v), default=0.0))  # NaN: a layer GEOS refused
    cav = report.cavities
    return {"islands": report.n_islands, "island_layers": int(report.island_layers.size), "traps": cav.n_traps,
            "suction_cups": cav.n_cups, "max_unsupported_mm2": worst, "print_time_s": float(report.print_time_s),
            "resin_ml": float(report.resin_ml)}


def run_model(model: Model, opts: BatchOptions, out_root: str | None, data: bytes | None = None) -> dict[str, Any]:
    """Slice one model and write its output; never raises.

    Parameters
    ----------
    model : the model (``src`` is read unless ``data`` is given).
    opts : the batch options.
    out_root : the output folder, reachable from this process (a shared file system); ``None``: the output is
        returned as bytes in the record's ``"payload"`` (a dict of relative path → bytes for a folder output).
    data : the model file's bytes, when the inputs travel as bytes instead of through a shared file system.

    Returns
    -------
    dict
        ``model``, ``output``, ``status`` (``"done"`` or ``"failed"``), ``error`` (one line naming the file, or
        None), ``facets``, ``layers``, ``loops``, ``points``, ``open_chains``, ``device``, ``pid``, ``host``,
        ``timings_s`` (the pipeline's stages, :mod:`gpuslice.pipeline`, and ``total``; s), ``worker_init_s``
        (the worker's one-off device and kernel set-up, on the first
        task a worker runs, else 0); with ``opts.check``, ``checks`` (:func:`check_summary`) and, when the output
        travels as bytes, ``check_payload`` (the check report's bytes, written next to the output by the driver).
    """
    t0 = time.perf_counter()
    started_ns = time.time_ns()
    rec: dict[str, Any] = {"model": model.rel, "output": model.out, "status": "failed", "error": None,
                           "pid": os.getpid(), "host": socket.gethostname()}
    mine = [Path(out_root) / model.out] if out_root is not None else []
    if mine and opts.check:
        mine.append(check_path(mine[0]))
    timings: dict[str, float] = {}
    try:
        _WORKER["in_model"] = True  # (a SIGTERM now unwinds the model: _terminated)
        from ..pipeline import run_job

        dev = None
        if opts.params.backend == "opencl":
            t = time.perf_counter()
            dev = _worker_device(opts.params.device)
            timings["device"] = time.perf_counter() - t
        threads = int(os.environ.get("POCL_MAX_PTHREAD_COUNT", "0")) or None  # this worker's share of the cores

        def run(target: Path):
            job = opts.job(model.location, target, name=model.rel, label=model.src, data=data, workers=threads)
            return run_job(job, device=dev)

        if out_root is not None:
            target = Path(out_root) / model.out
            target.parent.mkdir(parents=True, exist_ok=True)
            done = run(target)
        else:
            with tempfile.TemporaryDirectory(prefix="gpuslice-batch-") as tmp:
                target = Path(tmp) / (Path(model.out).name or "out")
                done = run(target)
                rec["payload"] = _collect(target)
                if opts.check:
                    rec["check_payload"] = check_path(target).read_bytes()
        if "checks" in done.stats:
            rec["checks"] = check_summary(done.stats["checks"])
        meta = done.result.meta
        for k, v in done.timings.items():
            if k != "device":
                timings[k] = v
        rec.update(facets=meta["facets"], layers=meta["layers"], loops=meta["loops"], points=meta["points"],
                   open_chains=meta["open_chains"],
                   device=done.device.name if done.device is not None else "numpy (reference)")
        rec["status"] = "done"
    except Exception as exc:  # a failing model must not stop the batch: one line in its record
        _remove_written(mine, started_ns)
        msg = one_line(exc)
        named = any(n in msg for n in (model.src, model.rel, flatten(model.src), flatten(model.rel)))  # (escaped)
        rec["error"] = msg if named else f"{model.src}: {msg}"
        # what the file holds or the options are at fault, or the output folder's disk: another worker would fail
        # the same way, so no retry (a file this worker could not read, its memory, a device, its own temporary
        # folder when outputs travel as bytes: it may not)
        full = isinstance(exc, OSError) and exc.errno in _OUTPUT_FULL and out_root is not None
        rec["deterministic"] = full or isinstance(exc, ParameterError) or (
            isinstance(exc, MeshFileError) and not getattr(exc, "os_error", False))
    except BaseException as exc:  # stopped (Ctrl-C, SIGTERM): none of its files, or all
        _remove_written(mine, started_ns)
        if isinstance(exc, SystemExit) and _WORKER.get("local"):  # (a local worker's SIGTERM: the process ends)
            _exit_now()
        raise
    finally:
        _WORKER["in_model"] = False
    timings["total"] = time.perf_counter() - t0
    rec["timings_s"] = timings
    if "distributed" in sys.modules:  # on a Dask worker: its address, so a retry can avoid it
        with contextlib.suppress(Exception):
            from distributed import get_worker

            rec["worker"] = get_worker().address
    rec["worker_init_s"] = _WORKER.pop("init_s", 0.0)
    return rec
