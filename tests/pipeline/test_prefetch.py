"""gpuslice.prefetch: items in order, made on another thread ahead of the consumer, errors and early stops."""

from __future__ import annotations

import threading
import time

import pytest

from gpuslice.prefetch import prefetch


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
    assert not [t for t in threading.enumerate() if t.name == "gpuslice-prefetch"]
