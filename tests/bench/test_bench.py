"""Schedule quality (gpuslice.bench.quality), `gpuslice bench` (gpuslice.bench.runner, cli.bench) and the plots
(gpuslice.bench.plots)."""

from __future__ import annotations

import csv
import io
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.bench.quality import cusp_heights, layer_geometries, mean_cusp, schedule_quality, volume_deviation
from gpuslice.bench.runner import parse_settings, run_bench
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh.shapes import box, icosphere, write_stl

R = 20.0


@pytest.fixture(scope="module")
def sphere():
    return mesh_from_triangles(icosphere(R))


@pytest.fixture(scope="module")
def sphere_ref(sphere):
    return slice_mesh(sphere, thickness=0.01, backend="numpy")


@pytest.fixture(scope="module")
def sphere_stl(tmp_path_factory):
    path = tmp_path_factory.mktemp("bench") / "sphere.stl"
    write_stl(icosphere(R), path)
    return path


# ---- quality --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("t", [0.1, 0.3])
def test_cusp_of_uniform_layers_on_a_sphere(sphere, t):
    res = slice_mesh(sphere, thickness=t, backend="numpy")
    c = cusp_heights(sphere, res)
    assert c.shape == (res.n_layers,)
    assert c.max() <= t + 1e-9 and c.max() > 0.99 * t  # the poles are nearly flat
    # on a sphere the area-weighted mean of |n_z| is 1/2, so the mean cusp is t/2
    assert mean_cusp(sphere, res) == pytest.approx(t / 2, rel=0.02)


def test_mean_cusp_in_chunks_and_on_the_device_is_the_whole_pass(sphere, monkeypatch):
    # the facets' float64 areas are made a chunk at a time (memory: a chunk's, not the model's), and the slopes on
    # the device when there is one: the report's mean must be the very float of one numpy pass over every facet
    import gpuslice.bench.quality as q

    res = slice_mesh(sphere, thickness=0.1, backend="numpy")
    monkeypatch.setattr(q, "AREA_CHUNK", 10**9)
    whole = mean_cusp(sphere, res)
    monkeypatch.setattr(q, "AREA_CHUNK", 7)  # (the icosphere has 5,120 facets: hundreds of chunks, a short last one)
    assert mean_cusp(sphere, res) == whole
    try:
        from gpuslice.device import get_device

        dev = get_device()
    except Exception as exc:  # noqa: BLE001 (no OpenCL here: the numpy pass above is all there is)
        pytest.skip(f"no OpenCL device: {exc}")
    assert mean_cusp(sphere, res, device=dev) == whole




def test_facet_areas_are_the_textbook_formula_bit_for_bit(sphere):
    # the areas are made from 1-D gathers and written-out cross products (2x faster on 1.6M facets): each must be
    # the very float of 0.5 * |(b - a) x (c - a)| in float64 with numpy's cross and norm, on any subset of facets
    from gpuslice.bench.quality import _facet_areas

    rng = np.random.default_rng(3)
    mesh = mesh_from_triangles(rng.normal(0.0, 20.0, (500, 3, 3)).astype(np.float32))
    for m in (sphere, mesh):
        which = np.flatnonzero(rng.random(m.n_faces) < 0.7)
        tri = m.vertices[m.faces[which]].astype(np.float64)
        want = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        assert np.array_equal(_facet_areas(m, which), want)
def test_volume_deviation_of_a_sphere_matches_the_staircase_formula(sphere, sphere_ref):
    # mid-plane sections of a sphere: per slab the XOR is |A'(z)|·|z - z_mid| integrated, t²/4·|A'|, in all
    # t/4 · 2πR² (A(z) rises from 0 to πR² and falls back)
    prev = 0.0
    for t in (0.05, 0.1, 0.3):
        res = slice_mesh(sphere, thickness=t, backend="numpy")
        vd = volume_deviation(res, sphere_ref)
        assert vd["volume_deviation_mm3"] == pytest.approx(t / 4 * 2 * np.pi * R**2, rel=0.1)
        assert vd["volume_deviation_mm3"] > prev
        prev = vd["volume_deviation_mm3"]
    same = volume_deviation(sphere_ref, sphere_ref)
    assert same["volume_deviation_mm3"] == pytest.approx(0.0, abs=1e-6)


def test_quality_of_explicit_planes_scores_their_own_slabs(sphere):
    """Explicit planes over a band of the sphere (z 5.25 .. 14.75, 0.5 mm) are the same layers as the uniform
    schedule's there: the same cusp heights (an audit found them scored as slabs stacked from the bed, [0, 10]);
    planes whose slabs neither stack nor tile (z 1, 2, 3 at 0.1 mm) get no figures, not wrong ones."""
    full = slice_mesh(sphere, thickness=0.5, backend="numpy")
    band = slice_mesh(sphere, z=full.z[10:30], layer_thickness=0.5, backend="numpy")
    assert band.bottom[0] == pytest.approx(5.0)
    np.testing.assert_allclose(cusp_heights(sphere, band), cusp_heights(sphere, full)[10:30], rtol=1e-12)
    assert mean_cusp(sphere, band) == pytest.approx(mean_cusp(sphere, full), rel=0.05)
    ref = slice_mesh(sphere, thickness=0.05, backend="numpy")
    vd = volume_deviation(band, ref)["volume_deviation_mm3"]
    outside = float(np.dot(ref.area, ref.thickness) - np.dot(ref.area[100:300], ref.thickness[100:300]))
    assert outside < vd < outside * 1.2  # the sphere outside the band, plus the band's staircase
    equator = slice_mesh(sphere, z=np.array([R]), layer_thickness=0.1, backend="numpy")
    assert cusp_heights(sphere, equator)[0] < 0.02  # |n_z| is small at the equator (was 0.0999: the pole's slab)
    with pytest.raises(ParameterError, match="do not stack"):
        cusp_heights(sphere, slice_mesh(sphere, z=np.array([1.0, 2.0, 3.0]), layer_thickness=0.1, backend="numpy"))


def test_volume_deviation_counts_missing_and_shifted_material():
    cube = mesh_from_triangles(box((0, 0, 0), (10, 10, 10)))
    ref = slice_mesh(cube, thickness=0.05, backend="numpy")
    exact = slice_mesh(cube, thickness=0.5, backend="numpy")  # tiles [0, 10] exactly: no deviation
    assert volume_deviation(exact, ref)["volume_deviation_mm3"] == pytest.approx(0.0, abs=1e-6)
    short = slice_mesh(cube, z=np.array([0.5, 1.5]), layer_thickness=1.0, backend="numpy")  # only [0, 2] covered
    vd = volume_deviation(short, ref)
    assert vd["volume_deviation_mm3"] == pytest.approx(800.0, rel=1e-6)
    assert vd["volume_deviation_pct"] == pytest.approx(80.0, rel=1e-6)


def test_layer_geometries_keep_holes():
    from gpuslice.mesh.shapes import torus

    res = slice_mesh(mesh_from_triangles(torus()), thickness=1.0, backend="numpy")
    g = layer_geometries(res)
    assert len(g) == res.n_layers
    np.testing.assert_allclose([x.area for x in g], res.area, rtol=1e-5)


def test_schedule_quality_keys(sphere, sphere_ref):
    res = slice_mesh(sphere, adaptive="cusp", backend="numpy")
    q = schedule_quality(sphere, res, sphere_ref)
    assert q["layers"] == res.n_layers
    assert q["max_cusp_mm"] <= 0.05 + 1e-6
    assert 0 < q["mean_cusp_mm"] < q["max_cusp_mm"]
    uni = schedule_quality(sphere, slice_mesh(sphere, thickness=0.05, backend="numpy"), sphere_ref)
    # the cusp schedule trades a little volume accuracy for about half the layers
    assert q["layers"] < 0.6 * uni["layers"]
    assert uni["volume_deviation_mm3"] < q["volume_deviation_mm3"] < 4 * uni["volume_deviation_mm3"]


def test_the_fine_reference_is_plain_whatever_the_params(sphere, sphere_ref):
    """The reference a quality figure is measured against is uniform, mid-slab and without a first layer of its own:
    params with ``first_layer`` 1.5 mm (or paper planes) gave it a 1.5 mm first layer (or paper planes), and
    another volume deviation."""
    from gpuslice import SliceParams

    res = slice_mesh(sphere, thickness=0.3, first_layer=1.5, backend="numpy")
    want = schedule_quality(sphere, res, sphere_ref)
    for params in (SliceParams(thickness=0.3, first_layer=1.5, backend="numpy"),
                   SliceParams(thickness=0.3, z_mode="paper", backend="numpy")):
        got = schedule_quality(sphere, res, ref_thickness=0.01, params=params)
        assert got["volume_deviation_mm3"] == pytest.approx(want["volume_deviation_mm3"], rel=1e-9)


def test_first_layer_and_paper_planes_are_refused_with_adaptive_layers():
    """They were ignored, silently (the report still listed first_layer 0.3)."""
    from gpuslice import SliceParams
    from gpuslice.errors import ParameterError

    with pytest.raises(ParameterError, match="first_layer applies to uniform layers") as info:
        SliceParams(adaptive="cusp", first_layer=0.3)
    assert info.value.params == ("first_layer",)
    with pytest.raises(ParameterError, match="z_mode 'paper' applies to uniform layers"):
        SliceParams(adaptive="roi", z_mode="paper")


# ---- bench ----------------------------------------------------------------------------------------------------


def test_parse_settings():
    s = parse_settings("0.1, 0.2", "roi,cusp")
    assert [x.label for x in s] == ["0.1 mm", "0.2 mm", "adaptive roi", "adaptive cusp"]
    for bad in (("0", None), ("x", None), (None, "nope"), (None, None)):
        with pytest.raises(ParameterError):
            parse_settings(*bad)


def test_run_bench_rows(sphere):
    calls = []
    res = run_bench(sphere, parse_settings("0.2,0.5", "cusp,roi"), repeat=2, ref_thickness=0.02,
                    progress=lambda d, a=1: calls.append(d))
    rows = {r["setting"]: r for r in res.rows}
    assert list(rows) == ["0.2 mm", "0.5 mm", "adaptive cusp", "adaptive roi"]
    for label, r in rows.items():
        assert r["layers"] == res.results[label].n_layers
        assert len(r["times_s"]) == 2 and r["total_s"] == pytest.approx(np.median(r["times_s"]))
        assert r["total_s"] >= r["crossings_s"] + r["chaining_s"] + r["nesting_s"]
        assert r["volume_deviation_pct"] > 0
    assert rows["0.2 mm"]["layers"] > rows["0.5 mm"]["layers"]
    assert rows["0.5 mm"]["volume_deviation_mm3"] > rows["0.2 mm"]["volume_deviation_mm3"]
    assert rows["adaptive cusp"]["max_cusp_mm"] <= 0.05 + 1e-6
    assert rows["adaptive roi"]["roi_windows"][0]["windows_mm"]
    assert res.context["reference_thickness_mm"] == 0.02
    assert calls.count("quality") == 4 and "warm-up" in calls


def test_cli_bench_table_json_csv(sphere_stl, capsys):
    args = ["bench", str(sphere_stl), "-t", "0.5,1", "--adaptive", "roi", "--repeat", "1", "--ref-thickness", "0.05"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "0.5 mm" in out and "adaptive roi" in out and "level 0 (1 mm) window" in out
    assert "note: the" not in out  # (0.05 mm: finer than every setting's layers)
    assert main([*args[:-1], "0.7"]) == 0  # a reference coarser than 0.5 mm layers (an audit: said nowhere)
    assert "note: the 0.7 mm reference is coarser than the thinnest layers of settings 0.5 mm, adaptive roi" in \
        capsys.readouterr().out
    assert main([*args, "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert [r["setting"] for r in data["rows"]] == ["0.5 mm", "1 mm", "adaptive roi"]
    assert data["load_s"] > 0 and data["facets"] == 5120
    assert main([*args[:-2], "--csv", "--no-quality"]) == 0  # (no --ref-thickness without the volume deviation)
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["setting"] for r in rows] == ["0.5 mm", "1 mm", "adaptive roi"]
    assert int(rows[0]["layers"]) == 80


@pytest.mark.parametrize("args", [["-t", "0"], ["--adaptive", "x"], ["--repeat", "0"], ["--json", "--csv"],
                                  ["--plots", "/nonexistent/dir"],
                                  # options no setting uses (an audit: accepted, then only recorded in the JSON)
                                  ["--max-cusp", "0.1"], ["--min-height", "0.1", "--adaptive", "roi"],
                                  ["--roi-windows", "2", "--adaptive", "cusp"],
                                  ["--no-quality", "--ref-thickness", "0.1"]])
def test_cli_bench_bad_options(sphere_stl, capsys, args):
    assert main(["bench", str(sphere_stl), "-t", "1", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gpuslice: error:")


# ---- plots ----------------------------------------------------------------------------------------------------


def _check_png(path):
    from PIL import Image

    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert 10_000 < len(data) < 300_000
    with Image.open(path) as im:
        w, h = im.size
        assert w >= 300 and h >= 200
        # not a blank canvas: several distinct colours
        assert len(im.convert("RGB").getcolors(maxcolors=1 << 20) or []) > 8


def _check_svg(path):
    data = path.read_bytes()
    assert 5_000 < len(data) < 300_000
    root = ET.fromstring(data)
    assert root.tag.endswith("svg")
    assert sum(1 for _ in root.iter()) > 50


def test_bench_plots(sphere_stl, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    pytest.importorskip("PIL")
    assert main(["bench", str(sphere_stl), "-t", "0.3,1", "--adaptive", "roi,cusp", "--repeat", "1",
                 "--no-quality", "--plots", str(tmp_path)]) == 0
    names = sorted(p.name for p in tmp_path.iterdir())
    for stem in ("sphere_points", "sphere_schedule", "sphere_stack", "sphere_layers", "sphere_roi_levels"):
        assert f"{stem}.png" in names and f"{stem}.svg" in names
        _check_png(tmp_path / f"{stem}.png")
        _check_svg(tmp_path / f"{stem}.svg")
    assert not [n for n in names if n.startswith(".")]  # no temporaries left


def test_options_of_the_modes_benched_are_taken(sphere_stl, capsys, tmp_path):
    """The same options with their modes benched run (the refusal is only for options no setting uses)."""
    args = ["bench", str(sphere_stl), "-t", "1", "--repeat", "1", "--no-quality", "--json"]
    assert main([*args, "--adaptive", "area", "--min-height", "0.2", "--max-height", "0.5"]) == 0
    row = json.loads(capsys.readouterr().out)["rows"][1]
    assert row["setting"] == "adaptive area" and row["thickness_max_mm"] <= 0.5 + 1e-9 and row["layers"] > 0
    assert main(["plot", str(sphere_stl), "-t", "1", "--roi-windows", "2", "-o", str(tmp_path / "p")]) == 2
    assert "--roi-windows shapes roi layers" in capsys.readouterr().err and not (tmp_path / "p").exists()


def test_plot_command(sphere_stl, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    assert main(["plot", str(sphere_stl), "-t", "0.5", "--adaptive", "roi", "-o", str(tmp_path),
                 "--layers", "3,20"]) == 0
    out = capsys.readouterr().out
    assert "roi level 0 (1 mm): window z" in out
    _check_png(tmp_path / "sphere_layers_chosen.png")
    assert main(["plot", str(sphere_stl), "-t", "0.5", "-o", str(tmp_path), "--layers", "999"]) == 2
    # a new plot folder is created (as mkdir), but not a missing parent, nor over a file
    assert main(["plot", str(sphere_stl), "-t", "0.5", "-o", str(tmp_path / "new")]) == 0
    assert (tmp_path / "new" / "sphere_points.png").is_file()
    assert main(["plot", str(sphere_stl), "-t", "0.5", "-o", str(tmp_path / "missing" / "deeper")]) == 2
    assert main(["plot", str(sphere_stl), "-t", "0.5", "-o", str(tmp_path / "sphere_points.png")]) == 2


def test_plot_of_one_layer_warns_of_nothing(tmp_path, capsys):
    """A one-layer result's 3-D stack had equal z limits: matplotlib's "Attempting to set identical low and high
    zlims" UserWarning on stderr (a helper's sweep with warnings as errors)."""
    pytest.importorskip("matplotlib")
    import warnings

    stl = tmp_path / "plate.stl"
    write_stl(box((0, 0, 0), (20, 10, 3)), stl)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["plot", str(stl), "-t", "4", "-o", str(tmp_path / "p")]) == 0
    _check_png(tmp_path / "p" / "plate_stack.png")


def test_a_plot_set_that_fails_halfway_leaves_nothing(sphere_stl, tmp_path, monkeypatch, capsys):
    """A full disk at the third plot left the first two (and the folder plot made): the set is written together,
    or none of it (an audit of the outputs)."""
    pytest.importorskip("matplotlib")
    import errno

    import gpuslice.bench.plots as plots

    real, count = plots._save, []

    def save(fig, stem):
        count.append(stem)
        if len(count) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(stem) + ".png")
        return real(fig, stem)

    monkeypatch.setattr(plots, "_save", save)
    assert main(["plot", str(sphere_stl), "-t", "0.5", "-o", str(tmp_path / "new")]) == 2
    assert "No space left on device" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()
    old = tmp_path / "old"
    old.mkdir()
    (old / "keep.txt").write_text("x")
    count.clear()
    assert main(["plot", str(sphere_stl), "-t", "0.5", "-o", str(old)]) == 2
    assert sorted(p.name for p in old.iterdir()) == ["keep.txt"]


def test_plot_svg_is_reproducible(sphere_stl, tmp_path):
    """The same plot twice gives the same SVG bytes (matplotlib's element ids are salted, not random)."""
    pytest.importorskip("matplotlib")
    for d in ("a", "b"):
        assert main(["plot", str(sphere_stl), "-t", "0.5", "-o", str(tmp_path / d), "--layers", "3"]) == 0
    svg = sorted(p.name for p in (tmp_path / "a").glob("*.svg"))
    assert svg and all((tmp_path / "a" / n).read_bytes() == (tmp_path / "b" / n).read_bytes() for n in svg)
