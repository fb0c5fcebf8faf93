"""gpuslice.prefetch: items in order, made on another thread ahead of the consumer, errors and early stops."""

from __future__ import annotations

import threading
import time

import pytest

from gpuslice.prefetch import beside, live_threads, prefetch


def test_items_in_order_made_on_another_thread():
    made_on = []

    def items():
        for k in range(50):
            made_on.append(threading.get_ident())
            yield k

    assert list(prefetch(items())) == list(range(50))
    assert set(made_on) and threading.get_ident() not in made_on


def test_depth_zero_runs_in_the_callers_thread():
    made_on = []

    def items():
        for k in range(3):
            made_on.append(threading.get_ident())
            yield k

    assert list(prefetch(items(), depth=0)) == [0, 1, 2]
    assert made_on == [threading.get_ident()] * 3


def test_producer_runs_at_most_depth_ahead():
    made = []

    def items():
        for k in range(20):
            made.append(k)
            yield k

    it = prefetch(items(), depth=2)
    assert next(it) == 0
    time.sleep(0.3)  # let the producer run as far as it may
    # the consumer holds item 0; 2 wait in the queue; the producer holds at most one more while blocked
    assert len(made) <= 4
    assert list(it) == list(range(1, 20))


def test_producer_error_raised_in_consumer_after_earlier_items():
    def items():
        yield 1
        yield 2
        raise ValueError("bad batch")

    got = []
    with pytest.raises(ValueError, match="bad batch"):
        for x in prefetch(items()):
            got.append(x)
    assert got == [1, 2]


def test_early_close_stops_the_producer():
    made = []

    def items():
        for k in range(10_000):
            made.append(k)
            yield k

    it = prefetch(items())
    assert next(it) == 0
    it.close()  # joins the producer thread
    n = len(made)
    time.sleep(0.1)
    assert len(made) == n < 10_000
    assert "gpuslice-prefetch" not in live_threads()


def test_a_source_stopped_early_is_closed_also_while_an_exception_keeps_the_consumer():
    """An interrupt inside the consumer (Ctrl-C while it waits for an item) whose exception is kept keeps the
    consumer's frame, and so the source generator: its clean-up (the runs' lane threads) must not wait for that
    exception to go. The producer closes the source itself when it stops early."""
    closed = threading.Event()

    def items():
        try:
            yield from range(10_000)
        finally:
            closed.set()

    it = prefetch(items())
    assert next(it) == 0
    kept = []
    try:
        it.throw(KeyboardInterrupt)  # (lands in the consumer, as a signal would)
    except KeyboardInterrupt as exc:
        kept.append(exc)  # its traceback holds the consumer's frame, hence the source
    assert closed.wait(5)
    deadline = time.monotonic() + 5  # (the producer ends just after it closes the source)
    while time.monotonic() < deadline and "gpuslice-prefetch" in live_threads():
        time.sleep(0.01)
    assert kept and "gpuslice-prefetch" not in live_threads()


@pytest.mark.parametrize("fmt", ["goo", "sl1", "pwmx"])
def test_a_failed_resin_job_leaves_no_thread_while_its_exception_is_kept(tmp_path, device, fmt):
    """A resin job stopped by its progress callback (Ctrl-C, a server cancelling it): a caller that keeps the
    exception (a job table, a future) kept the preview's thread and its arrays alive with it, one per failure."""
    from gpuslice import Placement, SliceParams
    from gpuslice.mesh import shapes
    from gpuslice.pipeline import Job, ResinOutput, run_job
    from gpuslice.raster import RasterSpec, ResinOptions

    model = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 40, 20), model)

    def stop(k: int, n: int) -> None:
        if k >= 5:
            raise RuntimeError("cancelled")

    spec = RasterSpec(resolution=(3840, 2400) if fmt == "pwmx" else (1920, 1080), pixel=0.05)  # (the Mono X's)
    kept = []
    for i in range(3):
        job = Job(source=str(model), placement=Placement(fit=30.0), params=SliceParams(thickness=0.2),
                  resin=ResinOutput(str(tmp_path / f"out{i}.{fmt}"), fmt, spec, ResinOptions()))
        with pytest.raises(RuntimeError, match="cancelled") as info:
            run_job(job, device=device, progress=stop)
        kept.append(info.value)
    ours = ("gpuslice-heightmap", "gpuslice-runs-lane", "gpuslice-prefetch")
    deadline = time.monotonic() + 5
    names = lambda: [n for n in [*live_threads(), *(t.name for t in threading.enumerate())] if n.startswith(ours)]  # noqa: E731
    while time.monotonic() < deadline and names():
        time.sleep(0.05)
    assert not names()
    assert len(kept) == 3 and not list(tmp_path.glob("out*"))


def test_live_threads_names_a_running_call_until_it_returns():
    """The threads are started without ``threading.Thread`` (not waiting for them to run): the registry is what
    shows one still running, from before it runs until it has returned."""
    go = threading.Event()
    fut = beside(go.wait, 5, name="gpuslice-test-beside")
    assert "gpuslice-test-beside" in live_threads()
    go.set()
    assert fut.result(5) is True
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and "gpuslice-test-beside" in live_threads():
        time.sleep(0.01)
    assert "gpuslice-test-beside" not in live_threads()


def test_a_producer_is_listed_while_it_runs():
    it = prefetch(iter(range(100)))
    assert next(it) == 0
    assert "gpuslice-prefetch" in live_threads()
    it.close()
    assert "gpuslice-prefetch" not in live_threads()


def test_workers_run_calls_on_at_most_n_threads_and_end_them():
    from gpuslice.prefetch import Workers

    seen: set[int] = set()
    lock = threading.Lock()

    def call(x):
        with lock:
            seen.add(threading.get_ident())
        time.sleep(0.002)
        return x * x

    with Workers(3, "gpuslice-test-workers") as pool:
        assert pool.map(call, range(40)) == [x * x for x in range(40)]
        futures = [pool.submit(call, x) for x in range(10)]
    assert [f.result() for f in futures] == [x * x for x in range(10)]  # (shutdown ran the calls given before it)
    assert 1 <= len(seen) <= 3 and threading.get_ident() not in seen
    assert "gpuslice-test-workers" not in live_threads()  # (the with block waited for the threads to end)


def test_workers_hand_an_error_to_its_future_and_go_on():
    from gpuslice.prefetch import Workers

    def call(x):
        if x == 2:
            raise ValueError("bad call")
        return x

    with Workers(2, "gpuslice-test-workers") as pool:
        futures = [pool.submit(call, x) for x in range(5)]
        with pytest.raises(ValueError, match="bad call"):
            pool.map(call, range(5))
    assert [f.exception() is not None for f in futures] == [False, False, True, False, False]
    assert futures[4].result() == 4
    with pytest.raises(RuntimeError, match="after shutdown"):  # (not a call queued that no thread takes)
        pool.submit(call, 1)


def test_workers_that_cannot_start_a_thread_raise_and_do_not_hang(monkeypatch):
    """A thread that cannot start ("can't start new thread") is the caller's error at submit; nothing is queued for
    it and the pool's shutdown does not wait for a thread that never ran."""
    import gpuslice.prefetch as P

    real, made = P._spawn, []

    def spawn(fn, name, finished=None):  # (the test's own thread and the pool's first start; then none)
        if len(made) >= 2:
            raise RuntimeError("can't start new thread")
        made.append(name)
        return real(fn, name, finished)

    monkeypatch.setattr(P, "_spawn", spawn)

    def run():
        gate = threading.Event()
        with P.Workers(3, "gpuslice-test-workers") as pool:
            first = pool.submit(gate.wait, 5)  # (its thread busy: the next call needs a second thread)
            with pytest.raises(RuntimeError, match="start new thread"):
                pool.submit(time.sleep, 0)
            gate.set()
            return first.result(5)

    assert beside(run).result(timeout=20) is True


def test_workers_take_calls_from_several_threads_at_once(monkeypatch):
    """Threads submitting at once each start their own worker thread when none is idle, and each worker gets its own
    end mark: before, a submit read the newest mark after letting go of the pool's lock, so two of them could hand
    their threads the same one, and a shutdown then waited for ever (a review found it). The queue is slowed here to
    hold that window open."""
    import queue

    import gpuslice.prefetch as P

    class SlowQueue(queue.SimpleQueue):
        def put(self, item, block=True, timeout=None):
            if item is not None:
                time.sleep(0.005)
            super().put(item, block, timeout)

    real, marks = P._spawn, []

    def spawn(fn, name, finished=None):
        if name == "gpuslice-test-workers":
            marks.append(finished)
        return real(fn, name, finished)

    monkeypatch.setattr(P, "_spawn", spawn)
    for _ in range(5):
        marks.clear()
        pool = P.Workers(4, "gpuslice-test-workers")
        pool._calls = SlowQueue()
        go = threading.Barrier(2)
        gate = threading.Event()

        def feed(pool=pool, go=go, gate=gate):
            go.wait(10)
            return pool.submit(gate.wait, 10)  # (busy until the gate opens: the next call needs a thread of its own)

        calls = [f.result(20) for f in [beside(feed) for _ in range(2)]]
        gate.set()
        beside(pool.shutdown, True).result(timeout=10)  # (every thread had its end mark)
        assert len(marks) == 2 and marks[0] is not marks[1]
        assert all(c.result(0) is True for c in calls)


def test_thread_names_and_tracers_reach_the_threads():
    """``current_name`` on a thread started here is the name it was given (nesting's halves ask it so as not to
    split work again on their own thread); a tracer set for threads (coverage's) runs on them too."""
    from gpuslice.prefetch import current_name

    assert beside(current_name, name="gpuslice-test-name").result(5) == "gpuslice-test-name"
    seen = []

    def tracer(frame, event, arg):
        if event == "call" and frame.f_code.co_name == "traced_call":
            seen.append(current_name())
        return None

    def traced_call():
        return 1

    threading.settrace(tracer)
    try:
        beside(traced_call, name="gpuslice-test-traced").result(5)
    finally:
        threading.settrace(None)
    assert seen == ["gpuslice-test-traced"]
