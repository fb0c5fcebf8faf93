"""Threads: one producer thread ahead of its consumer (:func:`prefetch`: the next batch is made while the current
one is used), one call on a thread of its own (:func:`beside`), and a few threads taking calls in turn
(:class:`Workers`: the runs' lanes, the layer encoders, the checks' GEOS chunks).

The resin path's runs kernel (OpenCL: it releases the GIL while the device works) and the archive encoders
(numpy on worker threads) then overlap instead of taking turns. Items are handed over in order; an exception in
the producer is raised in the consumer at the item where it happened; when the consumer closes the iterator early
(``close``, or garbage collection of an abandoned one) the producer stops at its next item, closes the source (a
generator's ``finally`` blocks run then, on the producer's thread) and its thread ends: callers that may stop early
close it in a ``finally`` (an exception held somewhere keeps the generator alive).

All three start their threads without waiting for them to run (:func:`_spawn`): ``threading.Thread.start`` waits
until the new thread has been scheduled, which with both cores busy (the device's threads) is often a whole
scheduler tick (4 ms: a tenth of the starts, measured), and a resin job starts about a hundred. Such threads are not
in ``threading.enumerate()``: :func:`live_threads` names those still running.
"""

from __future__ import annotations

import _thread
import itertools
import os
import queue
import sys
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future
from typing import TypeVar

__all__ = ["prefetch", "beside", "Workers", "current_name", "live_threads"]

T = TypeVar("T")

_DONE = object()
_LIVE: dict[int, str] = {}  # threads started by _spawn and not yet ended: token -> name
_LOCAL = threading.local()  # .name: the name _spawn gave the calling thread
_LIVE_LOCK = threading.Lock()
_TOKENS = itertools.count()


def _forked() -> None:  # a forked child has none of its parent's threads, and its lock may have been held
    global _LIVE_LOCK
    _LIVE_LOCK = threading.Lock()
    _LIVE.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forked)


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

    producer = [0]  # the producer thread's identifier, once it runs

    def produce() -> None:
        producer[0] = threading.get_ident()
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

    finished = threading.Event()
    _spawn(produce, "gpuslice-prefetch", finished)
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
        if threading.get_ident() != producer[0]:  # (closed by the collector on the producer's own thread)
            finished.wait()


def beside(fn: Callable, *args, name: str = "gpuslice-beside") -> Future:
    """``fn(*args)`` started on a thread of its own, named ``name`` (:func:`live_threads`); its :class:`Future`. For
    work independent of what the caller does meanwhile, so that a second core takes it. A thread per call, not a pool:
    the thread ends with its call, so nothing outlives the result, also when the caller fails and an exception held
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

    _spawn(run, name)
    return fut


def _spawn(fn: Callable[[], None], name: str, finished: threading.Event | None = None) -> None:
    """Start ``fn()`` on a new thread, listed by :func:`live_threads` as ``name`` until it returns (``finished`` is
    set then), and return at once, before it runs (module docstring). Like a daemon thread, it does not keep the
    interpreter from ending; ``fn`` handles its own exceptions."""
    token = next(_TOKENS)
    with _LIVE_LOCK:
        _LIVE[token] = name

    def run() -> None:
        try:
            _LOCAL.name = name
            # (what threading.Thread does: a tracer or profiler set for threads, e.g. coverage's, sees this one too)
            trace, profile = threading.gettrace(), threading.getprofile()
            if trace is not None:
                sys.settrace(trace)
            if profile is not None:
                sys.setprofile(profile)
            fn()
        finally:
            with _LIVE_LOCK:
                _LIVE.pop(token, None)
            if finished is not None:
                finished.set()

    try:
        _thread.start_new_thread(run, ())
    except BaseException:  # (no thread: "can't start new thread")
        with _LIVE_LOCK:
            _LIVE.pop(token, None)
        raise


class Workers:
    """Up to ``n`` threads named ``name`` taking the calls given to :meth:`submit` in order: the part of
    ``concurrent.futures.ThreadPoolExecutor`` used here, with its threads started as :func:`_spawn` starts them (the
    module docstring), each when a call finds no idle one. :meth:`shutdown` lets the threads end once the calls given
    so far are done (a ``with`` block: and waits for them)."""

    def __init__(self, n: int, name: str) -> None:
        self._n = max(int(n), 1)
        self._name = name
        self._calls: queue.SimpleQueue = queue.SimpleQueue()
        self._ended: list[threading.Event] = []
        self._idle = 0
        self._lock = threading.Lock()
        self._idents: set[int] = set()

    def submit(self, fn: Callable[..., T], *args) -> Future:
        """``fn(*args)`` on one of the threads; its :class:`Future`. Safe to call from several threads."""
        fut: Future = Future()
        with self._lock:  # (the call is queued under it: a shutdown's end marks never overtake it)
            if self._n == 0:
                raise RuntimeError(f"{self._name}: no calls after shutdown")
            if self._idle <= 0 and len(self._ended) < self._n:  # (idle: idle threads less calls waiting)
                ended = threading.Event()
                _spawn(self._work, self._name, ended)  # (raises when no thread can start: nothing is queued then)
                self._ended.append(ended)
            else:
                self._idle -= 1
            self._calls.put((fut, fn, args))
        return fut

    def map(self, fn: Callable[..., T], items: Iterable) -> list[T]:
        """``[fn(x) for x in items]`` on the threads (the first error raised, after every call is done)."""
        futures = [self.submit(fn, x) for x in items]
        for f in futures:
            f.exception()
        return [f.result() for f in futures]

    def on_own_thread(self) -> bool:
        """Whether the caller is one of these threads (which cannot wait for itself to end)."""
        return threading.get_ident() in self._idents

    def _work(self) -> None:
        me = threading.get_ident()
        self._idents.add(me)
        while True:
            call = self._calls.get()
            if call is None:
                self._idents.discard(me)  # (an identifier is reused once its thread has ended)
                return
            fut, fn, args = call
            del call
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn(*args))
                except BaseException as exc:  # noqa: BLE001 - handed to whoever waits on the future
                    fut.set_exception(exc)
            del fut, fn, args  # (nothing of a finished call stays alive while the thread waits)
            with self._lock:
                self._idle += 1

    def shutdown(self, wait: bool = True) -> None:
        """No more calls: each thread ends after the calls given before this; ``wait``: return when they have."""
        with self._lock:
            ended = list(self._ended)
            self._n = 0  # (a later submit raises, as the executor's does)
            for _ in ended:
                self._calls.put(None)
        if wait and not self.on_own_thread():
            for e in ended:
                e.wait()

    def __enter__(self) -> Workers:
        return self

    def __exit__(self, *exc) -> None:
        self.shutdown(wait=True)


def current_name() -> str:
    """The name of the calling thread: the one :func:`prefetch`, :func:`beside` or :class:`Workers` gave it, else
    ``threading.current_thread().name`` (asked only then: on a thread not started by ``threading``, that call leaves a
    dummy thread object behind)."""
    name = getattr(_LOCAL, "name", None)
    return name if name is not None else threading.current_thread().name


def live_threads() -> list[str]:
    """The names of the threads :func:`prefetch`, :func:`beside` and :class:`Workers` started that have not ended yet
    (they are not ``threading.Thread`` objects: ``threading.enumerate()`` does not list them)."""
    with _LIVE_LOCK:
        return list(_LIVE.values())
