"""Adaptive schedules (gpuslice.schedule.adaptive, kernels/adaptive.cl): kernel twins, the cusp/area bounds checked by
plain
loops, tiling, smoothing, the roi ladder, and the `slice --adaptive` command line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gpuslice import mesh_from_arrays, mesh_from_triangles, roi_schedule, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh.shapes import box, icosphere, torus, write_stl
from gpuslice.schedule.adaptive import (
    _range_max,
    cusp_schedule,
    facet_slopes,
    facet_slopes_numpy,
    slab_max_nz,
    slab_max_nz_numpy,
)
from gpuslice.schedule.uniform import uniform

C, A, B = 0.05, 0.05, 0.3


@pytest.fixture(scope="module")
def sphere():
    return mesh_from_triangles(icosphere(20.0))


def _facets64(mesh):
    """Per facet zmin, zmax, |n_z| in float64, computed here independently of gpuslice.schedule.adaptive."""
    t = mesh.vertices.astype(np.float64)[mesh.faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    nz = np.abs(n[:, 2]) / np.linalg.norm(n, axis=1)
    return t[:, :, 2].min(axis=1), t[:, :, 2].max(axis=1), nz


def _worst(mesh, sched, per_facet_limit, layers=None):
    """Largest ratio t / limit(facet) over layers (all, or a boolean mask) and the non-horizontal facets
    overlapping each slab (a plain loop)."""
    zmin, zmax, nz = _facets64(mesh)
    lim = per_facet_limit(nz)
    worst = 0.0
    keep = np.ones(len(sched), bool) if layers is None else layers
    for bottom, top, t in zip(sched.bottom[keep], sched.top[keep], sched.thickness[keep], strict=True):
        sel = (zmin < top) & (zmax > bottom) & (zmax > zmin)
        if sel.any():
            worst = max(worst, float(np.max(t / lim[sel])))
    return worst


def _check_tiling(mesh, sched, lo=A, hi=B):
    edges = np.concatenate(([0.0], np.cumsum(sched.thickness)))
    assert edges[-1] == pytest.approx(mesh.height, abs=1e-9)
    np.testing.assert_allclose(sched.z, (edges[1:] + edges[:-1]) / 2, atol=1e-9)  # cut at mid-slab
    assert np.all(sched.thickness[:-1] >= lo - 1e-9) and np.all(sched.thickness <= hi + 1e-9)


# ---- the kernels against their numpy twins --------------------------------------------------------------------


def test_range_max_matches_brute_force():
    rng = np.random.default_rng(1)
    n = 300
    lo = rng.integers(0, n, 500)
    hi = np.minimum(lo + rng.integers(0, 80, 500), n)
    val = rng.random(500).astype(np.float32)
    want = np.zeros(n, np.float32)
    for a, b, v in zip(lo, hi, val, strict=True):
        want[a:b] = np.maximum(want[a:b], v)
    np.testing.assert_array_equal(_range_max(n, lo, hi, val), want)


@pytest.mark.parametrize("shape", ["sphere", "torus"])
def test_facet_kernel_matches_numpy_twin(device, shape):
    mesh = mesh_from_triangles(icosphere(20.0) if shape == "sphere" else torus())
    got = facet_slopes(mesh, device)
    want = facet_slopes_numpy(mesh)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)  # bit-identical (no FMA, correctly rounded sqrt and division)
    np.testing.assert_allclose(want[2], _facets64(mesh)[2], atol=1e-5)


def test_slab_kernel_matches_numpy_twin(device, sphere):
    rng = np.random.default_rng(7)
    irregular = np.concatenate(([0.0], np.sort(rng.uniform(0, sphere.height, 300)), [sphere.height]))
    for edges in (np.linspace(0, sphere.height, 4001), irregular, uniform(sphere.height, 0.3).bottom):
        got = slab_max_nz(sphere, edges, device)
        want = slab_max_nz_numpy(*facet_slopes_numpy(sphere), edges)
        np.testing.assert_array_equal(got, want)
    # edges bunched together (most slabs in one millimetre, the guide's buckets all but empty elsewhere), edges equal
    # once in float32, edges reaching far below and above the mesh
    bunched = np.concatenate(([-50.0], np.linspace(7.0, 8.0, 2000), 8.0 + np.zeros(5), [8.0 + 1e-7, 9.0, 500.0]))
    for edges in (bunched, np.array([0.0, sphere.height]), np.array([3.0, 3.0 + 1e-6])):
        want = slab_max_nz_numpy(*facet_slopes_numpy(sphere), edges)
        np.testing.assert_array_equal(slab_max_nz(sphere, edges, device), want)
    # the searches start from the guide's guesses, but any guess must give the same slabs: random ones here
    import gpuslice.schedule.adaptive as adaptive

    real = adaptive._search_guide
    for seed in range(3):
        def random_guide(e32, seed=seed):
            n_guide, e0, inv_w, guide = real(e32)
            return n_guide, e0, inv_w, np.random.default_rng(seed).integers(0, e32.size + 1, guide.size, np.int32)

        adaptive._search_guide = random_guide
        try:
            for edges in (irregular, bunched):
                want = slab_max_nz_numpy(*facet_slopes_numpy(sphere), edges)
                np.testing.assert_array_equal(slab_max_nz(sphere, edges, device), want)
        finally:
            adaptive._search_guide = real
    # against a plain loop: every slab's max |n_z| over the facets overlapping it (touching ones may add)
    zmin, zmax, nz = _facets64(sphere)
    got = slab_max_nz(sphere, irregular, device)
    for k in range(0, irregular.size - 1, 7):
        sel = (zmin < irregular[k + 1]) & (zmax > irregular[k]) & (zmax > zmin)
        assert got[k] >= nz[sel].max() - 1e-6


# ---- error-bounded schedules ----------------------------------------------------------------------------------


def test_slab_kernel_follows_the_mesh_not_its_id(device):
    """The device's slabs are always those of the mesh as it is now: not of another mesh that had the same id and facet
    count (a dead mesh's id reused; here: new vertices on the same object), nor of the mesh before an edit in place,
    and no KeyError once the buffers were let go (``release_scratch`` before a resin job's layers)."""
    from gpuslice.device import release_scratch

    mesh = mesh_from_triangles(icosphere(20.0))
    edges = np.linspace(0, mesh.height, 301)
    first = slab_max_nz(mesh, edges, device)
    tilted = mesh.vertices.copy()
    tilted[:, 2] = mesh.vertices[:, 2] + 0.3 * mesh.vertices[:, 0]  # sheared: other normals, as many facets
    tilted[:, 2] -= tilted[:, 2].min()
    mesh.vertices = tilted
    want = slab_max_nz_numpy(*facet_slopes_numpy(mesh), edges)
    assert not np.array_equal(want, first)
    np.testing.assert_array_equal(slab_max_nz(mesh, edges, device), want)
    release_scratch(device)
    np.testing.assert_array_equal(slab_max_nz(mesh, edges, device), want)
    mesh.vertices[:, 2] *= 0.5  # edited in place: the same arrays, other facets
    np.testing.assert_array_equal(slab_max_nz(mesh, edges, device), slab_max_nz_numpy(*facet_slopes_numpy(mesh), edges))


@pytest.mark.parametrize("backend", ["numpy", "opencl"])
def test_icosphere_cusp_bound_and_layer_count(request, sphere, backend):
    dev = request.getfixturevalue("device") if backend == "opencl" else None
    sched = cusp_schedule(sphere, max_cusp=C, min_height=A, max_height=B, device=dev)
    assert _worst(sphere, sched, lambda nz: C / np.maximum(nz, 1e-300)) <= 1 + 1e-9  # t·|n_z| <= C
    n_uniform = len(uniform(sphere.height, 0.05))
    assert len(sched) <= 0.6 * n_uniform, (len(sched), n_uniform)
    assert len(sched) >= 0.45 * n_uniform  # the ideal is 50 %: a schedule far below it cannot honour the bound
    _check_tiling(sphere, sched)
    assert sched.info["bound_violations"] == 0
    # thick layers near the equator (vertical walls), thin ones at the poles
    mid = np.argmin(np.abs(sched.z - 20.0))
    assert sched.thickness[mid] == pytest.approx(B)
    assert sched.thickness[0] == pytest.approx(A)


def test_area_mode_bound(sphere):
    amax = 0.0025

    def limit(nz):
        with np.errstate(divide="ignore"):
            return np.sqrt(2 * amax * np.sqrt(1 - nz**2) / nz)

    # near the poles the error area allows only ~0.015 mm: with min_height 0.01 the bound holds everywhere
    fine = cusp_schedule(sphere, mode="area", max_area=amax, min_height=0.01, max_height=B)
    assert _worst(sphere, fine, limit) <= 1 + 1e-9
    assert fine.info["bound_violations"] == 0
    _check_tiling(sphere, fine, lo=0.01)
    # with min_height 0.05 the clamp wins there: those layers are counted, every thicker layer keeps the bound
    sched = cusp_schedule(sphere, mode="area", max_area=amax, min_height=A, max_height=B)
    assert sched.info["bound_violations"] > 0
    assert _worst(sphere, sched, limit, sched.thickness > A + 1e-9) <= 1 + 1e-9
    assert len(sched) < len(uniform(sphere.height, A))


def test_smoothing_keeps_the_bound_and_limits_jumps(sphere):
    rough = cusp_schedule(sphere, max_cusp=C, min_height=A, max_height=B)
    smooth = cusp_schedule(sphere, max_cusp=C, min_height=A, max_height=B, smooth=0.05)
    assert _worst(sphere, smooth, lambda nz: C / np.maximum(nz, 1e-300)) <= 1 + 1e-9
    jumps = np.abs(np.diff(smooth.thickness[:-1]))
    # the thickness changes by at most g per mm of height (g·t of the layer), plus one grid step
    assert np.all(jumps <= 0.05 * smooth.thickness[:-2] + smooth.info["resolution_mm"] + 1e-9)
    assert len(smooth) >= len(rough)


@pytest.mark.parametrize("rate", [1e3, 1e12, 1e308])
def test_a_smoothing_rate_too_large_to_bound_anything_is_no_smoothing(sphere, rate):
    """A rate at or above the most bins a layer holds lets every layer be what its slab allows: the schedule without
    smoothing. Taken literally, t - rate·height lost t's digits (nefertiti: 714 layers where 702 was right at 1e12)
    and 1e308 overflowed (a numpy warning, then min-height layers)."""
    import warnings

    rough = cusp_schedule(sphere, max_cusp=C, min_height=A, max_height=B)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        huge = cusp_schedule(sphere, max_cusp=C, min_height=A, max_height=B, smooth=rate)
    np.testing.assert_array_equal(huge.z, rough.z)
    np.testing.assert_array_equal(huge.thickness, rough.thickness)


@pytest.mark.parametrize("mode", ["cusp", "area"])
@pytest.mark.parametrize("lo, hi", [(1e30, 1e30), (1e308, 1e308), (A, 1e308)])
def test_layer_bounds_beyond_the_model_give_one_layer_of_its_height(sphere, mode, lo, hi):
    """--max-height 1e308 was an OverflowError (an int of inf bins), --min-height 1e30 no layer at all (the model was
    thinner than one bin: zero bins), 1e308 a float32 overflow: a max_height beyond the model is the model's height
    (the schedule is the one that bound gives), a min_height beyond it one layer of the model's height."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sched = cusp_schedule(sphere, mode=mode, max_cusp=C, max_area=0.1, min_height=lo, max_height=hi)
    if lo > sphere.height:
        assert len(sched) == 1 and sched.thickness[0] == pytest.approx(sphere.height)
    else:
        same = cusp_schedule(sphere, mode=mode, max_cusp=C, max_area=0.1, min_height=lo, max_height=sphere.height)
        assert len(sched) > 1
        np.testing.assert_array_equal(sched.z, same.z)


def test_horizontal_facets_make_no_staircase():
    cube = mesh_from_triangles(box((10, 10, 10)))  # only vertical and horizontal facets
    sched = cusp_schedule(cube, max_cusp=C, min_height=A, max_height=B)
    assert np.all(sched.thickness[:-1] == pytest.approx(B))
    assert sched.top[-1] == pytest.approx(10.0)


def test_min_height_clamp_is_counted():
    # a 45° wedge: cusp 0.05 allows 0.0707 mm, but min_height 0.1 forces thicker layers
    v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [0, 0, 10], [0, 10, 10]], float)
    f = [[0, 2, 1], [0, 3, 2], [0, 1, 4], [3, 5, 2], [1, 2, 5], [1, 5, 4], [0, 4, 5], [0, 5, 3]]
    wedge = mesh_from_arrays(v, f)
    sched = cusp_schedule(wedge, max_cusp=C, min_height=0.1, max_height=B)
    assert np.allclose(sched.thickness[:-1], 0.1)
    assert sched.info["bound_violations"] == len(sched)  # the slope is in every slab
    assert _worst(wedge, sched, lambda nz: C / np.maximum(nz, 1e-300)) == pytest.approx(0.1 / C / np.sqrt(2))
    ok = cusp_schedule(wedge, max_cusp=C, min_height=0.01, max_height=B)
    assert ok.info["bound_violations"] == 0
    assert np.all(ok.thickness[:-1] <= C * np.sqrt(2) + 1e-9)


def test_layers_of_a_tall_model_are_never_under_min_height():
    """550 mm tall: the bins are height / 400000 = 0.001375 mm wide, and min_height 0.01 mm is 7.27 of them;
    rounded to 7, every layer came out 0.009625 mm, under the clamp it promises."""
    from gpuslice.mesh.shapes import prism

    tri = prism([(0, 0), (1, 0), (0.2, 1)], 0.0, 550.0)
    tri[..., 0] += tri[..., 2] * 0.01  # leaning walls: |n_z| > 0, so the cusp bound wants thin layers
    tall = mesh_from_triangles(tri)
    sched = cusp_schedule(tall, max_cusp=0.00002, min_height=0.01, max_height=0.3)
    assert sched.thickness[:-1].min() >= 0.01 - 1e-12
    assert sched.info["bound_violations"] > 0  # the clamp is what set them


def test_no_last_layer_is_a_sliver_under_a_micrometre():
    """An audit found a cusp schedule at --min-height 0.001 ending with a 0.0006 mm layer (a 20 mm icosphere), and an
    roi schedule of the same sphere 20.0003 mm tall with a 0.0003 mm one, in resin archives that refuse layers under
    1 µm: such a sliver joins the layer below (at most 1 µm thicker), and the bound is still kept or the excess
    counted; a step asked for finer than that keeps its layers."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=4, radius=10.0)
    m = mesh_from_arrays(np.asarray(ico.vertices, np.float32), np.asarray(ico.faces))
    c = cusp_schedule(m, max_cusp=C, min_height=0.001, max_height=B)
    big = mesh_from_arrays(np.asarray(ico.vertices * 1.000015, np.float32), np.asarray(ico.faces))
    r = roi_schedule(big, (1.0, 0.5, 0.1))
    for mesh, sched in ((m, c), (big, r)):
        assert sched.thickness.min() >= 0.001 - 1e-12, (sched.info["mode"], sched.thickness[-3:])
        assert sched.top[-1] == pytest.approx(mesh.height, abs=1e-9)
    with np.errstate(divide="ignore"):
        assert _worst(m, c, lambda nz: C / nz) <= 1.0 + 1e-9 or c.info["bound_violations"] > 0
    fine = cusp_schedule(m, max_cusp=C, min_height=0.0002, max_height=B, resolution=0.0001)
    assert fine.thickness[:-1].min() >= 0.0002 - 1e-12 and fine.top[-1] == pytest.approx(m.height, abs=1e-9)


@pytest.mark.parametrize("kw", [{"max_cusp": 0}, {"min_height": 0}, {"min_height": 0.3, "max_height": 0.1},
                                {"smooth": -1}, {"mode": "nope"}])
def test_bad_parameters_raise(sphere, kw):
    with pytest.raises(ParameterError):
        cusp_schedule(sphere, **kw)


def test_slicer_takes_the_adaptive_schedule(sphere, backend):
    res = slice_mesh(sphere, backend=backend, adaptive="cusp", max_cusp=C, min_height=A, max_height=B)
    sched = cusp_schedule(sphere, max_cusp=C, min_height=A, max_height=B)
    np.testing.assert_array_equal(res.z, sched.z)
    np.testing.assert_array_equal(res.thickness, sched.thickness)
    assert res.meta["schedule_mode"] == "adaptive-cusp" and res.meta["adaptive"]["mode"] == "cusp"
    assert np.all(res.area > 0)
    assert res.volume == pytest.approx(4 / 3 * np.pi * 20**3, rel=0.01)


# ---- the roi ladder -------------------------------------------------------------------------------------------


def test_roi_ladder_on_a_sphere(sphere):
    sched = roi_schedule(sphere, (1.0, 0.5, 0.1))
    _check_tiling(sphere, sched, lo=0.1 - 1e-9, hi=1.0)
    assert set(np.round(sched.thickness[:-1], 9)) == {1.0, 0.5, 0.1}
    levels = sched.info["levels"]
    assert [lv["thickness_mm"] for lv in levels] == [1.0, 0.5]
    (a0, b0), (a1, b1) = levels[0]["windows"][0]["z_mm"], levels[1]["windows"][0]["z_mm"]
    assert a0 <= a1 < b1 <= b0  # the second window lies inside the first
    assert a0 < 20 < b0  # the busiest layers of a sphere are around its equator
    # inside each window the layers have that level's next thickness
    inner = (sched.z > a1) & (sched.z < b1)
    assert np.allclose(sched.thickness[inner], 0.1)
    outer = (sched.z < a0) | (sched.z > b0)
    assert np.allclose(sched.thickness[outer & (sched.top < sphere.height)], 1.0)
    # the window rule: every layer of the level-0 window has at least the threshold's points
    pts = np.asarray(levels[0]["points"])
    i0, i1 = levels[0]["windows"][0]["layers"]
    assert np.all(pts[i0 : i1 + 1] >= levels[0]["threshold_points"])
    assert levels[0]["threshold_points"] == pytest.approx(np.quantile(pts, 0.75))


def test_roi_absolute_threshold_and_all_windows(sphere):
    sched = roi_schedule(sphere, (1.0, 0.25), threshold=(10**9,))
    assert np.allclose(sched.thickness[:-1], 1.0)  # nothing reaches the threshold: no refinement
    assert sched.info["levels"][0]["windows"] == []
    many = roi_schedule(sphere, (1.0, 0.5), quantile=0.0, max_windows=0)
    assert np.allclose(many.thickness[:-1], 0.5)  # everything is of interest


@pytest.mark.parametrize("ladder", [(1.0, 0.3, 0.0999), (1.0, 0.5, 0.0999), (1.0, 0.3, 0.07), (1.0, 0.3), (0.7, 0.3)])
def test_roi_steps_that_do_not_divide_each_other(sphere, ladder):
    """A window is tiled with its step from its bottom; a remainder under half a step used to be a layer of its own
    inside the part (0.0015 mm at z 5.7 with 1, 0.3, 0.0999: a helper's audit): it is shared with the layer below."""
    sched = roi_schedule(sphere, ladder, quantile=0.5, max_windows=0)
    assert all(level["windows"] for level in sched.info["levels"])  # every level refined somewhere
    _check_tiling(sphere, sched, lo=ladder[-1] / 2 - 1e-9, hi=ladder[0] + 1e-9)  # no layer under half the finest


@pytest.mark.parametrize("ladder", [(0.1, 1.0), (1.0, -0.5), ()])
def test_roi_bad_ladder(sphere, ladder):
    with pytest.raises(ParameterError):
        roi_schedule(sphere, ladder)


# ---- real meshes (the numbers) ------------------------------------------------------------------------


def test_nefertiti_80mm_cusp_bound(shared_meshes, device):
    from gpuslice import load_mesh

    mesh = load_mesh(shared_meshes / "nefertiti.stl", fit=80, device=device)
    assert mesh.height == pytest.approx(80.0, rel=1e-6)  # the longest side is the height
    sched = cusp_schedule(mesh, max_cusp=C, min_height=A, max_height=B, device=device)
    assert _worst(mesh, sched, lambda nz: C / np.maximum(nz, 1e-300)) <= 1 + 1e-9
    n_uniform = len(uniform(mesh.height, 0.05))
    print(f"nefertiti 80 mm: cusp schedule {len(sched)} layers, uniform 0.05 mm {n_uniform}")
    assert len(sched) < n_uniform
    _check_tiling(mesh, sched)


def test_nefertiti_226mm_roi(shared_meshes, device):
    from gpuslice import load_mesh

    mesh = load_mesh(shared_meshes / "nefertiti.stl", fit=226, device=device)
    assert mesh.height == pytest.approx(226.0, rel=1e-6)
    sched = roi_schedule(mesh)
    assert len(set(np.round(sched.thickness[:-1], 9))) >= 2
    assert all(lv["windows"] for lv in sched.info["levels"])
    _check_tiling(mesh, sched, lo=0.1 - 1e-9, hi=1.0)


# ---- command line ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere_stl(tmp_path_factory):
    path = tmp_path_factory.mktemp("adaptive") / "sphere.stl"
    write_stl(icosphere(20.0), path)
    return path


@pytest.mark.parametrize("args", [["-t", "0.2"], ["--adaptive", "cusp"], ["--adaptive", "area"],
                                  ["--adaptive", "roi", "--roi-ladder", "1,0.25"]])
def test_cli_report_carries_the_schedule_and_cusp(sphere_stl, tmp_path, capsys, args):
    rep = tmp_path / "r.json"
    assert main(["slice", str(sphere_stl), *args, "--report", str(rep)]) == 0
    out = capsys.readouterr().out
    data = json.loads(rep.read_text())
    n = data["layers"]
    assert len(data["z"]) == len(data["thickness"]) == len(data["cusp_mm"]) == n
    assert data["max_cusp_mm"] == pytest.approx(max(data["cusp_mm"]))
    assert 0 < data["mean_cusp_mm"] <= data["max_cusp_mm"]
    if args[0] == "--adaptive" and args[1] == "cusp":
        assert data["max_cusp_mm"] <= C + 1e-6
    if args[0] == "-t":
        assert data["max_cusp_mm"] <= 0.2 and data["max_cusp_mm"] > 0.19
    if "roi" in args:
        assert "roi level 0: 1 mm" in out and "window layers" in out
        assert data["adaptive"]["levels"][0]["windows"]


@pytest.mark.parametrize("args", [["--adaptive", "cusp", "--min-height", "0"],
                                  ["--adaptive", "roi", "--roi-ladder", "1,abc"],
                                  ["--adaptive", "roi", "--roi-threshold", "5,6,7"],
                                  ["--adaptive", "bogus"]])
def test_cli_bad_adaptive_options(sphere_stl, capsys, args, tmp_path):
    out = tmp_path / "x.npz"
    assert main(["slice", str(sphere_stl), *args, "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gpuslice: error:")
    assert not out.exists()
