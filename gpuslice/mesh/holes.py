"""Holes filled: each loop of open edges closed by a fan of facets (a mesh repair before slicing).

An open scan (the Stanford bunny's base), a model with a facet missing or a surface an exporter left open slices into
chains that do not close where a layer crosses a hole; a chain whose ends are farther apart than the gap closing's
``max_gap`` is not filled, so such a layer lost its whole area (the bunny at 40 mm, cut along the file's z: 193 of
its 620 layers empty; Slic3r, whose loader fills holes as admesh's ``stl_fill_holes`` does, fills them). This module
fills them on the mesh, before any crossing is cut:

* the open edges' facet sides (``a`` to ``b``, the facet's winding) are linked head to tail: at each vertex the
  sides that arrive are paired with the sides that leave, in order of side index (holes that touch at a vertex: a
  review found 38 of 40 layers of a sphere with 3,000 facets missing empty while such vertices ended paths), so the
  open sides fall into loops, the holes' rims;
* a side that cannot be linked (a vertex where more sides arrive than leave: a facet flipped beside the hole) ends a
  path; sides on paths are left open (chaining joins their chains across gaps, as before);
* each loop is closed by a fan from its corner ``v0`` whose fan has the least facet area (every corner of a loop of
  up to :data:`FAN_SEARCH` sides tried; larger loops, and ties, the corner that comes first by (x, y, z): so the fan
  does not depend on the order or the winding of the facets): the facet ``(v0, b, a)`` for every side ``a -> b`` of
  the loop that does not touch ``v0``, where the rim's vector area is at least :data:`FLAT_SHARE` of the fan's facet
  area (else the fan folds over itself, and the loop is left open: a crack, or a seam of failed joins in a soup that
  follows a curve, whose fans on a benchy soup added up to 860 mm² of facets, up to 79 mm² each). Each new facet runs
  against its rim side and against its fan neighbours, so the filled shell is wound as the rim is; the fan of a
  planar rim covers the hole exactly (its facets' signed areas add up to the rim polygon's, whatever its shape), a
  warped rim gets the surface of the fan (the least-area fan: the bunny's warped hole within 1.3e-3 of Slic3r's fill
  in every layer, where the lowest corner's fan was 1.2 % off in 15 layers).

Holes no wider than chaining's ``max_gap`` across the layers (the diagonal of the rim's x, y box) are left to it: it
closes their gaps in every layer exactly (a slit 1.3 mm wide along a sphere's wall: a fan across its curved length
put a layer 0.9 % off; the sides a soup's partial joins leave form such small loops by the thousand). Only meshes
whose open sides are at most :data:`OPEN_SHARE` of all their facet sides, and that were no soup with failed joins
(:data:`SOUP_SHARE`), are filled: such a soup (joined first where its edges are one, :mod:`gpuslice.mesh.seams`) or a
surface model is left to chaining. No vertex is added or moved. Meshes without an open edge are returned as they are.
"""

from __future__ import annotations

import math

import numpy as np

from ..ragged import expand_ranges, group_ranks
from .graph import connected_labels
from .mesh import Mesh, with_faces

__all__ = ["filled_holes", "OPEN_SHARE"]

#: holes are filled only where at most this share of the facet sides are open (a closed surface with holes); a mesh
#: with more is a soup or a surface, whose open "loops" are single facets or patches: filled, each would become a
#: flat closed pillow of no volume and take its facets' area out of every layer
OPEN_SHARE = 0.15
#: a mesh whose open edges were joined in more pairs than this share of its facets was a triangle soup (each facet
#: needs 1.5); where more than :data:`FAILED_SHARE` of the sides it joined are still open, those are joins that failed
#: (its facets' sides shorter than four times their corners' rounding), not holes, linked into loops along seams:
#: fans across them cost 4 layers off by more than 1 % on a benchy soup (±0.001 mm) where chaining alone had none, so
#: its holes are left to chaining. A soup of an open scan (the bunny's: 223 sides left of 208,353) is filled
SOUP_SHARE = 0.5
FAILED_SHARE = 0.01
#: ... and more than this many sides (a small soup's one hole is filled)
FAILED_SIDES = 64
#: a loop is filled only where its rim's vector area is at least this share of its fan's total facet area: below, the
#: fan folds over itself (a seam of failed joins that runs along a curve, a crack), and it is left open
FLAT_SHARE = 0.3
#: loops of up to this many sides get the fan of least area (every corner tried: n^2 facets' areas); larger ones the
#: fan from their lowest corner
FAN_SEARCH = 512
#: ... and up to this many (corner, side) pairs in all, smallest loops first (bounded memory: a scan with a thousand
#: holes of 500 sides would need 250 million), the rest from their lowest corner
FAN_WORK = 1 << 22


def filled_holes(mesh: Mesh, min_size: float = 0.0, joined: int = 0) -> tuple[Mesh, int]:
    """``mesh`` with every loop of its open edges closed by a fan of facets (module docstring), and the number of
    holes filled; ``mesh`` itself (and 0) when there is none, or when more than :data:`OPEN_SHARE` of its facet sides
    are open. ``min_size``: loops whose x, y box has a diagonal of at most this many mm are left open (the slicer passes
    ``max_gap``: chaining closes the gaps of such a hole in every layer). ``joined``: the pairs of open edges joined
    before (:mod:`gpuslice.mesh.seams`); more than :data:`SOUP_SHARE` of the facets: a soup, not filled where its
    joins failed (:data:`FAILED_SHARE`)."""
    sides = mesh.edge_sides()
    open_e = np.flatnonzero(sides.count == 1)
    if open_e.size < 3 or open_e.size > OPEN_SHARE * 3 * mesh.n_faces or (
            joined > SOUP_SHARE * mesh.n_faces and open_e.size > max(FAILED_SHARE * 2 * joined, FAILED_SIDES)):
        return mesh, 0
    s = np.sort(sides.first[open_e].astype(np.int64))
    f, k = s // 3, s % 3
    a, b = mesh.faces[f, k].astype(np.int64), mesh.faces[f, (k + 1) % 3].astype(np.int64)
    nxt = _linked(a, b)
    on_loop = _on_loops(nxt)
    if not on_loop.any():
        return mesh, 0
    idx = np.flatnonzero(on_loop)
    label = connected_labels(s.size, idx, nxt[idx])  # each loop labelled with its smallest side
    v = mesh.vertices  # (only the rims' corners in float64, not every vertex)
    pa, pb = v[a[idx]].astype(np.float64), v[b[idx]].astype(np.float64)
    loop, at = np.unique(label[idx], return_inverse=True)
    # each loop's fan from the corner whose fan has the least area (the lowest by (x, y, z) among equals): the same
    # fan whatever the facets' order or winding
    v0 = np.full(s.size, -1, dtype=np.int64)
    v0[idx] = a[idx][_fan_corners(pa, pb, at, loop.size)][at]
    # each loop's rim vector area against its fan's facet area
    rim = np.zeros((loop.size, 3))
    np.add.at(rim, at, 0.5 * np.cross(pa, pb))
    q = v[v0[idx]].astype(np.float64)
    fan_area = np.bincount(at, 0.5 * np.linalg.norm(np.cross(pb - q, pa - q), axis=1), minlength=loop.size)
    flat = (np.linalg.norm(rim, axis=1) >= FLAT_SHARE * fan_area) & (fan_area > 0)
    # the rim's extent across the layers (its x, y box): no wider than max_gap, every layer's gap is one chaining closes
    lo = np.full((loop.size, 2), np.inf)
    hi = np.full((loop.size, 2), -np.inf)
    np.minimum.at(lo, at, pa[:, :2])
    np.maximum.at(hi, at, pa[:, :2])
    flat &= np.linalg.norm(hi - lo, axis=1) > min_size
    on_loop[idx[~flat[at]]] = False
    fan = on_loop & (a != v0) & (b != v0)
    new = np.stack([v0[fan], b[fan], a[fan]], axis=1).astype(np.int32)
    if new.shape[0] == 0:
        return mesh, 0
    normals = mesh.stored_normals
    out = with_faces(mesh, np.concatenate([mesh.faces, new]), stored_normals=None if normals is None else
                     np.concatenate([normals, np.zeros((new.shape[0], 3), normals.dtype)]))
    return out, int(np.count_nonzero(flat))


def _fan_corners(pa: np.ndarray, pb: np.ndarray, at: np.ndarray, n_loops: int) -> np.ndarray:
    """For each of ``n_loops`` loops (its sides ``pa[i] -> pb[i]`` with ``at[i]`` its loop), the side whose start
    corner makes the fan of least facet area (up to :data:`FAN_SEARCH` sides a loop, and :data:`FAN_WORK` pairs in
    all: every corner tried; larger loops, and ties, the lowest corner by (x, y, z)). Returns (n_loops,) side
    indices."""
    order = np.lexsort((pa[:, 2], pa[:, 1], pa[:, 0], at))  # sides by loop, lowest corner first
    cnt = np.bincount(at, minlength=n_loops)
    first = np.cumsum(cnt) - cnt
    best = order[first]
    small = np.flatnonzero((cnt <= FAN_SEARCH) & (cnt > 3))
    small = small[np.argsort(cnt[small], kind="stable")]
    small = np.sort(small[np.cumsum(cnt[small] ** 2) <= FAN_WORK])
    if small.size:
        cand_of, cand = expand_ranges(first[small], cnt[small])  # every corner of every small loop ...
        pair_of, side = expand_ranges(first[small][cand_of], cnt[small][cand_of])  # ... against each side of it
        c, s = order[cand][pair_of], order[side]
        q = pa[c]
        area = np.bincount(pair_of, 0.5 * np.linalg.norm(np.cross(pb[s] - q, pa[s] - q), axis=1),
                           minlength=cand.size)
        pick = np.lexsort((cand, area, cand_of))  # least area, then the lowest corner (cand is in that order)
        lead = np.ones(pick.size, dtype=bool)
        lead[1:] = cand_of[pick][1:] != cand_of[pick][:-1]
        best[small] = order[cand[pick[lead]]]
    return best


def _linked(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each open side ``a[i] -> b[i]``, the side that leaves its end ``b[i]`` (-1: none): at each vertex the
    k-th arriving side (by index) is linked to the k-th leaving one."""
    n = a.size
    idx = np.arange(n)
    out_o, in_o = np.lexsort((idx, a)), np.lexsort((idx, b))  # leaving and arriving sides, by vertex then index
    out_rank, in_rank = group_ranks(a[out_o]), group_ranks(b[in_o])
    width = int(max(out_rank.max(), in_rank.max())) + 1
    key_out = a[out_o] * width + out_rank  # (sorted: by vertex, then rank)
    key_in = b[in_o] * width + in_rank
    pos = np.searchsorted(key_out, key_in)
    found = (pos < n) & (key_out[np.minimum(pos, n - 1)] == key_in)
    nxt = np.full(n, -1, dtype=np.int64)
    nxt[in_o[found]] = out_o[pos[found]]
    return nxt


def _on_loops(nxt: np.ndarray) -> np.ndarray:
    """Which sides lie on a loop of ``nxt`` (an injective partial map): those from which following ``nxt`` never
    ends. Pointer doubling, enough rounds to cross the longest path."""
    n = nxt.size
    ends = nxt < 0
    p = np.where(ends, 0, nxt)
    for _ in range(max(1, math.ceil(math.log2(n + 1))) + 1):
        live = ~ends
        q = p[live]
        ends[live] = ends[q]
        p[live] = p[q]
    return ~ends
