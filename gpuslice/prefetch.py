"""Threads: one producer thread ahead of its consumer (:func:`prefetch`: the next batch is made while the current
one is used), and one call on a thread of its own (:func:`beside`).

The resin path's runs kernel (OpenCL: it releases the GIL while the device works) and the archive encoders
(numpy on worker threads) then overlap instead of taking turns. Items are handed over in order; an exception in
the producer is raised in the consumer at the item where it happened; when the consumer closes the iterator early
(``close``, or garbage collection of an abandoned one) the producer stops at its next item, closes the source (a
generator's ``finally`` blocks run then, on the producer's thread) and its thread ends: callers that may stop early
close it in a ``finally`` (an exception held somewhere keeps the generator alive).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from typing import TypeVar

__all__ = ["prefetch", "beside"]

T = TypeVar("T")

_DONE = object()


class _Failed:
    def __init__(self, exc: BaseException) -> None:
        self.exc = exc


def prefetch(items: Iterable[T], depth: int = 1) -> Iterator[T]:
    """Yield the items of ``items``, made on a background thread at most ``depth`` items ahead of the consumer
    (memory: ``depth`` + 2 items alive at once: the one used, those waiting, the one being made).

    The producer runs ``iter(items)`` on its own thread, so whatever the iterable uses (an OpenCL queue, a kernel
    driver's reused buffers) must only be used from there until the iteration ends. ``depth`` < 1: no thread, the
    items are made in the consumer's thread as they are asked for.
    """
    if depth < 1:
        yield from items
        return
    box: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(value) -> bool:
        while not stop.is_set():
            try:
                box.put(value, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        source = iter(items)
        try:
            for item in source:
                if not put(item):
                    return
            put(_DONE)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            put(_Failed(exc))
        finally:  # stopped early: a generator's own clean-up (e.g. the runs' lane threads) runs now, on this thread
            close = getattr(source, "close", None)
            if close is not None:
                try:
                    close()
                except BaseException:  # noqa: BLE001, S110 - the consumer has gone: nobody to hand it to
                    pass

    worker = threading.Thread(target=produce, name="gpuslice-prefetch", daemon=True)
    worker.start()
    try:
        while True:
            got = box.get()
            if got is _DONE:
                return
            if isinstance(got, _Failed):
                exc = got.exc
                del got  # (no cycle: exception -> traceback -> this frame -> got -> exception)
                raise exc
            yield got
            del got
    finally:
        stop.set()
        if worker is not threading.current_thread():  # (closed by the collector on the producer's own thread)
            worker.join()


def beside(fn: Callable, *args, name: str = "gpuslice-beside") -> Future:
    """``fn(*args)`` started on a daemon thread of its own, named ``name``; its :class:`Future`. For work independent
    of what the caller does meanwhile, so that a second core takes it. A thread per call (~0.1 ms), not a pool: the
    thread ends with its call, so nothing outlives the result, also when the caller fails and an exception held
    somewhere keeps its frames alive (a pool's idle thread would stay as long as the pool object), a forked child
    has nothing to rebuild, and no idle thread keeps the command line from ending without the interpreter's teardown
    (``gpuslice.cli.main.exit_now``)."""
    fut: Future = Future()

    def run() -> None:
        if fut.set_running_or_notify_cancel():
            try:
                fut.set_result(fn(*args))
            except BaseException as exc:  # noqa: BLE001 - handed to whoever waits on the future
                fut.set_exception(exc)

    threading.Thread(target=run, name=name, daemon=True).start()
    return fut
