"""Stage 5: nesting closed loops into polygons with holes, under a fill rule.

Loops arrive oriented by the mesh's winding (material on the left: counter-clockwise around material seen from
+z for an outward-wound mesh). For each closed loop we find the loops of its layer that contain it (a point of its
first edge tested against their winding number; candidates from a bounding-box R-tree, shapely's ``STRtree``), and
from the orientations of the containing loops the winding number w just outside it; just inside it is
``w + s`` (s = +1 counter-clockwise, -1 clockwise). The fill rule decides which side is filled:

- ``nonzero`` (default): filled where w != 0;
- ``evenodd``: filled where the number of loops around a point is odd (orientation ignored);
- ``positive``: filled where w > 0.

A loop with the filled side inside is an outer contour, with the filled side outside a hole; a loop with the same
fill on both sides bounds nothing and is dropped (``unfilled_loops``). Outer contours are then made
counter-clockwise and holes clockwise, each hole is attached to the smallest outer contour around it, and loops are
ordered per layer as polygons (outer, then its holes), with open chains last. Areas are exact shoelace sums in
float64. Layers whose loops cross each other (overlapping bodies) or themselves are then rebuilt exactly by
:mod:`gpuslice.slicing.overlaps` (:func:`~gpuslice.slicing.overlaps.resolve_overlaps`).
"""

from __future__ import annotations

import numpy as np

from ..errors import ParameterError
from ..ragged import expand_ranges, isin_ints, unique_ints
from .chain import Loops
from .contain import containment_pairs
from .rings import (
    BESIDE_MIN_POINTS,
    Nested,
    _as_complex,
    _polygons,
    beside,
    filled,
    in_halves,
    move_chains,
    signed_areas,
)

__all__ = ["FILL_RULES", "Nested", "signed_areas", "nest_loops"]

FILL_RULES = ("nonzero", "evenodd", "positive")


def _loop_boxes(points: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (R, 2) float64 corners of each loop's box (every loop has a point: reduceat over the starts)."""
    starts = offsets[:-1]
    cols = [np.ascontiguousarray(points[:, k]) for k in (0, 1)]  # (reduceat runs ~2x faster on contiguous data)
    lo = np.stack([np.minimum.reduceat(c, starts) for c in cols], axis=1).astype(np.float64)
    hi = np.stack([np.maximum.reduceat(c, starts) for c in cols], axis=1).astype(np.float64)
    return lo, hi


def _containment_pairs(points, pc, offsets, layer, closed, q, area, chunk_boxes=None):
    """Pairs (i, j), i != j, both closed and in the same layer, where loop j contains loop i's query point; the
    layers and loops whose boundaries may cross; the polygons made for the tests and their loops (sorted; (None,
    None) when numpy made the tests, :func:`~gpuslice.slicing.contain.containment_pairs`); the loops' boxes (None
    when no layer has two closed loops: then nothing is tested, and shapely is not imported). ``chunk_boxes``:
    the device's boxes of the loops' chunks (:attr:`~gpuslice.slicing.chain.Loops.chunk_boxes`), or None, or a
    callable giving them (called only when a layer has two closed loops)."""
    idx = np.flatnonzero(closed)
    # (the tree below keeps every loop: the order of its answers decides ties between equal-area parents)
    if idx.size < 2 or np.bincount(layer[idx]).max() < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty, empty, (None, empty), None
    fast = containment_pairs(points, pc, offsets, layer, idx, q, area, chunk_boxes)
    if fast is not None:
        return (*fast[:4], (None, None), fast[4])
    import shapely

    lo, hi = _loop_boxes(points, offsets)
    # separate the layers along y so one tree serves all of them
    span = float(np.max(hi[idx, 1]) - np.min(lo[idx, 1])) + 1.0
    shift = layer.astype(np.float64) * span * 2.0
    boxes = shapely.box(lo[idx, 0], lo[idx, 1] + shift[idx], hi[idx, 0], hi[idx, 1] + shift[idx])
    tree = shapely.STRtree(boxes)
    qpts = shapely.points(q.real[idx], q.imag[idx] + shift[idx])
    qi, tj = tree.query(qpts, predicate="intersects")
    pi, pj = idx[qi], idx[tj]
    keep = pi != pj
    pi, pj = pi[keep], pj[keep]
    # pairs whose boxes overlap without one holding the other: loops that may cross (overlapping bodies)
    bi, bj = tree.query(boxes, predicate="intersects")
    bi, bj = idx[bi], idx[bj]
    up = bi < bj
    bi, bj = bi[up], bj[up]
    holds = lambda a, b: np.all((lo[a] <= lo[b]) & (hi[b] <= hi[a]), axis=1)  # noqa: E731
    inner_ij, inner_ji = holds(bi, bj), holds(bj, bi)  # j's box inside i's, i's inside j's
    partial = ~inner_ij & ~inner_ji
    # nested boxes: the inner loop (a) and the outer one (b), checked below when a's query point is not inside b
    a = np.where(inner_ji, bi, bj)[~partial]
    b = np.where(inner_ji, bj, bi)[~partial]
    bi, bj = bi[partial], bj[partial]
    # containment: the query point of loop i strictly inside loop j (GEOS point-in-polygon, in C), polygons made
    # only for the loops j tested
    involved = unique_ints(pj)
    polys = _polygons(points, offsets, involved, pc)
    held, counts = polys[np.searchsorted(involved, pj)], np.diff(offsets)
    inside = in_halves(shapely.contains_xy, counts[pj], held, q.real[pi], q.imag[pi])
    n = offsets.size - 1
    out = ~isin_ints(a * n + b, pi[inside] * n + pj[inside])  # box within b's, query point not inside b
    a, b = a[out], b[out]
    bi, bj = np.concatenate([bi, a]), np.concatenate([bj, b])
    if bi.size:  # exact test on the partial pairs and those: do their boundaries meet (a point on the other)?
        both = unique_ints(bi, bj)
        have = isin_ints(both, involved)  # the polygons made above serve; the others are made here
        rings = np.empty(both.size, dtype=object)
        rings[have] = shapely.get_exterior_ring(polys[np.searchsorted(involved, both[have])])
        rings[~have] = shapely.get_exterior_ring(_polygons(points, offsets, both[~have], pc))
        meet = in_halves(shapely.intersects, counts[bi] + counts[bj], rings[np.searchsorted(both, bi)],
                         rings[np.searchsorted(both, bj)])
        bi, bj = bi[meet], bj[meet]
    return pi[inside], pj[inside], unique_ints(layer[bi]), unique_ints(bi, bj), (polys, involved), (lo, hi)


def nest_loops(loops: Loops, n_layers: int, fill_rule: str = "nonzero") -> Nested:
    """Classify, orient, group and order ``loops`` into polygons with holes (see the module docstring)."""
    if fill_rule not in FILL_RULES:
        raise ParameterError(f"unknown fill rule '{fill_rule}' (use {', '.join(FILL_RULES)})")
    points, offsets, layer, closed = loops.points, loops.offsets, loops.layer, loops.closed
    n = layer.size
    counts = np.diff(offsets)
    pc = _as_complex(points)
    area = np.where(closed, signed_areas(points, offsets, pc), 0.0)
    s = np.sign(area).astype(np.int64)
    # query point: the midpoint of each loop's first edge
    q = np.zeros(n, dtype=np.complex128)
    if n and points.size:
        first = offsets[:-1]
        q = (pc[first] + pc[np.where(counts >= 2, first + 1, first)]) / 2
    # the loops that cross themselves (GEOS, after the device's screen), beside the containment tests when large
    crossing_of = lambda: _self_crossing_loops(points, offsets, closed, loops.simple, pc)  # noqa: E731
    crossing_f = beside(crossing_of) if points.shape[0] >= BESIDE_MIN_POINTS else None
    ci, cj, crossing_layers, seeds, (polys, involved), boxes = _containment_pairs(points, pc, offsets, layer,
                                                                                  closed & (s != 0), q, area,
                                                                                  lambda: loops.chunk_boxes)
    w_out = np.bincount(ci, weights=s[cj], minlength=n).astype(np.int64)
    depth = np.bincount(ci, minlength=n)
    # the fill just outside each loop and just inside it (even-odd: one more loop around the point)
    count, step = (depth, 1) if fill_rule == "evenodd" else (w_out, s)
    out_f, in_f = filled(count, fill_rule), filled(count + step, fill_rule)
    boundary = closed & (s != 0) & (out_f != in_f)
    is_hole = boundary & out_f
    is_outer = boundary & in_f
    unfilled = closed & ~boundary
    # parent of a hole: the smallest outer contour containing it
    parent = np.full(n, -1, dtype=np.int64)
    m = is_hole[ci] & is_outer[cj]
    if m.any():
        hi_, hj = ci[m], cj[m]
        o = np.lexsort((np.abs(area[hj]), hi_))
        hi_, hj = hi_[o], hj[o]
        firsts = np.ones(hi_.size, dtype=bool)
        firsts[1:] = hi_[1:] != hi_[:-1]
        parent[hi_[firsts]] = hj[firsts]
    # orientation: outer counter-clockwise, holes clockwise
    flip = (is_outer & (area < 0)) | (is_hole & (area > 0))
    # order: per layer, polygon by polygon (outer then its holes), open chains last; drop non-boundary loops
    keep = boundary | ~closed
    poly_key = np.where(is_hole & (parent >= 0), parent, np.arange(n))
    kind = np.where(is_hole, 1, 0) + np.where(~closed, 2, 0)
    group = np.where(~closed, 1, 0)
    order = np.lexsort((np.arange(n), kind, poly_key, group, layer))
    order = order[keep[order]]
    new_index = np.full(n, -1, dtype=np.int64)
    new_index[order] = np.arange(order.size)
    new_counts = counts[order]
    new_offsets = np.zeros(order.size + 1, dtype=np.int64)
    np.cumsum(new_counts, out=new_offsets[1:])
    rev = np.flatnonzero(flip[order])
    pz = points.view(np.complex64).reshape(-1)
    if rev.size <= 64:  # (the usual case: runs of loops copied as slices, the few reversed ones turned after)
        (out_z,) = move_chains(offsets[:-1][order], new_offsets, (pz,))
        for a, b in zip(new_offsets[rev].tolist(), new_offsets[rev + 1].tolist(), strict=True):
            out_z[a:b] = out_z[a:b][::-1].copy()
    else:
        out_z = np.take(pz, _gather_index(offsets[:-1][order], new_counts, new_offsets, flip[order]))
    out_points = out_z.view(np.float32).reshape(-1, 2)
    out_layer = layer[order].astype(np.int32)
    out_parent = np.where(parent[order] >= 0, new_index[np.maximum(parent[order], 0)], -1).astype(np.int32)
    layer_offsets = np.zeros(n_layers + 1, dtype=np.int64)
    np.cumsum(np.bincount(out_layer, minlength=n_layers), out=layer_offsets[1:])
    abs_area = np.abs(area)
    layer_area = np.bincount(layer[is_outer], weights=abs_area[is_outer], minlength=n_layers) - np.bincount(
        layer[is_hole], weights=abs_area[is_hole], minlength=n_layers
    )
    layer_area = layer_area.astype(np.float64)  # (numpy's bincount of nothing is int64, weights or not)
    nested = Nested(
        points=out_points,
        loop_offsets=new_offsets,
        layer_offsets=layer_offsets,
        loop_layer=out_layer,
        loop_is_hole=is_hole[order],
        loop_parent=out_parent,
        loop_closed=closed[order],
        area=layer_area,
        unfilled_loops=np.bincount(layer[unfilled], minlength=n_layers).astype(np.int32),
        overlaps_resolved=np.zeros(n_layers, dtype=np.int32),
        reoriented=np.bincount(layer[flip], minlength=n_layers).astype(np.int32),
    )
    # layers where loops cross: two loops whose boxes overlap partially and whose boundaries meet, or an unfilled
    # loop (a sign of misclassification) whose boundary meets one of the loops containing it
    suspect = crossing_layers
    m = unfilled[ci]
    if m.any():
        import shapely

        u, c = ci[m], cj[m]
        cnt = np.diff(offsets)[u]
        ring_of, sel = expand_ranges(offsets[:-1][u], cnt)
        u_rings = shapely.linearrings(points[sel].astype(np.float64), indices=ring_of)
        if polys is None:  # (numpy made the containment tests: the containing loops' polygons made here)
            involved = unique_ints(c)
            polys = _polygons(points, offsets, involved, pc)
        meet = shapely.intersects(u_rings, shapely.get_exterior_ring(polys[np.searchsorted(involved, c)]))
        suspect = unique_ints(suspect, layer[u[meet]])
        seeds = unique_ints(seeds, np.concatenate([u[meet], c[meet]]))
    # and layers with a loop that crosses itself (cut through self-intersecting facets): its signed area is not the
    # area it bounds
    # (a loop whose lobes cancel, net area 0, included: it is not degenerate, it bounds both lobes)
    crossing = crossing_of() if crossing_f is None else crossing_f.result()
    suspect = unique_ints(suspect, layer[crossing])
    seeds = unique_ints(seeds, crossing)
    if suspect.size:
        rings = closed & (s != 0)
        rings[crossing] = True
        from .overlaps import resolve_overlaps

        nested = resolve_overlaps(nested, points, pc, offsets, layer, rings, suspect, fill_rule, n_layers, seeds,
                                  new_index, area, unfilled, boxes or _loop_boxes(points, offsets))
    return nested


def _gather_index(src_start: np.ndarray, counts: np.ndarray, new_offsets: np.ndarray, rev: np.ndarray) -> np.ndarray:
    """Source point of every output point when output loop k takes ``counts[k]`` points from ``src_start[k]``,
    reversed where ``rev[k]``. Output loops whose sources follow each other form runs that shift by one amount
    (most loops keep their place: one add per point), and only the reversed loops' points are computed apart."""
    total = int(new_offsets[-1])
    first = np.ones(src_start.size, dtype=bool)
    first[1:] = src_start[1:] != src_start[:-1] + counts[:-1]
    runs = np.flatnonzero(first)
    run_points = np.diff(np.append(new_offsets[runs], total))
    src = np.arange(total, dtype=np.int64) + np.repeat(src_start[runs] - new_offsets[runs], run_points)
    flipped = np.flatnonzero(rev)
    if flipped.size:
        owner, dst = expand_ranges(new_offsets[flipped], counts[flipped])
        src[dst] = (src_start[flipped] + counts[flipped] - 1 + new_offsets[flipped])[owner] - dst
    return src


def _self_crossing_loops(points: np.ndarray, offsets: np.ndarray, closed: np.ndarray,
                         simple: np.ndarray | None = None, pc: np.ndarray | None = None) -> np.ndarray:
    """The closed loops that cross or touch themselves: GEOS's validity reasons "Self-intersection" and "Ring
    Self-intersection" (a ring through one of its own points: its lobes may wind the same way twice, and then its
    signed area counts their overlap twice, or opposite ways) of every loop of four points or more as a
    polygon, at once (about 50 ns a point on the 2-core VM, two thirds of it making the polygons), skipping the loops
    ``simple`` marks as proven simple (the device's screen, ``Loops.simple``). Returns their indices."""
    counts = np.diff(offsets)
    test = closed & (counts >= 4)  # a triangle cannot cross itself
    if simple is not None:
        test &= ~simple
    ids = np.flatnonzero(test)
    if ids.size == 0:
        return ids
    import shapely

    reason = shapely.is_valid_reason(_polygons(points, offsets, ids, pc))  # one validity pass ("Valid Geometry")
    return ids[np.array([r.startswith(("Self-intersection", "Ring Self-intersection")) for r in reason.tolist()],
                        dtype=bool)]

