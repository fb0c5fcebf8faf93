"""Driver of ``kernels/walk.cl``: chain walking on the OpenCL device, one work-item per layer.

Its numpy twin is :func:`gpuslice.chain.order_chains` (pointer jumping); both return the same chains in the same
canonical order, which the tests check.
"""

from __future__ import annotations

import numpy as np

__all__ = ["WalkKernel", "walk_chains"]


def layer_lists(layer: np.ndarray, n_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Segment ids sorted by layer (stable, so increasing within a layer) and the layer offsets (L + 1,)."""
    key = layer.astype(np.uint16) if n_layers <= 65535 else layer
    perm = np.argsort(key, kind="stable").astype(np.int32)  # radix sort for 16-bit keys
    off = np.zeros(n_layers + 1, dtype=np.int64)
    np.cumsum(np.bincount(layer, minlength=n_layers), out=off[1:])
    return perm, off


class WalkKernel:
    """Builds ``walk.cl`` once per device and reuses its buffers."""

    def __init__(self, device) -> None:
        self.device = device
        self._walk = device.program("walk.cl").walk_layers
        self._buffers: dict[str, tuple[object, int]] = {}

    def _buffer(self, name: str, nbytes: int):
        import pyopencl as cl

        buf, size = self._buffers.get(name, (None, 0))
        if size < nbytes:
            size = max(nbytes, int(size * 1.5), 64)
            buf = cl.Buffer(self.device.context, cl.mem_flags.READ_WRITE, size)
            self._buffers[name] = (buf, size)
        return buf

    def __call__(self, nxt: np.ndarray, layer: np.ndarray, n_layers: int):
        import pyopencl as cl

        q = self.device.queue
        n = int(nxt.size)
        if n == 0:
            return np.zeros(0, np.int32), np.zeros(1, np.int64), np.zeros(0, bool)
        perm, off = layer_lists(layer, n_layers)
        has_prev = np.zeros(n, dtype=np.uint8)
        has_prev[nxt[nxt >= 0]] = 1
        bufs = {}
        for name, arr in (("next", nxt.astype(np.int32)), ("has_prev", has_prev), ("perm", perm), ("off", off)):
            bufs[name] = self._buffer(name, arr.nbytes)
            cl.enqueue_copy(q, bufs[name], np.ascontiguousarray(arr), is_blocking=False)
        d_visited = self._buffer("visited", n)
        d_flag = self._buffer("flag", n)
        d_order = self._buffer("order", 4 * n)
        cl.enqueue_fill_buffer(q, d_visited, np.uint8(0), 0, n)
        cl.enqueue_fill_buffer(q, d_flag, np.uint8(0), 0, n)
        ls = self.device.local_size
        gs = ((n_layers + ls - 1) // ls) * ls
        self._walk(q, (gs,), (ls,), bufs["next"], bufs["has_prev"], bufs["perm"], bufs["off"],
                   np.int32(n_layers), d_visited, d_order, d_flag)
        order = np.empty(n, dtype=np.int32)
        flag = np.empty(n, dtype=np.uint8)
        cl.enqueue_copy(q, order, d_order, is_blocking=False)
        cl.enqueue_copy(q, flag, d_flag, is_blocking=True)
        starts = np.flatnonzero(flag)
        offsets = np.append(starts, n).astype(np.int64)
        return order, offsets, flag[starts] == 2


_KERNELS: dict[int, WalkKernel] = {}


def walk_chains(nxt: np.ndarray, layer: np.ndarray, n_layers: int, device):
    """Chains of the successor graph ``nxt`` on ``device``: (order, chain_offsets, chain_closed) as
    :func:`gpuslice.chain.order_chains` returns them."""
    key = id(device)
    if key not in _KERNELS:
        _KERNELS[key] = WalkKernel(device)
    return _KERNELS[key](nxt, layer, n_layers)
