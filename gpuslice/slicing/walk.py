"""Driver of ``kernels/walk.cl``: chaining on the OpenCL device.

Two entry points, both returning chains in the canonical order of :func:`gpuslice.chain.order_chains` (the numpy
twin, pointer jumping), which the tests check:

- :func:`walk_chains` walks a successor array computed on the host (used when a mesh needs the host's general
  pairing of non-manifold slots or repairs of open chains);
- :meth:`ChainKernels.chain_on_device` does everything on the device from the segment buffers the crossings kernel
  left there: edge slots, successors, per-layer lists and the walk, which finds each layer's loops, sorts them by
  smallest segment and gathers their points from it, so the device leaves them in the canonical order; it reads
  back the loops' first positions, their points and the points' zero-length flags (not the segment ids).

:meth:`ChainKernels.simple_loops` is nesting's screen: it proves loops simple so that GEOS's self-crossing test
runs only on the others (its oracle is GEOS itself: ``tests/slicing/test_simple_screen.py``).
"""

from __future__ import annotations

import numpy as np

from ..device import STRIPES, KernelDriver
from ..ragged import loop_chunks
from .rings import move_chains as _move_chains

__all__ = ["ChainKernels", "walk_chains", "chain_kernels", "canonical_chain_order"]


def layer_lists(layer: np.ndarray, n_layers: int) -> tuple[np.ndarray, np.ndarray]:
    """Segment ids sorted by layer (stable, so increasing within a layer) and the layer offsets (L + 1,)."""
    key = layer.astype(np.uint16) if n_layers <= 65535 else layer
    perm = np.argsort(key, kind="stable").astype(np.int32)  # radix sort for 16-bit keys
    off = np.zeros(n_layers + 1, dtype=np.int64)
    np.cumsum(np.bincount(layer, minlength=n_layers), out=off[1:])
    return perm, off


def canonical_chain_order(order: np.ndarray, flag: np.ndarray, layer_off: np.ndarray, *along: np.ndarray):
    """Sort walked chains by (layer, open before closed, first segment): (order, chain_offsets, closed, layer), then
    each array of ``along`` (one entry per position of ``order``) in the same order."""
    n = order.size
    starts = np.flatnonzero(flag != 0)  # (a bool mask: ~10x faster than on the uint8 flags)
    lengths = np.diff(np.append(starts, n))
    kind = flag[starts]
    chain_layer = (np.searchsorted(layer_off, starts, side="right") - 1).astype(np.int32)
    o = np.lexsort((order[starts], kind, chain_layer))
    offsets = np.zeros(starts.size + 1, dtype=np.int64)
    np.cumsum(lengths[o], out=offsets[1:])
    if not np.array_equal(o, np.arange(o.size)):
        order, *along = _move_chains(starts[o], offsets, (order, *along))
    return (order, offsets, kind[o] == 2, chain_layer[o], *along)


class ChainKernels(KernelDriver):
    """Builds ``walk.cl`` once per device, keeps its kernels and reuses grown buffers."""

    #: work-items per work-group of :meth:`_task_grid` on CPU devices (4: the best of 1 to 64 on PoCL, 2 cores)
    CPU_TASK_GROUP = 4

    def __init__(self, device) -> None:
        super().__init__(device)
        prg = device.program("walk.cl")
        self._edge_ranges = prg.edge_ranges
        self._place = prg.place_segments
        self._link = prg.link_segments
        self._starts = prg.part_starts
        self._walk = prg.walk_layers
        self._boxes = prg.chunk_boxes
        try:  # absent on devices without float64 (kernels/walk.cl builds it under cl_khr_fp64)
            self._simple = prg.simple_loops
        except AttributeError:  # pyopencl's answer for a kernel name the program lacks
            self._simple = None

    def _task_grid(self, n: int) -> tuple[tuple[int], tuple[int]]:
        """The grid of the kernels that give each work-item one long task of uneven size (a layer's walk, a loop's
        screen; ``walk_layers`` and ``simple_loops`` have no required work-group size): the device's local size on
        GPUs; on CPU devices (PoCL), which hand whole work-groups to the cores, groups of :attr:`CPU_TASK_GROUP`
        items, so that the cores finish together (with 64, one core idled at the end: the walk and the screen
        took 20 to 40 % longer on benchy and an icosphere)."""
        ls = self.device.local_size if self.device.is_gpu else self.CPU_TASK_GROUP
        return (max(ls, ((n + ls - 1) // ls) * ls),), (ls,)

    def _run_walk(self, d_next, d_has_prev, d_perm, d_off, n: int, n_layers: int, gather: bool = False,
                  d_seg_points=None, d_conflict=None):
        """The walk: (order, flag); with ``gather`` (closed loops only: see ``walk_layers``), instead (flag,
        starts, zero): the loops in the canonical order, and from ``d_seg_points`` (the crossings kernel's
        segments) the start point of the segment at each position, (n,) complex64, and its zero-length flag, (n,)
        bool; the points stay on the device in the buffer ``loop_points`` (for :meth:`simple_loops`); ``d_perm``
        (the per-layer lists) is overwritten. Nothing is walked where the device int ``d_conflict`` is set."""
        if n == 0:
            if gather:
                return np.zeros(0, np.uint8), np.zeros(0, np.complex64), np.zeros(0, bool)
            return np.zeros(0, np.int32), np.zeros(0, np.uint8)
        q = self.device.queue
        if d_conflict is None:
            d_conflict = self._fill("no_conflict", 4, np.int32(0))  # (set by the walk if a segment is met twice)
        d_visited = self._fill("visited", n, np.uint8(0))
        d_flag = self._fill("flag", n, np.uint8(0))
        d_order = self._buffer("order", 4 * n) if not gather else d_flag  # (a dummy argument with gather)
        d_out = self._buffer("loop_points", 8 * n) if gather else d_flag  # (a dummy argument without gather)
        d_zero = self._buffer("zero_length", n) if gather else d_flag
        d_points = d_seg_points if d_seg_points is not None else d_flag
        self._walk(q, *self._task_grid(n_layers), d_next, d_has_prev, d_perm, d_off, np.int32(n_layers),
                   d_visited, d_order, d_flag, np.int32(gather), d_points, d_out, d_zero, d_conflict)
        flag = np.empty(n, dtype=np.uint8)
        if not gather:
            order = np.empty(n, dtype=np.int32)
            self._read((order, d_order), (flag, d_flag))
            return order, flag
        starts = np.empty(n, dtype=np.complex64)
        zero = np.empty(n, dtype=np.uint8)
        self._read((flag, d_flag), (zero, d_zero), (starts, d_out))
        return flag, starts, zero.view(bool)

    def walk(self, nxt: np.ndarray, layer: np.ndarray, n_layers: int):
        """Chains of a host successor array ``nxt`` (see :func:`walk_chains`)."""
        n = int(nxt.size)
        if n == 0:
            return np.zeros(0, np.int32), np.zeros(1, np.int64), np.zeros(0, bool)
        perm, off = layer_lists(layer, n_layers)
        has_prev = np.zeros(n, dtype=np.uint8)
        has_prev[nxt[nxt >= 0]] = 1
        d_conflict = self._fill("no_conflict", 4, np.int32(0))
        order, flag = self._run_walk(self._put("next", nxt.astype(np.int32)), self._put("has_prev", has_prev),
                                     self._put("perm", perm), self._put("layer_off", off), n, n_layers,
                                     d_conflict=d_conflict)
        met_twice = np.zeros(1, np.int32)
        self._read((met_twice, d_conflict))
        if met_twice[0]:  # (the host pairs each slot's i-th incoming segment with its i-th outgoing one: never)
            raise RuntimeError("walk_layers: the host's successor array gives some segment two predecessors")
        order, offsets, closed, _ = canonical_chain_order(order, flag, off)
        return order, offsets, closed

    def chain_on_device(self, dseg, mesh, zs: np.ndarray, n_layers: int, layer_counts: np.ndarray | None = None,
                        mesh_on_device: bool = False):
        """Chain the segments left on the device by the crossings kernel (``layer_counts``: the number of segments
        of each layer when known, i.e. of facets crossing it, as ``slicer._batches`` counts them; else counted here;
        ``mesh_on_device``: the call before uploaded this mesh's edges and nothing has used this driver since, as in
        the slicer's later layer batches under :meth:`~gpuslice.device.Device.exclusive`).

        Returns (None, chain_offsets, chain_closed, chain_layer, starts, zero_length, resident): the chains (their
        segments are not returned: the caller needs their points) and, per position in chain order, its segment's
        start point ((S,) complex64, x + iy mm) and whether that segment has zero length ((S,) bool); ``resident``:
        the points are also on the device in that order (for :meth:`simple_loops`). None when the mesh needs the
        host's general pairing (a slot with several segments starting or ending: non-manifold or flipped facets) or
        leaves open chains to repair; the caller then fetches the segments and chains them on the host.
        """
        import pyopencl as cl

        q = self.device.queue
        n = dseg.n
        n_edges = int(mesh.edge_vertices.shape[0])
        d_vub = dseg.kernel.buffer("vub")
        d_ev = self.buffer("edge_vertices") if mesh_on_device else self._put("edge_vertices", mesh.edge_vertices)
        d_k0 = self._buffer("k0", 4 * n_edges)
        d_count = self._buffer("edge_count", 4 * n_edges)
        self._edge_ranges(q, *self._grid(n_edges), d_vub, d_ev, np.int32(n_edges), d_k0, d_count)
        count = np.empty(n_edges, dtype=np.int32)
        cl.enqueue_copy(q, count, d_count)
        n_slots = int(count.sum(dtype=np.int64))
        if n_slots >= 2**31 - 1:
            return None
        # each edge's first slot, the exclusive prefix sum: in int32 (the total fits), one pass and no int64 copies
        # (done per batch over every edge of the mesh: with int64 temporaries, 1.0 of 1.8 s of chaining 6.4M facets)
        off = np.empty_like(count)
        off[:1] = 0
        np.cumsum(count[:-1], dtype=np.int32, out=off[1:])
        d_off = self._put("edge_off", off)
        d_starter = self._fill("starter", 4 * n_slots, np.int32(-1))
        d_end = self._buffer("end_slot", 4 * n)
        known = layer_counts is not None and layer_counts.size == n_layers and int(layer_counts.sum()) == n
        d_parts = self._fill("part_count", 4 * STRIPES * n_layers, np.int32(0))
        d_conflict = self._fill("conflict", 4, np.int32(0))
        d_next = self._buffer("next", 4 * n)  # (the segments' ranks in their layer's part, then their successors)
        grid = self._grid(n)
        self._place(q, *grid, dseg.layer, dseg.edges, np.int32(n), d_k0, d_off, d_starter, d_end,
                    d_parts, np.int32(n_layers), d_next, d_conflict)
        conflict = np.zeros(1, dtype=np.int32)
        layer_off = np.zeros(n_layers + 1, dtype=np.int64)
        if known:  # the conflict flag is read with the walk's results (the walk skips everything when it is set)
            np.cumsum(layer_counts, out=layer_off[1:])
            d_loff = self._put("layer_off", layer_off)
            self._starts(q, *self._grid(n_layers), d_parts, np.int32(n_layers), d_loff, d_loff, np.int32(0),
                         d_conflict)
        else:
            lcount = np.empty(n_layers, dtype=np.int32)
            d_totals = self._buffer("layer_count", 4 * n_layers)
            self._starts(q, *self._grid(n_layers), d_parts, np.int32(n_layers), d_totals, d_totals,
                         np.int32(1), d_conflict)
            self._read((conflict, d_conflict), (lcount, d_totals))
            if conflict[0]:
                return None
            np.cumsum(lcount, out=layer_off[1:])
            d_loff = self._put("layer_off", layer_off)
        d_perm = self._buffer("perm", 4 * n)
        self._link(q, *grid, dseg.layer, d_end, np.int32(n), d_starter, d_loff, d_parts, np.int32(n_layers), d_next,
                   d_perm, d_conflict)
        # (every chain closed, so the walk reads no predecessor flags: `next` stands in for them)
        flag, starts, zero = self._run_walk(d_next, d_next, d_perm, d_loff, n, n_layers, True, dseg.points,
                                            d_conflict)
        cl.enqueue_copy(q, conflict, d_conflict, is_blocking=True)  # (the queue is done: the walk's results are read)
        if conflict[0]:
            return None  # several segments at one slot, open chains (or wrong layer counts): chained on the host
        # the walk left the loops in the canonical order (by layer, then smallest segment: every chain is closed)
        first = np.flatnonzero(flag != 0)  # (a bool mask: ~10x faster than on the uint8 flags)
        offsets = np.empty(first.size + 1, dtype=np.int64)
        offsets[:-1], offsets[-1] = first, n
        chain_layer = (np.searchsorted(layer_off, first, side="right") - 1).astype(np.int32)
        return None, offsets, np.ones(first.size, dtype=bool), chain_layer, starts, zero, True

    def chunk_boxes(self, points: np.ndarray, offsets: np.ndarray, *, resident: bool = False, wait: bool = True):
        """(C, 4) float32 boxes (x min, y min, x max, y max) of the chunks of every closed loop
        ``points[offsets[r]:offsets[r + 1]]`` (float32 (P, 2), mm) as :func:`gpuslice.ragged.loop_chunks` lays them
        out: what :class:`gpuslice.slicing.contain.Chunks` computes on the host (its twin), made by ``chunk_boxes``
        in ``kernels/walk.cl`` (the same values; where +0.0 and -0.0 tie, either may be kept). None when there are
        no points or a loop has none. ``resident``: the points are on the device already (:meth:`chain_on_device`);
        else they are uploaded and stay there (for :meth:`simple_loops`). Without ``wait``, returns at once a
        callable that waits for the answer."""
        counts = np.diff(offsets)
        if counts.size == 0 or points.shape[0] == 0 or counts.min() < 1:  # (a loop without points: the host cuts)
            return None
        _, _, start, end, nxt = loop_chunks(offsets)
        n = int(start.size)
        d_box = self._buffer("chunk_box", 16 * n)
        self._boxes(self.device.queue, *self._grid(n), self._loop_points(points, resident),
                    self._put("chunk_start", start), self._put("chunk_end", end), self._put("chunk_next", nxt),
                    np.int32(n), d_box)
        return self._fetch(np.empty((n, 4), dtype=np.float32), d_box, wait)

    def simple_loops(self, points: np.ndarray, offsets: np.ndarray, *, resident: bool = False, wait: bool = True):
        """(R,) bool: True for each loop ``points[offsets[r]:offsets[r + 1]]`` (float32 (P, 2), mm, closed) that
        ``simple_loops`` in ``kernels/walk.cl`` proves simple (no two edges meet but consecutive ones at their
        vertex); False where it may cross or touch itself. None when the device lacks float64 (no screen).
        ``resident``: the points are already on the device, as :meth:`chain_on_device` left them. Without
        ``wait``, returns at once a callable that waits for the device's answer and returns it (the kernel runs
        while the host does other work)."""
        n = int(offsets.size) - 1
        if self._simple is None:
            return None
        if n <= 0 or points.shape[0] == 0:
            return np.zeros(max(n, 0), dtype=bool)
        d_offsets = self._put("loop_offsets", offsets.astype(np.int64, copy=False))
        d_simple = self._buffer("simple", n)
        self._simple(self.device.queue, *self._task_grid(n), self._loop_points(points, resident), d_offsets,
                     np.int32(n), d_simple)
        return self._fetch(np.empty(n, dtype=bool), d_simple, wait)

    def _loop_points(self, points: np.ndarray, resident: bool):
        """The device buffer ``loop_points``: as :meth:`chain_on_device` left it (``resident``), else ``points``
        uploaded into it (where they stay for the next kernel)."""
        if resident:
            return self.buffer("loop_points")
        return self._put("loop_points", np.ascontiguousarray(points, dtype=np.float32))

    def _fetch(self, out: np.ndarray, d_buf, wait: bool):
        """``out`` read from ``d_buf`` after what the queue holds: filled (``wait``), or at once a callable that
        waits for the read and returns it (the kernel runs while the host does other work)."""
        import pyopencl as cl

        q = self.device.queue
        done = cl.enqueue_copy(q, out, d_buf, is_blocking=wait)
        if wait:
            return out
        q.flush()

        def result() -> np.ndarray:
            done.wait()
            return out

        return result


def chain_kernels(device) -> ChainKernels:
    """The :class:`ChainKernels` of ``device`` (built once per device)."""
    return ChainKernels.of(device)


def walk_chains(nxt: np.ndarray, layer: np.ndarray, n_layers: int, device):
    """Chains of the successor graph ``nxt`` on ``device``: (order, chain_offsets, chain_closed) as
    :func:`gpuslice.chain.order_chains` returns them."""
    return chain_kernels(device).walk(nxt, layer, n_layers)
