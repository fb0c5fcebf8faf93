"""Nesting's containment tests in numpy, for the common case: few closed loops per layer (stage 5's fast path).

:func:`containment_pairs` answers what ``nest._containment_pairs`` asks GEOS (an R-tree of the loops' boxes,
``shapely.contains_xy`` of each loop's query point in the loops whose box holds it, ``shapely.intersects`` of the
rings of loops whose boxes overlap partially), with the same answers:

- candidate pairs: every two closed loops of a layer (all pairs, when their number stays under
  :data:`MAX_PAIRS`), kept where their closed boxes meet;
- the loops are cut into chunks of :data:`CHUNK` edges with their boxes (:class:`Chunks`), so that each test
  looks only at the edges of the chunks near its point or its pair's common box, not at every edge of a loop;
- point in loop: the crossings of the horizontal ray from the query point to its right with the loop's edges,
  counted as GEOS counts them (an edge counts when one end is above the point and the other on or below its line;
  odd: inside, a self-crossing loop's doubly wound lobes included). A point on the loop's boundary is not inside
  (``contains_xy`` is strict): a pair whose point lies on an edge, on a vertex, or within the rounding of the
  orientation (GEOS's own first test, ``(a - p) x (b - p)`` in float64, with its error bound) is handed to GEOS;
- boundaries that may meet (loops of overlapping bodies): the pairs whose boxes overlap without one holding the
  other, or whose inner loop's point is not inside the outer one: their edges near the common box are tested two
  by two (boxes, then the four orientations); a pair with an orientation within rounding (a touch, collinear
  edges) or more than :data:`MAX_EDGE_PAIRS` edge pairs (or beyond :data:`MAX_EDGE_PAIRS_ALL` in all) goes to GEOS
  (``intersects`` of the rings).

Every answer given here is the exact one (a sure orientation has the exact sign), and so GEOS's (exact
predicates). shapely is imported only when some pair needs GEOS. The containing loops of a loop are found in
another order than the R-tree's, and that order decides which of two outer contours of equal area becomes a
hole's parent: when any loop has two containing loops of equal area, :func:`containment_pairs` returns None and
the caller takes the R-tree path.
"""

from __future__ import annotations

import numpy as np

from ..ragged import LOOP_CHUNK, expand_ranges, isin_ints, loop_chunks, unique_ints
from .rings import _polygons, in_halves

__all__ = ["containment_pairs", "point_in_loops", "rings_meet_numpy", "Chunks", "MAX_PAIRS", "MAX_EDGE_PAIRS"]

#: unordered pairs of closed loops sharing a layer above which the caller's R-tree finds the candidates
MAX_PAIRS = 200_000
#: edges per chunk
CHUNK = LOOP_CHUNK
#: edge pairs of two loops tested in numpy for one pair of loops, above which GEOS tests the pair
MAX_EDGE_PAIRS = 1024
#: edge pairs tested in numpy for all pairs of loops together (the pairs with the fewest first; the others: GEOS)
MAX_EDGE_PAIRS_ALL = 65536
#: relative bound on the rounding of a float64 orientation, |error| <= _ERR * (|t1| + |t2|) for t1 - t2 (GEOS's
#: DP_SAFE_EPSILON; Shewchuk's ccwerrboundA is 3.3e-16)
_ERR = 1e-15


def layer_pairs(layer: np.ndarray, ids: np.ndarray, limit: int | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Every unordered pair (x, y), x < y, of the loops ``ids`` (ascending) that share a layer, grouped by layer;
    None when there are more than ``limit`` (default :data:`MAX_PAIRS`)."""
    limit = MAX_PAIRS if limit is None else limit
    lay = layer[ids]
    if lay.size and np.any(lay[1:] < lay[:-1]):
        o = np.argsort(lay, kind="stable")
        ids, lay = ids[o], lay[o]
    k = np.bincount(lay)
    if int((k * (k - 1) // 2).sum()) > limit:
        return None
    pos = np.arange(ids.size)
    end = np.searchsorted(lay, lay, side="right")  # one past the last loop of each loop's layer
    own, other = expand_ranges(pos + 1, end - pos - 1)
    return ids[own], ids[other]


class Chunks:
    """The loops' boxes (``loop_lo``, ``loop_hi``: (R, 2) float64, those of their points) and, after :meth:`cut`,
    the chosen loops cut into runs of :data:`CHUNK` edges (edge k: point k to the next one, the last back to the
    loop's first), each with its closed box: ``lo``, ``hi`` (C, 2) float64; chunk c holds edges ``start[c]`` to
    ``end[c] - 1`` of loop ``loop[c]``; loop r's chunks are ``off[r]`` to ``off[r + 1] - 1`` (none for the loops
    not cut). ``boxes``: the (C, 4) float32 boxes (x min, y min, x max, y max) of every loop's chunks, as
    :func:`~gpuslice.ragged.loop_chunks` lays them out, when the device made them (``chunk_boxes`` in
    ``kernels/walk.cl``, the same values; where +0.0 and -0.0 tie, either may be kept, as the boxes are only
    compared): then every loop is cut already and no pass over the points is made."""

    def __init__(self, points: np.ndarray, offsets: np.ndarray, boxes: np.ndarray | None = None):
        self.offsets, self.first, self.last = offsets, offsets[:-1], offsets[1:]
        self._all = boxes is not None and CHUNK == LOOP_CHUNK  # (the device's layout: LOOP_CHUNK edges a chunk)
        if self._all:
            self.off, self.loop, self.start, self.end, _ = loop_chunks(offsets)
            b = boxes.astype(np.float64)
            self.lo, self.hi = np.ascontiguousarray(b[:, :2]), np.ascontiguousarray(b[:, 2:])
            self.loop_lo = np.minimum.reduceat(self.lo, self.off[:-1], axis=0)
            self.loop_hi = np.maximum.reduceat(self.hi, self.off[:-1], axis=0)
            return
        # (reduceat runs ~2x faster on contiguous data)
        self.cols = [np.ascontiguousarray(points[:, k]) for k in (0, 1)]
        self.loop_lo = np.stack([np.minimum.reduceat(c, self.first) for c in self.cols], axis=1).astype(np.float64)
        self.loop_hi = np.stack([np.maximum.reduceat(c, self.first) for c in self.cols], axis=1).astype(np.float64)

    def cut(self, ids: np.ndarray) -> None:
        """Cut the loops ``ids`` (ascending, unique) into chunks (a reduction over the points, a segment per chunk;
        nothing to do when the device's boxes came with every loop cut)."""
        if self._all:
            return
        self.off, self.loop, self.start, self.end, nxt = loop_chunks(self.offsets, CHUNK, ids)
        # segments: the chunks, and the gaps after the loops cut that the next one cut does not follow (unused)
        end = self.last[ids]
        gap = np.append(end[:-1] != self.first[ids][1:], end[-1:] < self.cols[0].size)
        cuts = np.insert(self.start, self.off[ids + 1][gap], end[gap])
        at = np.arange(self.start.size) + np.searchsorted(self.off[ids + 1][gap], np.arange(self.start.size),
                                                          side="right")
        lo, hi = [], []
        for col in self.cols:
            lo.append(np.minimum(np.minimum.reduceat(col, cuts)[at], col[nxt]))
            hi.append(np.maximum(np.maximum.reduceat(col, cuts)[at], col[nxt]))
        self.lo = np.stack(lo, axis=1).astype(np.float64)
        self.hi = np.stack(hi, axis=1).astype(np.float64)

    def edges(self, owner: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The edges (a -> b, point indices) of chunks ``c``, each with the ``owner`` of its chunk."""
        k, a = expand_ranges(self.start[c], self.end[c] - self.start[c])
        loop = self.loop[c][k]
        b = a + 1
        wrap = b == self.last[loop]
        b[wrap] = self.first[loop[wrap]]
        return owner[k], a, b

    def near(self, loops: np.ndarray, box_lo: np.ndarray, box_hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The chunks of loop ``loops[k]`` whose box meets box k: (k, chunk), sorted by k."""
        own, c = expand_ranges(self.off[loops], self.off[loops + 1] - self.off[loops])
        keep = np.all((self.lo[c] <= box_hi[own]) & (box_lo[own] <= self.hi[c]), axis=1)
        return own[keep], c[keep]


def _orient(pc: np.ndarray, a: np.ndarray, b: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sign of the orientation of p against the edge a -> b (> 0: p on its left) as GEOS computes it first, from
    (a - p) x (b - p) in float64, and whether that sign is sure (beyond the rounding bound); a zero is never sure."""
    pa, pb = pc[a] - p, pc[b] - p
    t1 = pa.real * pb.imag
    t2 = pa.imag * pb.real
    det = t1 - t2
    return det, np.abs(det) > _ERR * (np.abs(t1) + np.abs(t2))


def point_in_loops(pc: np.ndarray, chunks: Chunks, pi: np.ndarray, pj: np.ndarray,
                   q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether query point ``q[pi[k]]`` (complex, mm) is strictly inside loop ``pj[k]`` (even-odd: an odd number of
    the loop's edges cross the horizontal ray to its right), and whether that answer is unsure: the point on an
    edge or a vertex, or so near an edge's line that the orientation's sign may be rounding. ``pc``: all points as
    complex128; only the edges of chunks whose box meets the ray are looked at. Returns two (K,) bool arrays
    (inside, unsure)."""
    own, c = expand_ranges(chunks.off[pj], chunks.off[pj + 1] - chunks.off[pj])
    qo = q[pi][own]
    rel = (chunks.lo[c, 1] <= qo.imag) & (qo.imag <= chunks.hi[c, 1]) & (qo.real <= chunks.hi[c, 0])
    pair_of, a, b = chunks.edges(own[rel], c[rel])
    p = q[pi][pair_of]
    ay = pc.imag[a] - p.imag  # (the sign of a float64 difference is exact)
    by = pc.imag[b] - p.imag
    unsure = np.zeros(pi.size, dtype=bool)
    # on the point's line: a vertex at the point, or a horizontal edge through it
    on = np.flatnonzero(ay == 0)
    if on.size:
        ax, bx, px = pc.real[a[on]], pc.real[b[on]], p.real[on]
        hit = (ax == px) | ((by[on] == 0) & (np.minimum(ax, bx) <= px) & (px <= np.maximum(ax, bx)))
        unsure[pair_of[on[hit]]] = True
    up = by > 0
    e = np.flatnonzero((ay > 0) != up)  # only the edges across the point's line can count
    det, sure = _orient(pc, a[e], b[e], p[e])
    unsure[pair_of[e[~sure]]] = True
    right = np.where(up[e], det > 0, det < 0)  # the edge crosses the ray right of the point
    inside = np.bincount(pair_of[e[right]], minlength=pi.size) % 2 == 1
    return inside, unsure


def _edges_in(chunks: Chunks, pc: np.ndarray, k: np.ndarray, c: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """The edges (k, a, b) of chunks ``c`` (owners ``k``) whose closed boxes meet box ``k`` (``lo``, ``hi``)."""
    k, a, b = chunks.edges(k, c)
    za, zb = pc[a], pc[b]
    kl, kh = lo[k], hi[k]
    keep = ((np.minimum(za.real, zb.real) <= kh[:, 0]) & (kl[:, 0] <= np.maximum(za.real, zb.real))
            & (np.minimum(za.imag, zb.imag) <= kh[:, 1]) & (kl[:, 1] <= np.maximum(za.imag, zb.imag)))
    return k[keep], a[keep], b[keep]


def rings_meet_numpy(pc: np.ndarray, chunks: Chunks, bi: np.ndarray, bj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether the boundaries of loops ``bi[k]`` and ``bj[k]`` meet (a common point), and whether that is sure:
    the edges of each that meet the intersection of their boxes, tested two by two (their boxes, then the four
    orientations); unsure where an orientation is within rounding (touching, collinear) or the edge pairs are more
    than :data:`MAX_EDGE_PAIRS` (or :data:`MAX_EDGE_PAIRS_ALL` for all pairs). Returns two (K,) bool arrays (meet,
    sure)."""
    lo = np.maximum(chunks.loop_lo[bi], chunks.loop_lo[bj])
    hi = np.minimum(chunks.loop_hi[bi], chunks.loop_hi[bj])
    # the chunks of each in the common box, the box shrunk to theirs (twice), then their edges in it
    for _ in range(2):
        ka, ca = chunks.near(bi, lo, hi)
        kb, cb = chunks.near(bj, lo, hi)
        for k, c in ((ka, ca), (kb, cb)):
            box_lo = np.full((bi.size, 2), np.inf)
            box_hi = np.full((bi.size, 2), -np.inf)
            np.minimum.at(box_lo, k, chunks.lo[c])
            np.maximum.at(box_hi, k, chunks.hi[c])
            lo, hi = np.maximum(lo, box_lo), np.minimum(hi, box_hi)
    ka, a1, a2 = _edges_in(chunks, pc, ka, ca, lo, hi)
    kb, b1, b2 = _edges_in(chunks, pc, kb, cb, lo, hi)
    na, nb = np.bincount(ka, minlength=bi.size), np.bincount(kb, minlength=bi.size)
    work = na * nb
    big = work > MAX_EDGE_PAIRS
    o = np.argsort(work, kind="stable")  # the smallest first, within the budget of all pairs
    big[o[np.cumsum(work[o]) > MAX_EDGE_PAIRS_ALL]] = True
    sure = ~big
    meet = np.zeros(bi.size, dtype=bool)
    # every edge of one against every edge of the other, pair by pair
    take = ~big[ka]
    ka, a1, a2 = ka[take], a1[take], a2[take]
    b_first = np.cumsum(nb) - nb
    ea, eb = expand_ranges(b_first[ka], nb[ka])
    k = ka[ea]
    p1, p2, r1, r2 = pc[a1[ea]], pc[a2[ea]], pc[b1[eb]], pc[b2[eb]]
    box = ((np.minimum(p1.real, p2.real) <= np.maximum(r1.real, r2.real))
           & (np.minimum(r1.real, r2.real) <= np.maximum(p1.real, p2.real))
           & (np.minimum(p1.imag, p2.imag) <= np.maximum(r1.imag, r2.imag))
           & (np.minimum(r1.imag, r2.imag) <= np.maximum(p1.imag, p2.imag)))
    w = np.flatnonzero(box)
    if w.size:
        k, ia, ib = k[w], a1[ea[w]], a2[ea[w]]
        ja, jb = b1[eb[w]], b2[eb[w]]
        d1, s1 = _orient(pc, ja, jb, pc[ia])
        d2, s2 = _orient(pc, ja, jb, pc[ib])
        d3, s3 = _orient(pc, ia, ib, pc[ja])
        d4, s4 = _orient(pc, ia, ib, pc[jb])
        apart = (s1 & s2 & ((d1 > 0) == (d2 > 0))) | (s3 & s4 & ((d3 > 0) == (d4 > 0)))
        cross = s1 & s2 & s3 & s4 & ((d1 > 0) != (d2 > 0)) & ((d3 > 0) != (d4 > 0))
        meet[k[cross]] = True
        sure[k[~apart & ~cross]] = False
    return meet, sure | meet


def _geos_contains(points, pc, offsets, pi, pj, q) -> np.ndarray:
    """``shapely.contains_xy`` of loop ``pj[k]`` (as a polygon) and the query point ``q[pi[k]]``."""
    import shapely

    involved = unique_ints(pj)
    polys = _polygons(points, offsets, involved, pc)
    counts = np.diff(offsets)
    return in_halves(shapely.contains_xy, counts[pj], polys[np.searchsorted(involved, pj)], q.real[pi], q.imag[pi])


def rings_meet(points, pc, offsets, bi, bj) -> np.ndarray:
    """``shapely.intersects`` of the rings of loops ``bi[k]`` and ``bj[k]`` (closed by their first point)."""
    import shapely

    both = unique_ints(bi, bj)
    rings = shapely.get_exterior_ring(_polygons(points, offsets, both, pc))
    counts = np.diff(offsets)
    return in_halves(shapely.intersects, counts[bi] + counts[bj], rings[np.searchsorted(both, bi)],
                     rings[np.searchsorted(both, bj)])


def containment_pairs(points, pc, offsets, layer, ids, q, area, chunk_boxes=None):
    """The answers of ``nest._containment_pairs`` for the closed loops ``ids`` (ascending) without an R-tree:
    (ci, cj) with loop cj[k] containing the query point ``q[ci[k]]`` (strictly), the layers with loops whose
    boundaries meet, those loops, and the boxes of all loops ((R, 2) float64 lo, hi) (see the module docstring).
    ``area``: the loops' signed areas; ``chunk_boxes``: the device's boxes of every loop's chunks (:class:`Chunks`),
    a callable giving them (or None), or None. None when the pairs are too many or a loop has two containing loops of
    equal area: then the R-tree path answers."""
    pairs = layer_pairs(layer, ids)
    if pairs is None:
        return None
    chunks = Chunks(points, offsets, chunk_boxes() if callable(chunk_boxes) else chunk_boxes)
    lo, hi = chunks.loop_lo, chunks.loop_hi
    x, y = pairs
    meet = np.all((lo[x] <= hi[y]) & (lo[y] <= hi[x]), axis=1)
    x, y = x[meet], y[meet]
    chunks.cut(unique_ints(x, y))
    # candidates: a loop's query point in the other's closed box (as the R-tree's "intersects" finds them)
    qx, qy = q.real, q.imag
    in_y = (lo[y, 0] <= qx[x]) & (qx[x] <= hi[y, 0]) & (lo[y, 1] <= qy[x]) & (qy[x] <= hi[y, 1])
    in_x = (lo[x, 0] <= qx[y]) & (qx[y] <= hi[x, 0]) & (lo[x, 1] <= qy[y]) & (qy[y] <= hi[x, 1])
    pi, pj = np.concatenate([x[in_y], y[in_x]]), np.concatenate([y[in_y], x[in_x]])
    inside, unsure = point_in_loops(pc, chunks, pi, pj, q)
    if unsure.any():
        inside[unsure] = _geos_contains(points, pc, offsets, pi[unsure], pj[unsure], q)
    ci, cj = pi[inside], pj[inside]
    # two containing loops of equal area: the R-tree's order decides the parent
    o = np.lexsort((np.abs(area[cj]), ci))
    sa, sc = np.abs(area[cj])[o], ci[o]
    if np.any((sc[1:] == sc[:-1]) & (sa[1:] == sa[:-1])):
        return None
    # boxes overlapping partially, or nested with the inner loop's point not inside the outer one: may cross
    x_in_y = np.all((lo[y] <= lo[x]) & (hi[x] <= hi[y]), axis=1)
    y_in_x = np.all((lo[x] <= lo[y]) & (hi[y] <= hi[x]), axis=1)
    partial = ~x_in_y & ~y_in_x
    a = np.where(x_in_y, x, y)[~partial]  # the inner loop (x when the boxes are equal)
    b = np.where(x_in_y, y, x)[~partial]
    n = offsets.size - 1
    out = ~isin_ints(a * n + b, ci * n + cj)
    bi = np.concatenate([x[partial], a[out]])
    bj = np.concatenate([y[partial], b[out]])
    if bi.size:
        m, sure = rings_meet_numpy(pc, chunks, bi, bj)
        if not sure.all():
            m[~sure] = rings_meet(points, pc, offsets, bi[~sure], bj[~sure])
        bi, bj = bi[m], bj[m]
    return ci, cj, unique_ints(layer[bi]), unique_ints(bi, bj), (lo, hi)
