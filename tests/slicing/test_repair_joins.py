"""Open chains joined all layers at once (``chain._repair``) against the walk it replaced, kept here as the reference:
a Python loop per layer and per chain end, which took 4.3 s of a 225k-facet triangle soup's 5.9 s.

Random layers of open and closed chains, with free ends sharing slots (joined by id, some reversed), ends within and
beyond ``max_gap`` (gap closing, a chain's own two ends included), coincident ends (cycles whose last point repeats
the first) and single-point chains: every output array and every repair count equal to the reference's."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice.slicing.chain import _SMALL, REPAIR_KINDS, _closest_first, _few_pairs, _greedy_listed, _repair


def _reference_repair(points, offsets, chain_layer, closed, open_idx, head_slot, tail_slot, max_gap, repairs):
    """The walk ``_repair`` was before it was vectorised (gpuslice 7e1563a), verbatim but for its names, its
    matching call (as now), the loops turned round to the way most of their segments go and the points where two
    chains meet kept once (new)."""
    pieces = [points[offsets[i] : offsets[i + 1]] for i in open_idx]
    new_points, new_layer = [], []
    layers = chain_layer[open_idx]
    for lay in np.unique(layers):
        sel = np.flatnonzero(layers == lay)
        m = sel.size
        link = np.full(2 * m, -1, dtype=np.int64)
        slots = np.empty(2 * m, dtype=np.int64)
        slots[0::2], slots[1::2] = head_slot[sel], tail_slot[sel]
        order = np.argsort(slots, kind="stable")
        s = slots[order]
        for a in range(len(order) - 1):
            i, j = order[a], order[a + 1]
            if s[a] == s[a + 1] and link[i] < 0 and link[j] < 0:
                link[i], link[j] = j, i
                repairs["joined_by_id"][lay] += 1
                if (i % 2) == (j % 2):
                    repairs["reversed"][lay] += 1
        free = np.flatnonzero(link < 0)
        if free.size > 1 and max_gap > 0:
            xy = np.array([pieces[sel[e // 2]][0 if e % 2 == 0 else -1] for e in free], dtype=np.float64)
            # (the matching as _repair makes it now: every pair listed up to _SMALL ends)
            matched = (_greedy_listed(xy, np.arange(free.size), max_gap)
                       if free.size <= _SMALL or _few_pairs(xy, max_gap) else _closest_first(xy, max_gap))
            for a, b in matched.tolist():
                i, j = free[a], free[b]
                link[i], link[j] = j, i
            repairs["gap_closed"][lay] += len(matched)
        used = np.zeros(m, dtype=bool)
        starts = [e for e in range(2 * m) if link[e] < 0] + list(range(0, 2 * m, 2))
        for e0 in starts:
            if used[e0 // 2]:
                continue
            parts, e = [], e0
            is_closed = False
            along = 0
            while True:
                c = e // 2
                used[c] = True
                p = pieces[sel[c]]
                parts.append(p if e % 2 == 0 else p[::-1])
                along += (len(p) - 1) * (1 if e % 2 == 0 else -1)
                nxt = link[e ^ 1]
                if nxt < 0:
                    break
                if nxt == e0:
                    is_closed = True
                    break
                e = nxt
            pts = np.concatenate(parts)
            if is_closed and along < 0:  # (new: a loop goes the way most of its segments go)
                pts = pts[::-1]
            again = np.zeros(len(pts), dtype=bool)  # (new: a point where two chains meet kept once)
            again[1:] = np.all(pts[1:] == pts[:-1], axis=1)
            pts = pts[~again]
            if is_closed and len(pts) > 1 and np.all(pts[0] == pts[-1]):
                pts = pts[:-1]
            new_points.append((pts, is_closed))
            new_layer.append(lay)
    keep = np.ones(closed.size, dtype=bool)
    keep[open_idx] = False
    counts = np.diff(offsets)
    base_points = points[np.repeat(keep, counts)]
    all_counts = np.concatenate([counts[keep], [len(p) for p, _ in new_points]]).astype(np.int64)
    all_layer = np.concatenate([chain_layer[keep], np.array(new_layer, dtype=chain_layer.dtype)])
    all_closed = np.concatenate([closed[keep], np.array([c for _, c in new_points], dtype=bool)])
    all_points = np.concatenate([base_points] + [p.astype(np.float32) for p, _ in new_points])
    order = np.argsort(all_layer, kind="stable")
    starts = np.concatenate([[0], np.cumsum(all_counts)])
    new_offsets = np.zeros(order.size + 1, dtype=np.int64)
    np.cumsum(all_counts[order], out=new_offsets[1:])
    idx = np.arange(int(new_offsets[-1])) + np.repeat(starts[order] - new_offsets[:-1], all_counts[order])
    return all_points[idx], new_offsets, all_layer[order], all_closed[order]


def _case(rng: np.random.Generator, n_chains: int, n_layers: int, grid: int, n_slots: int):
    """Chains (1-5 points on a ``grid`` x ``grid`` lattice of 0.5 mm, so ends coincide) in random layers, a third
    closed; open chains' slots drawn from ``n_slots`` values (shared slots)."""
    counts = rng.integers(1, 6, n_chains)
    closed = rng.random(n_chains) < 0.33
    counts[closed] = np.maximum(counts[closed], 3)
    offsets = np.zeros(n_chains + 1, dtype=np.int64)
    np.cumsum(counts, out=offsets[1:])
    points = (rng.integers(0, grid, (int(offsets[-1]), 2)) * 0.5).astype(np.float32)
    layer = np.sort(rng.integers(0, n_layers, n_chains)).astype(np.int32)
    if rng.random() < 0.5:  # chains not grouped by layer (as after chaining: per layer, open chains first)
        layer = rng.permutation(layer).astype(np.int32)
    open_idx = np.flatnonzero(~closed)
    head_slot = rng.integers(0, n_slots, open_idx.size)
    tail_slot = rng.integers(0, n_slots, open_idx.size)
    return points, offsets, layer, closed, open_idx, head_slot, tail_slot


def _both(args, n_layers, max_gap):
    out = []
    for fn in (_repair, _reference_repair):
        repairs = {k: np.zeros(n_layers, dtype=np.int32) for k in REPAIR_KINDS}
        got = fn(*[a.copy() for a in args], max_gap, repairs)
        out.append((got, repairs))
    return out


@pytest.mark.parametrize("seed", range(40))
def test_joins_equal_the_reference_walk(seed):
    rng = np.random.default_rng(seed)
    n_layers = int(rng.integers(1, 6))
    args = _case(rng, int(rng.integers(1, 120)), n_layers, grid=int(rng.integers(2, 12)),
                 n_slots=int(rng.integers(2, 400)))
    max_gap = float(rng.choice([0.0, 0.4, 0.5, 1.0, 3.0]))
    (got, rep), (want, rep_ref) = _both(args, n_layers, max_gap)
    for g, w, name in zip(got, want, ("points", "offsets", "layer", "closed"), strict=True):
        assert g.dtype == w.dtype, name
        np.testing.assert_array_equal(g, w, err_msg=name)
    for k in REPAIR_KINDS:
        np.testing.assert_array_equal(rep[k], rep_ref[k], err_msg=k)


def test_joins_of_a_dense_layer_equal_the_reference_walk():
    """One layer of 3,000 one-segment chains on a fine lattice: more pairs within max_gap than the listed walk takes
    (``_closest_first``), long joined loops, and slots shared by many ends."""
    rng = np.random.default_rng(7)
    n = 3000
    offsets = np.arange(0, 2 * n + 1, 2, dtype=np.int64)
    points = (rng.integers(0, 60, (2 * n, 2)) * 0.1).astype(np.float32)
    args = (points, offsets, np.zeros(n, np.int32), np.zeros(n, bool), np.arange(n), rng.integers(0, 2000, n),
            rng.integers(0, 2000, n))
    (got, rep), (want, rep_ref) = _both(args, 1, 2.0)
    assert rep["gap_closed"][0] > 0 and rep["joined_by_id"][0] > 0 and rep["reversed"][0] > 0
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    for k in REPAIR_KINDS:
        np.testing.assert_array_equal(rep[k], rep_ref[k], err_msg=k)


def test_a_chain_joined_to_itself_closes_without_its_repeated_point():
    """An open chain whose two ends share a slot becomes one closed loop; its last point, equal to its first, goes."""
    points = np.array([[0, 0], [1, 0], [1, 1], [0, 0]], np.float32)
    repairs = {k: np.zeros(1, dtype=np.int32) for k in REPAIR_KINDS}
    pts, off, lay, cl = _repair(points, np.array([0, 4]), np.zeros(1, np.int32), np.zeros(1, bool), np.array([0]),
                                np.array([5]), np.array([5]), 0.0, repairs)
    assert cl.tolist() == [True] and off.tolist() == [0, 3] and lay.tolist() == [0]
    np.testing.assert_array_equal(pts, points[:3])
    assert repairs["joined_by_id"].tolist() == [1] and repairs["reversed"].tolist() == [0]


def test_a_soups_hole_stays_a_hole():
    """A square tube's walls as a soup (no two facets share a vertex), its first facet wound the wrong way: gap
    closing joins that segment the other way round, and the outer loop's walk began on it, so the loop came out
    clockwise like its hole; under the nonzero rule the hole was then filled (400 mm² instead of 300: found on a
    jittered benchy, a layer 117 % too large). The loop now goes the way most of its segments go. (The soup's
    open edges are left unjoined and unfilled on the mesh, ``join_edges=0, fill_holes=False``: it is chaining's gap
    closing that is tested.)"""
    from gpuslice import mesh_from_triangles, slice_mesh

    def walls(corners):  # two facets a wall, the material on the left going round the corners
        out = []
        for (ax, ay), (bx, by) in zip(corners, corners[1:] + corners[:1], strict=True):
            a0, b0, a1, b1 = [ax, ay, 0.0], [bx, by, 0.0], [ax, ay, 10.0], [bx, by, 10.0]
            out += [[a0, b0, b1], [a0, b1, a1]]
        return out

    tri = np.array(walls([(0, 0), (20, 0), (20, 20), (0, 20)]) + walls([(5, 5), (5, 15), (15, 15), (15, 5)]))
    tri[0] = tri[0][[0, 2, 1]]
    tri += np.random.default_rng(0).uniform(-1e-5, 1e-5, tri.shape)
    res = slice_mesh(mesh_from_triangles(tri), z=np.array([2.5, 5.0, 7.5]), join_edges=0, fill_holes=False)
    assert res.repairs["gap_closed"].tolist() == [16, 16, 16]
    np.testing.assert_allclose(res.area, 300.0, atol=1e-3)
