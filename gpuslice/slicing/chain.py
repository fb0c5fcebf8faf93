"""Stage 4: chaining segments into loops by the mesh's edge ids (exact topology, no coordinate rounding).

Every mesh edge e crosses a contiguous range of layers ``[k0(e), k1(e))`` (its endpoints' z bracket the planes);
a prefix sum over edges gives every (edge, layer) crossing its own *slot*. A segment starts at one slot and ends at
another. On a closed, consistently wound mesh each slot is the end of exactly one segment and the start of exactly
one other, so the successor of every segment is found with one scatter and one gather, no sort (a direct-address
table). Where a slot has several segments ending and starting (non-manifold edges shared by 4 or 6 facets), the
i-th segment ending there is paired with the i-th starting there (by segment index). What cannot be paired is an
open end.

Loops are then put in a canonical order: per layer, open chains from their head (the segment without
predecessor) by increasing head, then closed loops from their smallest segment index, increasing; so the output
does not depend on how the walk ran (numpy pointer jumping or the OpenCL walk of ``kernels/walk.cl``). Each
loop's points are the start points of its segments (plus the end point of the last one for open chains). A
zero-length segment (the plane through a vertex, Fig. 3a) starts where its successor starts, so its point is
skipped: no loop holds consecutive duplicate points. Closed loops left with fewer than three points are dropped
as degenerate (``degenerate_loops``).

Repairs of open chains, per layer, in this order (counted by kind):
``joined_by_id``: two free ends on the same slot are joined, reversing a chain (a facet wound against its neighbour
where its shell could not be turned outward first, :func:`gpuslice.mesh.defects.wound_for_slicing`: a
non-orientable shell, a non-manifold edge);
``gap_closed``: the nearest free ends closer than ``max_gap`` mm are joined, closest first (a chain's own two ends
included, as the free ends are all candidates alike). Chains still open are kept as open chains and reported. A loop
closed by these joins goes the way most of its segments go (the mesh's winding), whichever chain its walk began on.
All layers are repaired at once (:func:`_repair`: a triangle soup's layers are all open chains).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..mesh.mesh import Mesh
from ..ragged import expand_ranges
from .crossings import Segments, vertex_layers

__all__ = ["Loops", "link_segments", "order_chains", "chain_segments", "REPAIR_KINDS"]

REPAIR_KINDS = ("joined_by_id", "reversed", "gap_closed", "open_chains", "degenerate_loops")


@dataclass
class Loops:
    """Chained loops before nesting: ``points`` (P, 2) float32, ``offsets`` (R + 1,) int64, ``layer`` (R,)
    int32, ``closed`` (R,) bool, per-layer repair counts, :attr:`simple` and :attr:`chunk_boxes`. ``screen`` and
    ``boxes`` hold the device's answers, or callables that wait for them: the device computes them while the host
    goes on."""

    points: np.ndarray
    offsets: np.ndarray
    layer: np.ndarray
    closed: np.ndarray
    repairs: dict[str, np.ndarray] = field(default_factory=dict)
    screen: np.ndarray | Callable[[], np.ndarray | None] | None = None
    boxes: np.ndarray | Callable[[], np.ndarray] | None = None

    @property
    def chunk_boxes(self) -> np.ndarray | None:
        """(C, 4) float32 boxes of the loops' chunks for nesting's containment tests, as
        :class:`gpuslice.slicing.contain.Chunks` would compute them (None: no device made them; the host does).
        Waits for the device the first time."""
        if callable(self.boxes):
            self.boxes = self.boxes()
        return self.boxes

    @property
    def simple(self) -> np.ndarray | None:
        """(R,) bool or None: True for the loops the device's screen (``simple_loops`` in ``kernels/walk.cl``)
        proved simple, so nesting need not test them for self-crossings (None: no screen ran; every loop is
        tested). Waits for the device the first time, where the screen still runs there."""
        if callable(self.screen):
            self.screen = self.screen()
        return self.screen


def edge_slots(mesh: Mesh, zs: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Per edge: its first crossed layer ``k0`` and slot offset; and the total number of slots."""
    ev = vertex_layers(mesh, zs)[mesh.edge_vertices]
    k0 = ev.min(axis=1)
    count = (ev.max(axis=1) - k0).astype(np.int64)
    off = np.cumsum(count) - count
    return k0, off, int(count.sum())


def link_segments(seg: Segments, mesh: Mesh, zs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Successor of every segment (-1 where none), and each segment's start and end slot.

    Returns ``next`` (S,) int32, ``start_slot`` (S,) int64, ``end_slot`` (S,) int64.
    """
    k0, off, n_slots = edge_slots(mesh, zs)
    e0, e1 = seg.edges[:, 0], seg.edges[:, 1]
    start = off[e0] + (seg.layer - k0[e0])
    end = off[e1] + (seg.layer - k0[e1])
    n = len(seg)
    n_start = np.bincount(start, minlength=n_slots)
    n_end = np.bincount(end, minlength=n_slots)
    if n == 0 or (n_start.max() <= 1 and n_end.max() <= 1):
        starter = np.full(n_slots, -1, dtype=np.int32)
        starter[start] = np.arange(n, dtype=np.int32)
        return starter[end], start, end
    # general pairing: the i-th segment ending at a slot continues with the i-th segment starting there
    s_order = np.argsort(start, kind="stable").astype(np.int32)
    e_order = np.argsort(end, kind="stable")
    s_first = np.cumsum(n_start) - n_start
    e_first = np.cumsum(n_end) - n_end
    sorted_end = end[e_order]
    rank = np.arange(n, dtype=np.int64) - e_first[sorted_end]
    ok = rank < n_start[sorted_end]
    nxt = np.full(n, -1, dtype=np.int32)
    nxt[e_order[ok]] = s_order[s_first[sorted_end[ok]] + rank[ok]]
    return nxt, start, end


def order_chains(nxt: np.ndarray, layer: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut the successor graph into chains in canonical order (numpy pointer jumping, O(S log S)).

    Returns ``order`` (S,) int32 (segments chain after chain), ``chain_offsets`` (C + 1,) int64 and
    ``chain_closed`` (C,) bool. Per layer, open chains come first, from their head (the segment without
    predecessor) in increasing head order, then closed loops, each from its smallest segment index, in increasing
    order (the order ``kernels/walk.cl`` produces).
    """
    n = nxt.shape[0]
    if n == 0:
        return np.zeros(0, np.int32), np.zeros(1, np.int64), np.zeros(0, bool)
    idx = np.arange(n, dtype=np.int32)
    has_next = nxt >= 0
    jump = np.where(has_next, nxt, idx)
    label = idx.copy()
    longest = int(np.bincount(layer).max())
    rounds = max(1, int(np.ceil(np.log2(longest + 1))))
    for _ in range(rounds):
        np.minimum(label, label[jump], out=label)
        jump = jump[jump]
    on_path = ~has_next[jump]
    # break each cycle before its smallest segment
    cut = ~on_path & (nxt == label)
    nxt2 = np.where(cut, -1, nxt)
    has_prev = np.zeros(n, dtype=bool)
    has_prev[nxt2[nxt2 >= 0]] = True
    heads = np.flatnonzero(~has_prev).astype(np.int32)
    # list ranking: distance of every segment to the end of its chain
    tail_of = np.where(nxt2 >= 0, nxt2, idx)
    dist = (nxt2 >= 0).astype(np.int32)
    for _ in range(rounds):
        dist += dist[tail_of]
        tail_of = tail_of[tail_of]
    chain_order = np.lexsort((heads, ~on_path[heads], layer[heads]))
    heads = heads[chain_order]
    lengths = dist[heads].astype(np.int64) + 1
    offsets = np.zeros(heads.size + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    chain_of_tail = np.empty(n, dtype=np.int64)
    chain_of_tail[tail_of[heads]] = np.arange(heads.size)
    c = chain_of_tail[tail_of]
    pos = offsets[c] + (lengths[c] - 1 - dist)
    order = np.empty(n, dtype=np.int32)
    order[pos] = idx
    closed = ~on_path[heads]
    return order, offsets, closed


def chain_segments(seg, mesh: Mesh, zs: np.ndarray, n_layers: int, *, max_gap: float = 2.0, device=None,
                   layer_counts: np.ndarray | None = None, mesh_on_device: bool = False) -> Loops:
    """Chain the segment buffer into loops (see the module docstring).

    ``seg``: :class:`~gpuslice.crossings.Segments` on the host, or ``DeviceSegments`` left on ``device`` by the
    crossings kernel, which are then chained on the device when the mesh allows (no slot shared by several
    segment ends, no open chain), and fetched and chained on the host otherwise. ``layer_counts``: optional (L,)
    number of facets crossing each layer (= its segments), which spares the device counting them;
    ``mesh_on_device``: the mesh's edges are on the device from the call before (:meth:`ChainKernels.chain_on_device`).
    """
    chain_layer = None
    gathered = None  # the segments' start points in chain order and their zero-length flags, from the device
    if not isinstance(seg, Segments):
        from .walk import chain_kernels

        done = chain_kernels(device).chain_on_device(seg, mesh, zs, n_layers, layer_counts, mesh_on_device)
        if done is not None:
            order, coff, cclosed, chain_layer, *gathered = done
        else:
            seg = seg.fetch()
    if chain_layer is None:
        seg_points = seg.points
        nxt, start_slot, end_slot = link_segments(seg, mesh, zs)
        if device is not None:
            from .walk import walk_chains

            order, coff, cclosed = walk_chains(nxt, seg.layer, n_layers, device)
        else:
            order, coff, cclosed = order_chains(nxt, seg.layer)
        chain_layer = seg.layer[order[coff[:-1]]] if coff.size > 1 else np.zeros(0, np.int32)
    lengths = np.diff(coff)
    n_chains = lengths.size
    if gathered is not None:  # every chain closed: the points are the segments' starts but for zero-length ones
        starts, zero_at, resident = gathered
        offsets = coff
        if zero_at.any():
            keep = ~zero_at
            kept = lengths - np.add.reduceat(zero_at.view(np.uint8), coff[:-1], dtype=np.int64)  # chains: >= 1 each
            offsets = np.zeros(n_chains + 1, dtype=np.int64)
            np.cumsum(kept, out=offsets[1:])
            starts, resident = starts[keep], False
        points = starts.view(np.float32).reshape(-1, 2)
        return _finish(points, offsets, chain_layer, cclosed, None, max_gap, n_layers, device, resident)
    # points: the start of every segment, plus the end of the last segment of open chains. A zero-length segment
    # (through a vertex on the plane) starts where its successor starts: its start point is skipped, which
    # removes every consecutive duplicate.
    # each point viewed as one complex64 (x + iy): 1-D gathers are much faster than 2-D fancy indexing
    ends = seg_points.view(np.complex64)
    first_pt, last_pt = ends[:, 0], ends[:, 1]
    zero_length = first_pt == last_pt
    open_idx = np.flatnonzero(~cclosed)
    keep_seg = None if not zero_length.any() else ~zero_length[order]
    if keep_seg is None:
        kept = lengths
        points_of = order
    else:
        chain_of = np.repeat(np.arange(n_chains), lengths)
        kept = np.bincount(chain_of[keep_seg], minlength=n_chains).astype(np.int64)
        points_of = order[keep_seg]
    extra = np.zeros(n_chains, dtype=np.int64)
    extra[open_idx] = 1
    offsets = np.zeros(n_chains + 1, dtype=np.int64)
    np.cumsum(kept + extra, out=offsets[1:])
    packed = np.empty(int(offsets[-1]), dtype=np.complex64)
    if open_idx.size == 0:
        np.take(first_pt, points_of, out=packed)
    else:
        is_extra = np.zeros(packed.size, dtype=bool)
        tails = order[coff[open_idx + 1] - 1]
        is_extra[offsets[open_idx + 1] - 1] = True
        packed[~is_extra] = first_pt[points_of]
        packed[is_extra] = last_pt[tails]
    points = packed.view(np.float32).reshape(-1, 2)
    open_ends = None
    if open_idx.size:
        heads = order[coff[open_idx]]
        open_ends = (open_idx, start_slot[heads], end_slot[tails])
    return _finish(points, offsets, chain_layer, cclosed, open_ends, max_gap, n_layers, device, False)


def _finish(points, offsets, chain_layer, cclosed, open_ends, max_gap, n_layers, device, resident) -> Loops:
    """Repairs of open chains (``open_ends``: their indices, head and tail slots), degenerate loops dropped, counts,
    and the device's self-crossing screen (``resident``: the points are still on the device)."""
    repairs = {k: np.zeros(n_layers, dtype=np.int32) for k in REPAIR_KINDS}
    if open_ends is not None:
        open_idx, head_slot, tail_slot = open_ends
        points, offsets, chain_layer, cclosed = _repair(
            points, offsets, chain_layer, cclosed, open_idx, head_slot, tail_slot, max_gap, repairs
        )
    counts = np.diff(offsets)
    degenerate = (cclosed & (counts < 3)) | (~cclosed & (counts < 2))
    if degenerate.any():
        np.add.at(repairs["degenerate_loops"], chain_layer[degenerate], 1)
        keep = ~degenerate
        pt_keep = np.repeat(keep, counts)
        points = np.ascontiguousarray(points).view(np.complex64).reshape(-1)[pt_keep].view(np.float32).reshape(-1, 2)
        offsets = np.zeros(int(keep.sum()) + 1, dtype=np.int64)
        np.cumsum(counts[keep], out=offsets[1:])
        chain_layer, cclosed = chain_layer[keep], cclosed[keep]
        resident = False
    np.add.at(repairs["open_chains"], chain_layer[~cclosed], 1)
    simple = boxes = None
    if device is not None:  # the chunks' boxes and the self-crossing screen, left running on the device (see Loops)
        from .walk import chain_kernels

        kernels = chain_kernels(device)
        if cclosed.any() and np.bincount(chain_layer[cclosed]).max() >= 2:  # (containment tests to come)
            boxes = kernels.chunk_boxes(points, offsets, resident=resident, wait=False)
            resident = resident or boxes is not None  # (the points uploaded for the boxes serve the screen)
        simple = kernels.simple_loops(points, offsets, resident=resident, wait=False)
    return Loops(points, offsets, chain_layer.astype(np.int32), cclosed, repairs, simple, boxes)


_PAIRS_LISTED = 16  # a layer's free ends with more pairs within max_gap than this many per end: _closest_first
_SMALL = 64  # a layer's free ends up to this many: every pair listed, in numpy (an open scan's holes: 2-8 a layer)


def _closest_first(xy: np.ndarray, max_gap: float, tree=None) -> np.ndarray:
    """(M, 2) index pairs of ``xy``: the greedy matching, closest pair first, of the points within ``max_gap`` of
    each other, in rounds that match every pair of mutual nearest neighbours (a locally dominant edge: the greedy
    matching's, for distances ordered with ties broken by index). Memory and time grow with the points, not with
    the pairs (a cluster of n points has ~n^2/2 of them). A round that matches under a twentieth of the points left
    (a chain of ends whose gaps shrink along it matches one pair a round: quadratic, a review found) hands the rest
    to the listed pairs' walk, the dense clusters gone by then. ``tree``: a ``cKDTree`` of ``xy`` already made (the
    first round's)."""
    from scipy.spatial import cKDTree

    left = np.arange(len(xy))
    out = []
    reach = float(np.nextafter(max_gap, np.inf))  # (the tree's bound is strict; the listed pairs take d <= max_gap)
    while left.size > 1:
        k = min(4, left.size)
        if tree is None or tree.n != left.size:
            tree = cKDTree(xy[left])
        d, nb = tree.query(xy[left], k=k, distance_upper_bound=reach)
        d, nb = d.reshape(left.size, k), nb.reshape(left.size, k)
        me = np.arange(left.size)[:, None]
        d = np.where(nb == me, np.inf, d)  # not itself (duplicates may come before it)
        nb = np.where(np.isfinite(d), nb, left.size)
        # nearest other by (distance, index)
        best = np.lexsort((nb, d), axis=1)[:, 0]
        near = nb[me[:, 0], best]
        has = near < left.size
        ext = np.append(near, -1)
        mutual = has & (ext[np.where(has, near, left.size)] == me[:, 0]) & (me[:, 0] < near)
        if not mutual.any():
            break
        a = np.flatnonzero(mutual)
        out.append(np.stack([left[a], left[near[a]]], axis=1))
        gone = np.zeros(left.size, dtype=bool)
        gone[a] = gone[near[a]] = True
        few = 20 * a.size < left.size
        left = left[~gone & has]  # ends with nothing left within max_gap stay unmatched
        if few and left.size > 1:
            out.append(_greedy_listed(xy, left, max_gap))
            break
    return np.concatenate(out) if out else np.empty((0, 2), dtype=np.int64)


def _few_pairs(xy: np.ndarray, max_gap: float, tree=None) -> bool:
    """Whether the points ``xy`` have at most :data:`_PAIRS_LISTED` pairs within ``max_gap`` per point, counted
    without listing them (a cluster of n free ends has ~n^2/2). The count's time grows with the pairs: those within a
    quarter of the gap are counted first, and where they are already too many, that is the answer (a benchy soup's
    640 layers: 0.69 s of counting against 1.16 s; where they are still few both counts are made: a bunny soup's,
    0.54 s against 0.36 s). ``tree``: a ``cKDTree`` of ``xy`` already made."""
    from scipy.spatial import cKDTree

    tree = cKDTree(xy) if tree is None else tree
    n = tree.n
    return all((int(tree.count_neighbors(tree, r)) - n) // 2 <= _PAIRS_LISTED * n for r in (max_gap / 4, max_gap))


def _greedy_listed(xy: np.ndarray, left: np.ndarray, max_gap: float) -> np.ndarray:
    """The greedy matching of the points ``left`` of ``xy`` within ``max_gap``: every pair listed, closest first,
    ties by index (the pairs (i, j), i < j, in lexicographic order before a stable sort by distance). Up to
    :data:`_SMALL` points, the pairs are all compared in numpy (no k-d tree: scipy.spatial's import alone takes
    0.3 s, most of an open scan's whole slice); the tree's pairs are the same (d^2 <= max_gap^2, as its own test)."""
    if left.size <= _SMALL:
        i, j = np.triu_indices(left.size, 1)
        dx, dy = xy[left[i], 0] - xy[left[j], 0], xy[left[i], 1] - xy[left[j], 1]
        near = dx * dx + dy * dy <= max_gap * max_gap
        pairs = np.stack([i[near], j[near]], axis=1)
    else:
        from scipy.spatial import cKDTree

        pairs = cKDTree(xy[left]).query_pairs(max_gap, output_type="ndarray")
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    d = np.linalg.norm(xy[left[pairs[:, 0]]] - xy[left[pairs[:, 1]]], axis=1)
    free, out = np.ones(left.size, dtype=bool), []
    for a, b in pairs[np.argsort(d, kind="stable")].tolist():
        if free[a] and free[b]:
            free[a] = free[b] = False
            out.append((left[a], left[b]))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def _repair(points, offsets, chain_layer, closed, open_idx, head_slot, tail_slot, max_gap, repairs):
    """Join open chains: equal slots first (reversing where needed), then nearest ends within ``max_gap``; all
    layers at once, without a Python loop per chain (a triangle soup's layers are all open chains: 0.7M of them on
    a 225k-facet one).

    Ends are numbered per open chain k (ordered by layer, stably): 2k its head, 2k + 1 its tail. In a layer, free ends
    sharing a slot are paired in turn (sorted by slot, then end); the ends still free are matched closest first
    (:func:`_greedy_listed` or :func:`_closest_first`, one call per layer). The joined chains are then the chains of
    the ends' successor graph (``next(e) = link[e ^ 1]``) that :func:`order_chains` cuts in canonical order, one of
    each component's two directions kept: a path from its smaller free end, a cycle entered at the head of its
    smallest chain. Per layer, the paths by that end, then the cycles by that chain. A cycle whose chains were walked
    against their own direction for more segments than along it is turned round: a loop goes the way the mesh's
    winding takes most of it (nesting reads holes from it: a soup's hole joined the other way round was filled). A
    point where two chains meet is kept once, and a cycle's last point is dropped where it repeats its first: no
    loop holds consecutive duplicate points.
    """
    n_layers = repairs["gap_closed"].size
    by = np.argsort(chain_layer[open_idx], kind="stable")
    chains = open_idx[by]
    m = chains.size
    e_layer = np.repeat(chain_layer[chains].astype(np.int64), 2)
    slots = np.empty(2 * m, dtype=np.int64)
    slots[0::2], slots[1::2] = head_slot[by], tail_slot[by]
    ends = np.arange(2 * m, dtype=np.int64)
    link = np.full(2 * m, -1, dtype=np.int64)
    # free ends sharing a slot, in a layer: the first with the second, the third with the fourth, ...
    o = np.lexsort((ends, slots, e_layer))
    same = (e_layer[o][1:] == e_layer[o][:-1]) & (slots[o][1:] == slots[o][:-1])
    run_start = np.ones(2 * m, dtype=bool)
    run_start[1:] = ~same
    starts = np.flatnonzero(run_start)
    rank = ends - np.repeat(starts, np.diff(np.append(starts, 2 * m)))
    a = np.flatnonzero(same & (rank[:-1] % 2 == 0))
    i, j = o[a], o[a + 1]
    link[i], link[j] = j, i
    repairs["joined_by_id"] += np.bincount(e_layer[i], minlength=n_layers).astype(repairs["joined_by_id"].dtype)
    flip = (i % 2) == (j % 2)
    repairs["reversed"] += np.bincount(e_layer[i[flip]], minlength=n_layers).astype(repairs["reversed"].dtype)
    # the ends still free, matched closest first within max_gap, layer by layer
    first, last = offsets[:-1][chains], offsets[1:][chains] - 1
    free = np.flatnonzero(link < 0)
    if free.size > 1 and max_gap > 0:
        at = np.where(free % 2 == 0, first[free >> 1], last[free >> 1])
        xy_all = points[at].astype(np.float64)
        f_layer = e_layer[free]
        cuts = np.flatnonzero(np.diff(f_layer)) + 1
        bounds = np.concatenate([[0], cuts, [free.size]]).tolist()
        for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
            if hi - lo < 2:
                continue
            xy = xy_all[lo:hi]
            if hi - lo <= _SMALL:
                matched = _greedy_listed(xy, np.arange(hi - lo), max_gap)
            else:  # (one tree of the layer's free ends: counted, then the first round of _closest_first's)
                from scipy.spatial import cKDTree

                tree = cKDTree(xy)
                matched = (_greedy_listed(xy, np.arange(hi - lo), max_gap) if _few_pairs(xy, max_gap, tree)
                           else _closest_first(xy, max_gap, tree))
            if len(matched):
                i, j = free[lo:hi][matched[:, 0]], free[lo:hi][matched[:, 1]]
                link[i], link[j] = j, i
            repairs["gap_closed"][int(f_layer[lo])] += len(matched)
    # the joined chains: chains of the ends' successor graph, one direction of each
    nxt = link[ends ^ 1].astype(np.int32)
    order, seq_off, seq_closed = order_chains(nxt, e_layer)
    head, tail = order[seq_off[:-1]].astype(np.int64), order[seq_off[1:] - 1].astype(np.int64)
    kept = np.where(seq_closed, head % 2 == 0, head < (tail ^ 1))
    n_seq = np.diff(seq_off)[kept]
    _, at = expand_ranges(seq_off[:-1][kept], n_seq)
    e = order[at].astype(np.int64)  # the kept chains' entering ends, in output order
    k = e >> 1
    size = last[k] - first[k] + 1
    owner, step = expand_ranges(np.zeros(e.size, dtype=np.int64), size)
    pt = np.where(e[owner] % 2 == 0, first[k][owner] + step, last[k][owner] - step)
    seq_of = np.repeat(np.arange(n_seq.size), n_seq)
    new_count = np.bincount(seq_of, weights=size, minlength=n_seq.size).astype(np.int64)
    new_closed = seq_closed[kept]
    new_end = np.cumsum(new_count)
    # a closed loop goes the way most of its segments go (the mesh's winding), not the way its walk began
    along = np.bincount(seq_of, weights=np.where(e % 2 == 0, size - 1, 1 - size), minlength=n_seq.size)
    turn = new_closed & (along < 0)
    if turn.any():
        p_seq = np.repeat(np.arange(n_seq.size), new_count)
        pos = np.arange(pt.size)
        pt = pt[np.where(turn[p_seq], 2 * new_end[p_seq] - new_count[p_seq] - 1 - pos, pos)]
    c_pts = np.ascontiguousarray(points).view(np.complex64).reshape(-1)
    # where two chains meet on one point (joined by slot, or ends that coincide) it is kept once
    z = c_pts[pt]
    again = np.zeros(pt.size, dtype=bool)
    again[1:] = z[1:] == z[:-1]
    again[new_end[:-1]] = False  # (a chain's first point never repeats the chain before)
    if again.any():
        pt = pt[~again]
        new_count = new_count - np.bincount(np.repeat(np.arange(n_seq.size), new_count)[again], minlength=n_seq.size)
        new_end = np.cumsum(new_count)
    seq_first, seq_last = pt[new_end - new_count], pt[new_end - 1]
    drop = new_closed & (new_count > 1) & (c_pts[seq_first] == c_pts[seq_last])
    if drop.any():
        keep_pt = np.ones(pt.size, dtype=bool)
        keep_pt[(new_end - 1)[drop]] = False
        pt = pt[keep_pt]
        new_count = new_count - drop
    new_layer = e_layer[order[seq_off[:-1]][kept]].astype(chain_layer.dtype)
    keep = np.ones(closed.size, dtype=bool)
    keep[open_idx] = False
    counts = np.diff(offsets)
    all_counts = np.concatenate([counts[keep], new_count]).astype(np.int64)
    all_layer = np.concatenate([chain_layer[keep], new_layer])
    all_closed = np.concatenate([closed[keep], new_closed])
    # restore the per-layer order: stable by layer, repaired chains after the layer's closed loops
    order = np.argsort(all_layer, kind="stable")
    src = np.concatenate([np.flatnonzero(np.repeat(keep, counts)), pt])
    starts = np.concatenate([[0], np.cumsum(all_counts)])
    new_offsets = np.zeros(order.size + 1, dtype=np.int64)
    np.cumsum(all_counts[order], out=new_offsets[1:])
    idx = np.arange(int(new_offsets[-1])) + np.repeat(starts[order] - new_offsets[:-1], all_counts[order])
    return c_pts[src[idx]].view(np.float32).reshape(-1, 2), new_offsets, all_layer[order], all_closed[order]
