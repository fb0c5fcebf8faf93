"""The slicing core on solids with exactly known sections, and each case of the paper's Fig. 3.

Expected areas come from geometry computed here independently of gpuslice: regular n-gon formulas for revolved
solids (their sections are n-gons whose circumradius is linear between rings) and convex hulls of plane–edge
intersection points.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from gpuslice import mesh_from_arrays, mesh_from_triangles, slice_mesh
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes as S
from gpuslice.schedule.uniform import uniform
from gpuslice.slicing.chain import link_segments, order_chains
from gpuslice.slicing.crossings import compute_crossings, crossings_numpy
from gpuslice.slicing.nest import signed_areas

F32 = 2e-6  # relative error of float32 coordinates in areas (a few ulps of each coordinate)


def revolved_area(profile, n, z):
    """Section area at each z of a profile revolved with n segments; the plane counts as just above the solid
    below it (the half-open rule): a profile edge counts for z in (z_low, z_high]."""
    prof = np.asarray(profile, float)
    out = []
    for zz in np.atleast_1d(z):
        radii = []
        for i in range(len(prof)):
            (r0, z0), (r1, z1) = prof[i], prof[(i + 1) % len(prof)]
            if z0 == z1 or not (min(z0, z1) < zz <= max(z0, z1)):
                continue
            radii.append(r0 + (zz - z0) / (z1 - z0) * (r1 - r0))
        radii = sorted(radii, reverse=True)
        out.append(sum((-1) ** k * S.ngon_area(n, r) for k, r in enumerate(radii)))
    return np.array(out)


def uv_profile(radius, n_lat):
    phi = np.pi * np.arange(n_lat + 1) / n_lat
    prof = np.stack([radius * np.sin(phi), radius * (1 - np.cos(phi))], axis=1)
    prof[0, 0] = prof[-1, 0] = 0.0
    # close it along the axis (zero-radius edges add nothing)
    return prof


def torus_profile(major, minor, n_minor):
    phi = 2 * np.pi * np.arange(n_minor) / n_minor - np.pi / 2
    return np.stack([major + minor * np.cos(phi), minor + minor * np.sin(phi)], axis=1)


def run(tri, backend, **kw):
    return slice_mesh(mesh_from_triangles(tri), backend=backend, **kw)


def assert_clean(r):
    assert r.meta["open_chains"] == 0, r.meta["repairs"]
    assert r.loop_closed.all()
    assert r.meta["repairs"]["joined_by_id"] == 0 and r.meta["repairs"]["gap_closed"] == 0


# ---- solids with analytic sections ------------------------------------------------------------------------


def test_cube_area_and_volume(backend):
    r = run(S.box(hi=(20, 20, 20)), backend, thickness=0.2)
    assert_clean(r)
    assert r.n_layers == 100
    np.testing.assert_allclose(r.area, 400.0, rtol=F32)
    assert r.volume == pytest.approx(8000.0, rel=1e-9)


def test_cylinder_is_a_regular_ngon(backend):
    r = run(S.cylinder(radius=10, height=20, n=64), backend, thickness=0.1)
    assert_clean(r)
    np.testing.assert_allclose(r.area, S.ngon_area(64, 10.0), rtol=F32)
    assert r.volume == pytest.approx(S.ngon_area(64, 10.0) * 20, rel=1e-6)
    # each side quad is two triangles: the plane crosses 64 vertical edges and 64 diagonals (collinear points)
    assert np.all(r.loops_per_layer == 1) and np.all(r.points_per_layer == 128)


def test_sphere_sections(backend):
    r = run(S.uv_sphere(radius=10, n_lat=16, n_lon=32), backend, thickness=0.05)
    assert_clean(r)
    expected = revolved_area(uv_profile(10, 16), 32, r.z)
    np.testing.assert_allclose(r.area, expected, rtol=1e-5, atol=1e-4)
    vol = mesh_from_triangles(S.uv_sphere(10, 16, 32)).info()["volume"]
    assert r.volume == pytest.approx(vol, rel=2e-4)  # midpoint rule on a piecewise-quadratic area


def test_torus_annulus(backend):
    r = run(S.torus(15, 5, 48, 24), backend, thickness=0.05)
    assert_clean(r)
    expected = revolved_area(torus_profile(15, 5, 24), 48, r.z)
    # float32 coordinates (~2e-6 mm at 20 mm) times ~190 mm of perimeter: ~5e-4 mm^2 on the thin pole layers
    np.testing.assert_allclose(r.area, expected, rtol=1e-5, atol=1e-3)
    # every layer is an outer ring with one hole
    assert np.all(r.loops_per_layer == 2)
    assert r.loop_is_hole.sum() == r.n_layers
    vol = mesh_from_triangles(S.torus(15, 5, 48, 24)).info()["volume"]
    assert r.volume == pytest.approx(vol, rel=2e-3)


def test_hollow_box_holes_are_holes(backend):
    r = run(S.hollow_box(20, 10), backend, thickness=0.5)
    assert_clean(r)
    inside = (r.z > 5) & (r.z <= 15)
    np.testing.assert_allclose(r.area[inside], 300.0, rtol=F32)
    np.testing.assert_allclose(r.area[~inside], 400.0, rtol=F32)
    assert r.volume == pytest.approx(7000.0, rel=1e-9)
    for i in np.flatnonzero(inside):
        lay = r.layer(i)
        (outer, holes), = lay.polygons()
        assert len(holes) == 1
        a_out = signed_areas(outer, np.array([0, len(outer)]))[0]
        a_hole = signed_areas(holes[0], np.array([0, len(holes[0])]))[0]
        assert a_out == pytest.approx(400.0) and a_hole == pytest.approx(-100.0)  # CCW outer, CW hole


def test_box_inside_a_box(backend):
    r = run(S.hollow_box(20, 10, core=6), backend, thickness=0.5)
    assert_clean(r)
    cavity = (r.z > 5) & (r.z <= 15)
    core = (r.z > 7) & (r.z <= 13)
    expected = np.where(cavity, 300.0, 400.0) + np.where(core, 36.0, 0.0)
    np.testing.assert_allclose(r.area, expected, rtol=F32)
    # the island inside the hole is an outer contour of its own polygon
    i = int(np.flatnonzero(core)[0])
    polys = r.layer(i).polygons()
    assert sorted(len(h) for _, h in polys) == [0, 1]
    assert r.volume == pytest.approx(8000 - 1000 + 216, rel=1e-9)


def test_icosphere_volume(backend):
    tri = S.icosphere(radius=20, subdivisions=4)
    r = run(tri, backend, thickness=0.05)
    assert_clean(r)
    vol = mesh_from_triangles(tri).info()["volume"]
    assert r.volume == pytest.approx(vol, rel=1e-4)


# ---- the paper's Fig. 3: planes exactly through vertices, edges and facets ---------------------------------


def hull_area(tri, z):
    """Independent reference for convex solids: the area of the convex hull of the plane–edge crossings."""
    edges = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    a, b = edges[:, 0], edges[:, 1]
    pts = [v[:2] for v in tri.reshape(-1, 3) if v[2] == z]
    cross = (a[:, 2] - z) * (b[:, 2] - z) < 0
    t = (z - a[cross, 2]) / (b[cross, 2] - a[cross, 2])
    pts += list(a[cross, :2] + t[:, None] * (b[cross, :2] - a[cross, :2]))
    pts = np.unique(np.round(np.array(pts), 9), axis=0)
    return ConvexHull(pts).volume if len(pts) >= 3 else 0.0


TETRA = np.array([[0, 0, 0], [10, 0, 2], [3, 9, 5], [4, 3, 10]], float)
TETRA_FACES = [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]


def test_fig3a_vertex_on_plane_others_on_one_side(backend):
    # pyramid cut exactly at its apex: every facet has its apex vertex on the plane and the others below
    tri = S.cone(radius=10, height=10, n=4)
    r = run(tri, backend, z=np.array([5.0, 10.0]))
    assert_clean(r)
    assert r.area[0] == pytest.approx(S.ngon_area(4, 5.0), rel=F32)
    assert r.area[1] == 0.0 and r.loops_per_layer[1] == 0
    assert r.repairs["degenerate_loops"][1] == 1  # the zero-length loop at the apex is dropped, not left open
    # the tetrahedron's bottom vertex: a plane at z = 0 has all four vertices on or above it
    r0 = slice_mesh(mesh_from_arrays(TETRA, TETRA_FACES), z=np.array([0.0]), backend=backend)
    assert r0.area[0] == 0.0 and r0.n_loops == 0


def test_fig3b_edge_on_plane(backend):
    # a UV sphere cut exactly at its ring heights: ring edges lie in the plane, ring vertices too
    prof = uv_profile(10, 8)
    z = np.unique(prof[1:-1, 1])
    r = run(S.uv_sphere(10, 8, 16), backend, z=z)
    assert_clean(r)
    np.testing.assert_allclose(r.area, S.ngon_area(16, np.interp(z, prof[:, 1], prof[:, 0])), rtol=F32)
    assert np.all(r.points_per_layer == 16)  # no duplicate points from zero-length segments


def test_fig3c_plane_through_vertex_and_opposite_edge(backend):
    mesh = mesh_from_arrays(TETRA, TETRA_FACES)
    for z in (2.0, 5.0):  # the heights of the two middle vertices
        r = slice_mesh(mesh, z=np.array([z]), backend=backend)
        assert_clean(r)
        assert r.n_loops == 1 and r.points_per_layer[0] == 3
        assert r.area[0] == pytest.approx(hull_area(mesh.triangles.astype(float), z), rel=1e-6)


def test_fig3d_facet_in_plane(backend):
    # cube faces and the hollow box's cavity floor and ceiling: the section is the limit from below
    r = run(S.box(hi=(20, 20, 20)), backend, z=np.array([0.0, 20.0]))
    assert r.area.tolist() == [0.0, pytest.approx(400.0)]
    assert_clean(r)
    r = run(S.hollow_box(20, 10), backend, z=np.array([5.0, 15.0]))
    assert_clean(r)
    np.testing.assert_allclose(r.area, [400.0, 300.0], rtol=F32)
    # a stair cut at every step height
    steps, rise, run_, width = 4, 2.0, 3.0, 10.0
    z = rise * np.arange(1, steps + 1)
    rs = run(S.stair(steps, rise, run_, width), backend, z=z)
    assert_clean(rs)
    np.testing.assert_allclose(rs.area, [(steps - k) * run_ * width for k in range(steps)], rtol=F32)


def test_fig3e_plane_through_two_edges(backend):
    mesh = mesh_from_arrays(TETRA, TETRA_FACES)
    z = np.array([1.0, 3.5, 7.25])
    r = slice_mesh(mesh, z=z, backend=backend)
    assert_clean(r)
    np.testing.assert_allclose(r.area, [hull_area(mesh.triangles.astype(float), v) for v in z], rtol=1e-6)


# ---- kernels against their numpy references ------------------------------------------------------------------


@pytest.mark.parametrize("name", ["sphere", "torus", "box-in-box", "stair", "pyramid"])
def test_kernel_equals_numpy_reference(device, name):
    mesh = mesh_from_triangles(S.SHAPES[name]())
    zs = uniform(mesh.height, 0.05).z
    # add planes exactly through vertices to exercise the on-plane rule
    zs = np.unique(np.concatenate([zs, mesh.vertices[:, 2].astype(np.float64)]))
    zs = zs[(zs > 0) & (zs <= mesh.height)]
    ref = crossings_numpy(mesh, zs)
    got = compute_crossings(mesh, zs, device)
    assert len(ref) == len(got) > 0
    np.testing.assert_array_equal(got.layer, ref.layer)
    np.testing.assert_array_equal(got.edges, ref.edges)
    np.testing.assert_allclose(got.points, ref.points, atol=1e-5, rtol=0)
    from gpuslice.slicing.walk import walk_chains

    z32 = zs.astype(np.float32)
    nxt, _, _ = link_segments(ref, mesh, z32)
    for a, b in zip(order_chains(nxt, ref.layer), walk_chains(nxt, ref.layer, zs.size, device), strict=True):
        np.testing.assert_array_equal(a, b)


def test_backends_give_identical_results(device):
    mesh = mesh_from_triangles(S.torus())
    a = slice_mesh(mesh, thickness=0.1, backend="numpy")
    b = slice_mesh(mesh, thickness=0.1, backend="opencl")
    for name in ("loop_offsets", "layer_offsets", "loop_is_hole", "loop_parent", "loop_closed"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_allclose(a.points, b.points, atol=1e-5)
    np.testing.assert_allclose(a.area, b.area, rtol=1e-6)


# ---- chaining on broken meshes -------------------------------------------------------------------------------


def test_nonmanifold_edge_pairs_half_edges(backend):
    # two cubes sharing one vertical edge: that edge has four facets
    tri = np.concatenate([S.box((0, 0, 0), (10, 10, 10)), S.box((10, 10, 0), (20, 20, 10))])
    mesh = mesh_from_triangles(tri)
    assert mesh.info()["nonmanifold_edges"] >= 1
    r = slice_mesh(mesh, thickness=1.0, backend=backend)
    assert_clean(r)
    np.testing.assert_allclose(r.area, 200.0, rtol=F32)


def test_flipped_facet_is_turned_before_slicing(backend):
    """A side facet wound the wrong way: the shell mixes both windings, so it is sliced turned outward
    (``defects.wound_for_slicing``) and its chains close by themselves (they were joined by id, one reversed)."""
    tri = S.box(hi=(20, 20, 20)).copy()
    side = int(np.flatnonzero(np.ptp(tri[:, :, 2], axis=1) > 0)[0])  # a side facet
    tri[side] = tri[side, ::-1]
    r = run(tri, backend, thickness=1.0)
    assert r.meta["open_chains"] == 0
    assert r.repairs["joined_by_id"].sum() == 0 and r.repairs["reversed"].sum() == 0
    np.testing.assert_allclose(r.area, 400.0, rtol=F32)


@pytest.mark.parametrize("seed", range(6))
def test_a_cavity_of_partly_flipped_facets_stays_empty(backend, seed):
    """A hollow box (20 mm, a 10 mm cavity) with a random minority of each shell's facets wound the wrong way. Loops
    took their direction from the chain their walk began on, later from most of their segments; a cavity wall cut
    from flipped facets then ran the way of the outer wall, and the nonzero rule filled the cavity (400 mm² instead
    of 300: 64 of 150 random cases before, at one facet in ten; a helper's sweep found 4 of the cavity's 8 side
    facets enough). Shells of mixed winding are now sliced turned outward."""
    tri = np.asarray(S.hollow_box(), float)
    rng = np.random.default_rng(seed)
    flip = np.zeros(len(tri), bool)
    for shell in (slice(0, 12), slice(12, 24)):  # (the outer box's facets, then the cavity's)
        flip[shell][rng.choice(12, int(rng.integers(1, 6)), replace=False)] = True
    if seed == 0:
        flip[:] = False
        flip[[17, 18, 21, 22]] = True  # the helper's case: half the cavity's side facets
    tri[flip] = tri[flip][:, ::-1]
    r = slice_mesh(mesh_from_triangles(tri), z=np.array([2.5001, 7.5001, 10.0001, 12.5001]), backend=backend)
    np.testing.assert_allclose(r.area, [400.0, 300.0, 300.0, 300.0], rtol=F32)


def test_missing_facet_gap_closed_within_max_gap(backend):
    tri = S.box(hi=(20, 20, 20))
    side = int(np.flatnonzero(np.ptp(tri[:, :, 2], axis=1) > 0)[0])
    missing = tri[side]
    tri = np.delete(tri, side, axis=0)
    kept = run(tri, backend, thickness=1.0, max_gap=2.0, fill_holes=False)  # (filled, the hole has no gap: test_holes)
    # the gap is the missing triangle's section: left open where it is wider than max_gap, closed elsewhere
    z = kept.z
    lo, hi = missing[:, 2].min(), missing[:, 2].max()
    width = np.array([hull_width(missing, v) for v in z])
    assert lo == 0 and hi == 20
    np.testing.assert_array_equal(kept.open_chains_per_layer, (width > 2.0).astype(int))
    np.testing.assert_array_equal(kept.repairs["gap_closed"], (width <= 2.0).astype(int))
    closed = run(tri, backend, thickness=1.0, max_gap=30.0, fill_holes=False)
    assert closed.meta["open_chains"] == 0 and closed.repairs["gap_closed"].sum() == closed.n_layers
    np.testing.assert_allclose(closed.area, 400.0, rtol=F32)


def hull_width(triangle, z):
    """Length of a single triangle's section at height z."""
    pts = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        p, q = triangle[a], triangle[b]
        if (p[2] - z) * (q[2] - z) < 0:
            pts.append(p[:2] + (z - p[2]) / (q[2] - p[2]) * (q[:2] - p[:2]))
    return float(np.linalg.norm(pts[0] - pts[1]))


def test_fill_rules_on_nested_shells(backend):
    # an inner cube wound outward inside an outer cube: a second shell, not a cavity
    tri = np.concatenate([S.box((0, 0, 0), (20, 20, 20)), S.box((5, 5, 5), (15, 15, 15))])
    nonzero = run(tri, backend, thickness=1.0)
    evenodd = run(tri, backend, thickness=1.0, fill_rule="evenodd")
    mid = (nonzero.z > 5) & (nonzero.z <= 15)
    np.testing.assert_allclose(nonzero.area, 400.0, rtol=F32)  # the inner shell bounds nothing
    assert nonzero.repairs["unfilled_loops"][mid].tolist() == [1] * int(mid.sum())
    np.testing.assert_allclose(evenodd.area[mid], 300.0, rtol=F32)  # even-odd makes it a hole


def test_layer_batches_give_the_same_result(backend):
    # memory is bounded by slicing in batches of layers: the result must not depend on the batch size
    mesh = mesh_from_triangles(S.hollow_box(20, 10, core=6))
    whole = slice_mesh(mesh, thickness=0.25, backend=backend)
    parts = slice_mesh(mesh, thickness=0.25, backend=backend, max_segments_per_batch=100)
    assert parts.meta["batches"] > 5 and whole.meta["batches"] == 1
    for name in ("points", "loop_offsets", "layer_offsets", "loop_layer", "loop_is_hole", "loop_parent", "area"):
        np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name))


def test_overlapping_bodies_union(backend):
    # two closed boxes that overlap: nonzero fills the union once, even-odd leaves the overlap empty
    tri = np.concatenate([S.box((0, 0, 0), (20, 20, 20)), S.box((10, 5, 0), (30, 15, 20))])
    nonzero = run(tri, backend, thickness=1.0)
    evenodd = run(tri, backend, thickness=1.0, fill_rule="evenodd")
    np.testing.assert_allclose(nonzero.area, 400 + 200 - 100, rtol=F32)
    np.testing.assert_allclose(evenodd.area, 400 + 200 - 2 * 100, rtol=F32)
    assert nonzero.repairs["overlaps_resolved"].sum() == nonzero.n_layers
    lay = nonzero.layer(3)
    (outer, holes), = lay.polygons()
    assert not holes and signed_areas(outer, np.array([0, len(outer)]))[0] == pytest.approx(500.0)


def test_expand_ranges_matches_a_loop():
    from gpuslice.ragged import expand_ranges

    rng = np.random.default_rng(3)
    starts, counts = rng.integers(-50, 50, 200), rng.integers(0, 6, 200)
    owner, values = expand_ranges(starts, counts)
    want = [(i, s + k) for i, (s, c) in enumerate(zip(starts, counts, strict=True)) for k in range(c)]
    assert owner.tolist() == [i for i, _ in want]
    assert values.tolist() == [v for _, v in want]
    assert [a.size for a in expand_ranges(np.zeros(0), np.zeros(0))] == [0, 0]


def test_set_helpers_match_numpy():
    """``ragged.unique_ints`` and ``isin_ints`` (numpy's ``unique``/``union1d``/``isin`` import ``numpy.ma`` at their
    first call, which the slicing path now avoids) give numpy's results, dtypes included."""
    import subprocess
    import sys

    from gpuslice.ragged import isin_ints, unique_ints

    rng = np.random.default_rng(11)
    for n, m in ((0, 0), (1, 0), (0, 3), (1, 1), (7, 3), (300, 50), (2000, 2000)):
        for dt in (np.int32, np.int64):
            a, b = rng.integers(-40, 40, n).astype(dt), rng.integers(-40, 40, m).astype(np.int64)
            for got, want in ((unique_ints(a), np.unique(a)), (unique_ints(a, b), np.union1d(a, b)),
                              (isin_ints(a, b), np.isin(a, b))):
                assert got.dtype == want.dtype and np.array_equal(got, want), (n, m, dt)
    # a command's slicing of a layer with several loops (containment, a rebuilt overlap) imports no numpy.ma
    code = ("import sys; from gpuslice import mesh_from_triangles, slice_mesh; from gpuslice.mesh import shapes as S;"
            "import numpy as np; t = np.concatenate([S.box((0, 0, 0), (10, 10, 10)), S.box((5, 5, 0), (15, 15, 10)),"
            "S.box((30, 0, 0), (40, 10, 10))]); r = slice_mesh(mesh_from_triangles(t), thickness=1.0);"
            "assert r.repairs['overlaps_resolved'].sum() > 0; print('numpy.ma' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_open_chains_kept_in_layers_whose_overlaps_are_rebuilt(backend):
    """A layer whose loops cross is rebuilt (overlaps resolved), and the open chains of the same layer stay in the
    result: two overlapping closed boxes plus an open box (one side wall missing, its gap wider than --max-gap, and
    the hole not filled: ``fill_holes=False``)."""
    a = S.box((0, 0, 0), (10, 10, 10))
    b = S.box((5, 5, 0), (15, 15, 10))
    c = S.box((30, 0, 0), (40, 10, 10))
    side = np.all(np.isclose(c[:, :, 0], 30.0), axis=1)  # the two facets of the x = 30 wall
    assert side.sum() == 2
    tri = np.concatenate([a, b, c[~side]])
    res = slice_mesh(mesh_from_triangles(tri), thickness=1.0, backend=backend, fill_holes=False)
    assert res.n_layers == 10
    assert (res.repairs["overlaps_resolved"] == 1).all()
    open_per_layer = res.open_chains_per_layer
    np.testing.assert_array_equal(open_per_layer, res.repairs["open_chains"])  # counted and present alike
    assert (open_per_layer == 1).all()
    # the union of the two boxes (175 mm^2) is filled, the open chain is not
    np.testing.assert_allclose(res.area, 175.0, rtol=1e-6)
    # each open chain is the open box's three walls: its points at x in [30, 40]
    for i in np.flatnonzero(~res.loop_closed):
        pts = res.points[res.loop_offsets[i] : res.loop_offsets[i + 1]]
        assert pts[:, 0].min() >= 30 - 1e-4 and pts[:, 0].max() <= 40 + 1e-4 and len(pts) >= 4


def test_loop_crossing_itself_is_rebuilt(backend):
    """A figure-8 cross-section (a prism over a self-crossing polygon): nesting rebuilds the layer, so its area is
    the two lobes' (nonzero fill), not their signed difference, and the polygons are valid."""
    import shapely

    bowtie = np.array([[0.0, 0.0], [10.0, 6.0], [10.0, 0.0], [0.0, 3.0]])  # two lobes of opposite signs, unequal
    lobes = shapely.make_valid(shapely.Polygon(bowtie)).area  # both lobes, filled (nonzero: |winding| = 1 in each)
    signed = abs(shapely.Polygon(bowtie).area)  # what the signed area alone gives: their difference
    assert lobes > signed + 5.0
    res = slice_mesh(mesh_from_triangles(S.prism(bowtie, 0.0, 2.0)), thickness=1.0, backend=backend, max_gap=0.0)
    assert res.n_layers == 2
    np.testing.assert_allclose(res.area, lobes, rtol=1e-6)
    assert (res.repairs["overlaps_resolved"] == 1).all()
    polys = res.to_shapely()
    assert shapely.is_valid(polys).all()
    np.testing.assert_allclose(shapely.area(polys), res.area, rtol=1e-9)


def test_loop_crossing_itself_with_cancelling_lobes(backend):
    """A symmetric figure-8 (lobes of equal area, opposite signs: net area 0) is not degenerate: both lobes fill."""
    bowtie = np.array([[0.0, 0.0], [10.0, 6.0], [10.0, 0.0], [0.0, 6.0]])  # two lobes of 15 mm^2
    res = slice_mesh(mesh_from_triangles(S.prism(bowtie, 0.0, 2.0)), thickness=1.0, backend=backend, max_gap=0.0)
    np.testing.assert_allclose(res.area, 30.0, rtol=1e-6)


def test_layer_batches_with_rebuilt_overlaps_give_the_same_result(backend):
    # batches gather their points into one buffer sized by the segments; loops rebuilt where bodies overlap have
    # points of their own (the crossings of the two outlines): the result must still equal the one-batch slice
    tri = np.concatenate([S.box((0, 0, 0), (20, 20, 20)), S.box((10, 5, 0), (30, 15, 20)),
                          S.box((5, -5, 2), (15, 25, 18))])
    mesh = mesh_from_triangles(tri)
    whole = slice_mesh(mesh, thickness=0.5, backend=backend)
    parts = slice_mesh(mesh, thickness=0.5, backend=backend, max_segments_per_batch=60)
    assert parts.meta["batches"] > 5 and whole.meta["batches"] == 1
    assert whole.repairs["overlaps_resolved"].sum() > 0
    for name in ("points", "loop_offsets", "layer_offsets", "loop_layer", "loop_is_hole", "loop_parent", "area"):
        np.testing.assert_array_equal(getattr(parts, name), getattr(whole, name))


def test_points_buffer_grows_past_its_hint():
    from gpuslice.slicing.slicer import _PointsBuffer

    rng = np.random.default_rng(3)
    pieces = [rng.random((k, 2), dtype=np.float32) for k in (5, 0, 17, 3, 40)]
    for hint in (0, 10, 65, 1000):
        buf = _PointsBuffer(hint)
        for p in pieces:
            buf.append(p)
        np.testing.assert_array_equal(buf.array(), np.concatenate(pieces))


def test_planes_that_coincide_in_float32_are_refused_naming_the_model():
    mesh = mesh_from_triangles(S.box((0, 0, 0), (10, 10, 10)), name="block.stl")
    with pytest.raises(ParameterError, match=r"^block\.stl: layers closer than float32 resolution.*z = 4 mm"):
        slice_mesh(mesh, z=[1.0, 4.0, 4.0 + 1e-9, 6.0])


def test_batches_of_one_mesh_after_another_use_each_its_own_arrays(backend):
    # after its first batch a slice keeps the mesh's arrays on the device (not uploaded again): the next mesh's
    # first batch must replace them, whatever the sizes
    a = mesh_from_triangles(S.hollow_box(20, 10, core=6))
    b = mesh_from_triangles(np.concatenate([S.box((0, 0, 0), (8, 8, 12)), S.box((3, 3, 2), (14, 6, 9))]))
    ref_a, ref_b = (slice_mesh(m, thickness=0.25, backend=backend) for m in (a, b))
    for m, ref in ((a, ref_a), (b, ref_b), (a, ref_a)):
        got = slice_mesh(m, thickness=0.25, backend=backend, max_segments_per_batch=100)
        assert got.meta["batches"] > 5
        for name in ("points", "loop_offsets", "layer_offsets", "loop_is_hole", "area"):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))


def test_layers_too_thin_for_float32_planes_are_refused():
    # float32 planes stray from their schedule by up to half a float32 step: at 300 mm that is 1.5e-5 mm, 30 % of a
    # 0.00005 mm layer (a helper's probe: the layers came out unevenly thick without a word)
    tall = mesh_from_triangles(S.box((0, 0, 0), (5, 5, 300)), name="tall.stl")
    with pytest.raises(ParameterError, match=r"^tall\.stl: layers of 0\.0002 mm are too thin for float32 planes"):
        slice_mesh(tall, thickness=0.0002)
    short = mesh_from_triangles(S.box((0, 0, 0), (5, 5, 2)), name="short.stl")
    assert slice_mesh(short, thickness=0.0002).n_layers == 10_000  # 2 mm: a step is 1.2e-7 mm, under 0.1 %


def test_a_layer_of_one_self_crossing_loop_keeps_its_fractional_area(backend):
    """A prism over a bow tie (a quadrilateral crossing itself): its one loop per layer bounds nothing on the fast
    path (the lobes cancel), so the layers' areas began as numpy's bincount of nothing, int64, and the rebuilt
    lobes' 6.6 mm² was stored as 6 (seen on one layer; the same prism cut at two came out right; a helper's sweep
    saw the int64)."""
    p = np.array([[0, 0], [4, 3.3], [4, 0], [0, 3.3]], float)
    tri = []
    for i in range(4):
        (ax, ay), (bx, by) = p[i], p[(i + 1) % 4]
        tri += [[[ax, ay, 0], [bx, by, 0], [bx, by, 5]], [[ax, ay, 0], [bx, by, 5], [ax, ay, 5]]]
    r = slice_mesh(mesh_from_triangles(np.array(tri, float)), z=np.array([2.5]), backend=backend)
    assert r.area.dtype == np.float64 and r.repairs["overlaps_resolved"].tolist() == [1]
    np.testing.assert_allclose(r.area, 6.6, rtol=1e-6)


def test_a_repeated_facet_is_cut_once(backend):
    """Two bars 0.8 mm apart whose facing walls are each stored twice (an exporter's repeats): every edge of a
    repeat has three sides, chaining paired one copy with its neighbours and left the other a loose chain, and gap
    closing joined the two loose chains across the gap into a rectangle that was filled (56 mm² for 40; a helper's
    sweep). Repeats (the same corners in the same turn) are now cut once; a closed box stored twice over, too. A copy
    the other way round goes where its sides have one neighbour each (the one that runs with it); two boxes that
    touch, their shared wall stored once by each, keep both walls (their sides have two neighbours) and merge."""
    a = np.asarray(S.box(lo=(0, 0, 0), hi=(1, 20, 10)), float)
    b = np.asarray(S.box(lo=(1.8, 0, 0), hi=(2.8, 20, 10)), float)
    tri = np.concatenate([a, b])
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    facing = np.flatnonzero(np.r_[n[:12, 0] > 0, n[12:, 0] < 0])
    z = np.array([2.5001, 5.0001, 7.5001])
    r = slice_mesh(mesh_from_triangles(np.concatenate([tri, tri[facing]])), z=z, backend=backend)
    np.testing.assert_allclose(r.area, 40.0, rtol=F32)
    assert not any(v.any() for v in r.repairs.values())
    twice = np.concatenate([a, np.roll(a, 1, axis=1)])  # (the repeat's corners listed from another one)
    r = slice_mesh(mesh_from_triangles(twice), z=z, backend=backend)
    np.testing.assert_allclose(r.area, 20.0, rtol=F32)
    r = slice_mesh(mesh_from_triangles(np.concatenate([tri, tri[facing][:, ::-1]])), z=z, backend=backend)
    np.testing.assert_allclose(r.area, 40.0, rtol=F32)
    assert not any(v.any() for v in r.repairs.values())
    c, d = np.asarray(S.box(hi=(10, 10, 10)), float), np.asarray(S.box(lo=(10, 0, 0), hi=(20, 10, 10)), float)
    r = slice_mesh(mesh_from_triangles(np.concatenate([c, d])), z=z, backend=backend)
    np.testing.assert_allclose(r.area, 200.0, rtol=F32)


def test_overlapping_bodies_that_share_a_face_keep_it(backend):
    """Two boxes, one inside the other but for a face they share, stored with the same corners and turn: the second
    box's copy of that face is no repeat to drop (its sides have three other facets), or the box opens and is lost
    (a review: 5 mm² for 15)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    f = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7],
                  [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    m = mesh_from_arrays(np.vstack([v * [1, 5, 4], v * [3, 5, 4]]), np.vstack([f, f + 8]))
    for rule, want in (("nonzero", 15.0), ("evenodd", 10.0), ("positive", 15.0)):
        r = slice_mesh(m, thickness=0.5, fill_rule=rule, backend=backend)
        np.testing.assert_allclose(r.area, want, rtol=F32)
        assert r.repairs["open_chains"].sum() == 0
