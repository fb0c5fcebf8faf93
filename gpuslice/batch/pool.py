"""Local worker processes of a batch: the start method (forkserver, modules preloaded), one single-process executor
a worker (:class:`Slot`), multiprocessing's helper processes started so that a closed terminal does not kill them,
and stopping every worker at once (Ctrl-C, SIGTERM)."""

from __future__ import annotations

import contextlib
import multiprocessing
import signal
import time
from collections.abc import Iterable
from concurrent.futures import Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Slot", "mp_context", "helpers_ignoring_sighup", "stop_slots"]

_PRELOAD = ["gpuslice.batch.task", "gpuslice.pipeline", "gpuslice.slicing.slicer", "gpuslice.io.meshfile",
            "gpuslice.formats", "gpuslice.io.atomic", "gpuslice.mesh.defects", "shapely"]


def mp_context():
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" in methods:  # pyopencl contexts do not survive fork; forkserver forks a clean process
        ctx = multiprocessing.get_context("forkserver")
        # imported once in the forkserver, inherited by every worker (no OpenCL there: contexts come after the fork)
        ctx.set_forkserver_preload(_PRELOAD)
        return ctx
    return multiprocessing.get_context("spawn")


@dataclass
class Slot:
    """One local worker: a single-process executor, so a retry can be sent to another worker and a dead worker
    breaks only its own executor."""

    name: str
    executor: ProcessPoolExecutor
    inflight: dict[Future, Any] = field(default_factory=dict)


def helpers_ignoring_sighup(ctx) -> None:
    """Start multiprocessing's resource tracker and forkserver with SIGHUP ignored (they keep it): a closed terminal
    sends SIGHUP to the whole group, and the driver stops its workers itself; killed by it, the tracker was started
    again by the driver and printed a traceback for each semaphore it did not know."""
    from multiprocessing import resource_tracker

    try:
        old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    except (ValueError, AttributeError):  # not the main thread, or no SIGHUP: leave them as they are
        return
    try:
        resource_tracker.ensure_running()
        if ctx.get_start_method() == "forkserver":
            from multiprocessing import forkserver

            forkserver.ensure_running()
    finally:
        signal.signal(signal.SIGHUP, old)


def stop_slots(slots: Iterable[Slot]) -> None:
    """Cancel what is queued and stop every worker now (Ctrl-C): SIGTERM (the worker removes its temporary
    output), then SIGKILL for any still running a second later."""
    procs = []
    for slot in slots:
        for fut in slot.inflight:
            fut.cancel()
        procs += list((getattr(slot.executor, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = time.monotonic() + 1.0
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)
    for slot in slots:
        with contextlib.suppress(Exception):
            slot.executor.shutdown(wait=False, cancel_futures=True)
