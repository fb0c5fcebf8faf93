"""Holes closed by fans of facets before slicing (``gpuslice.mesh.holes``): a missing facet, a missing end cap (convex
and not), an open scan; and what is left open. References: the same solids closed (not filled by the code under
test), and the open scan's own chains closed across the holes by chaining (another path through the code)."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import load_mesh, mesh_from_triangles, slice_mesh
from gpuslice.mesh import shapes as S
from gpuslice.mesh.holes import filled_holes


def _on_its_side(tri: np.ndarray) -> np.ndarray:
    """(x, y, z) -> (z, y, x): a solid along z laid along x (its caps then stand upright; mirrored, so re-wound)."""
    out = tri[:, :, ::-1].copy()
    return out[:, [0, 2, 1]]


def _without_cap(tri: np.ndarray) -> np.ndarray:
    """``tri`` without the facets of its end cap at the largest x."""
    return tri[~np.all(np.isclose(tri[:, :, 0], tri[:, :, 0].max()), axis=1)]


def test_a_missing_facet_is_filled_and_every_layer_closes():
    tri = S.box(hi=(20.0, 20.0, 20.0))
    side = int(np.flatnonzero(np.ptp(tri[:, :, 2], axis=1) > 0)[0])
    open_box = mesh_from_triangles(np.delete(tri, side, axis=0))
    res = slice_mesh(open_box, thickness=1.0)
    np.testing.assert_allclose(res.area, 400.0, rtol=1e-6)
    assert res.loop_closed.all() and res.meta["repairs"]["filled_holes"] == 1
    old = slice_mesh(open_box, thickness=1.0, fill_holes=False)  # chaining's gap closing only: wide gaps stay open
    assert not old.loop_closed.all() and "filled_holes" not in old.meta["repairs"]


@pytest.mark.parametrize("shape", ["cylinder", "star prism"])
def test_an_end_cap_removed_is_filled_as_it_was(shape):
    """A solid lying on its side without one end cap: the fan over the cap's rim covers it exactly, convex (a
    cylinder) or not (a star: the fan's facets overlap, their windings add up to the star)."""
    if shape == "cylinder":
        tri = S.cylinder(radius=8.0, height=30.0, n=48)
    else:
        ang = np.arange(10) * np.pi / 5
        rad = np.where(np.arange(10) % 2 == 0, 9.0, 3.5)
        tri = S.prism(np.c_[rad * np.cos(ang), rad * np.sin(ang)], 0.0, 30.0)
    closed = _on_its_side(tri)
    closed[:, :, 2] += 10.0  # (the axis at z = 10: layers cut the cap's plane across)
    z = np.linspace(1.3, 18.7, 30)
    want = slice_mesh(mesh_from_triangles(closed), z=z)
    got = slice_mesh(mesh_from_triangles(_without_cap(closed)), z=z)
    assert got.meta["repairs"]["filled_holes"] == 1 and got.loop_closed.all()
    np.testing.assert_allclose(got.area, want.area, rtol=1e-6, atol=1e-6)
    assert (np.asarray(want.area) > 0).sum() > 20


def test_every_new_facet_runs_against_its_rim_and_its_neighbours():
    tri = _on_its_side(S.cylinder(radius=8.0, height=30.0, n=32))
    m = mesh_from_triangles(_without_cap(tri))
    filled, holes = filled_holes(m)
    sides = filled.edge_sides()
    assert holes == 1 and (sides.count == 2).all() and (sides.forward == 1).all()  # closed, consistently wound
    assert filled.n_faces == m.n_faces + 30  # a fan over a 32-gon


def test_a_mesh_without_holes_is_returned_as_it_is():
    m = mesh_from_triangles(S.box())
    assert filled_holes(m) == (m, 0)


def test_a_soup_or_a_surface_is_left_to_chaining():
    """Where more than OPEN_SHARE of the facet sides are open (separate facets, a strip), the "holes" are single
    facets or patches: filled, each would be a closed pillow of no volume and its area would leave every layer."""
    rng = np.random.default_rng(5)
    tri = rng.uniform(0.0, 10.0, (60, 3, 3))
    m = mesh_from_triangles(tri)
    assert filled_holes(m) == (m, 0)
    res = slice_mesh(m, thickness=0.5, join_edges=0)
    assert "filled_holes" not in res.meta["repairs"] and res.area.max() > 0
    np.testing.assert_array_equal(res.area, slice_mesh(m, thickness=0.5, join_edges=0, fill_holes=False).area)
    box = S.box()
    wall = np.all(np.isclose(box[:, :, 0], 0.0), axis=1) | np.all(np.isclose(box[:, :, 1], 0.0), axis=1)
    assert filled_holes(mesh_from_triangles(box[~wall]))[1] == 0  # 8 open sides of 24: a third
    assert filled_holes(mesh_from_triangles(box[~np.all(np.isclose(box[:, :, 0], 0.0), axis=1)]))[1] == 1  # 4 of 30


def test_the_open_bunny_has_no_empty_layer(shared_meshes):
    """The Stanford bunny's scan holes (its base) cut across by the file's z: 193 of 620 layers at 0.05 mm came out
    empty (their chains crossed a hole wider than the 2 mm gap closing). Filled, every layer matches the same layers
    with the chains closed across the holes (``max_gap`` 100 mm, no fill) within 2 %."""
    m = load_mesh(shared_meshes / "stanford_bunny.stl", fit=40)
    got = slice_mesh(m, thickness=0.2)
    across = slice_mesh(m, thickness=0.2, fill_holes=False, max_gap=100.0)
    old = slice_mesh(m, thickness=0.2, fill_holes=False)
    # (its fifth hole is no wider than max_gap across the layers: chaining closes it)
    assert got.meta["repairs"]["filled_holes"] == 4 and got.loop_closed.all() and across.loop_closed.all()
    ref = np.asarray(across.area)
    assert (ref > 0).all()
    np.testing.assert_allclose(got.area, ref, rtol=0.02, atol=0.01)
    assert (np.asarray(old.area) < 0.5 * ref).sum() > 40  # (what it was)


@pytest.mark.parametrize("fill", [True, "yes", 1])
def test_fill_holes_is_a_flag(fill):
    if fill is True:
        assert slice_mesh(mesh_from_triangles(S.box()), z=[5.0], fill_holes=fill).area[0] == pytest.approx(400.0)
    else:
        from gpuslice.errors import ParameterError

        with pytest.raises(ParameterError, match="fill_holes"):
            slice_mesh(mesh_from_triangles(S.box()), z=[5.0], fill_holes=fill)


def test_a_soup_of_an_open_mesh_is_joined_then_filled():
    """An open box written as a triangle soup (each corner rounded on its own): its edges are joined first, and the
    hole they leave (a missing side facet) is filled; joined but left unfilled, layers across the hole stay open."""
    tri = S.box(hi=(20.0, 20.0, 20.0))
    side = int(np.flatnonzero(np.ptp(tri[:, :, 2], axis=1) > 0)[0])
    soup = np.delete(tri, side, axis=0) + np.random.default_rng(2).uniform(-1e-5, 1e-5, (11, 3, 3))
    res = slice_mesh(mesh_from_triangles(soup), thickness=1.0)
    assert res.meta["repairs"]["joined_edges"] == 15 and res.meta["repairs"]["filled_holes"] == 1
    np.testing.assert_allclose(res.area, 400.0, rtol=1e-5)
    assert res.loop_closed.all()
    assert not slice_mesh(mesh_from_triangles(soup), thickness=1.0, fill_holes=False).loop_closed.all()


def test_holes_that_touch_at_a_vertex_are_filled():
    """Two facets missing that share one corner: two sides arrive at it and two leave (a review: such a vertex ended
    the rim, the holes stayed open and the layers across them were empty)."""
    closed = mesh_from_triangles(S.uv_sphere(20.0, 16, 32))
    f = closed.faces
    vid = int(np.flatnonzero(np.isclose(closed.vertices[:, 2], 20.0))[0])  # a vertex on the equator
    at = np.flatnonzero((f == vid).any(axis=1))
    i, j = next((i, j) for i in at for j in at if i < j and len(set(f[i]) & set(f[j])) == 1)
    keep = np.ones(len(f), dtype=bool)
    keep[[i, j]] = False
    tri = closed.vertices[f[keep]].astype(np.float64)
    z = np.linspace(0.25, 39.75, 80)
    got = slice_mesh(mesh_from_triangles(tri), z=z, max_gap=0.0)
    # (the two rims link into one loop through the shared corner, a figure of eight; its fan covers both)
    assert got.meta["repairs"]["filled_holes"] == 1 and got.loop_closed.all()
    # (one fan for both, from the corner of least fan area: the shared one, so each facet comes back as it was; from
    # the loop's lowest corner it spanned both facets' planes, 5.3e-4 off)
    np.testing.assert_allclose(got.area, slice_mesh(closed, z=z).area, rtol=1e-9)
    assert not slice_mesh(mesh_from_triangles(tri), z=z, max_gap=0.0, fill_holes=False).loop_closed.all()


def test_the_least_area_search_is_bounded(monkeypatch):
    """Loops past the pairs' budget (FAN_WORK, smallest loops first) get the fan from their lowest corner: a planar
    hole is filled exactly either way, and no more (corner, side) pairs than the budget are made."""
    from gpuslice.mesh import holes

    made = []
    real = holes.expand_ranges

    def counting(starts, counts):
        out = real(starts, counts)
        made.append(out[0].size)
        return out

    monkeypatch.setattr(holes, "expand_ranges", counting)
    monkeypatch.setattr(holes, "FAN_WORK", 40)  # (the cylinder's 32-sided cap: 1,024 pairs, over the budget)
    tri = _on_its_side(S.cylinder(radius=8.0, height=30.0, n=32))
    filled, n = filled_holes(mesh_from_triangles(_without_cap(tri)))
    assert n == 1 and (filled.edge_sides().count == 2).all() and max(made, default=0) <= 40
