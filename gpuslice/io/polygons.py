"""Triangles of a mesh file's polygon faces (OBJ, PLY and OFF faces of more than three vertices).

A face of n vertices becomes n − 2 triangles that keep its orientation (the triangles' normals point the way the
face's Newell normal does). Most faces are convex and get the fan from their first vertex, as every reader does;
a fan is exact for a face when none of its triangles turns against the face's normal. A concave face (a CAD
part's L- or U-shaped side, a letter's outline) would get fan triangles that turn round and overlap their
neighbours: the mesh's winding number stays right, but every cutting plane through such a face yields
segments that double back on themselves, which the slicer must then repair as overlapping loops. Those faces are
triangulated inside their outline instead (GEOS's constrained Delaunay triangulation, ``shapely
.constrained_delaunay_triangles``, in the plane of the face's dominant axes, each face in its own frame: no new
vertex). A face whose outline crosses itself, or repeats a point, has no inside to triangulate: it keeps its fan;
so do faces past :data:`MAX_INSIDE` vertices and those past a file's :data:`INSIDE_BUDGET`.

Columnar: one pass of numpy over all faces; GEOS only for the concave ones, in one call (one a face only after
GEOS fails on one).
"""

from __future__ import annotations

import numpy as np

__all__ = ["triangulate", "fan", "MAX_INSIDE", "INSIDE_BUDGET"]

#: a fan triangle turned against its face's normal by more than this share of |its normal| · |the face's| is
#: wrong (collinear vertices, e.g. a point in the middle of a face's edge, give triangles of zero area, which are
#: not wrong: a fan through them is still the face)
_AGAINST = 1e-9
#: concave faces of more vertices keep their fan (GEOS's constrained Delaunay triangulation of one face costs about
#: the cube of its vertex count: 2,048 take a fraction of a second)
MAX_INSIDE = 2048
#: and all of a file's concave faces together, by the sum of their vertex counts squared: 20 spirals of 2,048
#: vertices took 13 s (a review); past it, faces keep their fans (the slices stay right, through the overlap repair)
INSIDE_BUDGET = float(1 << 25)


def fan(counts: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) int64 fan triangles ``(i_0, i_j, i_j+1)`` of faces given as ``counts`` (F,) vertices each (>= 3) and
    their ``indices`` (flat, face after face), and (T,) the face of each triangle."""
    pos, face = _fan_positions(np.asarray(counts, np.int64))
    return np.asarray(indices, np.int64)[pos], face


def _starts(counts: np.ndarray) -> np.ndarray:
    start = np.zeros(counts.size, np.int64)
    np.cumsum(counts[:-1], out=start[1:])
    return start


def _fan_positions(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 3) positions in the flat index list of each fan triangle's corners, and (T,) its face."""
    start = _starts(counts)
    per = counts - 2
    face = np.repeat(np.arange(counts.size), per)
    first = _starts(per)
    j = np.arange(face.size, dtype=np.int64) - np.repeat(first, per) + 1  # 1 .. n-2 within each face
    base = start[face]
    return np.stack([base, base + j, base + j + 1], axis=1), face


def _newell(p: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(F, 3) Newell normal of each face of corners ``p`` (flat, face after face): twice its vector area; its
    direction is the face's orientation."""
    start = _starts(counts)
    nxt = np.arange(p.shape[0], dtype=np.int64) + 1
    nxt[start + counts - 1] = start  # each face's last vertex goes back to its first
    return np.add.reduceat(np.cross(p, p[nxt]), start, axis=0) if p.shape[0] else np.zeros((0, 3))


def _face_frames(vertices: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """The faces' corners (flat), each face moved to its first corner and scaled by a power of two to about unit
    size: the turn tests below then neither underflow (a face 1e-100 across had products of 0, and a folded fan
    passed for convex: a fuzzing helper) nor overflow."""
    start = _starts(counts)
    p = vertices[indices]
    d = p - np.repeat(p[start], counts, axis=0)
    extent = np.maximum.reduceat(np.abs(d).max(axis=1), start) if p.shape[0] else np.zeros(0)
    _, exponent = np.frexp(extent)  # (0: exponent 0, scale 1)
    return d * np.repeat(np.ldexp(1.0, -exponent), counts)[:, None]


def triangulate(vertices: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, int]:
    """Triangles ``(T, 3)`` int64 (indices into ``vertices``) of polygon faces, face by face in order, and how many
    faces were concave and triangulated inside their outline (see the module docstring).

    ``vertices``: (V, 3) float64 (file units); ``counts``: (F,) vertices per face, each >= 3; ``indices``: (sum of
    counts,) vertex indices, face after face, each in range (the callers check). Triangles keep their face's
    vertex order: a triangle face is itself, a convex face its fan from its first vertex. A concave face of more
    than :data:`MAX_INSIDE` vertices, or past :data:`INSIDE_BUDGET`, keeps its fan too (GEOS's time grows with the
    cube of the count: a spiral of 16,000 took 91 s).
    """
    counts = np.asarray(counts, np.int64)
    indices = np.asarray(indices, np.int64)
    if counts.size == 0:
        return np.zeros((0, 3), np.int64), 0
    if (counts == 3).all():
        return indices.reshape(-1, 3).copy(), 0
    pos, face = _fan_positions(counts)
    tri = indices[pos]
    sel = np.flatnonzero((counts > 3)[face])  # the fan triangles of faces of more than three vertices
    vertices = np.asarray(vertices, np.float64)
    q = _face_frames(vertices, counts, indices)
    normal = _newell(q, counts)
    a, b, c = (q[pos[sel, k]] for k in range(3))
    own = np.cross(b - a, c - a)
    fn = normal[face[sel]]
    dot = np.einsum("ij,ij->i", own, fn)
    scale = np.linalg.norm(own, axis=1) * np.linalg.norm(fn, axis=1)
    wrong = np.zeros(counts.size, bool)
    wrong[face[sel][dot < -_AGAINST * scale]] = True
    concave = np.flatnonzero(wrong & (counts <= MAX_INSIDE))
    work = np.cumsum(counts[concave].astype(np.float64) ** 2)
    concave = concave[work <= INSIDE_BUDGET]  # (in face order: the faces past the budget keep their fans)
    if concave.size == 0:
        return tri, 0
    done, inner = _inside(q, counts, indices, normal, concave)
    if done.size == 0:
        return tri, 0
    keep = ~np.isin(face, done)
    # the faces' triangles in face order: the fan's of the others, the outline's of these
    out_face = np.concatenate([face[keep], np.repeat(done, counts[done] - 2)])
    out = np.concatenate([tri[keep], inner])
    order = np.argsort(out_face, kind="stable")
    return out[order], int(done.size)


def _inside(q, counts, indices, normal, faces) -> tuple[np.ndarray, np.ndarray]:
    """The faces among ``faces`` that GEOS triangulates inside their outline (in order) and their triangles, n − 2
    a face in face order, each turned as its face; the others (an outline crossing itself, a point repeated, GEOS
    failing on it or giving other than n − 2 triangles) are left to the fan. ``q``: the corners in each face's own
    frame (:func:`_face_frames`: GEOS, given a face 1e-100 across or far from the origin, failed or cut it wrongly)."""
    import shapely

    start = _starts(counts)
    axis = np.abs(normal[faces]).argmax(axis=1)  # drop the dominant axis: (u, v) = the next two, cyclically
    up = normal[faces, axis] > 0  # the outline is counter-clockwise in (u, v) where the normal points up that axis
    n = counts[faces]
    owner = np.repeat(np.arange(faces.size), n)
    first = _starts(n)
    flat = np.repeat(start[faces] - first, n) + np.arange(int(n.sum()), dtype=np.int64)
    idx, p = indices[flat], q[flat]
    rows = np.arange(p.shape[0])
    ax = axis[owner]
    uv = np.stack([p[rows, (ax + 1) % 3], p[rows, (ax + 2) % 3]], axis=1) + 0.0  # (+ 0.0: no negative zero)
    # (face, u, v) of every outline point, as integers: the way back from a triangle's corner to its vertex index
    keys = np.column_stack([owner, uv.view(np.int64)])
    order = np.lexsort(keys.T[::-1])
    twice = (keys[order[1:]] == keys[order[:-1]]).all(axis=1)
    repeated = np.zeros(faces.size, bool)
    repeated[keys[order[1:]][twice, 0]] = True  # a point twice: no outline to triangulate inside, no way back
    ring_off = np.zeros(faces.size + 1, np.int64)
    np.cumsum(n + 1, out=ring_off[1:])
    ring = np.empty((int(ring_off[-1]), 2))
    ring[rows + owner] = uv
    ring[ring_off[1:] - 1] = uv[first]
    polys = shapely.from_ragged_array(shapely.GeometryType.POLYGON, ring, (ring_off, np.arange(faces.size + 1)))
    take = np.flatnonzero(~repeated & shapely.is_valid(polys))
    if take.size == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64)
    parts, of = shapely.get_parts(_triangulated(polys[take]), return_index=True)
    full = np.bincount(of, minlength=take.size) == n[take] - 2
    if not full.all():  # (GEOS made other than n - 2 triangles: that face keeps its fan)
        mine = full[of]
        take, parts, of = take[full], parts[mine], (np.cumsum(full) - 1)[of[mine]]
    corner = shapely.get_coordinates(parts).reshape(-1, 4, 2)[:, :3] + 0.0  # (each ring closed: its first again)
    wanted = np.column_stack([np.repeat(take[of], 3), corner.reshape(-1, 2).view(np.int64)])
    pos = _rows_in(keys, wanted)
    if (pos < 0).any():  # pragma: no cover - GEOS made a point of its own (it does not)
        raise AssertionError("a triangle corner that is not one of its face's vertices")
    tri = idx[pos].reshape(-1, 3)
    c = corner  # each triangle turned as its face: the sign of its (u, v) area against the outline's
    area = (c[:, 1, 0] - c[:, 0, 0]) * (c[:, 2, 1] - c[:, 0, 1]) - (c[:, 1, 1] - c[:, 0, 1]) * (c[:, 2, 0] - c[:, 0, 0])
    flip = (area > 0) != up[take[of]]
    tri[flip] = tri[flip][:, ::-1]
    order = np.argsort(of, kind="stable")  # (each face's triangles together, faces in order)
    return faces[take], tri[order]


def _triangulated(polys: np.ndarray) -> np.ndarray:
    """GEOS's constrained Delaunay triangulation of each polygon (a GeometryCollection of triangles each; an empty
    one where GEOS fails on that polygon: "Unable to find a convex corner", on valid but nearly degenerate
    outlines), all in one call unless one fails."""
    import shapely
    from shapely.errors import GEOSException

    try:
        return shapely.constrained_delaunay_triangles(polys)
    except GEOSException:
        out = np.empty(polys.size, dtype=object)
        for k, poly in enumerate(polys):  # (only after a failure: one call a face)
            try:
                out[k] = shapely.constrained_delaunay_triangles(poly)
            except GEOSException:
                out[k] = shapely.GeometryCollection()
        return out


def _rows_in(keys: np.ndarray, q: np.ndarray) -> np.ndarray:
    """For each row of ``q`` (int64, 3 columns), the index of the equal row of ``keys`` (rows distinct), -1 where
    there is none: both sorted together (lexsort; a key before the queries equal to it), each query taking the
    first row of its run of equal rows."""
    k = keys.shape[0]
    rows = np.concatenate([keys, q])
    tag = np.concatenate([np.zeros(k, np.int8), np.ones(q.shape[0], np.int8)])
    order = np.lexsort((tag, rows[:, 2], rows[:, 1], rows[:, 0]))
    s = rows[order]
    new = np.ones(order.size, bool)
    new[1:] = (s[1:] != s[:-1]).any(axis=1)
    head = order[np.maximum.accumulate(np.where(new, np.arange(order.size), 0))]  # the first row of each run
    out = np.full(q.shape[0], -1, np.int64)
    mine = order >= k
    out[order[mine] - k] = np.where(head[mine] < k, head[mine], -1)
    return out
