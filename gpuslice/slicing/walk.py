"""Driver of ``kernels/walk.cl``: chaining on the OpenCL device.

Two entry points, both returning chains in the canonical order of :func:`gpuslice.chain.order_chains` (the numpy
twin, pointer jumping), which the tests check:

- :func:`walk_chains` walks a successor array computed on the host (used when a mesh needs the host's general
  pairing of non-manifold slots or repairs of open chains);
- :meth:`ChainKernels.chain_on_device` does everything on the device from the segment buffers the crossings kernel
  left there: edge slots, successors, per-layer lists and the walk, reading back only the chain order;
  :meth:`ChainKernels.gather_starts` then gathers the loops' points there in that order.

:meth:`ChainKernels.simple_loops` is nesting's screen: it proves loops simple so that GEOS's self-crossing test
runs only on the others (its oracle is GEOS itself: ``tests/slicing/test_simple_screen.py``).
"""

from __future__ import annotations

import numpy as np

from ..device import KernelDriver

__all__ = ["ChainKernels", "walk_chains", "chain_kernels", "canonical_chain_order"]


def layer_lists(layer: np.ndarray, n_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Segment ids sorted by layer (stable, so increasing within a layer) and the layer offsets (L + 1,)."""
    key = layer.astype(np.uint16) if n_layers <= 65535 else layer
    perm = np.argsort(key, kind="stable").astype(np.int32)  # radix sort for 16-bit keys
    off = np.zeros(n_layers + 1, dtype=np.int64)
    np.cumsum(np.bincount(layer, minlength=n_layers), out=off[1:])
    return perm, off


def canonical_chain_order(order: np.ndarray, flag: np.ndarray, layer_off: np.ndarray):
    """Sort walked chains by (layer, open before closed, first segment): (order, chain_offsets, closed, layer)."""
    n = order.size
    starts = np.flatnonzero(flag)
    lengths = np.diff(np.append(starts, n))
    kind = flag[starts]
    chain_layer = (np.searchsorted(layer_off, starts, side="right") - 1).astype(np.int32)
    o = np.lexsort((order[starts], kind, chain_layer))
    offsets = np.zeros(starts.size + 1, dtype=np.int64)
    np.cumsum(lengths[o], out=offsets[1:])
    if not np.array_equal(o, np.arange(o.size)):
        src = np.arange(n, dtype=np.int64) + np.repeat(starts[o] - offsets[:-1], lengths[o])
        order = order[src]
    return order, offsets, kind[o] == 2, chain_layer[o]


class ChainKernels(KernelDriver):
    """Builds ``walk.cl`` once per device, keeps its kernels and reuses grown buffers."""

    def __init__(self, device) -> None:
        super().__init__(device)
        prg = device.program("walk.cl")
        self._edge_ranges = prg.edge_ranges
        self._place = prg.place_segments
        self._link = prg.link_segments
        self._walk = prg.walk_layers
        self._gather = prg.gather_starts
        try:  # absent on devices without float64 (kernels/walk.cl builds it under cl_khr_fp64)
            self._simple = prg.simple_loops
        except AttributeError:  # pyopencl's answer for a kernel name the program lacks
            self._simple = None

    def _run_walk(self, d_next, d_has_prev, d_perm, d_off, n: int, n_layers: int):
        import pyopencl as cl

        q = self.device.queue
        d_visited = self._fill("visited", n, np.uint8(0))
        d_flag = self._fill("flag", n, np.uint8(0))
        d_order = self._buffer("order", 4 * n)
        self._walk(q, *self._grid(n_layers), d_next, d_has_prev, d_perm, d_off, np.int32(n_layers),
                   d_visited, d_order, d_flag)
        order = np.empty(n, dtype=np.int32)
        flag = np.empty(n, dtype=np.uint8)
        cl.enqueue_copy(q, order, d_order, is_blocking=False)
        cl.enqueue_copy(q, flag, d_flag, is_blocking=True)
        return order, flag

    def walk(self, nxt: np.ndarray, layer: np.ndarray, n_layers: int):
        """Chains of a host successor array ``nxt`` (see :func:`walk_chains`)."""
        n = int(nxt.size)
        if n == 0:
            return np.zeros(0, np.int32), np.zeros(1, np.int64), np.zeros(0, bool)
        perm, off = layer_lists(layer, n_layers)
        has_prev = np.zeros(n, dtype=np.uint8)
        has_prev[nxt[nxt >= 0]] = 1
        order, flag = self._run_walk(self._put("next", nxt.astype(np.int32)), self._put("has_prev", has_prev),
                                     self._put("perm", perm), self._put("layer_off", off), n, n_layers)
        order, offsets, closed, _ = canonical_chain_order(order, flag, off)
        return order, offsets, closed

    def chain_on_device(self, dseg, mesh, zs: np.ndarray, n_layers: int):
        """Chain the segments left on the device by the crossings kernel.

        Returns (order, chain_offsets, chain_closed, chain_layer), or None when the mesh needs the host's general
        pairing (a slot with several segments starting or ending: non-manifold or flipped facets) or leaves open
        chains to repair; the caller then fetches the segments and chains them on the host.
        """
        import pyopencl as cl

        q = self.device.queue
        n = dseg.n
        n_edges = int(mesh.edge_vertices.shape[0])
        d_vub = dseg.kernel.buffer("vub")
        d_ev = self._put("edge_vertices", mesh.edge_vertices)
        d_k0 = self._buffer("k0", 4 * n_edges)
        d_count = self._buffer("edge_count", 4 * n_edges)
        self._edge_ranges(q, *self._grid(n_edges), d_vub, d_ev, np.int32(n_edges), d_k0, d_count)
        count = np.empty(n_edges, dtype=np.int32)
        cl.enqueue_copy(q, count, d_count)
        off = np.cumsum(count, dtype=np.int64)
        n_slots = int(off[-1]) if n_edges else 0
        if n_slots >= 2**31 - 1:
            return None
        off = (off - count).astype(np.int32)
        d_off = self._put("edge_off", off)
        d_starter = self._fill("starter", 4 * n_slots, np.int32(-1))
        d_enders = self._fill("n_enders", 4 * n_slots, np.int32(0))
        d_end = self._buffer("end_slot", 4 * n)
        d_lcount = self._fill("layer_count", 4 * n_layers, np.int32(0))
        d_conflict = self._fill("conflict", 4, np.int32(0))
        grid = self._grid(n)
        self._place(q, *grid, dseg.layer, dseg.edges, np.int32(n), d_k0, d_off, d_starter, d_enders, d_end,
                    d_lcount, d_conflict)
        conflict = np.zeros(1, dtype=np.int32)
        lcount = np.empty(n_layers, dtype=np.int32)
        cl.enqueue_copy(q, conflict, d_conflict, is_blocking=False)
        cl.enqueue_copy(q, lcount, d_lcount, is_blocking=True)
        if conflict[0]:
            return None
        layer_off = np.zeros(n_layers + 1, dtype=np.int64)
        np.cumsum(lcount, out=layer_off[1:])
        d_loff = self._put("layer_off", layer_off)
        d_fill = self._fill("layer_fill", 4 * n_layers, np.int32(0))
        d_next = self._buffer("next", 4 * n)
        d_has_prev = self._fill("has_prev", n, np.uint8(0))
        d_perm = self._buffer("perm", 4 * n)
        self._link(q, *grid, dseg.layer, d_end, np.int32(n), d_starter, d_loff, d_fill, d_next, d_has_prev, d_perm)
        order, flag = self._run_walk(d_next, d_has_prev, d_perm, d_loff, n, n_layers)
        if np.any(flag == 1):
            return None  # open chains: repaired on the host
        return canonical_chain_order(order, flag, layer_off)

    def gather_starts(self, dseg, order: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The start points of the device segments ``dseg`` in chain ``order``, gathered on the device: (S,)
        complex64 (x + iy, mm), and (S,) bool, True where that segment has zero length. The points stay on the
        device for :meth:`simple_loops`."""
        import pyopencl as cl

        n = int(order.size)
        q = self.device.queue
        starts = np.empty(n, dtype=np.complex64)
        zero = np.empty(n, dtype=np.uint8)
        if n == 0:
            return starts, zero.view(bool)
        d_order = self._put("gather_order", order.astype(np.int32, copy=False))
        d_zero = self._buffer("zero_length", n)
        d_out = self._buffer("loop_points", 8 * n)
        self._gather(q, *self._grid(n), d_order, dseg.points, np.int32(n), d_out, d_zero)
        cl.enqueue_copy(q, zero, d_zero, is_blocking=False)
        cl.enqueue_copy(q, starts, d_out, is_blocking=True)
        return starts, zero.view(bool)

    def simple_loops(self, points: np.ndarray, offsets: np.ndarray, *, resident: bool = False) -> np.ndarray | None:
        """(R,) bool: True for each loop ``points[offsets[r]:offsets[r + 1]]`` (float32 (P, 2), mm, closed) that
        ``simple_loops`` in ``kernels/walk.cl`` proves simple (no two edges meet but consecutive ones at their
        vertex); False where it may cross or touch itself. None when the device lacks float64 (no screen).
        ``resident``: the points are already on the device, as :meth:`gather_starts` left them."""
        import pyopencl as cl

        n = int(offsets.size) - 1
        if self._simple is None:
            return None
        if n <= 0 or points.shape[0] == 0:
            return np.zeros(max(n, 0), dtype=bool)
        q = self.device.queue
        if resident:
            d_points = self.buffer("loop_points")
        else:
            d_points = self._put("loop_points", np.ascontiguousarray(points, dtype=np.float32))
        d_offsets = self._put("loop_offsets", offsets.astype(np.int64, copy=False))
        d_simple = self._buffer("simple", n)
        self._simple(q, *self._grid(n), d_points, d_offsets, np.int32(n), d_simple)
        out = np.empty(n, dtype=np.uint8)
        cl.enqueue_copy(q, out, d_simple, is_blocking=True)
        return out.view(bool)


def chain_kernels(device) -> ChainKernels:
    """The :class:`ChainKernels` of ``device`` (built once per device)."""
    return ChainKernels.of(device)


def walk_chains(nxt: np.ndarray, layer: np.ndarray, n_layers: int, device):
    """Chains of the successor graph ``nxt`` on ``device``: (order, chain_offsets, chain_closed) as
    :func:`gpuslice.chain.order_chains` returns them."""
    return chain_kernels(device).walk(nxt, layer, n_layers)
