"""Probe: which PyOpenCL transfer calls wait for a running kernel (of their queue or of another), and which hold
the GIL meanwhile.

The reason for :data:`gpuslice.device.TRANSFERS` (docs/BENCHMARKS.md, "The GIL"). A kernel that spins for a while is
enqueued, then one call is timed while a Python thread counts as fast as it can: a wait with the GIL released lets
the counter run at its free rate, a wait with the GIL held stops it (as it stops every other Python thread of a
process). A non-blocking ``enqueue_copy`` is timed in two steps: the call, then dropping its event (PyOpenCL's
transfer event waits for its transfer in its destructor) or ``wait()`` on it.

    python scripts/probe_transfers.py [--device pocl] [--spin 100000] [--repeat 1]

Prints a Markdown table: the kernel's queue, the call, its wall time (ms) and the counter's rate meanwhile (millions
of increments per second).
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default=None, help="gpuslice device spec (default: gpuslice's default device)")
    ap.add_argument("--spin", type=int, default=100_000, help="iterations of the spinning kernel per work-item")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()

    import pyopencl as cl

    from gpuslice.device import get_device

    dev = get_device(args.device)
    ctx, q = dev.context, dev.queue
    prg = cl.Program(ctx, """
__kernel void spin(__global float *a, int n) {
    const int i = get_global_id(0);
    float s = a[i];
    for (int k = 0; k < n; ++k) s = s * 1.0000001f + 0.5f;
    a[i] = s;
}""").build()
    spin = cl.Kernel(prg, "spin")
    a = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 4 * 4096)
    b = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 4 * 1_000_000)
    host = np.ones(1_000_000, np.float32)
    ticks = [0]
    stop = threading.Event()

    def counter() -> None:
        while not stop.is_set():
            ticks[0] += 1

    mf = cl.mem_flags

    def dropped(call):  # the non-blocking call, then its event dropped: two timed steps
        return [("call", call), ("event dropped", lambda ev: None)]

    def waited(call):
        return [("call", call), ("event.wait()", lambda ev: ev.wait())]

    write = lambda: cl.enqueue_copy(q, b, host, is_blocking=False)  # noqa: E731
    read = lambda: cl.enqueue_copy(q, host, b, is_blocking=False)  # noqa: E731
    kinds = {
        "finish": [("call", lambda: q.finish())],
        "write, non-blocking": dropped(write),
        "write, non-blocking, kept": waited(write),
        "write, blocking": [("call", lambda: cl.enqueue_copy(q, b, host, is_blocking=True))],
        "read, non-blocking": dropped(read),
        "read, non-blocking, kept": waited(read),
        "read, blocking": [("call", lambda: cl.enqueue_copy(q, host, b, is_blocking=True))],
        "new buffer, COPY_HOST_PTR": [("call", lambda: cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=host))],
        "fill": [("call", lambda: cl.enqueue_fill_buffer(q, b, np.int32(0), 0, host.nbytes))],
    }
    other = cl.CommandQueue(ctx, dev.device)  # the kernel on another queue: the call's own queue is idle
    th = threading.Thread(target=counter, daemon=True)
    th.start()
    try:
        print(f"device: {dev.name}")
        print("| kernel on | call | step | wall ms | counter meanwhile, M/s |")
        print("|---|---|---|---:|---:|")
        for _ in range(args.repeat):
            for where, kq in (("its queue", q), ("another queue", other)):
                for label, steps in kinds.items():
                    q.finish()
                    spin(kq, (4096,), (64,), a, np.int32(args.spin))
                    kq.flush()
                    time.sleep(0.002)
                    value = None
                    for step, fn in steps:
                        t, k = time.perf_counter(), ticks[0]
                        value = fn() if step == "call" else fn(value)
                        if step == "event dropped":
                            del value
                            value = None
                        dt, dk = time.perf_counter() - t, ticks[0] - k
                        print(f"| {where} | {label} | {step} | {1e3 * dt:.1f} | {dk / max(dt, 1e-9) / 1e6:.2f} |")
                    kq.finish()
                    q.finish()
    finally:
        stop.set()
        th.join()


if __name__ == "__main__":
    main()
