"""One producer thread ahead of its consumer: the next batch is made while the current one is used.

The resin path's runs kernel (OpenCL: it releases the GIL while the device works) and the archive encoders
(numpy on worker threads) then overlap instead of taking turns. Items are handed over in order; an exception in
the producer is raised in the consumer at the item where it happened; when the consumer closes the iterator early
(``close``, or garbage collection of an abandoned one) the producer stops at its next item and its thread ends:
callers that may stop early close it in a ``finally`` (an exception held somewhere keeps the generator alive).
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator
from typing import TypeVar

__all__ = ["prefetch"]

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
        try:
            for item in items:
                if not put(item):
                    return
            put(_DONE)
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer, raised there
            put(_Failed(exc))

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
