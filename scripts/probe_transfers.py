"""Probe: does a PyOpenCL transfer enqueued behind a running kernel wait for it, and with the GIL held?

The reason for :attr:`gpuslice.device.Device.sync_transfers` (docs/BENCHMARKS.md, "The GIL"). A kernel that spins
for a while is enqueued on the device's queue, then one transfer (or ``finish``); meanwhile a Python thread counts
as fast as it can. A call that waits for the kernel with the GIL released lets the counter run at its free rate; one
that waits holding the GIL stops it (every other Python thread of a process stops the same way).

    python scripts/probe_transfers.py [--device pocl] [--spin 100000] [--repeat 2]

Prints, per transfer kind, the call's wall time (the kernel takes about the ``finish`` line's time) and the counter's
rate during the call, in millions of increments per second.
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
    kinds = {
        "finish": lambda: q.finish(),
        "write, non-blocking": lambda: cl.enqueue_copy(q, b, host, is_blocking=False),
        "write, blocking": lambda: cl.enqueue_copy(q, b, host, is_blocking=True),
        "read, non-blocking": lambda: cl.enqueue_copy(q, host, b, is_blocking=False),
        "read, blocking": lambda: cl.enqueue_copy(q, host, b, is_blocking=True),
        "new buffer, COPY_HOST_PTR": lambda: cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=host),
        "fill": lambda: cl.enqueue_fill_buffer(q, b, np.int32(0), 0, host.nbytes),
    }
    th = threading.Thread(target=counter, daemon=True)
    th.start()
    try:
        print(f"device: {dev.name}")
        print("| call | wall ms | counter during the call, M/s |")
        print("|---|---:|---:|")
        for _ in range(args.repeat):
            for label, call in kinds.items():
                q.finish()
                spin(q, (4096,), (64,), a, np.int32(args.spin))
                time.sleep(0.001)
                t, k = time.perf_counter(), ticks[0]
                call()
                dt, dk = time.perf_counter() - t, ticks[0] - k
                q.finish()
                print(f"| {label} | {1e3 * dt:.1f} | {dk / max(dt, 1e-9) / 1e6:.2f} |")
    finally:
        stop.set()
        th.join()


if __name__ == "__main__":
    main()
