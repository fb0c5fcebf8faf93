"""PNG layers from runs encoded in worker processes: the PNG-based resin outputs (SL1, SL1S, NanoDLP, the PNG stack)
on every core.

The encoder of a PNG from runs (:mod:`gpuslice.raster.deflate_runs`) is a few dozen numpy calls per layer on arrays
of a few thousand elements; on threads they spend much of their time waiting for the GIL (armadillo at 12K, 1,900
layers, 2 cores: 2.0 s one after the other, 2.1 s on two threads, 1.3 s on two processes). So the writers' threads
hand each group of layers (consecutive entries of one batch of runs, :func:`gpuslice.raster.layers.run_groups`) to a
process pool and wait (without the GIL) for the PNGs, and for the zip members deflated from them where the archive
wants those. The bytes are those of the threads' path.

Within :func:`enabled` the pool is made once per worker count and kept (``forkserver`` start: a clean server
process that imports the encoder once, then forks the workers; never a fork of this process, which holds OpenCL and
other threads); :func:`prestart` starts it early, so the workers' imports overlap the slicing.

Processes are **opt-in**: a worker process imports the caller's main module, as every ``multiprocessing`` start
but ``fork`` does, so a script without an ``if __name__ == "__main__":`` guard would run again in it. The command
line runs its job inside :func:`enabled`, and a library caller may too: processes are then used where the main
module is safe to import (:func:`main_is_import_safe`). Otherwise, in a daemonic process (a batch or Dask worker:
no children allowed), where the platform has no ``forkserver`` (Windows) or for one worker, :func:`process_pool`
is None and the threads encode.
"""

from __future__ import annotations

import ast
import multiprocessing
import os
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from pathlib import Path

from .runs import Runs

__all__ = ["enabled", "main_is_import_safe", "shutdown", "process_pool", "prestart", "encode_group", "write_group",
           "group_runs", "threads_for"]

_LOCK = threading.Lock()
_POOLS: dict[int, ProcessPoolExecutor] = {}
_ENABLED_IN: int | None = None  # the process inside enabled() (a fork of it does not inherit the choice)
_OPEN = 0  # enabled() blocks open in that process


@contextmanager
def enabled() -> Iterator[None]:
    """Within the block, this process may encode PNG layers in worker processes (module docstring: its main module
    must be safe to import, as the command line's is); when the last open block of the process ends, the pools are
    shut down. Blocks may overlap (jobs on several threads)."""
    global _ENABLED_IN, _OPEN
    with _LOCK:
        if _ENABLED_IN != os.getpid():  # (a fork of an enabling process starts its own count)
            _OPEN = 0
        _OPEN += 1
        if main_is_import_safe():
            _ENABLED_IN = os.getpid()
    try:
        yield
    finally:
        with _LOCK:  # (no pool is made after the last block: process_pool checks under the same lock)
            _OPEN -= 1
            last = _OPEN == 0
            if last:
                _ENABLED_IN = None
        if last:
            shutdown()


def main_is_import_safe() -> bool:
    """Whether a worker process may import this process's main module without running work again: a package's
    ``__main__`` (``python -m``: multiprocessing does not import those), no main file (an interactive session), or a
    main file whose top level only imports, defines, assigns without calls and guards the rest with ``if __name__ ==
    "__main__":`` (console scripts do). Not for a frozen application."""
    if getattr(sys, "frozen", False):
        return False
    main = sys.modules.get("__main__")
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if name:
        return name == "__main__" or name.endswith(".__main__")
    path = getattr(main, "__file__", None)
    if path is None:
        return True
    try:
        tree = ast.parse(Path(path).read_text(encoding="utf-8", errors="replace"))
    except (OSError, SyntaxError, ValueError):
        return False
    return all(_quiet(node) for node in tree.body)


def _quiet(node: ast.stmt) -> bool:
    """A top-level statement that does no work when the module is imported under another name."""
    if isinstance(node, (ast.Import, ast.ImportFrom, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Pass)):
        return True
    if isinstance(node, ast.Expr):
        return isinstance(node.value, ast.Constant)  # a docstring
    if isinstance(node, (ast.Assign, ast.AnnAssign)):
        return node.value is None or not any(isinstance(n, ast.Call) for n in ast.walk(node.value))
    if isinstance(node, ast.If):  # the guard
        t = node.test
        return (isinstance(t, ast.Compare) and isinstance(t.left, ast.Name) and t.left.id == "__name__"
                and len(t.ops) == 1 and isinstance(t.ops[0], ast.Eq) and len(t.comparators) == 1
                and isinstance(t.comparators[0], ast.Constant) and t.comparators[0].value == "__main__"
                and not node.orelse)
    return False


def process_pool(workers: int | None) -> ProcessPoolExecutor | None:
    """The shared pool of ``workers`` encoder processes (made at the first call), or None when processes are not
    enabled in this process (:func:`enabled`), it is daemonic, ``workers`` < 2 or the platform has no
    ``forkserver`` start method."""
    if (multiprocessing.current_process().daemon or workers is None or workers < 2
            or "forkserver" not in multiprocessing.get_all_start_methods()):
        return None
    with _LOCK:
        if _ENABLED_IN != os.getpid():
            return None
        pool = _POOLS.get(workers)
        if pool is None:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload(["gpuslice.raster.deflate_runs"])
            pool = _POOLS[workers] = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_start)
        return pool


def _worker_start() -> None:
    """In each worker: Ctrl-C (sent to the whole process group) is the parent's to handle; the worker finishes its
    group and is stopped by the parent's shutdown, without a traceback of its own."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def shutdown() -> None:
    """Stop every pool of this process (waits for its workers)."""
    with _LOCK:
        pools = list(_POOLS.values())
        _POOLS.clear()
    for pool in pools:
        pool.shutdown(wait=True)


def threads_for(pool: ProcessPoolExecutor | None, workers: int | None) -> int | None:
    """The writer's thread count: with ``pool``, two threads per process (one waits for its group while the other
    hands its PNGs on, so the processes never idle), else ``workers``."""
    return 2 * (workers or os.cpu_count() or 1) if pool is not None else workers


def _ready() -> None:
    """Nothing: a task that makes the pool start its server and workers."""


def prestart(workers: int | None) -> None:
    """Start the pool of :func:`process_pool` now, on a thread of its own: the server's imports and the workers'
    start (the caller would wait for them, ~0.2 s each) overlap the caller's work."""
    def start() -> None:
        pool = process_pool(workers)
        try:
            for _ in range(workers if pool is not None else 0):
                pool.submit(_ready)
        except RuntimeError:  # the job ended first and shut the pool down: nothing to start
            pass

    if _ENABLED_IN == os.getpid():
        threading.Thread(target=start, name="gpuslice-png-procs", daemon=True).start()


def group_runs(group: list) -> Runs:
    """The runs of a group of consecutive :class:`~gpuslice.raster.layers.RunLayer` entries of one batch, as a
    :class:`Runs` of their own (the only data a worker gets)."""
    return group[0].runs.entries(group[0].j, group[-1].j + 1)


def _encode(runs: Runs, width: int, height: int, member: str | None,
            paths: list[str] | None = None) -> list[tuple[bytes, bytes | None]] | list[int]:
    """In a worker: each entry's PNG, and its zip member deflated at level 1 by ``member`` (a deflater name: the same
    module as the threads' path, :func:`gpuslice.raster.png.deflate_module`), or None. ``paths`` given: each PNG is
    written to its path instead, and its size in bytes returned."""
    from .deflate_runs import encode_png_from_runs
    from .png import deflate_module

    z = deflate_module(member) if member is not None else None
    out = []
    for j in range(len(runs.layers)):
        png = encode_png_from_runs(runs, j, width, height)
        if paths is not None:
            with open(paths[j], "wb") as f:
                f.write(png)
            out.append(len(png))
            continue
        deflated = None
        if z is not None:
            c = z.compressobj(1, z.DEFLATED, -15)
            deflated = c.compress(png) + c.flush()
        out.append((png, deflated))
    return out


def _run(pool: ProcessPoolExecutor, *args):
    """``_encode(*args)`` in ``pool``; in this thread if a worker died (the pool is broken: it is let go, and the
    next job makes a new one) or the pool was shut down meanwhile."""
    try:
        return pool.submit(_encode, *args).result()
    except BrokenProcessPool:
        with _LOCK:
            for key, p in list(_POOLS.items()):
                if p is pool:
                    del _POOLS[key]
        pool.shutdown(wait=False)
    except RuntimeError:  # "cannot schedule new futures after shutdown"
        pass
    return _encode(*args)


def encode_group(pool: ProcessPoolExecutor, group: list, width: int, height: int,
                 member: str | None = None) -> list[tuple[bytes, bytes | None]]:
    """The PNGs (``width`` × ``height``) of a group of consecutive run layers of one batch, made in ``pool``, each
    with its zip member deflated by the deflater named ``member`` (None: no member). Blocks the calling thread
    (not the GIL) until they are done."""
    return _run(pool, group_runs(group), int(width), int(height), member)


def write_group(pool: ProcessPoolExecutor, group: list, width: int, height: int, paths: list) -> list[int]:
    """Like :func:`encode_group`, but each PNG is written to its path in ``paths`` by the worker (nothing comes back
    but the sizes, bytes)."""
    return _run(pool, group_runs(group), int(width), int(height), None, [str(p) for p in paths])
