"""Open edges joined to the nearby open edge they were meant to share (a mesh repair before slicing).

A triangle soup (an exporter that writes each facet's corners with its own rounding, so no two facets share a
vertex) or a mesh whose exporter did not weld some edges bit for bit has *open* edges (one facet each) where its
surface is closed. Slicing it as stored leaves every crossing of such an edge
an open chain end, joined to another only across a gap by distance (``chain._repair``), and a noisy soup's loops
then double back or stay open. PrusaSlicer's loader (admesh's ``stl_check_facets_nearby``) joins them on the mesh
instead; so does this module:

* each open edge's facet side runs from corner ``a`` to corner ``b`` (the facet's winding); its *partner* is another
  open side from ``b'`` to ``a'`` (the other way round, as two facets of a consistently wound surface use an edge)
  or from ``a'`` to ``b'`` (a facet flipped in a soup: the joined shell is then turned outward,
  :func:`gpuslice.mesh.defects.wound_for_slicing`), whichever is nearer: ``cost = max(|a - a'|, |b - b'|)`` (mm);
* a pair is allowed when its cost is at most :data:`RELATIVE` times the shorter of its two sides and at most the
  ``limit`` (mm): the corners are much nearer each other than the edge is long, so the two sides are one edge;
* sides are matched closest first (cost, then index), each at most once, pairs of opposite sides before pairs of
  sides that run the same way: in rounds of mutual best candidates, vectorised (a candidate is among the
  :data:`NEIGHBOURS` nearest side midpoints);
* the corners of each matched pair are merged (``a`` with ``a'``, ``b`` with ``b'``; chains of merges join whole
  classes) onto the class's vertex used by the most facet corners, the smallest id among equals (a soup's first
  copy; the true corner beside a nudged one), whose position is kept as stored: no new coordinate is made;
* merges that would fold a facet (two of its corners into one class) are given up, for every pair of that class:
  no facet is lost, and those sides stay open.

Sides of clearly different lengths are not joined, nor edges already shared by two or more facets, nor the sides of
a hole wider than a quarter of its edges or than the slicer's ``join_edges`` (0.01 mm by default: wider gaps are
holes, filled by :mod:`gpuslice.mesh.holes`; at 2 mm a cup without its 0.8 mm rim face had its inner and outer rims
zipped together and its walls tilted, a review). Meshes without an open edge are returned as they are, at the cost
of one test of their edge counts.
"""

from __future__ import annotations

import numpy as np

from .graph import connected_labels
from .mesh import Mesh, with_faces

__all__ = ["joined_open_edges", "RELATIVE", "NEIGHBOURS"]

#: a pair's corners lie at most this fraction of the shorter side's length apart
RELATIVE = 0.25
#: open sides up to this many: every pair compared in numpy (no k-d tree)
SMALL = 1024
#: candidates per open side: its nearest side midpoints (a soup vertex's copies: 6 facets; its sides: a dozen)
NEIGHBOURS = 8


def joined_open_edges(mesh: Mesh, limit: float) -> tuple[Mesh, int]:
    """``mesh`` with its open edges joined to their nearby partners (module docstring) and the number of pairs
    joined; ``mesh`` itself (and 0) when it has no open edge or nothing is joined. ``limit``: the largest distance
    (mm) a corner moves; 0 joins nothing."""
    sides = mesh.edge_sides()
    open_e = np.flatnonzero(sides.count == 1)
    if open_e.size < 2 or not limit > 0:
        return mesh, 0
    s = sides.first[open_e].astype(np.int64)
    f, k = s // 3, s % 3
    faces = mesh.faces
    a, b = faces[f, k].astype(np.int64), faces[f, (k + 1) % 3].astype(np.int64)
    v = mesh.vertices  # (only the open sides' corners in float64, not every vertex)
    pa, pb = v[a].astype(np.float64), v[b].astype(np.float64)
    length = np.linalg.norm(pb - pa, axis=1)
    mid = 0.5 * (pa + pb)
    i, j, cost, same = _candidates(mid, pa, pb, length, limit)
    if i.size == 0:
        return mesh, 0
    mi, mj, ms = _closest_first(open_e.size, i, j, cost, same)
    if mi.size == 0:
        return mesh, 0
    while True:  # merges that would fold a facet (two of its corners in one class) are given up, with their class's
        aj, bj = np.where(ms, a[mj], b[mj]), np.where(ms, b[mj], a[mj])  # (i's corners a, b meet these)
        label = connected_labels(v.shape[0], np.concatenate([a[mi], b[mi]]), np.concatenate([aj, bj]))
        new_faces = label[faces]
        folded = (new_faces[:, 0] == new_faces[:, 1]) | (new_faces[:, 1] == new_faces[:, 2]) | \
            (new_faces[:, 2] == new_faces[:, 0])
        if not folded.any():
            break
        bad = np.zeros(v.shape[0], dtype=bool)
        bad[new_faces[folded].reshape(-1)] = True  # (class labels: every merge into such a class)
        keep = ~(bad[label[a[mi]]] | bad[label[b[mi]]])
        mi, mj, ms = mi[keep], mj[keep], ms[keep]
        if mi.size == 0:
            return mesh, 0
    # each class onto its vertex with the most facet corners (the true corner beside a nudged copy), ties by id
    used = np.bincount(faces.reshape(-1), minlength=v.shape[0])
    o = np.lexsort((np.arange(v.shape[0]), -used, label))
    lead = np.ones(o.size, dtype=bool)
    lead[1:] = label[o][1:] != label[o][:-1]
    onto = np.empty(v.shape[0], dtype=np.int64)
    onto[label[o][lead]] = o[lead]
    return with_faces(mesh, onto[new_faces]), int(mi.size)


def _candidates(mid, pa, pb, length, limit):
    """Pairs (i < j) of open sides that may be one edge (:func:`_allowed`), their costs (mm) and whether they run
    the same way: up to :data:`SMALL` sides every pair; else each side with its nearest other midpoint (a soup's
    partner, nearly always), then the sides that found none among each other's :data:`NEIGHBOURS` nearest."""
    n = mid.shape[0]
    if n <= SMALL:  # every pair, in numpy (scipy.spatial's import alone takes 0.2 s: an open scan has a few holes)
        i, j = np.triu_indices(n, 1)
        near = np.einsum("ij,ij->i", mid[i] - mid[j], mid[i] - mid[j]) <= limit * limit
        return (*_allowed(i[near], j[near], pa, pb, length, limit),)
    from scipy.spatial import cKDTree

    _, nb = cKDTree(mid).query(mid, k=2, distance_upper_bound=limit, workers=-1)
    own = np.arange(n)
    near = np.where(nb[:, 0] == own, nb[:, 1], nb[:, 0])  # (exact copies may list another before the side itself)
    i, j, cost, same = _allowed(own, near, pa, pb, length, limit)
    found = np.zeros(n, dtype=bool)  # (a side whose nearest runs the same way, a copy of it, looks further: a review)
    found[i[~same]] = found[j[~same]] = True
    rest = np.flatnonzero(~found)
    if rest.size > 1:
        kk = min(NEIGHBOURS + 1, rest.size)
        _, nb = cKDTree(mid[rest]).query(mid[rest], k=kk, distance_upper_bound=limit, workers=-1)
        nb = nb.reshape(rest.size, kk)
        ok = nb < rest.size
        i2, j2, c2, s2 = _allowed(rest[np.nonzero(ok)[0]], rest[nb[ok]], pa, pb, length, limit)
        i, j, cost, same = (np.concatenate(x) for x in ((i, i2), (j, j2), (cost, c2), (same, s2)))
    # each pair once
    key = i * n + j
    o = np.argsort(key, kind="stable")
    first = np.ones(o.size, dtype=bool)
    first[1:] = key[o][1:] != key[o][:-1]
    o = o[first]
    return i[o], j[o], cost[o], same[o]


def _allowed(i, j, pa, pb, length, limit):
    """The pairs (i, j) of open sides (as i < j) that may be one edge (module docstring), their costs, and whether
    they run the same way."""
    keep = (j < pa.shape[0]) & (j != i)
    i, j = i[keep], j[keep]
    i, j = np.minimum(i, j), np.maximum(i, j)
    back = np.maximum(np.linalg.norm(pa[i] - pb[j], axis=1), np.linalg.norm(pb[i] - pa[j], axis=1))
    along = np.maximum(np.linalg.norm(pa[i] - pa[j], axis=1), np.linalg.norm(pb[i] - pb[j], axis=1))
    same = along < back
    cost = np.where(same, along, back)
    ok = cost <= np.minimum(limit, RELATIVE * np.minimum(length[i], length[j]))
    return i[ok], j[ok], cost[ok], same[ok]


def _closest_first(n: int, i: np.ndarray, j: np.ndarray, cost: np.ndarray, same: np.ndarray):
    """The greedy matching of the candidate pairs, least cost first (ties by the pair's indices), the pairs that run
    the other way first and then, among the sides left, those that run the same way (a soup's facet stored twice
    with its own rounding: its neighbours join one copy, and the other is not joined onto the first). Each in rounds
    in which every pair that is the best of both its sides is taken (a locally dominant pair: the greedy
    matching's). Returns the pairs' sides i, j and whether they run the same way."""
    order = np.lexsort((j, i, cost))
    i, j, same = i[order], j[order], same[order]
    free = np.ones(n, dtype=bool)
    taken = [_rounds(n, i[~same], j[~same], free), _rounds(n, i[same], j[same], free)]
    return (np.concatenate([taken[0][0], taken[1][0]]), np.concatenate([taken[0][1], taken[1][1]]),
            np.repeat([False, True], [taken[0][0].size, taken[1][0].size]))


def _rounds(n: int, i: np.ndarray, j: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j), in order of preference, taken in rounds of mutual best among the sides still ``free`` (which
    it updates)."""
    keep = free[i] & free[j]
    i, j = i[keep], j[keep]
    taken_i, taken_j = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    while i.size:
        rank = np.arange(i.size)
        best = np.full(n, i.size, dtype=np.int64)
        np.minimum.at(best, i, rank)
        np.minimum.at(best, j, rank)
        mutual = (best[i] == rank) & (best[j] == rank)  # (the first pair always is)
        taken_i.append(i[mutual])
        taken_j.append(j[mutual])
        free[i[mutual]] = free[j[mutual]] = False
        keep = free[i] & free[j]
        i, j = i[keep], j[keep]
    return np.concatenate(taken_i), np.concatenate(taken_j)
