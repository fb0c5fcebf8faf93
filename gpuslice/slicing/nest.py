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
float64. Loops that cross each other (overlapping bodies) are not merged here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..ragged import expand_ranges
from .chain import Loops

__all__ = ["FILL_RULES", "Nested", "signed_areas", "nest_loops"]

FILL_RULES = ("nonzero", "evenodd", "positive")


@dataclass
class Nested:
    points: np.ndarray
    loop_offsets: np.ndarray
    layer_offsets: np.ndarray
    loop_layer: np.ndarray
    loop_is_hole: np.ndarray
    loop_parent: np.ndarray
    loop_closed: np.ndarray
    area: np.ndarray
    unfilled_loops: np.ndarray
    overlaps_resolved: np.ndarray


def _as_complex(points: np.ndarray) -> np.ndarray:
    """(P,) complex128 view-copy x + iy of (P, 2) float32 points (1-D gathers are fast, 2-D fancy indexing is not)."""
    return np.ascontiguousarray(points, dtype=np.float32).view(np.complex64).reshape(-1).astype(np.complex128)


def signed_areas(points: np.ndarray, offsets: np.ndarray, pc: np.ndarray | None = None) -> np.ndarray:
    """(R,) float64 shoelace area of each loop, mm^2, positive for counter-clockwise.

    Products of float32 coordinates are exact in float64, so the sum is accurate to ~1e-16 of the coordinates'
    squared magnitude per point (1e-10 mm^2 for a 100 mm part with a million points).
    """
    n = offsets.size - 1
    if points.shape[0] == 0 or n == 0:
        return np.zeros(n)
    pc = _as_complex(points) if pc is None else pc
    nxt = np.empty_like(pc)
    nxt[:-1] = pc[1:]
    first, last = offsets[:-1], offsets[1:] - 1
    nxt[last] = pc[first]
    cross = (pc.conj() * nxt).imag
    return np.add.reduceat(cross, first) / 2.0


def _winding_numbers(pc, offsets, pairs_i, pairs_j, q) -> np.ndarray:
    """Winding number of query point q[i] (complex) around loop j for every pair (i, j)."""
    counts = np.diff(offsets)
    lens = counts[pairs_j]
    start = offsets[pairs_j]
    pair_of, a = expand_ranges(start, lens)  # every edge a -> b of loop j, once per pair
    b = np.where(a == (start + lens - 1)[pair_of], start[pair_of], a + 1)
    p = np.repeat(q[pairs_i], lens)
    pa, pb = pc[a] - p, pc[b] - p
    left = (pa.conj() * pb).imag  # > 0: the point is left of the edge a -> b
    ay, by = pa.imag, pb.imag
    contrib = ((ay <= 0) & (by > 0) & (left > 0)).astype(np.int64) - ((by <= 0) & (ay > 0) & (left < 0))
    return np.bincount(pair_of, weights=contrib, minlength=pairs_i.size).astype(np.int64)


def _loop_boxes(points: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (R, 2) float64 corners of each loop's box (every loop has a point: reduceat over the starts)."""
    starts = offsets[:-1]
    lo = np.stack([np.minimum.reduceat(points[:, k], starts) for k in (0, 1)], axis=1).astype(np.float64)
    hi = np.stack([np.maximum.reduceat(points[:, k], starts) for k in (0, 1)], axis=1).astype(np.float64)
    return lo, hi


def _containment_pairs(points, pc, offsets, layer, closed, q):
    """Pairs (i, j), i != j, both closed and in the same layer, where loop j contains loop i's query point; the
    layers and loops whose boundaries may cross; the rings made for the tests; the loops' boxes (None when no layer
    has two closed loops: then nothing is tested, and shapely is not imported)."""
    idx = np.flatnonzero(closed)
    # (the tree below keeps every loop: the order of its answers decides ties between equal-area parents)
    if idx.size < 2 or np.bincount(layer[idx]).max() < 2:
        empty = np.zeros(0, np.int64)
        return empty, empty, empty, empty, (None, empty), None
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
    # shapely rings of just the loops these tests need, built once
    involved = np.unique(np.concatenate([pj, bi, bj, a, b]))
    counts = np.diff(offsets)[involved]
    ring_of, sel = expand_ranges(offsets[:-1][involved], counts)
    rings = shapely.linearrings(points[sel].astype(np.float64), indices=ring_of)
    # containment: the query point of loop i strictly inside loop j (GEOS point-in-polygon, in C)
    polys = shapely.polygons(rings)
    inside = shapely.contains_xy(polys[np.searchsorted(involved, pj)], q.real[pi], q.imag[pi])
    n = offsets.size - 1
    out = ~np.isin(a * n + b, pi[inside] * n + pj[inside])  # box within b's, query point not inside b
    a, b = a[out], b[out]
    bi, bj = np.concatenate([bi, a]), np.concatenate([bj, b])
    if bi.size:  # exact test on the partial pairs and those: do their boundaries meet (a point on the other)?
        meet = shapely.intersects(rings[np.searchsorted(involved, bi)], rings[np.searchsorted(involved, bj)])
        bi, bj = bi[meet], bj[meet]
    return pi[inside], pj[inside], np.unique(layer[bi]), np.union1d(bi, bj), (rings, involved), (lo, hi)


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
    ci, cj, crossing_layers, seeds, (rings, involved), boxes = _containment_pairs(points, pc, offsets, layer,
                                                                                  closed & (s != 0), q)
    w_out = np.bincount(ci, weights=s[cj], minlength=n).astype(np.int64)
    depth = np.bincount(ci, minlength=n)
    if fill_rule == "nonzero":
        out_f, in_f = w_out != 0, (w_out + s) != 0
    elif fill_rule == "positive":
        out_f, in_f = w_out > 0, (w_out + s) > 0
    else:
        out_f, in_f = depth % 2 == 1, depth % 2 == 0
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
    src = _gather_index(offsets[:-1][order], new_counts, new_offsets, flip[order])
    out_points = np.take(points.view(np.complex64).reshape(-1), src).view(np.float32).reshape(-1, 2)
    out_layer = layer[order].astype(np.int32)
    out_parent = np.where(parent[order] >= 0, new_index[np.maximum(parent[order], 0)], -1).astype(np.int32)
    layer_offsets = np.zeros(n_layers + 1, dtype=np.int64)
    np.cumsum(np.bincount(out_layer, minlength=n_layers), out=layer_offsets[1:])
    abs_area = np.abs(area)
    layer_area = np.bincount(layer[is_outer], weights=abs_area[is_outer], minlength=n_layers) - np.bincount(
        layer[is_hole], weights=abs_area[is_hole], minlength=n_layers
    )
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
        meet = shapely.intersects(u_rings, rings[np.searchsorted(involved, c)])
        suspect = np.union1d(suspect, layer[u[meet]])
        seeds = np.union1d(seeds, np.concatenate([u[meet], c[meet]]))
    # and layers with a loop that crosses itself (cut through self-intersecting facets): its signed area is not the
    # area it bounds
    # (a loop whose lobes cancel, net area 0, included: it is not degenerate, it bounds both lobes)
    crossing = _self_crossing_loops(points, offsets, closed, loops.simple)
    suspect = np.union1d(suspect, layer[crossing])
    seeds = np.union1d(seeds, crossing)
    if suspect.size:
        rings = closed & (s != 0)
        rings[crossing] = True
        nested = _resolve_overlaps(nested, points, pc, offsets, layer, rings, suspect, fill_rule, n_layers, seeds,
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
                         simple: np.ndarray | None = None) -> np.ndarray:
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

    polys = _polygons(points, offsets, ids)
    bad = np.flatnonzero(~shapely.is_valid(polys))
    if bad.size == 0:
        return bad
    reason = shapely.is_valid_reason(polys[bad])
    return ids[bad[np.array([r.startswith(("Self-intersection", "Ring Self-intersection")) for r in reason],
                            dtype=bool)]]


def _polygons(points: np.ndarray, offsets: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Shapely polygons (no holes) of loops ``ids``, each ring closed by repeating its first point (float64 of the
    float32 points; the same geometry as ``shapely.polygons(shapely.linearrings(...))``, made about 3x faster)."""
    import shapely

    counts = np.diff(offsets)[ids]
    pc = np.ascontiguousarray(points, dtype=np.float32).view(np.complex64).reshape(-1)
    first = pc[offsets[:-1][ids]]
    shut = (first != pc[offsets[1:][ids] - 1]).astype(np.int64)  # 1: a closing point to add (as linearrings)
    ring_off = np.zeros(ids.size + 1, dtype=np.int64)
    np.cumsum(counts + shut, out=ring_off[1:])
    owner, sel = expand_ranges(offsets[:-1][ids], counts)
    ring = np.empty(int(ring_off[-1]), dtype=np.complex128)  # x + iy
    ring[sel - offsets[:-1][ids][owner] + ring_off[:-1][owner]] = pc[sel]
    ring[(ring_off[1:] - 1)[shut == 1]] = first[shut == 1]
    coords = ring.view(np.float64).reshape(-1, 2)
    return shapely.from_ragged_array(shapely.GeometryType.POLYGON, coords, (ring_off, np.arange(ids.size + 1)))


def _filled(w: np.ndarray, fill_rule: str) -> np.ndarray:
    if fill_rule == "nonzero":
        return w != 0
    if fill_rule == "positive":
        return w > 0
    return w % 2 != 0


def _affected(lo: np.ndarray, hi: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """Which of a layer's loops (boxes ``lo``, ``hi``, (n, 2)) can share a face of the arrangement with the
    ``seed`` loops (those that cross): the groups of loops joined by overlapping boxes that hold a seed, grown by
    every loop whose box meets a group's hull box until none does. A loop left out has a box apart from each
    group's hull, so no face of the group's arrangement (inside that hull) lies inside it or around it: its
    classification and the group's region do not depend on each other. Very crowded layers: all loops."""
    n = lo.shape[0]
    if n > 4000 or not seed.any():
        return np.ones(n, dtype=bool)
    meets = lambda a0, a1, b0, b1: np.all((a0 <= b1) & (b0 <= a1), axis=-1)  # noqa: E731  closed boxes
    ii, jj = np.nonzero(meets(lo[:, None], hi[:, None], lo[None], hi[None]))
    while True:
        label = np.arange(n)  # components: the smallest index reached, by propagation along the pairs
        while True:
            new = label.copy()
            np.minimum.at(new, ii, label[jj])
            new = new[new]
            if np.array_equal(new, label):
                break
            label = new
        groups = np.unique(label[seed])
        grown = False
        for g in groups:
            member = label == g
            touch = meets(lo, hi, lo[member].min(axis=0), hi[member].max(axis=0)) & ~member
            if touch.any():
                k = int(np.flatnonzero(member)[0])
                t = np.flatnonzero(touch)
                ii, jj = np.concatenate([ii, t, np.full(t.size, k)]), np.concatenate([jj, np.full(t.size, k), t])
                grown = True
        if not grown:
            return np.isin(label, groups)


def _resolve_overlaps(nested, points, pc, offsets, layer, closed, layers, fill_rule, n_layers, seeds, new_index,
                      loop_area, unfilled_loop, boxes):
    """Exact regions of the loops that cross, from the arrangement of their boundaries.

    In each layer, the loops that may share a face with a crossing one (``seeds``; :func:`_affected`) are noded
    (split at every crossing) and polygonized into faces; a face is filled when the winding number of a point
    inside it passes the fill rule; the filled faces are unioned. The layer's other loops (other parts of a plate,
    apart from the crossing ones) keep their fast result, and so do layers whose loops turn out not to cross.
    ``pc``: the points as complex numbers; ``new_index``: each loop's place in ``nested`` (-1: dropped);
    ``loop_area``: signed areas; ``unfilled_loop``: loops that bound nothing; ``boxes``: (lo, hi) of the loops.
    """
    import shapely

    lo, hi = boxes
    new_loops: list[tuple[int, np.ndarray, bool, int]] = []  # (layer, points, is_hole, parent slot)
    fixed, rebuilt = [], []
    for lay in layers:
        ids = np.flatnonzero((layer == lay) & closed)
        if ids.size == 0:  # one loop is enough when it crosses itself
            continue
        ids = ids[_affected(lo[ids], hi[ids], np.isin(ids, seeds))]
        rings = [points[offsets[i] : offsets[i + 1]].astype(np.float64) for i in ids]
        closed_rings = [np.vstack([r, r[:1]]) for r in rings]
        which = np.repeat(np.arange(len(rings)), [len(r) for r in closed_rings])
        lines = shapely.multilinestrings(shapely.linestrings(np.concatenate(closed_rings), indices=which))
        noded = shapely.node(lines)
        faces = shapely.get_parts(shapely.polygonize(shapely.get_parts(noded)))
        if faces.size == 0:
            continue
        reps = shapely.point_on_surface(faces)
        rx, ry = shapely.get_x(reps), shapely.get_y(reps)
        q = rx + 1j * ry
        pi = np.repeat(np.arange(faces.size), ids.size)
        pj = np.tile(ids, faces.size)
        near = (lo[pj, 0] <= rx[pi]) & (rx[pi] <= hi[pj, 0]) & (lo[pj, 1] <= ry[pi]) & (ry[pi] <= hi[pj, 1])
        pi, pj = pi[near], pj[near]  # a loop winds 0 times around a point outside its box
        w = np.bincount(pi, weights=_winding_numbers(pc, offsets, pi, pj, q), minlength=faces.size)
        kept = faces[_filled(np.rint(w).astype(np.int64), fill_rule)]
        region = shapely.union_all(kept) if kept.size else shapely.Polygon()
        fixed.append(lay)
        rebuilt.append(ids)
        for poly in shapely.get_parts(shapely.normalize(region)):
            if poly.is_empty or poly.area == 0:
                continue
            poly = shapely.geometry.polygon.orient(poly, 1.0)  # exterior counter-clockwise, holes clockwise
            outer = np.asarray(poly.exterior.coords)[:-1]
            slot = len(new_loops)
            new_loops.append((int(lay), outer, False, -1))
            for ring in poly.interiors:
                new_loops.append((int(lay), np.asarray(ring.coords)[:-1], True, slot))
    if not fixed:
        return nested
    fixed = np.array(fixed)
    # the rebuilt loops are replaced; the rest of their layers (open chains, loops apart) stays, first in the layer
    rebuilt = np.concatenate(rebuilt)
    gone = new_index[rebuilt]
    keep = np.ones(nested.loop_layer.size, dtype=bool)
    keep[gone[gone >= 0]] = False
    stay = np.ones(layer.size, dtype=bool)  # the loops (by their index here) that keep their fast result
    stay[rebuilt] = False
    counts = np.diff(nested.loop_offsets)
    old_index = np.flatnonzero(keep)
    remap = np.full(keep.size, -1, dtype=np.int64)
    n_old = old_index.size
    all_layer = np.concatenate([nested.loop_layer[keep], [lay for lay, *_ in new_loops]]).astype(np.int32)
    order = np.argsort(all_layer, kind="stable")
    position = np.empty(order.size, dtype=np.int64)
    position[order] = np.arange(order.size)
    remap[old_index] = position[:n_old]
    old_parent = nested.loop_parent[keep]
    parents = np.concatenate([
        np.where(old_parent >= 0, remap[np.maximum(old_parent, 0)], -1),
        [position[n_old + p] if p >= 0 else -1 for *_, p in new_loops],
    ])
    pts = [nested.points[np.repeat(keep, counts)]] + [p.astype(np.float32) for _, p, _, _ in new_loops]
    all_counts = np.concatenate([counts[keep], [len(p) for _, p, _, _ in new_loops]]).astype(np.int64)
    all_points = np.concatenate(pts).reshape(-1, 2)
    starts = np.concatenate([[0], np.cumsum(all_counts)])
    new_offsets = np.zeros(order.size + 1, dtype=np.int64)
    np.cumsum(all_counts[order], out=new_offsets[1:])
    src = np.arange(int(new_offsets[-1])) + np.repeat(starts[order] - new_offsets[:-1], all_counts[order])
    is_hole = np.concatenate([nested.loop_is_hole[keep], [h for _, _, h, _ in new_loops]]).astype(bool)[order]
    closed_all = np.concatenate([nested.loop_closed[keep], np.ones(len(new_loops), bool)])[order]
    layer_offsets = np.zeros(n_layers + 1, dtype=np.int64)
    np.cumsum(np.bincount(all_layer, minlength=n_layers), out=layer_offsets[1:])
    area = nested.area.copy()
    resolved = nested.overlaps_resolved.copy()
    unfilled = nested.unfilled_loops.copy()
    # what stays of a rebuilt layer: its loops' areas as the fast path had them, and its loops that bound nothing
    at = np.maximum(new_index, 0)
    if nested.loop_layer.size:
        was_closed, was_hole = nested.loop_closed[at].astype(bool), nested.loop_is_hole[at].astype(bool)
    else:  # the fast path kept no loop at all
        was_closed = was_hole = np.zeros(layer.size, dtype=bool)
    still = stay & (new_index >= 0) & was_closed
    sign = np.where(was_hole[still], -1.0, 1.0)
    kept_area = np.bincount(layer[still], weights=sign * np.abs(loop_area[still]), minlength=n_layers)
    kept_unfilled = np.bincount(layer[stay & unfilled_loop], minlength=n_layers)
    for lay in fixed:
        sel = [(p, h) for ly, p, h, _ in new_loops if ly == lay]
        area[lay] = sum(abs(signed_areas(p, np.array([0, len(p)]))[0]) * (-1 if h else 1) for p, h in sel)
        area[lay] += kept_area[lay]
        resolved[lay] = 1
        unfilled[lay] = kept_unfilled[lay]
    return Nested(
        points=np.ascontiguousarray(all_points[src], dtype=np.float32),
        loop_offsets=new_offsets,
        layer_offsets=layer_offsets,
        loop_layer=all_layer[order],
        loop_is_hole=is_hole,
        loop_parent=parents[order].astype(np.int32),
        loop_closed=closed_all,
        area=area,
        unfilled_loops=unfilled,
        overlaps_resolved=resolved,
    )

