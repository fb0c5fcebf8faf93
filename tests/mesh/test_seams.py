"""Open mesh edges joined to their nearby partners before slicing (``gpuslice.mesh.seams``): triangle soups, a crack,
a flipped or repeated facet in a soup; holes that stay holes, and the limits (a quarter of the edge, ``join_edges``).

The references are independent of the code under test: the same solids welded exactly (no soup), analytic areas."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.errors import ParameterError
from gpuslice.mesh import seams
from gpuslice.mesh import shapes as S
from gpuslice.mesh.seams import joined_open_edges

Z = np.array([0.5, 2.5, 5.0, 7.5, 9.5])


def _soup(tri: np.ndarray, jitter: float, seed: int = 0) -> np.ndarray:
    """Every corner of every facet moved on its own by up to ``jitter`` mm: no two facets share a vertex."""
    return tri + np.random.default_rng(seed).uniform(-jitter, jitter, tri.shape)


def _faces_ok(mesh) -> bool:
    f = mesh.faces
    return bool(np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])))


def test_a_box_soup_is_joined_whole_and_sliced_without_gap_closing():
    tri = _soup(S.box(hi=(20.0, 20.0, 10.0)), 1e-5)
    soup = mesh_from_triangles(tri)
    assert int((soup.edge_sides().count == 1).sum()) == 36  # (the soup: every side open)
    joined, n = joined_open_edges(soup, 2.0)
    assert n == 18 and (joined.edge_sides().count == 2).all() and joined.n_faces == 12
    res = slice_mesh(soup, z=Z)
    np.testing.assert_allclose(res.area, 400.0, atol=1e-2)
    assert res.repairs["gap_closed"].sum() == 0 and res.loop_closed.all()
    assert res.meta["repairs"]["joined_edges"] == 18
    old = slice_mesh(soup, z=Z, join_edges=0, fill_holes=False)  # the chains' gap closing, as before
    assert old.repairs["gap_closed"].sum() > 0 and "joined_edges" not in old.meta["repairs"]


def test_a_crack_closes_on_the_corner_most_facets_use():
    """A cube with one corner of one facet nudged (admesh's nearby-bad block): the nudged copy goes to the corner the
    other facets share, so every layer is the cube's, where the corner moved would have dented it."""
    tri = S.box(hi=(40.0, 40.0, 40.0))
    f, k = np.argwhere(np.all(tri == [0.0, 40.0, 40.0], axis=2))[0]
    cracked = tri.copy()
    cracked[f, k] = [1.0, 39.0, 39.0]
    m = mesh_from_triangles(cracked)
    joined, n = joined_open_edges(m, 2.0)
    assert n == 2 and (joined.edge_sides().count == 2).all()
    z = np.linspace(0.25, 39.75, 40)
    res = slice_mesh(m, z=z, join_edges=2.0)  # (by default, 0.01 mm, the crack is filled instead: test_holes)
    np.testing.assert_allclose(res.area, 1600.0, rtol=1e-9)
    assert res.loop_closed.all()
    assert not slice_mesh(m, z=z, join_edges=1.0).meta["repairs"].get("joined_edges")  # (1.73 mm away: left)


def test_a_flipped_facet_in_a_soup_is_joined_and_turned_outward():
    tri = S.hollow_box(20.0, 10.0)
    tri[3] = tri[3][[0, 2, 1]]
    soup = mesh_from_triangles(_soup(tri, 1e-5))
    res = slice_mesh(soup, z=Z)
    clean = slice_mesh(mesh_from_triangles(S.hollow_box(20.0, 10.0)), z=Z)
    np.testing.assert_allclose(res.area, clean.area, atol=1e-2)
    assert res.repairs["gap_closed"].sum() == 0 and res.loop_closed.all()


def test_a_jittered_copy_of_a_facet_in_a_soup_leaves_no_layer_empty():
    """A helper's case: a box soup with one facet stored twice, each copy with its own rounding; the copy closed on
    its twin and left a gap, the outline stayed open and the layer came out empty."""
    box = S.box(hi=(20.0, 20.0, 10.0))
    wall = int(np.flatnonzero(np.ptp(box[:, :, 2], axis=1) > 0)[0])  # a side wall's facet: every layer cuts it
    tri = np.concatenate([box, box[wall : wall + 1]])
    res = slice_mesh(mesh_from_triangles(_soup(tri, 1e-5)), z=Z)
    np.testing.assert_allclose(res.area, 400.0, atol=1e-2)


def test_an_open_scans_hole_stays_open_and_the_mesh_is_returned_as_it_is():
    tri = S.box(hi=(20.0, 20.0, 10.0))
    top = np.all(tri[:, :, 2] == 10.0, axis=1)
    m = mesh_from_triangles(tri[~top])
    joined, n = joined_open_edges(m, 2.0)
    assert n == 0 and joined is m


@pytest.mark.parametrize(("gap", "limit", "joined"), [(0.2, 2.0, True), (0.3, 2.0, False), (0.2, 0.1, False)])
def test_two_sides_are_one_edge_within_a_quarter_of_its_length_and_the_limit(gap, limit, joined):
    """Two facets whose facing sides (1 mm long, opposite ways) lie ``gap`` mm apart: joined when the gap is at most
    a quarter of the side and at most ``limit``."""
    tri = np.array([[[0, 0, 0], [1, 0, 0], [0.5, -1, 0]], [[1, gap, 0], [0, gap, 0], [0.5, 1 + gap, 0]]], float)
    _, n = joined_open_edges(mesh_from_triangles(tri), limit)
    assert n == (1 if joined else 0)


def test_a_noisy_soup_loses_no_facet():
    """Corners moved by up to 0.3 mm on a sphere whose facets near the poles are narrower than that: merges that
    would fold a facet are given up, so the joined mesh keeps every facet and none collapses (without that rule, 36
    of this soup's facets folded)."""
    tri = S.uv_sphere(10.0)
    soup = mesh_from_triangles(_soup(tri, 0.3, seed=0))
    joined, n = joined_open_edges(soup, 2.0)
    assert 0 < n < 3 * soup.n_faces // 2
    assert joined.n_faces == soup.n_faces and _faces_ok(joined)


def test_the_k_d_tree_path_joins_as_every_pair_does(monkeypatch):
    soup = mesh_from_triangles(_soup(S.icosphere(10.0, 3), 1e-4, seed=1))  # 3,840 open sides
    assert int((soup.edge_sides().count == 1).sum()) > seams.SMALL
    tree, n_tree = joined_open_edges(soup, 2.0)
    monkeypatch.setattr(seams, "SMALL", 10**6)
    listed, n_listed = joined_open_edges(soup, 2.0)
    assert n_tree == n_listed == 1920
    np.testing.assert_array_equal(tree.faces, listed.faces)


def test_join_edges_must_be_a_finite_length():
    tri = S.box()
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ParameterError, match="join_edges"):
            slice_mesh(mesh_from_triangles(tri), z=Z, join_edges=bad)
