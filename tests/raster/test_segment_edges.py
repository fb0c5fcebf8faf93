"""The segment-buffer shortcut of ``--z-samples`` (gpuslice.raster.segment_edges): the sub-planes' runs from their
segments equal the polygon path's byte for byte where it is taken, and it is not taken where the polygons are not
the segments (open, inside-out, overlapping or zero-volume shells, another fill rule)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import read_catalog

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec
from gpuslice.raster.edges import z_sample_planes
from gpuslice.raster.runs import Runs, iter_runs
from gpuslice.raster.segment_edges import (
    SegmentEdgesKernel,
    iter_sub_plane_edges,
    layers_through_vertices,
    segment_edges_numpy,
    shortcut_refusal,
)
from gpuslice.slicing.crossings import compute_crossings, crossings_numpy

SPEC = RasterSpec(resolution=(1600, 1200), pixel=0.05)
FIELDS = ("layer_offsets", "row", "x", "length", "grey")


def _bounds(mesh):
    b = mesh.bounds
    return (b[0, 0], b[0, 1], b[1, 0], b[1, 1])


def _both_paths(mesh, res, spec, k, device, chunk=128, bounds=None):
    """(runs of the z sub-planes through slicing, through the shortcut as the job takes it (segments on the device,
    layers through a vertex sliced and spliced in), the kernel's and the twin's raw edges of all the segments).
    ``bounds``: what is centred on the display (default: the mesh's box)."""
    bounds = _bounds(mesh) if bounds is None else bounds
    z, th = z_sample_planes(res, k)
    sub = slice_mesh(mesh, z=z, layer_thickness=th, backend="opencl")
    poly = Runs.concat(list(iter_runs(sub, spec, device=device, bounds=bounds, z_samples=k)), spec.shape)

    def cut(sel):
        return slice_mesh(mesh, z=z[sel], layer_thickness=th[sel], backend="opencl")

    parts = []
    for a, le, _ in iter_sub_plane_edges(mesh, z, k, spec, bounds, device, cut, chunk):
        for r in iter_runs(None, spec, device=device, bounds=bounds, z_samples=k, merged=le):
            parts.append(Runs(r.layers + a, r.layer_offsets, r.row, r.x, r.length, r.grey, r.shape))
    got = Runs.concat(parts, spec.shape)
    seg = compute_crossings(mesh, z, device, read_back=False)
    raw, short = SegmentEdgesKernel.of(device)(seg, z.size, k, spec, bounds)
    twin, twin_short = segment_edges_numpy(seg.fetch(), z.size, k, spec, bounds)
    assert np.array_equal(short, twin_short)
    return poly, got, raw, twin


def _same_runs(a: Runs, b: Runs) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in FIELDS)


def _same_edges(a, b) -> None:
    """Kernel and twin: the same tiles and layer offsets, the same edges in each layer (any order inside one)."""
    assert np.array_equal(a.tiles, b.tiles) and np.array_equal(a.edge_offsets, b.edge_offsets)
    for g in range(len(a.tiles)):
        x, y = (e[a.edge_offsets[g] : a.edge_offsets[g + 1]] for e in (a.edges, b.edges))
        assert np.array_equal(x[np.lexsort(x.T)], y[np.lexsort(y.T)]), g


@pytest.mark.parametrize("gamma", [1.0, 0.0])
@pytest.mark.parametrize("k", [2, 4])
def test_solids_equal_the_polygon_path(device, gamma, k):
    """A torus and a hollow box (a cavity wound inward): the shortcut is taken and gives the polygon path's runs."""
    spec = RasterSpec(resolution=SPEC.resolution, pixel=SPEC.pixel, gamma=gamma)
    for tri in (shapes.torus(15.0, 5.0, 40, 20), shapes.hollow_box(20.0, 10.0)):
        mesh = mesh_from_triangles(tri)
        res = slice_mesh(mesh, thickness=0.3, backend="opencl")
        assert shortcut_refusal(mesh, res, "nonzero", spec, _bounds(mesh)) is None
        poly, got, raw, twin = _both_paths(mesh, res, spec, k, device)
        assert poly.row.size > 1000 and _same_runs(got, poly)
        _same_edges(raw, twin)


def test_a_vertex_on_a_sub_plane(device):
    """A pyramid whose apex lies exactly on a sub-plane (a loop of one point there: zero-length segments, which the
    tiles leave out; the polygon path drops the loop): still the polygon path's runs."""
    k = 4
    tri = shapes.cone(radius=12.0, height=1.0625, n=4)  # apex at 1.0 + 0.5 * 0.5 / k: a sub-plane of layer 2
    mesh = mesh_from_triangles(tri)
    res = slice_mesh(mesh, z=np.array([0.25, 0.75, 1.25]), layer_thickness=0.5, backend="opencl")
    z, _ = z_sample_planes(res, k)
    assert np.isin(np.float32(1.0625), z.astype(np.float32)) and mesh.height == pytest.approx(1.0625)
    assert shortcut_refusal(mesh, res, "nonzero", SPEC, _bounds(mesh)) is None
    poly, got, raw, twin = _both_paths(mesh, res, SPEC, k, device)
    assert _same_runs(got, poly)
    _same_edges(raw, twin)
    seg = crossings_numpy(mesh, z)
    zero = (seg.points[:, 0] == seg.points[:, 2]) & (seg.points[:, 1] == seg.points[:, 3])
    assert zero.any()  # the apex's segments: the case is exercised


def _ridge_wedge(h: float, dx: float = 0.0, dy: float = 0.0) -> np.ndarray:
    """The convex hull of a 64-gon of radius 2 mm at z = 0 and a horizontal ridge 10 mm long at z = ``h`` (it
    overhangs the base by 3 mm each way), moved by (dx, dy) mm, outward wound."""
    from scipy.spatial import ConvexHull

    t = 2 * np.pi * np.arange(64) / 64
    pts = np.concatenate([np.stack([2 * np.cos(t), 2 * np.sin(t), np.zeros(64)], 1), [[-5, 0, h], [5, 0, h]]])
    pts += [dx, dy, 0.0]
    tri = pts[ConvexHull(pts).simplices]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = np.einsum("ij,ij->i", normal, tri[:, 0] - pts.mean(0)) < 0
    tri[inward] = tri[inward][:, ::-1]
    return tri


def test_a_ridge_on_a_sub_plane(device):
    """A horizontal ridge lying exactly on a sub-plane, both its facets below: a loop of two points there, which
    nesting drops and whose points lie outside the other sub-planes' boxes. Its layer goes the polygon way, the
    others from their segments: the job's runs equal the polygon path's at every placement tried. (The raw segment
    edges of that layer, in a wider tile, gave other runs at 3 of these 10 placements while each cell's share was
    rounded apart, before the tenth session; with the running share rounded once, the two-point loop's pieces cancel
    exactly and the tile's other float32 origin moves no grey here: the splice stays, as what is proven.)"""
    from gpuslice.raster.edges import iter_layer_edges

    k, bounds = 4, (-10.0, -10.0, 10.0, 10.0)  # a fixed centring: the wedge's moves move its pixels
    for dx, dy in np.random.default_rng(0).uniform(-3.0, 3.0, (10, 2)):
        mesh = mesh_from_triangles(_ridge_wedge(1.3125, dx, dy))  # 1.0 + 2.5 * 0.5 / k: a sub-plane of layer 2
        res = slice_mesh(mesh, z=np.array([0.25, 0.75, 1.25]), layer_thickness=0.5, backend="opencl")
        assert shortcut_refusal(mesh, res, "nonzero", SPEC, bounds) is None
        z, th = z_sample_planes(res, k)
        assert layers_through_vertices(mesh, z, k).tolist() == [False, False, True]
        poly, got, raw, twin = _both_paths(mesh, res, SPEC, k, device, bounds=bounds)
        assert _same_runs(got, poly)
        _same_edges(raw, twin)
        sub = slice_mesh(mesh, z=z, layer_thickness=th, backend="opencl")
        assert sub.repairs["degenerate_loops"].sum() >= 1  # the two-point loop: the case is exercised
        ((_, want),) = iter_layer_edges(sub, SPEC, bounds, k=k, dtype=np.float32)
        assert not np.array_equal(raw.tiles[2], want.tiles[2])  # the raw segments' box: wider than the polygons'


@pytest.mark.parametrize("display", ["mirror_x", "portrait"])
def test_mirrored_and_portrait_displays_several_chunks(device, display):
    """The pixel mapping with negative or swapped axes, and chunks of 7 layers: still the polygon path's runs."""
    spec = RasterSpec(resolution=(1200, 1600), pixel=0.05, **{display: True})
    mesh = mesh_from_triangles(shapes.torus(15.0, 5.0, 40, 20))
    res = slice_mesh(mesh, thickness=0.3, backend="opencl")
    poly, got, raw, twin = _both_paths(mesh, res, spec, 3, device, chunk=7)
    assert res.n_layers > 14 and _same_runs(got, poly)
    _same_edges(raw, twin)


def _refusal(tri, fill_rule="nonzero"):
    mesh = mesh_from_triangles(tri)
    res = slice_mesh(mesh, thickness=0.5, backend="opencl", fill_rule=fill_rule)
    return shortcut_refusal(mesh, res, fill_rule, SPEC, _bounds(mesh))


def test_not_taken_where_polygons_are_not_segments(device):
    box = shapes.box(hi=(10.0, 10.0, 10.0))
    assert _refusal(box) is None
    assert "not closed" in _refusal(box[1:])  # an open box
    assert "fill rule" in _refusal(box, "evenodd")
    inside_out = box[:, ::-1]  # closed and consistent, wound inward: nesting turns every loop round
    assert "not their segments" in _refusal(inside_out)
    overlapping = np.concatenate([box, shapes.box((5.0, 5.0, 0.0), (15.0, 15.0, 10.0))])  # rebuilt by nesting
    assert "not their segments" in _refusal(overlapping)
    nested_same_way = np.concatenate([box, shapes.box((3.0, 3.0, 3.0), (6.0, 6.0, 6.0))])  # its loops: unfilled
    assert "not their segments" in _refusal(nested_same_way)
    pillow = np.array([[[20, 0, 1], [22, 0, 4], [21, 2, 8]], [[20, 0, 1], [21, 2, 8], [22, 0, 4]]], float)
    assert "three vertices" in _refusal(np.concatenate([box, pillow]))  # a closed shell of two facets
    assert _refusal(np.concatenate([box, shapes.box((12.0, 0.0, 0.0), (20.0, 8.0, 6.0))])) is None  # side by side
    # a plate 0.03 mm thick across the box's edge, between two layers' planes: every layer is its segments, but the
    # sub-planes through the plate would count the overlap twice (the auditor's case: 141 pixels too bright)
    thin = np.concatenate([box, shapes.box((8.0, 2.0, 5.06), (14.0, 6.0, 5.09))])
    assert "shells meet" in _refusal(thin)
    assert _refusal(np.concatenate([box, shapes.box((10.0, 0.0, 0.0), (12.0, 8.0, 6.0))])) is not None  # touching


def test_the_job_takes_it_and_writes_the_same_file(tmp_path, device, monkeypatch):
    """`gpuslice raster --z-samples 4` through the shortcut and with it refused: the same archive, byte for byte."""
    import gpuslice.raster.segment_edges as se
    from gpuslice.cli import main

    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 40, 20), stl)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    args = ["raster", str(stl), "-t", "0.2", "--resolution", "1600x1200", "--pixel", "0.05", "--z-samples", "4",
            "-q", "--no-progress"]
    assert main([*args, "-o", str(tmp_path / "a.goo"), "--report", str(tmp_path / "a.json")]) == 0
    monkeypatch.setattr(se, "shortcut_refusal", lambda *a: "refused by the test")
    assert main([*args, "-o", str(tmp_path / "b.goo"), "--report", str(tmp_path / "b.json")]) == 0
    assert (tmp_path / "a.goo").read_bytes() == (tmp_path / "b.goo").read_bytes()
    import json

    stats = [json.loads((tmp_path / f"{x}.json").read_text()) for x in "ab"]
    assert stats[0]["z_samples_from"] == "segments"
    assert stats[1]["z_samples_from"] == "polygons (refused by the test)"


CATALOG = read_catalog()


@pytest.mark.parametrize("name", sorted(CATALOG) or ["(no shared meshes)"])
@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")  # trimesh on p_flt_max_coords
def test_shared_meshes(shared_meshes, device, name):
    """Every shared mesh at 20 mm, 0.1 mm layers, 4 sub-planes: where the shortcut is taken its runs equal the
    polygon path's; it is taken on every closed, consistently wound mesh whose layers are their segments, and on no
    other."""
    import trimesh

    from gpuslice.errors import GpusliceError

    m = trimesh.load(shared_meshes / f"{name}.stl", force="mesh")
    try:
        mesh = mesh_from_triangles(m.vertices[m.faces], fit=20.0)
    except GpusliceError as exc:  # (the empty and all-degenerate test files: nothing to slice)
        pytest.skip(f"{name}: nothing to slice ({exc})")
    res = slice_mesh(mesh, thickness=0.1, backend="opencl")
    refusal = shortcut_refusal(mesh, res, "nonzero", SPEC, _bounds(mesh))
    sides = mesh.edge_sides()
    closed = bool(np.all(sides.count == 2) and np.all(sides.forward == 1))
    if not closed:
        assert refusal == "the mesh is not closed and consistently wound"
        return
    if not np.all(res.segment_exact):
        assert refusal is not None
        return
    assert refusal is None or "three vertices" in refusal
    if name in ("armadillo", "nefertiti", "spot", "fandisk", "xyz_cube_20mm"):  # known closed, clean meshes
        assert refusal is None
    if refusal is None:
        poly, got, _, _ = _both_paths(mesh, res, SPEC, 4, device)
        assert _same_runs(got, poly)


def test_splice_layers():
    """Entries replaced at the start, inside and at the end, and none: against a layer-by-layer assembly."""
    from gpuslice.raster.edges import LayerEdges, splice_layers

    rng = np.random.default_rng(1)

    def random_edges(n):
        counts = rng.integers(0, 5, n)
        off = np.concatenate([[0], np.cumsum(counts)])
        return LayerEdges(rng.random((off[-1], 4)).astype(np.float32), off, rng.integers(0, 99, (n, 4)))

    base, other = random_edges(9), random_edges(6)
    for at, oat in (([0, 4, 8], [5, 0, 2]), ([3], [3]), ([], [])):
        got = splice_layers(base, at, other, oat)
        src = {i: (other, j) for i, j in zip(at, oat, strict=True)}
        for i in range(9):
            le, j = src.get(i, (base, i))
            want = le.edges[le.edge_offsets[j] : le.edge_offsets[j + 1]]
            assert np.array_equal(got.edges[got.edge_offsets[i] : got.edge_offsets[i + 1]], want)
            assert np.array_equal(got.tiles[i], le.tiles[j])
        assert got.edge_offsets[-1] == len(got.edges)


def test_a_sliver_one_ulp_under_a_ridge(device):
    """A case scripts/fuzz_z_samples.py found (seed 1, case 1911): a wedge whose ridge lies one float32 ulp above a
    sub-plane. That sub-plane cuts a sliver narrower than float32 can hold: its crossings round onto each other,
    nesting drops the loop as unfilled and its points would widen the tile. The kernel flags the layer's short
    segments, the layer goes the polygon way, and the runs equal the polygon path's. (From the raw segments they
    differed while each cell's share was rounded apart, before the tenth session; rounded once, they agree here
    too: the guard stays, as what is proven.)"""
    f = np.float32
    a, b, c = [f(1.5729523), f(-9.3100605), f(0.11500001)], [f(5.223868), f(-11.811739), f(0.11500001)], [
        f(3.726411), f(-9.339488), f(0)]
    d, e = [f(3.6428647), f(-11.856278), f(0)], [f(2.1195378), f(-10.666934), f(0)]
    tri = np.array([[a, b, c], [d, b, a], [d, c, b], [a, c, e], [e, d, a], [c, d, e]], np.float32)
    mesh = mesh_from_triangles(tri)
    spec = RasterSpec(resolution=(506, 382), pixel=0.0962530779526021, portrait=True, gamma=1.0)
    bounds = (-17.46512099449965, -17.46512099449965, 17.46512099449965, 17.46512099449965)
    res = slice_mesh(mesh, thickness=0.02, backend="opencl")
    assert shortcut_refusal(mesh, res, "nonzero", spec, bounds) is None
    z, _ = z_sample_planes(res, 2)
    assert not layers_through_vertices(mesh, z, 2).any()
    poly, got, raw, twin = _both_paths(mesh, res, spec, 2, device, chunk=6, bounds=bounds)
    assert _same_runs(got, poly)
    _same_edges(raw, twin)


@pytest.mark.parametrize("ulps", [1, 2, 3])
def test_a_ridge_a_few_ulps_off_a_sub_plane(device, ulps):
    """The ridge a few float32 ulps above the sub-plane (through no vertex): its sliver's segments are shorter than
    :data:`SHORT` (the kernel and the twin flag the layer), the layer goes the polygon way, and the job's runs equal
    the polygon path's at every placement tried."""
    from gpuslice.raster.segment_edges import short_segments

    k, bounds = 4, (-10.0, -10.0, 10.0, 10.0)
    h = np.float32(1.3125)
    for _ in range(abs(ulps)):
        h = np.nextafter(h, np.float32(np.sign(ulps) * np.inf))
    for dx, dy in np.random.default_rng(1).uniform(-3.0, 3.0, (6, 2)):
        mesh = mesh_from_triangles(_ridge_wedge(float(h), dx, dy))
        res = slice_mesh(mesh, z=np.array([0.25, 0.75, 1.25]), layer_thickness=0.5, backend="opencl")
        assert shortcut_refusal(mesh, res, "nonzero", SPEC, bounds) is None
        z, _ = z_sample_planes(res, k)
        assert not layers_through_vertices(mesh, z, k).any()
        seg = crossings_numpy(mesh, z)
        assert short_segments(seg.points)[seg.layer // k == 2].any()  # the sliver layer is flagged
        poly, got, raw, twin = _both_paths(mesh, res, SPEC, k, device, bounds=bounds)
        assert _same_runs(got, poly)
        _same_edges(raw, twin)
