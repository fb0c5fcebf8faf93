"""Closing gaps between open chains when a layer has thousands of loose ends close together (a fuzzed STL: every
layer of a garbled file cut 3,600-5,000 chain ends within 2 mm of each other; listing every pair within
``max_gap`` made 4-9 million pairs a layer, walked in Python: minutes for one file). Past 16 pairs an end, the ends
are paired closest first by rounds of mutual nearest neighbours (:func:`gpuslice.slicing.chain._closest_first`),
the same matching as the listed pairs' greedy walk where distances are not tied."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.slicing.chain import _closest_first


def greedy(xy: np.ndarray, max_gap: float) -> set[tuple[int, int]]:
    """The listed pairs' walk: every pair within max_gap, closest first, both ends still free."""
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    i, j = np.nonzero(np.triu(d <= max_gap, 1))
    free, out = np.ones(len(xy), bool), set()
    for k in np.argsort(d[i, j], kind="stable"):
        a, b = int(i[k]), int(j[k])
        if free[a] and free[b]:
            free[a] = free[b] = False
            out.add((a, b))
    return out


@pytest.mark.parametrize("seed", range(20))
def test_closest_first_is_the_greedy_matching(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 300))
    xy = rng.uniform(0.0, rng.choice([0.5, 2.0, 10.0]), size=(n, 2))
    got = {tuple(sorted(map(int, p))) for p in _closest_first(xy, 2.0)}
    assert got == greedy(xy, 2.0)


def test_a_chain_of_shrinking_gaps_is_matched_greedily():
    """Ends along a line whose gaps shrink: one mutual pair a round, quadratic (a review); the rest goes to the
    listed pairs' walk once a round matches little, with the same matching."""
    rng = np.random.default_rng(3)
    n = 1500
    gaps = 0.99 - np.arange(n) * (0.4 / n)
    chain = np.c_[np.r_[0.0, np.cumsum(gaps)], np.zeros(n + 1)]
    xy = np.r_[chain, rng.random((300, 2)) * 0.5 + [0.0, 50.0]]
    got = {tuple(sorted(map(int, p))) for p in _closest_first(xy, 1.0)}
    assert got == greedy(xy, 1.0)
    edge = np.array([[0.0, 0.0], [2.0, 0.0]])  # exactly max_gap apart: joined, as the listed pairs join them
    assert _closest_first(edge, 2.0).tolist() == [[0, 1]]


def test_thousands_of_loose_ends_in_one_layer():
    """2,000 separate sliver triangles in a 1.9 mm square: 4,000 free ends a layer, all within the default 2 mm gap
    of each other (67 s of chaining before, most of it listing and walking ~8 million pairs). Their open edges are
    left unjoined and unfilled on the mesh (``join_edges=0, fill_holes=False``): chaining is what is tested."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(0.0, 1.9, size=(2000, 2))
    tri = np.zeros((2000, 3, 3))
    tri[:, 0, :2], tri[:, 1, :2], tri[:, 2, :2] = xy, xy + [0.01, 0.0], xy + [0.005, 0.0]
    tri[:, 2, 2] = 2.0
    res = slice_mesh(mesh_from_triangles(tri), thickness=0.2, join_edges=0, fill_holes=False)
    assert res.n_layers == 10
    gaps = res.repairs["gap_closed"]
    assert np.all(gaps[:-1] >= 1900)  # (nearly every pair of ends within 2 mm closed; the top layer may be empty)


@pytest.mark.parametrize("seed", range(12))
def test_few_pairs_is_the_full_count(seed):
    """The pairs within a quarter of the gap, counted first, never change the answer of the full count."""
    from gpuslice.slicing.chain import _PAIRS_LISTED, _few_pairs

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 400))
    xy = rng.uniform(0.0, rng.choice([0.3, 1.0, 4.0, 20.0]), size=(n, 2))
    pairs = int((np.linalg.norm(xy[:, None] - xy[None], axis=2) <= 2.0).sum() - n) // 2
    assert _few_pairs(xy, 2.0) == (pairs <= _PAIRS_LISTED * n)


@pytest.mark.parametrize("seed", range(12))
def test_listed_pairs_in_numpy_are_the_trees(seed, monkeypatch):
    """Up to _SMALL ends the pairs are compared in numpy, past it listed by a k-d tree: the same matching, ties (a
    lattice's equal distances, ends exactly max_gap apart) broken by index either way."""
    from gpuslice.slicing import chain

    rng = np.random.default_rng(seed)
    xy = (rng.integers(0, 5, (int(rng.integers(2, 60)), 2)) * 0.5).astype(np.float64)
    left = rng.permutation(len(xy))[: max(2, len(xy) - 3)]
    small = chain._greedy_listed(xy, left, 1.0)
    monkeypatch.setattr(chain, "_SMALL", 0)
    assert small.tolist() == chain._greedy_listed(xy, left, 1.0).tolist()
    assert len(small) > 0
