"""A batch worker's SIGTERM taken by another of its threads: Python runs a signal's handler in the main thread only,
when that thread next runs; an idle worker's main thread, blocked reading its next task, never did, and the worker
lived on, holding the caller's pipes (about one group SIGTERM in 20 on a loaded machine). The worker's watching
thread now pokes the main thread (``gpuslice.batch.task._watch_driver``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

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
