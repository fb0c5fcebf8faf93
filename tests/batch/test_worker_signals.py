"""A batch worker's SIGTERM taken by another of its threads: Python runs a signal's handler in the main thread only,
when that thread next runs; an idle worker's main thread, blocked reading its next task, never did, and the worker
lived on, holding the caller's pipes (about one group SIGTERM in 20 on a loaded machine). The worker's watching
thread now pokes the main thread (``gpuslice.batch.task._watch_driver``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import pytest

CHILD = textwrap.dedent("""
    import os, signal, threading, time
    from gpuslice.batch.task import init_worker

    init_worker(backend="numpy")  # (no driver to watch: only the signals)
    other = threading.Thread(target=time.sleep, args=(60,), daemon=True)  # a thread that takes SIGTERM
    other.start()
    r, w = os.pipe()
    threading.Timer(0.5, signal.pthread_kill, (other.ident, signal.SIGTERM)).start()
    os.read(r, 1)  # the main thread blocked, as an idle worker's is on its task queue
    print("read returned", flush=True)
""")


def test_a_sigterm_another_thread_takes_ends_a_blocked_worker():
    p = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
    assert p.returncode == 143, (p.returncode, p.stderr[-500:])
    assert "read returned" not in p.stdout


# A worker between models whose SIGTERM's ``SystemExit`` the pool's own code takes for a result to send back (as
# ``concurrent.futures.process._sendback_result`` does): it went back to waiting for a task, SIGTERM ignored from then
# on, and lived on holding the caller's pipes (one group SIGTERM in about 12 on a loaded machine).
SWALLOWED = textwrap.dedent("""
    import os, signal, threading, time
    from gpuslice.batch import task

    task.init_worker(backend="numpy")
    {setup}
    r, w = os.pipe()
    threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGTERM)).start()
    try:
        os.read(r, 1)  # (blocked, as an idle worker on its task queue, or a model in a long call)
    except BaseException as exc:  # (taken for a result, as the pool's code does)
        print("swallowed", type(exc).__name__, flush=True)
    {after}
    os.read(r, 1)  # (waiting for the next task)
    print("read returned", flush=True)
""")


def _run(setup: str = "", after: str = "") -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SWALLOWED.format(setup=setup, after=after)], capture_output=True,
                          text=True, timeout=60)


def test_a_sigterm_between_models_ends_the_worker_at_once():
    p = _run()
    assert p.returncode == 143, (p.returncode, p.stdout, p.stderr[-500:])
    assert "swallowed" not in p.stdout and "read returned" not in p.stdout


def test_a_model_unwinding_swallowed_outside_it_ends_the_worker():
    """Mid-model SIGTERM unwinds the model (``SystemExit``); should code outside the model take it (the worker back
    out of its model, waiting for a task), the watching thread ends the worker."""
    p = _run(setup='task._WORKER["in_model"] = True', after='task._WORKER["in_model"] = False')
    assert p.returncode == 143, (p.returncode, p.stdout, p.stderr[-500:])
    assert "swallowed SystemExit" in p.stdout and "read returned" not in p.stdout


def test_a_slow_unwinding_is_not_cut_short():
    """A model whose unwinding takes a while (waiting for a thread's batch, removing its temporary output) is not
    ended before it is out of the model: a partial file would stay (a review: a 5 s limit left one)."""
    p = _run(setup='task._WORKER["in_model"] = True',
             after='time.sleep(6); print("unwound", flush=True); task._WORKER["in_model"] = False')
    assert p.returncode == 143, (p.returncode, p.stdout, p.stderr[-500:])
    assert "swallowed SystemExit" in p.stdout and "unwound" in p.stdout and "read returned" not in p.stdout


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a zombie is read from /proc (Linux)")
def test_a_worker_whose_driver_is_a_zombie_ends():
    """The driver ended but not yet reaped (its caller reads its pipes to the end first): a worker still in the
    group took it for alive and waited for its next task for ever."""
    driver = subprocess.Popen([sys.executable, "-c", "pass"])  # (not waited for: a zombie once it ends)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        with open(f"/proc/{driver.pid}/stat", "rb") as f:
            if f.read().rsplit(b")", 1)[1].split()[0] == b"Z":
                break
        time.sleep(0.05)
    child = textwrap.dedent(f"""
        import os
        from gpuslice.batch.task import init_worker
        init_worker(backend="numpy", driver={driver.pid})
        r, w = os.pipe()
        os.read(r, 1)
        print("read returned", flush=True)
    """)
    try:
        p = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=60)
    finally:
        driver.wait()
    assert p.returncode == 143, (p.returncode, p.stdout, p.stderr[-500:])
