"""Mesh defects the slicer works around, counted for the report: flipped facets, inside-out shells, non-manifold and
open edges, degenerate facets.

The slicer cuts a prepared copy where needed (:func:`wound_for_slicing`): open edges joined to the nearby open edge
they were meant to share (:mod:`gpuslice.mesh.seams`: a triangle soup, unwelded edges), the holes left closed by fans
of facets (:mod:`gpuslice.mesh.holes`), a facet stored twice once, and a shell whose facets disagree on their
winding turned outward (a loop's direction says which side is material, and a cavity whose walls were cut from facets
mostly wound the wrong way was filled). Inside-out shells that are consistently
wound stay as stored (the fill rules read them: ``positive`` as empty), open chains are joined in ``chain.py``,
degenerate facets are dropped in ``mesh.py``. Otherwise this module only *counts* what was wrong, so that
``gpuslice slice`` can say which repairs a file needed. Everything is vectorised and linear in the facets: the
pairing of the facet sides along each edge comes from the edge numbering (``Mesh.edge_sides``, no sort here), the
shells are connected components (:func:`gpuslice.mesh.graph.components`: on the device when the mesh was welded on one),
the volumes are summed a block of facets at a time, solid angles judge nested shells.

Definitions (all counts are integers):

* **shell**: a set of facets connected through *manifold* edges (edges used by exactly two facets). Non-manifold
  edges (three or more facets) and open edges (one facet) separate shells.
* **consistent orientation** of a shell: the two facets of every manifold edge traverse it in opposite directions.
  The facets of an orientable shell fall into two classes (wound with, or against, its first facet); a shell whose
  constraints contradict each other (a Möbius-like strip) is *non-orientable* and not judged.
* **outward** orientation: the consistent orientation whose enclosed volume is positive for a shell nested in an
  even number of other shells (an outer surface) and negative for one nested in an odd number (a cavity's wall),
  nesting judged by the winding number of the shell's vertices with respect to the other shells.
* ``flipped_facets``: facets whose stored winding disagrees with their shell's outward orientation.
* ``inverted_shells``: shells where that is more than half of their facets (stored inside out).
* ``non_orientable_shells``: shells without a consistent orientation.
* ``non_manifold_edges``: edges used by three or more facets; ``open_edges``: edges used by one facet.
* ``degenerate_facets``: facets dropped when the mesh was built (corners welded to fewer than three vertices).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .graph import components
from .holes import filled_holes
from .mesh import Mesh, _directed_edges_paired, need_mesh
from .seams import joined_open_edges

__all__ = ["MESH_REPAIR_KINDS", "mesh_repairs", "outward_facets", "wound_for_slicing"]

#: Keys of :func:`mesh_repairs`, in report order.
MESH_REPAIR_KINDS = (
    "flipped_facets",
    "inverted_shells",
    "non_orientable_shells",
    "non_manifold_edges",
    "open_edges",
    "degenerate_facets",
)

# vertices of a shell tested against each shell that may contain it
_SAMPLES = 8
# (sample point, facet) solid angles per numpy batch (about 100 bytes each)
_BATCH = 500_000
# rows of the shell-box containment test per block
_ROWS = 256
# total (sample point, facet) solid angles for the nesting test; candidates beyond it are left unjudged
_WORK = 50_000_000
# facets per block of the float64 volume terms (bounded memory: no (F, 3, 3) float64 copy of the mesh)
_FACET_BLOCK = 1 << 16


def _shells(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shell id (F,) of every facet (shells numbered by their first facet), its sign relative to the shell's first
    facet (F,) ±1 (int8), and a per-shell non-orientable flag (S,)."""
    n = mesh.n_faces
    sides = mesh.edge_sides()  # kept from the edge numbering: no sort, no scatter here
    manifold = np.flatnonzero(sides.count == 2)
    # the facets of the two sides of each manifold edge (in edge order)
    f1, f2 = sides.first[manifold] // 3, sides.last[manifold] // 3
    same_dir = sides.forward[manifold] != 1  # both sides run the same way: one facet is flipped
    del manifold
    device = mesh.device
    first = components(n, f1, f2, device)  # the first facet of each facet's shell
    is_root = first == np.arange(n, dtype=first.dtype)
    shell = (np.cumsum(is_root, dtype=np.int64) - 1)[first]  # shells numbered in the order of their first facets
    n_shells = int(is_root.sum())
    del is_root
    if not same_dir.any():  # consistently wound already: every facet agrees with its shell's first one
        return shell, np.ones(n, dtype=np.int8), np.zeros(n_shells, dtype=bool)
    # the doubled graph: node f is "facet f as stored", node f + n "facet f reversed"
    a = np.concatenate([f1, f1 + n])
    b = np.concatenate([np.where(same_dir, f2 + n, f2), np.where(same_dir, f2, f2 + n)])
    label = components(2 * n, a, b, device)
    del a, b
    sign = np.where(label[:n] == label[first], 1, -1).astype(np.int8)
    non_orientable = np.zeros(n_shells, dtype=bool)
    non_orientable[shell[label[:n] == label[n:]]] = True
    sign[non_orientable[shell]] = 1
    return shell, sign, non_orientable


def _solid_angle_winding(points: np.ndarray, tri: np.ndarray, orient: np.ndarray) -> np.ndarray:
    """Winding number (P,) of each point with respect to the triangles (T, 3, 3), each counted with its ``orient``
    (T,) ±1 (Van Oosterom–Strackee solid angles)."""
    out = np.zeros(points.shape[0])
    step = max(1, _BATCH // max(1, tri.shape[0]))
    for s in range(0, points.shape[0], step):
        r = tri[None, :, :, :] - points[s : s + step, None, None, :]  # (p, T, 3, 3)
        a, b, c = r[:, :, 0], r[:, :, 1], r[:, :, 2]
        la, lb, lc = (np.sqrt(np.einsum("ptk,ptk->pt", v, v)) for v in (a, b, c))
        det = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ptk,ptk->pt", a, b) * lc + np.einsum("ptk,ptk->pt", a, c) * lb
               + np.einsum("ptk,ptk->pt", b, c) * la)
        out[s : s + step] = (np.arctan2(det, den) * orient).sum(axis=1) / (2 * np.pi)
    return out


def _volume_terms(verts: np.ndarray, faces: np.ndarray, blocks: list[slice], centre: np.ndarray) -> np.ndarray:
    """(F,) float64 six times the signed volume of each facet's tetrahedron with ``centre`` (mm³): the differences
    once a vertex, as columns (1-D gathers: 2-D fancy indexing is ~3x slower), a block of facets at a time."""
    det = np.empty(faces.shape[0])
    about = [verts[:, k].astype(np.float64) - centre[k] for k in range(3)]
    for b in blocks:
        f = faces[b]
        (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) = ([c[f[:, j]] for c in about] for j in range(3))
        det[b] = x0 * (y1 * z2 - z1 * y2) + y0 * (z1 * x2 - x1 * z2) + z0 * (x1 * y2 - y1 * x2)
    return det


def outward_facets(mesh: Mesh) -> tuple[np.ndarray, dict[str, int]]:
    """Which facets are wound against their shell's outward orientation, and the counts of :func:`mesh_repairs`.

    Returns ``flipped`` (F,) bool (True: the stored winding is reversed with respect to the outward orientation;
    reversing exactly these facets gives a consistently, outward-oriented mesh) and the counts dictionary.
    """
    return _outward(mesh, _shells(mesh) if mesh.n_faces else None)


def _outward(mesh: Mesh, shells) -> tuple[np.ndarray, dict[str, int]]:
    """:func:`outward_facets` of ``mesh`` whose :func:`_shells` are ``shells`` (None: no facet)."""
    n = mesh.n_faces
    edge_counts = mesh.edge_face_counts()
    counts = {
        "flipped_facets": 0,
        "inverted_shells": 0,
        "non_orientable_shells": 0,
        "non_manifold_edges": int(np.sum(edge_counts > 2)),
        "open_edges": int(np.sum(edge_counts == 1)),
        "degenerate_facets": int(mesh.dropped_degenerate),
    }
    if n == 0:
        return np.zeros(0, bool), counts
    shell, sign, non_orientable = shells
    n_shells = non_orientable.size
    verts, faces = mesh.vertices, mesh.faces
    blocks = [slice(a, min(n, a + _FACET_BLOCK)) for a in range(0, n, _FACET_BLOCK)]
    # per-shell bounding boxes; volumes about the box centre (translation matters only for open shells)
    if n_shells == 1:
        lo = np.array([[verts[:, k].min() for k in range(3)]], dtype=np.float64)
        hi = np.array([[verts[:, k].max() for k in range(3)]], dtype=np.float64)
    else:
        lo = np.full((n_shells, 3), np.inf)
        hi = np.full((n_shells, 3), -np.inf)
        for b in blocks:
            tri = verts[faces[b]].astype(np.float64)  # (block, 3, 3) mm
            for k in range(3):
                c = tri[:, :, k]
                np.minimum.at(lo[:, k], shell[b], np.minimum(np.minimum(c[:, 0], c[:, 1]), c[:, 2]))
                np.maximum.at(hi[:, k], shell[b], np.maximum(np.maximum(c[:, 0], c[:, 1]), c[:, 2]))
    centre = (lo + hi) / 2
    if n_shells == 1:
        det = _volume_terms(verts, faces, blocks, centre[0])
    else:
        det = np.empty(n)
        for b in blocks:  # a block at a time: the same per-facet arithmetic as on the whole (F, 3, 3) array
            r = verts[faces[b]].astype(np.float64) - centre[shell[b]][:, None, :]
            det[b] = np.einsum("ij,ij->i", r[:, 0], np.cross(r[:, 1], r[:, 2]))
    volume = np.bincount(shell, weights=sign * det, minlength=n_shells) / 6.0  # with the first facet's winding
    del det
    # a shell is judged by its volume only when it is closed enough to have an inside (few open edges, not flat)
    size = np.maximum((hi - lo).max(axis=1), 1e-300)
    sides = mesh.edge_sides()
    open_sides = np.bincount(shell[sides.first[sides.count == 1] // 3], minlength=n_shells)  # an open edge: 1 side
    shell_size = np.bincount(shell, minlength=n_shells)
    solid = (open_sides * 4 <= 3 * shell_size) & (shell_size >= 4) & (np.abs(volume) > 1e-9 * size**3)
    solid &= ~non_orientable

    # shells nested in another shell (its box strictly holds theirs and its surface winds around their vertices)
    # may be cavities (wound inward) or overlaps (wound outward): both are meaningful, so they are not judged
    nested = np.zeros(n_shells, dtype=bool)
    cand = np.flatnonzero(solid)
    if cand.size > 1:
        pairs_t, pairs_s = [], []
        for c0 in range(0, cand.size, _ROWS):  # box containment in row blocks: memory ~ _ROWS x shells
            t = cand[c0 : c0 + _ROWS]
            holds = (
                np.all(lo[t, None, :] <= lo[None, cand, :], axis=2)
                & np.all(hi[None, cand, :] <= hi[t, None, :], axis=2)
                & np.any((lo[t, None, :] < lo[None, cand, :]) | (hi[None, cand, :] < hi[t, None, :]), axis=2)
            )  # holds[i, j]: the box of shell t[i] contains the box of shell cand[j]
            i, j = np.nonzero(holds)
            pairs_t.append(t[i])
            pairs_s.append(cand[j])
        t_idx, s_idx = np.concatenate(pairs_t), np.concatenate(pairs_s)
        if t_idx.size:
            order = np.argsort(shell, kind="stable")
            starts = np.searchsorted(shell[order], np.arange(n_shells + 1))
            work = 0
            for t in np.unique(t_idx):
                ft = order[starts[t] : starts[t + 1]]
                tri = None  # shell t's facets (T, 3, 3) mm, made at the first test
                for s in s_idx[t_idx == t]:
                    if nested[s]:
                        continue
                    if work > _WORK:  # too many candidates to test: leave them unjudged (majority), never guess
                        nested[s] = True
                        continue
                    ids = np.unique(faces[order[starts[s] : starts[s + 1]]].reshape(-1))
                    pick = ids[np.linspace(0, ids.size - 1, min(_SAMPLES, ids.size)).astype(np.int64)]
                    if tri is None:
                        tri = verts[faces[ft]].astype(np.float64)
                    # |winding number| is the same for either orientation of t, so t's first-facet class will do
                    w = _solid_angle_winding(verts[pick].astype(np.float64), tri, sign[ft])
                    work += pick.size * ft.size
                    nested[s] = bool(np.all(np.abs(w) > 0.5))
    # outward class (relative to each shell's first facet): positive volume for a free solid shell, else the
    # majority of its facets
    minus = np.bincount(shell, weights=(sign < 0), minlength=n_shells)
    majority = np.where(minus * 2 > shell_size, -1, 1)
    judged = solid & ~nested
    outward = np.where(judged, np.where(volume > 0, 1, -1), majority)
    flipped = (sign != outward[shell]) & ~non_orientable[shell]
    n_flipped = np.bincount(shell, weights=flipped, minlength=n_shells)
    counts["flipped_facets"] = int(flipped.sum())
    counts["inverted_shells"] = int(np.sum(n_flipped * 2 > shell_size))
    counts["non_orientable_shells"] = int(non_orientable.sum())
    return flipped, counts


def mesh_repairs(mesh: Mesh) -> dict[str, int]:
    """Counts of the mesh defects the slicer works around (keys :data:`MESH_REPAIR_KINDS`, see the module docstring).

    Flipped facets are sliced as if turned outward (:func:`wound_for_slicing`) and inside-out shells as stored; these
    counts, of the mesh as stored, say how many there were.
    """
    need_mesh(mesh, "mesh_repairs")
    if "mesh_repairs" not in mesh._cache:
        mesh._cache["mesh_repairs"] = outward_facets(mesh)[1]
    return dict(mesh._cache["mesh_repairs"])


def wound_for_slicing(mesh: Mesh, join: float = 0.0, fill: bool = False, max_gap: float = 0.0) -> Mesh:
    """The mesh the slicer cuts: ``mesh`` itself where every shell is consistently wound, no facet is repeated and no
    open edge is joined, else a copy whose open edges are joined to their nearby partners first (``join``: the
    largest distance, mm, between the corners of two open edges that are one edge; 0: none joined;
    :mod:`gpuslice.mesh.seams`; the number of pairs in the copy's ``_cache["joined_edges"]``) and, with ``fill``,
    the loops of open edges left closed by fans of facets (:mod:`gpuslice.mesh.holes`, those wider than ``max_gap``,
    mm; ``_cache["filled_holes"]``),
    without the repeats of a facet (the same corners in the same turn: :func:`_without_repeats`) in
    which the facets of each shell that mixes both windings face outward (:func:`outward_facets`; a facet turned has
    its corners 0, 2, 1 and its sides reordered to match, the same edge ids). Shells wound consistently, inside out
    or not, are left as stored, and non-orientable ones too.

    Why: chaining follows each facet's winding, and where a loop's segments disagree it goes the way most of them go
    (``chain._repair``); a cavity cut from facets mostly wound the wrong way then runs the way of its outer wall, and
    under the ``nonzero`` fill rule the cavity was filled (a hollow box with 4 of its cavity's 8 wall facets
    flipped: 400 mm² instead of 300; a helper's sweep). Costs nothing on a consistently wound manifold mesh (a test of
    the edge pairing); otherwise the repeats among the facets beside a crowded edge, and the shells' classes and
    volumes, as the mesh check computes them.
    """
    count = mesh.edge_sides().count
    if mesh.n_faces == 0 or (_directed_edges_paired(mesh) and not (count > 2).any() and
                             not ((join > 0 or fill) and (count == 1).any())):
        return mesh
    key = ("wound_for_slicing", float(join), bool(fill), float(max_gap))
    if key not in mesh._cache:  # (a resin job slices its sub-planes' chunks from the same mesh)
        joined, n = joined_open_edges(mesh, join)
        filled, holes = filled_holes(joined, max_gap, n) if fill else (joined, 0)
        once = _without_repeats(filled)
        out = once if _directed_edges_paired(once) else _turned_outward(once)
        if n or holes:  # (then a new mesh)
            out._cache["joined_edges"], out._cache["filled_holes"] = n, holes
        mesh._cache[key] = out
    return mesh._cache[key]


def _without_repeats(mesh: Mesh) -> Mesh:
    """``mesh``, or a copy keeping the first of the facets with the same corners in the same turn (an exporter's
    repeat: each edge of the facet is then used three times, and chaining paired the facet with its neighbours and
    left the repeat a loose chain, which gap closing could join to another body: two bars 0.8 mm apart with their
    facing walls repeated gave 56 mm² for 40; a helper's sweep), where the copies add nothing: every side of a copy
    is left with at most two facets without them (two overlapping bodies that share a face, stored with the same
    corners, each keep it: a review). Only the facets beside an edge of three or more sides are compared. A facet
    and a copy the other way round: where each of their sides has at most one other facet (the copy was flipped in a
    surface), the copy that runs with more of those neighbours goes; where a side has more (a wall between two bodies
    that touch) or the neighbours are split evenly, both stay."""
    sides = mesh.edge_sides()
    crowded = sides.count > 2
    if not crowded.any():
        return mesh
    cand = np.flatnonzero(crowded[mesh.face_edges].any(axis=1))
    f = mesh.faces[cand].astype(np.int64)
    turn = np.argmin(f, axis=1)  # each facet's corners from its smallest id, in its own turn
    rows = np.take_along_axis(f, (turn[:, None] + np.arange(3)) % 3, axis=1)
    order = np.lexsort((cand, rows[:, 2], rows[:, 1], rows[:, 0]))
    r = rows[order]
    again = np.zeros(r.shape[0], dtype=bool)
    again[1:] = np.all(r[1:] == r[:-1], axis=1)
    # a copy goes only where it adds nothing: each of its sides is left with at most two facets without the copies (a
    # body that shares a face with another, stored with the same corners, keeps its face: its sides have three)
    copies = cand[order][again]
    extra = np.bincount(mesh.face_edges[copies].reshape(-1), minlength=sides.count.size)
    spare = np.all((sides.count - extra)[mesh.face_edges[copies]] <= 2, axis=1)
    keep = np.ones(mesh.n_faces, dtype=bool)
    keep[copies[spare]] = False
    # a facet and a copy of it the other way round, each of their sides shared with one other facet only (a flipped
    # repeat in a closed surface, not a wall between two bodies): the copy that runs with its neighbours goes
    c = cand[keep[cand]]
    srt = np.sort(mesh.faces[c], axis=1)
    o2 = np.lexsort((c, srt[:, 2], srt[:, 1], srt[:, 0]))
    rot = rows[keep[cand]][o2]  # (the turns: a repeat kept above is not the other way round)
    same = np.all(srt[o2][1:] == srt[o2][:-1], axis=1) & ~np.all(rot[1:] == rot[:-1], axis=1)
    fi, fj = c[o2[:-1][same]], c[o2[1:][same]]
    e = mesh.face_edges[fi]
    pairs = np.bincount(e.reshape(-1), minlength=sides.count.size)  # (a pair's two sides run both ways)
    rest = (sides.count - 2 * pairs)[e]  # the other facets on fi's sides: 1, a neighbour; 0, none (no say)
    runs = mesh.faces[fi] < np.roll(mesh.faces[fi], -1, axis=1)  # fi's side k from the smaller vertex id
    against = runs != (sides.forward - pairs)[e].astype(bool)  # fi runs against that side's neighbour, as it should
    vote = np.where(rest == 1, np.where(against, 1, -1), 0).sum(axis=1)
    decided = np.all(rest <= 1, axis=1) & (vote != 0)
    keep[np.where(vote > 0, fj, fi)[decided]] = False
    if keep.all():
        return mesh
    return replace(mesh, faces=mesh.faces[keep], face_edges=mesh.face_edges[keep],
                   stored_normals=None if mesh.stored_normals is None else mesh.stored_normals[keep])


def _turned_outward(mesh: Mesh) -> Mesh:
    """:func:`wound_for_slicing` of a mesh with some edge used twice in one direction."""
    shells = shell, sign, non_orientable = _shells(mesh)
    mixed = np.zeros(non_orientable.size, dtype=bool)
    mixed[shell[sign < 0]] = True
    mixed &= ~non_orientable
    if not mixed.any():
        return mesh
    flipped, _ = _outward(mesh, shells)
    turn = flipped & mixed[shell]
    if not turn.any():
        return mesh
    faces, face_edges = mesh.faces.copy(), mesh.face_edges.copy()
    faces[turn] = faces[turn][:, [0, 2, 1]]  # sides: (0, 2) was side 2, (2, 1) side 1, (1, 0) side 0
    face_edges[turn] = face_edges[turn][:, [2, 1, 0]]
    return replace(mesh, faces=faces, face_edges=face_edges)
