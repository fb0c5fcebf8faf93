"""The *arrangement* path of nesting's exact rebuild (:mod:`.overlaps`): the regions of groups of crossing loops
from their noded boundaries, in numpy, for all groups at once.

The noded pieces form a planar graph whose nodes are the loops' start points (degree 2) and the crossing points
(degree 4 or more). Its faces are the cycles of half-edges (next = the first edge clockwise at the node); the
winding number of every face follows from the outer face of its connected component (the winding number of the
other loops at one of its vertices) by +1 across each piece from its right to its left. The pieces with the fill
rule's answer differing on their two sides are the region's boundary; they are linked into rings (at a node, the
next boundary edge clockwise), counter-clockwise rings are shells, clockwise ones holes, each hole in the smallest
shell around it: what ``polygonize`` then ``union_all`` of the filled faces gives (GEOS's minimal rings).

A group takes this path only when its noding is plain: no loop with a repeated point, every loop's pieces in order
and unchanged apart from the crossing points inserted (so no loop touches another at a vertex and no segments
overlap), no two edges leaving a node within 1e-9 rad of each other, a consistent winding number on every face, no
ring through a node twice and each hole's shell found unambiguously. The others go to GEOS (:mod:`.overlaps`).
"""

from __future__ import annotations

import numpy as np

from ..mesh.graph import connected_labels
from ..ragged import expand_ranges, unique_ints
from .rings import _winding_numbers, cycle_labels, filled

__all__ = ["Noded", "arrangement"]

_GAP = 1e-9  # rad: the smallest angle between two edges leaving a node that the arrangement path orders itself
_REL = 1e-12  # relative size of a shoelace sum below which its sign is left to GEOS


class Noded:
    """The noded pieces of every group: points ``z`` (complex), offsets ``off``, point counts ``cnt``, group ``g``."""

    def __init__(self, noded: np.ndarray):
        import shapely

        edges, self.g = shapely.get_parts(noded, return_index=True)
        self.cnt = shapely.get_num_coordinates(edges).astype(np.int64)
        self.z = np.ascontiguousarray(shapely.get_coordinates(edges)).view(np.complex128).reshape(-1)
        self.off = np.zeros(self.cnt.size + 1, dtype=np.int64)
        np.cumsum(self.cnt, out=self.off[1:])


def _walk(starts: np.ndarray, nxt: np.ndarray, h_node: np.ndarray) -> tuple[list[list[int]], list[bool]]:
    """The cycles of ``nxt`` through the half-edges ``starts`` (a permutation of them), each from its smallest
    member, and whether each passes a node twice (a Python loop per half-edge: boundary pieces are few)."""
    nx, hn = nxt.tolist(), h_node.tolist()
    seen: set[int] = set()
    rings, twice = [], []
    for h0 in starts.tolist():
        if h0 in seen:
            continue
        seq = [h0]
        h = nx[h0]
        while h != h0:
            seq.append(h)
            h = nx[h]
        seen.update(seq)
        rings.append(seq)
        twice.append(len({hn[x] for x in seq}) < len(seq))
    return rings, twice


def _half_edges(z, es, ee, start_node, end_node, group, bad):
    """Half-edges 2i (along piece i) and 2i + 1 (against it): the node each leaves, and per node the half-edges in
    counter-clockwise order ``o`` with their place: ``first`` (index in ``o`` of the node's first), ``size``,
    ``rank``. Marks ``bad`` the groups with two edges leaving a crossing within ``_GAP`` of each other."""
    h_node = np.empty(2 * es.size, dtype=np.int64)
    h_node[0::2], h_node[1::2] = start_node, end_node
    h_dir = np.empty(2 * es.size, dtype=np.complex128)
    h_dir[0::2], h_dir[1::2] = z[es + 1] - z[es], z[ee - 1] - z[ee]
    ang = np.angle(h_dir)
    o = np.lexsort((ang, h_node))
    sn = h_node[o]
    head = np.ones(o.size, dtype=bool)
    head[1:] = sn[1:] != sn[:-1]
    heads = np.flatnonzero(head)
    counts = np.diff(np.append(heads, o.size))
    first, size = np.repeat(heads, counts), np.repeat(counts, counts)
    rank = np.arange(o.size) - first
    a = ang[o]
    gap = np.empty(o.size)
    gap[:-1] = a[1:] - a[:-1]
    end = first + size - 1
    gap[end] = a[first[end]] + 2 * np.pi - a[end]
    bad[group[o >> 1][(size >= 4) & (gap <= _GAP)]] = True
    return h_node, o, first, size, rank


def arrangement(ne, rz, roff, loop_g, lid, n_groups, pc, offsets, lo, hi, fill_rule):
    """Regions of the groups by the arrangement path (see the module docstring): (ok (G,) bool, one MultiPolygon
    per group with ``ok``); the groups without ``ok`` are left to GEOS."""
    bad = np.zeros(n_groups, dtype=bool)
    n_loop = np.diff(roff) - 1
    bad[loop_g[n_loop < 3]] = True
    rep = np.flatnonzero(rz[1:] == rz[:-1])  # a repeated point (never across rings: a ring ends on its start)
    bad[loop_g[np.searchsorted(roff, rep, side="right") - 1]] = True
    z, off, eg = ne.z, ne.off, ne.g
    es, ee = off[:-1], off[1:] - 1
    n_e = es.size
    # nodes: the pieces' end points, per group
    end_g = np.concatenate([eg, eg])
    end_z = np.concatenate([z[es], z[ee]])
    o = np.lexsort((end_z.imag, end_z.real, end_g))
    new_node = np.ones(o.size, dtype=bool)
    new_node[1:] = (end_g[o][1:] != end_g[o][:-1]) | (end_z[o][1:] != end_z[o][:-1])
    nid = np.empty(o.size, dtype=np.int64)
    nid[o] = np.cumsum(new_node) - 1
    deg = np.bincount(nid)
    bad[end_g[o][new_node][(deg % 2 == 1) | (deg < 2)]] = True
    start_node, end_node = nid[:n_e], nid[n_e:]
    crossing = deg >= 4
    sc, ec = crossing[start_node], crossing[end_node]
    # without the crossing points, the pieces give back every ring exactly, in order (or the group goes to GEOS)
    keep = np.ones(z.size, dtype=bool)
    keep[es[sc]] = False
    keep[ee[ec]] = False
    coord_g = np.repeat(eg, ne.cnt)
    seq_g = coord_g[keep]
    bad |= np.bincount(seq_g, minlength=n_groups) != np.bincount(loop_g, weights=n_loop + 1, minlength=n_groups)
    ring_g = np.repeat(loop_g, n_loop + 1)
    if bad.any():
        differ = z[keep][~bad[seq_g]] != rz[~bad[ring_g]]
        bad[seq_g[~bad[seq_g]][differ]] = True
    else:
        bad[seq_g[z[keep] != rz]] = True
    # the pieces of the good groups, each assigned to its loop (pl: index into good_loop)
    k = np.flatnonzero(~bad[eg])
    good_loop = np.flatnonzero(~bad[loop_g])
    c = ne.cnt[k] - sc[k] - ec[k]
    cb = np.cumsum(c) - c
    r = np.zeros(good_loop.size + 1, dtype=np.int64)
    np.cumsum(n_loop[good_loop] + 1, out=r[1:])
    pl = np.minimum(np.searchsorted(r, cb, side="right") - 1, good_loop.size - 1)
    wrong = (c >= 1) & (np.searchsorted(r, cb + c - 1, side="right") - 1 != pl)
    wrong |= ~sc[k] & (cb != r[pl])
    wrong |= ~ec[k] & (cb + c != r[pl + 1])
    piece_g = eg[k]
    bad[piece_g[wrong]] = True
    ks, ke = es[k], ee[k]
    h_node, o, first, size, rank = _half_edges(z, ks, ke, start_node[k], end_node[k], piece_g, bad)
    nxt = np.empty(o.size, dtype=np.int64)
    nxt[o ^ 1] = o[first + (rank - 1) % size]  # arriving along o's twin: leave by the first edge clockwise
    # faces: the cycles of nxt, their signed areas (x2), and the components (loops joined at their crossings)
    cyc, h_cyc = np.unique(cycle_labels(nxt), return_inverse=True)
    cr = np.zeros(z.size)
    cr[:-1] = (z[:-1].conj() * z[1:]).imag
    cr[ee] = 0.0
    s_piece = np.add.reduceat(cr, es)[k] if n_e else np.zeros(0)
    a_piece = np.add.reduceat(np.abs(cr), es)[k] if n_e else np.zeros(0)
    cyc_area = np.bincount(h_cyc, weights=np.stack([s_piece, -s_piece], axis=1).reshape(-1), minlength=cyc.size)
    cyc_tol = _REL * np.bincount(h_cyc, weights=np.repeat(a_piece, 2), minlength=cyc.size)
    at_node = np.concatenate([start_node[k], end_node[k]])
    lead_of = np.full(deg.size, -1, dtype=np.int64)
    lead_of[at_node[::-1]] = np.concatenate([pl, pl])[::-1]  # a loop through each node; all its loops join it
    comp_loop = connected_labels(good_loop.size, np.concatenate([pl, pl]), lead_of[at_node])
    cyc_comp = comp_loop[pl[cyc >> 1]]
    cyc_g = piece_g[cyc >> 1]
    oc = np.lexsort((cyc_area, cyc_comp))
    lead = np.ones(oc.size, dtype=bool)
    lead[1:] = cyc_comp[oc][1:] != cyc_comp[oc][:-1]
    outer = oc[lead]  # per component, its most negative cycle: the outer face, the one face traversed clockwise
    comps = cyc_comp[outer]
    negative = np.bincount(cyc_comp, weights=cyc_area < -cyc_tol, minlength=good_loop.size)
    bad[cyc_g[(negative[cyc_comp] != 1)]] = True
    # winding number of each component's outer face: the other loops of its group around one of its points
    q = pc[offsets[:-1][lid[good_loop[comps]]]]
    gl_g = loop_g[good_loop]
    g_first = np.searchsorted(gl_g, gl_g[comps])
    pi, pj = expand_ranges(g_first, np.searchsorted(gl_g, gl_g[comps], side="right") - g_first)
    pair = comp_loop[pj] != comps[pi]
    pi, pj = pi[pair], lid[good_loop[pj[pair]]]
    qx, qy = q.real[pi], q.imag[pi]
    near = (lo[pj, 0] <= qx) & (qx <= hi[pj, 0]) & (lo[pj, 1] <= qy) & (qy <= hi[pj, 1])
    pi, pj = pi[near], pj[near]
    w_out = np.bincount(pi, weights=_winding_numbers(pc, offsets, pi, pj, q), minlength=comps.size)
    # every face from its component's outer face: +1 across a piece from its right to its left
    w = np.zeros(cyc.size, dtype=np.int64)
    known = np.zeros(cyc.size, dtype=bool)
    w[outer] = np.rint(w_out).astype(np.int64)
    known[outer] = True
    left, right = h_cyc[0::2], h_cyc[1::2]
    for _ in range(cyc.size):
        m1 = known[right] & ~known[left]
        w[left[m1]] = w[right[m1]] + 1
        known[left[m1]] = True
        m2 = known[left] & ~known[right]
        w[right[m2]] = w[left[m2]] - 1
        known[right[m2]] = True
        if not (m1.any() or m2.any()):
            break
    bad[piece_g[~known[left] | ~known[right] | (w[left] - w[right] != 1)]] = True
    # the region's boundary: pieces whose sides differ, kept with the filled side on the left, linked at the nodes
    # to the first boundary edge clockwise
    fill = filled(w, fill_rule)
    boundary = np.flatnonzero(fill[left] != fill[right])
    reg = np.zeros(o.size, dtype=bool)
    reg[2 * boundary + np.where(fill[left[boundary]], 0, 1)] = True
    arrive = reg[o ^ 1]
    found = np.full(o.size, -1, dtype=np.int64)
    for step in range(1, int(size.max()) if size.size else 1):
        cand = o[first + (rank - step) % size]
        take = arrive & (found < 0) & reg[cand] & (step < size)
        found[take] = cand[take]
    rnext = np.full(o.size, -1, dtype=np.int64)
    rnext[(o ^ 1)[arrive]] = found[arrive]
    r_h = np.flatnonzero(reg)
    lost = rnext[r_h] < 0
    bad[piece_g[r_h[lost] >> 1]] = True
    hits = np.bincount(rnext[r_h][~lost], minlength=o.size)
    bad[piece_g[np.flatnonzero(hits > 1) >> 1]] = True
    r_h = r_h[~bad[piece_g[r_h >> 1]]]
    rings, twice = _walk(r_h, rnext, h_node)
    ring_g = piece_g[np.array([s[0] for s in rings], dtype=np.int64) >> 1]
    bad[ring_g[np.array(twice, dtype=bool)]] = True
    h_seq = np.array([h for s in rings for h in s], dtype=np.int64)
    h_ring = np.repeat(np.arange(len(rings)), [len(s) for s in rings])
    box = [np.minimum.reduceat(z.real, es)[k], np.minimum.reduceat(z.imag, es)[k],
           np.maximum.reduceat(z.real, es)[k], np.maximum.reduceat(z.imag, es)[k]] if n_e else [np.zeros(0)] * 4
    return _polygons_of(ring_g, h_seq, h_ring, z, ks, ke, s_piece, a_piece, np.stack(box[:2], axis=1),
                        np.stack(box[2:], axis=1), bad, n_groups)


def _polygons_of(ring_g, h_seq, h_ring, z, ks, ke, s_piece, a_piece, p_lo, p_hi, bad, n_groups):
    """The rings (half-edge cycles ``h_seq``, ring ``h_ring`` of each) as shells and holes of one MultiPolygon per
    group; each hole goes to the shell with the smallest box among those around it (GEOS's rule; ambiguous cases
    mark the group ``bad``). Rings' signed areas (x2) and boxes come from their pieces' (``s_piece``, ``p_lo``...)."""
    import shapely

    n_ring = ring_g.size
    piece = h_seq >> 1
    back = (h_seq & 1) == 1
    area = np.bincount(h_ring, weights=np.where(back, -s_piece[piece], s_piece[piece]), minlength=n_ring)
    tol = _REL * np.bincount(h_ring, weights=a_piece[piece], minlength=n_ring)
    bad[ring_g[np.abs(area) <= tol]] = True
    shell = area > 0
    lo = np.full((n_ring, 2), np.inf)
    hi = np.full((n_ring, 2), -np.inf)
    np.minimum.at(lo, h_ring, p_lo[piece])
    np.maximum.at(hi, h_ring, p_hi[piece])
    # hole -> shell candidates in its group: box around the hole's box, not equal to it
    g_first = np.searchsorted(ring_g, ring_g)
    g_count = np.searchsorted(ring_g, ring_g, side="right") - g_first
    holes = np.flatnonzero(~shell)
    hi_, sj = expand_ranges(g_first[holes], g_count[holes])
    hi_ = holes[hi_]
    cand = shell[sj] & np.all(lo[sj] <= lo[hi_], axis=1) & np.all(hi[hi_] <= hi[sj], axis=1)
    cand &= ~np.all((lo[sj] == lo[hi_]) & (hi[sj] == hi[hi_]), axis=1)
    hi_, sj = hi_[cand], sj[cand]
    contains = np.ones(hi_.size, dtype=bool)
    multi = np.bincount(hi_, minlength=n_ring)[hi_] > 1
    if multi.any():  # several boxes around the hole's: which shells hold a point inside a piece of the hole
        mh, ms = hi_[multi], sj[multi]
        inner = ke[piece] - ks[piece] >= 2
        test = np.full(n_ring, -1, dtype=np.int64)
        test[h_ring[inner][::-1]] = np.where(back, ke[piece] - 1, ks[piece] + 1)[inner][::-1]
        bad[ring_g[mh[test[mh] < 0]]] = True
        ring, roff = _ring_points_of(h_seq, h_ring, n_ring, unique_ints(ms), z, ks, ke, close=False)
        contains[multi] = _winding_numbers(ring, roff, np.arange(mh.size), np.searchsorted(unique_ints(ms), ms),
                                           z[np.maximum(test[mh], 0)]) != 0
    hi_, sj = hi_[contains], sj[contains]
    o = np.lexsort((np.prod(hi[sj] - lo[sj], axis=1), hi_))
    lead = np.ones(o.size, dtype=bool)
    lead[1:] = hi_[o][1:] != hi_[o][:-1]
    parent = np.full(n_ring, -1, dtype=np.int64)
    parent[hi_[o][lead]] = sj[o][lead]
    c = parent[hi_]
    bad[ring_g[hi_[~np.all((lo[sj] <= lo[c]) & (hi[c] <= hi[sj]), axis=1)]]] = True
    bad[ring_g[holes[parent[holes] < 0]]] = True
    ok = ~bad
    groups = np.flatnonzero(ok)
    if groups.size == 0:
        return ok, np.zeros(0, dtype=object)
    # rings of the good groups: shells, each followed by its holes
    owner_shell = np.where(shell, np.arange(n_ring), parent)
    order = np.lexsort((np.arange(n_ring), ~shell, owner_shell, ring_g))
    order = order[ok[ring_g][order]]
    ring, coff = _ring_points_of(h_seq, h_ring, n_ring, order, z, ks, ke, close=True)
    is_shell = shell[order]
    poly_off = np.append(np.flatnonzero(is_shell), order.size)
    mp_off = np.zeros(groups.size + 1, dtype=np.int64)
    np.cumsum(np.bincount(ring_g[order][is_shell], minlength=n_groups)[groups], out=mp_off[1:])
    coords = ring.view(np.float64).reshape(-1, 2)
    return ok, shapely.from_ragged_array(shapely.GeometryType.MULTIPOLYGON, coords, (coff, poly_off, mp_off))


def _ring_points_of(h_seq, h_ring, n_ring, rings, z, ks, ke, close):
    """Points (complex) of ``rings`` (in that order; of ``n_ring``) from their half-edges: each gives its piece's
    points but the last, reversed when against the piece; ``close``: repeat each ring's first point at its end.
    And the rings' offsets."""
    h_count = np.bincount(h_ring, minlength=n_ring)
    h_off = np.cumsum(h_count) - h_count
    _, at = expand_ranges(h_off[rings], h_count[rings])
    h = h_seq[at]
    piece = h >> 1
    n_pts = ke[piece] - ks[piece]
    owner, t = expand_ranges(np.zeros(h.size, dtype=np.int64), n_pts)
    idx = np.where((h & 1)[owner] == 1, ke[piece][owner] - t, ks[piece][owner] + t)
    r_len = np.bincount(np.repeat(np.arange(rings.size), h_count[rings]), weights=n_pts, minlength=rings.size)
    r_len = r_len.astype(np.int64)
    pts = z[idx]
    off = np.zeros(rings.size + 1, dtype=np.int64)
    if close:
        np.cumsum(r_len + 1, out=off[1:])
        ends = np.cumsum(r_len)
        return np.insert(pts, ends, pts[ends - r_len]), off
    np.cumsum(r_len, out=off[1:])
    return pts, off
