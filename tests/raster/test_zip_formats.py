"""The zip-of-layers resin outputs (issue 19): Prusa SL1S (``.sl1s``), PrusaSlicer's vector SL1_SVG (``.sl1_svg``)
and NanoDLP plates (``.nanodlp`` / ``.zip``). Each archive is read back by ``zip_readers`` (independent of the
writers): header fields as set, layer count = schedule, every layer against ``gpuslice.raster.masks`` for the same
display (PNG: exact; SVG: its polygons against the result's under PrusaSlicer's own placement rules, and
rasterised)."""

from __future__ import annotations

import datetime as dt
import subprocess
import sys
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gpuslice import load_mesh, mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec, iter_tiles, masks
from gpuslice.raster.outputs import RESIN_FORMATS, ResinTarget, resin_format_for
from gpuslice.raster.settings import PrintSettings
from gpuslice.raster.spec import ResinOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import zip_readers as zr  # noqa: E402

pytest.importorskip("PIL.Image")

SMALL = RasterSpec(resolution=(900, 900), pixel=0.05)  # 45 x 45 mm
#: PrusaSlicer's SL1S display (PrusaResearchSLA.ini): PNGs 1620 x 2560
SL1S = RasterSpec(resolution=(2560, 1620), pixel=0.05, portrait=True, mirror_x=True)
WHEN = dt.datetime(2023, 11, 14, 22, 13, 20)
#: the shared settings' lifts, rests and PWM back at their defaults, for the SL1 family
SL1_UNSTORED = {k: getattr(PrintSettings(), k) for k in ("lift_height", "wait_after_lift", "wait_before_cure",
                                                          "light_pwm", "bottom_lift_height", "bottom_wait_before_cure",
                                                          "bottom_wait_after_cure", "bottom_wait_after_lift")}
SETTINGS = PrintSettings(bottom_layers=3, bottom_exposure=22.5, exposure=2.5, transition_layers=4, lift_height=6.0,
                         wait_after_lift=1.5, wait_before_cure=0.5, light_pwm=204, bottom_lift_height=7.0,
                         bottom_wait_before_cure=2.0, bottom_wait_after_cure=1.0, bottom_wait_after_lift=3.0)


@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=1.0, backend="numpy")


@pytest.fixture(scope="module")
def nested():
    """A box with a cavity and a floating core: mid layers hold a square with a square hole and an island in it."""
    return slice_mesh(mesh_from_triangles(shapes.hollow_box(20, 10, core=6)), thickness=2.0, backend="numpy")


def _spread(path, fit: float, n: int = 24):
    """The model at ``path`` fitted to ``fit`` mm, ``n`` layers of 0.05 mm spread over its height."""
    mesh = load_mesh(path, fit=fit)
    top = float(mesh.vertices[:, 2].max())
    z = (np.floor(np.linspace(0.0, top - 0.05, n) / 0.05) + 0.5) * 0.05
    return slice_mesh(mesh, z=z, layer_thickness=0.05, backend="numpy")


@pytest.fixture(scope="module")
def benchy(shared_meshes):
    """3DBenchy at 60 mm, 24 layers of 0.05 mm spread over its height (a subset of its 960)."""
    return _spread(shared_meshes / "benchy.stl", 60)


@pytest.fixture(scope="module")
def nefertiti(shared_meshes):
    """Nefertiti at 80 mm, 24 layers of 0.05 mm spread over its height (a subset of its 1600)."""
    return _spread(shared_meshes / "nefertiti.stl", 80)


def _target(tmp_path, name, result, spec, printer=None, **kw):
    opts = ResinOptions(printer=printer, workers=2)
    # the SL1 family holds one bottom layer (expTimeFirst) and no lift, rest or light setting (it refuses them): the
    # others take the shared settings' three bottom layers, lifts, rests and PWM
    settings = replace(SETTINGS, bottom_layers=1, **SL1_UNSTORED) if ".sl1" in name else SETTINGS
    return ResinTarget(tmp_path / name, spec, opts, result, "part", now=WHEN, settings=settings, **kw)


def _write(fmt, target, backend="numpy", device=None):
    if backend == "opencl":
        from gpuslice.raster.layers import iter_run_layers

        layers = iter_run_layers(target.result, target.spec, device=device)
    else:
        layers = iter_tiles(target.result, target.spec, backend="numpy")
    return RESIN_FORMATS[fmt].load()(layers, target)


def test_registry_names_and_suffixes():
    assert resin_format_for("a.sl1s").name == "sl1s"
    assert resin_format_for("a.SL1_SVG").name == "sl1svg"
    assert resin_format_for("a.nanodlp").name == "nanodlp" and RESIN_FORMATS["nanodlp"].suffix == ".nanodlp"


# ---- SL1S ----------------------------------------------------------------------------------------------------------
def _check_png_layers(archive_read, names, result, spec, backend="numpy", device=None):
    ref = masks(result, spec, backend=backend, **({"device": device} if device is not None else {}))
    assert len(names) == result.n_layers == ref.shape[0]
    for k, name in enumerate(names):
        got = zr.png_layer(archive_read(name))
        assert got.shape == spec.shape
        assert np.array_equal(got, ref[k]), (name, int(np.count_nonzero(got != ref[k])))
    return ref


def test_sl1s_reads_back(tmp_path, torus):
    t = _target(tmp_path, "p.sl1s", torus, SL1S, printer="prusa-sl1s")
    stats = _write("sl1s", t)
    a = zr.read_sl1(t.path)
    c, ini = a.config, a.prusaslicer
    assert (c["printerModel"], c["printerVariant"], c["printerProfile"]) == ("SL1S", "default",
                                                                            "Original Prusa SL1S Speed")
    assert (float(c["expTime"]), float(c["expTimeFirst"]), int(c["numFade"])) == (2.5, 22.5, 4)
    assert int(c["numFast"]) == torus.n_layers == stats["layers"] and float(c["layerHeight"]) == 1.0
    assert c["jobDir"] == "part" and c["fileCreationTimestamp"] == "2023-11-14 at 22:13:20 UTC"
    # PrusaSlicer's SL1S display keys, as its own SL1S archive carries them
    assert (ini["display_pixels_x"], ini["display_pixels_y"], ini["display_width"], ini["display_height"]) == (
        "2560", "1620", "128", "81")
    assert (ini["display_orientation"], ini["display_mirror_x"], ini["display_mirror_y"]) == ("portrait", "1", "0")
    assert (ini["printer_model"], ini["printer_variant"], ini["fast_tilt_time"]) == ("SL1S", "default", "2.5")
    assert set(a.thumbnails.values()) == {(400, 400), (800, 480)}
    ref = _check_png_layers(a.read, a.layers, torus, SL1S)
    assert ref[5].shape == (2560, 1620)  # rows x cols: the SL1S firmware's 1620 x 2560 buffer
    # PrusaSlicer's SL1 estimate with the SL1S's 2.5 s tilt: 3 layers at expTimeFirst, then numFade + 1 layers
    # stepping down by (22.5 - 2.5) / 5 = 4 s to expTime (18.5, 14.5, 10.5, 6.5, 2.5), the other 2 at expTime
    assert float(c["printTime"]) == pytest.approx(3 * 22.5 + (18.5 + 14.5 + 10.5 + 6.5 + 2.5) + 2 * 2.5 + 10 * 2.5)
    with zipfile.ZipFile(t.path) as z:
        assert {i.date_time for i in z.infolist()} == {WHEN.timetuple()[:6]}


def test_sl1s_default_model_and_refusals(tmp_path, torus):
    t = _target(tmp_path, "q.sl1s", torus, SL1S)  # no preset: still an SL1S archive
    _write("sl1s", t)
    assert zr.read_sl1(t.path).config["printerModel"] == "SL1S"
    with pytest.raises(ParameterError, match="1620x2560"):
        _write("sl1s", _target(tmp_path, "r.sl1s", torus, SMALL))
    with pytest.raises(ParameterError, match="1620x2560"):
        _write("sl1s", _target(tmp_path, "r.sl1s", torus, replace(SL1S, pixel=0.04725)))
    uneven = replace(torus, thickness=np.where(np.arange(torus.n_layers) < 5, 1.0, 0.5))
    with pytest.raises(ParameterError, match="one layer height"):
        _write("sl1s", _target(tmp_path, "r.sl1s", uneven, SL1S))
    assert not (tmp_path / "r.sl1s").exists()
    first = replace(torus, thickness=np.where(np.arange(torus.n_layers) == 0, 0.5, 1.0))
    _write("sl1s", _target(tmp_path, "s.sl1s", first, SL1S))  # only the first layer differs: allowed
    assert zr.read_sl1(tmp_path / "s.sl1s").prusaslicer["initial_layer_height"] == "0.5"


def test_sl1s_against_prusaslicer(tmp_path, device, torus):
    """PrusaSlicer's own SL1S archive (its SL1S printer keys and display, torus at 0.5 mm) read by the same reader,
    layer for layer against ours."""
    import peers

    if peers.find_peer("prusa-slicer") is None:
        pytest.skip("prusa-slicer not installed (../shared/peers/setup-peers.sh)")
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 96, 48), stl)
    ini = tmp_path / "sl1s.ini"
    ini.write_text("printer_model = SL1S\nprinter_variant = default\nprinter_settings_id = Original Prusa SL1S "
                   "SPEED\nfast_tilt_time = 2.5\nslow_tilt_time = 5\n")
    theirs, ours = tmp_path / "prusa.sl1s", tmp_path / "ours.sl1s"
    cmd = [peers.find_peer("prusa-slicer"), "--export-sla", "--printer-technology", "SLA", "--load", str(ini),
           "--layer-height", "0.5", "--initial-layer-height", "0.5", "--no-supports-enable", "--no-pad-enable",
           "--display-width", "128", "--display-height", "81", "--display-pixels-x", "2560", "--display-pixels-y",
           "1620", "--display-orientation", "portrait", "--display-mirror-x", "--no-display-mirror-y",
           "--bed-shape", "0x0,128x0,128x81,0x81", "--center", "64,40.5", "--slice-closing-radius", "0",
           "--gamma-correction", "1", "--dont-arrange", str(stl), "-o", str(theirs)]
    subprocess.run(cmd, check=True, capture_output=True)
    assert main(["raster", str(stl), "-t", "0.5", "--printer", "prusa-sl1s", "-o", str(ours), "-q",
                 "--no-progress"]) == 0
    a, b = zr.read_sl1(theirs), zr.read_sl1(ours)
    for key in ("printerModel", "printerVariant"):  # printerProfile: the preset's name, free text
        assert b.config[key] == a.config[key], key
    for key in ("display_pixels_x", "display_pixels_y", "display_width", "display_height", "display_orientation",
                "display_mirror_x", "display_mirror_y", "printer_model", "printer_variant", "fast_tilt_time"):
        assert b.prusaslicer[key] == a.prusaslicer[key], key
    assert len(a.layers) == len(b.layers) == 20
    for k in range(0, 20, 3):
        ma, mb = zr.png_layer(a.read(a.layers[k])) >= 128, zr.png_layer(b.read(b.layers[k])) >= 128
        assert ma.shape == mb.shape == (2560, 1620)
        iou = np.count_nonzero(ma & mb) / max(np.count_nonzero(ma | mb), 1)
        assert iou >= 0.99, (k, iou)


# ---- SL1_SVG -------------------------------------------------------------------------------------------------------
def _round_away(x: np.ndarray) -> np.ndarray:
    return (np.sign(x) * np.floor(np.abs(x) + 0.5)).astype(np.int64)


def _expected_polygons(result, spec, layer: int, precision: float = 0.001) -> list[tuple]:
    """The layer's polygons as PrusaSlicer's SVG raster would write them, derived here from its rules (SL1_SVG.cpp,
    RasterBase::Trafo), not from the writer: bed = model + (bed centre - bbox centre); portrait swaps X/Y and the
    display's sides; the trafo mirrors x when (portrait xor display_mirror_x) and y unless display_mirror_y; units of
    ``precision`` (res = round(side / precision), scale res / side), rounded half away from zero; points that round
    onto their predecessor dropped, loops under 3 points dropped."""
    pts_all = result.points.astype(np.float64)
    lo, hi = pts_all.min(axis=0), pts_all.max(axis=0)
    w, h = spec.nx * spec.px, spec.ny * spec.py
    d = np.array([w / 2, h / 2]) - (lo + hi) / 2
    if spec.portrait:
        w, h = h, w
    res = np.floor(np.array([w, h]) / precision + 0.5)
    polys = []
    view = result.layer(layer)
    for outer, holes in view.polygons():
        rings = []
        for ring in [outer, *holes]:
            p = ring.astype(np.float64) + d
            if spec.portrait:
                p = p[:, ::-1]
            if spec.portrait != spec.mirror_x:
                p[:, 0] = w - p[:, 0]
            if not spec.mirror_y:
                p[:, 1] = h - p[:, 1]
            q = _round_away(p * res / np.array([w, h]))
            q = q[np.r_[True, (q[1:] != q[:-1]).any(axis=1)]]
            rings.append(q)
        if len(rings[0]) < 3:
            continue
        polys.append(tuple(r.tobytes() for r in [rings[0], *[r for r in rings[1:] if len(r) >= 3]]))
    return polys


@pytest.mark.parametrize("spec", [SMALL, SL1S, replace(SMALL, mirror_y=True, portrait=True, resolution=(900, 800))],
                         ids=["landscape", "sl1s", "portrait-mirror-y"])
def test_sl1svg_polygons_and_masks(tmp_path, nested, spec):
    t = _target(tmp_path, "p.sl1_svg", nested, spec)
    _write("sl1svg", t)
    a = zr.read_sl1(t.path, ".svg")
    assert len(a.layers) == nested.n_layers and a.layers[0] == "part00000.svg"
    assert a.prusaslicer["sla_archive_format"] == "SL1SVG" and float(a.prusaslicer["sla_output_precision"]) == 0.001
    assert int(a.config["numFast"]) == nested.n_layers and float(a.config["expTime"]) == 2.5
    cols, rows = spec.png_size
    ref = masks(nested, spec, backend="numpy")
    for k, name in enumerate(a.layers):
        lay = zr.parse_svg_layer(a.read(name).decode("utf-8"))
        w_mm, h_mm = (spec.ny * spec.py, spec.nx * spec.px) if spec.portrait else (spec.nx * spec.px,
                                                                                   spec.ny * spec.py)
        assert (lay.width_mm, lay.height_mm) == pytest.approx((w_mm, h_mm))
        assert lay.viewbox == (round(w_mm * 1000), round(h_mm * 1000)) and "nonzero" in lay.style
        got = sorted(tuple(r.tobytes() for r in path) for path in lay.paths)
        assert got == sorted(_expected_polygons(nested, spec, k)), name
        # per path: holes wind against the outer loop (nonzero keeps them holes); larger polygons first
        areas = [zr.ring_area2(p[0]) for p in lay.paths]
        for p, a0 in zip(lay.paths, areas, strict=True):
            assert all(zr.ring_area2(r) * a0 < 0 for r in p[1:])
        assert all(abs(x) >= abs(y) for x, y in zip(areas, areas[1:], strict=False))
        grey = zr.rasterise_rings([r for p in lay.paths for r in p], (cols / lay.viewbox[0], rows / lay.viewbox[1]),
                                  (rows, cols))
        diff = np.abs(grey.astype(int) - ref[k])
        assert diff.max() <= 6, (name, int(diff.max()))  # 1 µm units: coverage within 0.02 of a pixel
    mid = zr.parse_svg_layer(a.read(a.layers[nested.n_layers // 2]).decode())
    assert [len(p) for p in mid.paths] == [2, 1]  # the box with its cavity, then the core inside the cavity


def test_sl1svg_benchy(tmp_path, benchy):
    t = _target(tmp_path, "b.sl1_svg", benchy, SL1S)
    _write("sl1svg", t)
    a = zr.read_sl1(t.path, ".svg")
    assert len(a.layers) == 24
    ref = masks(benchy, SL1S, backend="numpy", layers=range(0, 24, 4))
    for j, k in enumerate(range(0, 24, 4)):
        lay = zr.parse_svg_layer(a.read(a.layers[k]).decode())
        assert sorted(tuple(r.tobytes() for r in p) for p in lay.paths) == sorted(_expected_polygons(benchy, SL1S,
                                                                                                      k))
        grey = zr.rasterise_rings([r for p in lay.paths for r in p], (1620 / lay.viewbox[0], 2560 / lay.viewbox[1]),
                                  (2560, 1620))
        assert np.abs(grey.astype(int) - ref[j]).max() <= 6


# ---- NanoDLP -------------------------------------------------------------------------------------------------------
def _check_nanodlp(path, result, spec, settings, backend="numpy", device=None):
    p = zr.read_nanodlp(path)
    m = p.manifests
    for name in ("meta.json", "plate.json", "profile.json", "options.json", "slicer.json", "info.json"):
        assert name in m, name
    assert "3d.png" in p.names and m["options.json"] == m["slicer.json"]
    assert m["meta.json"]["Profile"] is False and m["meta.json"]["Program"] == "gpuslice"
    n = result.n_layers
    assert len(p.layers) == n == m["plate.json"]["LayersCount"] == m["options.json"]["LayerCount"] == len(
        m["info.json"])
    prof, opt, plate = m["profile.json"], m["options.json"], m["plate.json"]
    th = float(np.median(result.thickness))
    assert (prof["CureTime"], prof["SupportCureTime"], prof["SupportLayerNumber"], prof["TransitionalLayer"]) == (
        settings.exposure, settings.bottom_exposure, settings.bottom_layers, settings.transition_layers)
    assert prof["Depth"] == pytest.approx(th * 1000) and opt["Thickness"] == pytest.approx(th * 1000)
    assert (prof["WaitHeight"], prof["TopWait"], prof["WaitBeforePrint"]) == (
        settings.lift_height + settings.lift_height2, settings.wait_after_lift, settings.wait_before_cure)
    bot = settings.group(True)
    assert (prof["SupportWaitHeight"], prof["SupportTopWait"], prof["SupportWaitBeforePrint"],
            prof["SupportWaitAfterPrint"], prof["WaitAfterPrint"]) == (
        bot["lift_height"] + bot["lift_height2"], settings.group(True)["wait_after_lift"],
        settings.group(True)["wait_before_cure"], settings.group(True)["wait_after_cure"], settings.wait_after_cure)
    assert float(prof["CustomValues"]["UvPwmValue"]) == pytest.approx(settings.light_pwm / 255, abs=0.005)
    cols, rows = spec.png_size
    assert (opt["PWidth"], opt["PHeight"]) == (cols, rows)
    assert plate["TotalSolidArea"] == pytest.approx(float(np.dot(result.area, result.thickness)) / 1000, rel=1e-3)
    ref = _check_png_layers(p.read, p.layers, result, spec, backend, device)
    for k, info in enumerate(m["info.json"]):
        assert info["TotalSolidArea"] == pytest.approx(result.area[k], abs=1e-3)
        rr, cc = np.nonzero(ref[k])
        box = (int(cc.min()), int(rr.min()), int(cc.max()), int(rr.max())) if rr.size else (0, 0, 0, 0)
        assert (info["MinX"], info["MinY"], info["MaxX"], info["MaxY"]) == box, k
    return p


def test_nanodlp_reads_back(tmp_path, nested):
    t = _target(tmp_path, "p.nanodlp", nested, SMALL, printer=None)
    _write("nanodlp", t)
    p = _check_nanodlp(t.path, nested, SMALL, SETTINGS)
    info = p.manifests["info.json"]
    mid = info[nested.n_layers // 2]  # a 20 mm square with a 10 mm hole, and the 6 mm core in it
    assert mid["AreaCount"] == 2 and mid["LargestArea"] == pytest.approx(300, abs=0.01)
    assert mid["SmallestArea"] == pytest.approx(36, abs=0.01)
    plate = p.manifests["plate.json"]
    assert plate["CreatedDate"] == int(WHEN.replace(tzinfo=dt.timezone.utc).timestamp())
    assert (plate["XMax"] - plate["XMin"]) == pytest.approx(20, abs=1e-3) and plate["ZMax"] == pytest.approx(20)
    # the same bytes again (a fixed date); NanoDLP also takes these bytes named .zip
    t2 = replace(t, path=tmp_path / "p2.zip")
    _write("nanodlp", t2)
    assert t2.path.read_bytes() == t.path.read_bytes()


def test_nanodlp_lift_is_the_total_of_both_stages(tmp_path, nested):
    """NanoDLP's profile has one lift: a two-stage lift (3.1 mm, then 4.2 mm) is written as its 7.3 mm total, as CTB v3
    and Photon Workshop fold it (only the first stage was written, a lift 4.2 mm short)."""
    two = replace(SETTINGS, lift_height=3.1, lift_height2=4.2, lift_speed2=100.0, bottom_lift_height=5.0,
                  bottom_lift_height2=2.5, bottom_lift_speed2=80.0)
    t = replace(_target(tmp_path, "l.nanodlp", nested, SMALL, printer=None), settings=two)
    _write("nanodlp", t)
    prof = zr.read_nanodlp(t.path).manifests["profile.json"]
    assert prof["WaitHeight"] == pytest.approx(7.3) and prof["SupportWaitHeight"] == pytest.approx(7.5)


def test_nanodlp_benchy_runs(tmp_path, device, benchy):
    t = _target(tmp_path, "b.nanodlp", benchy, replace(SMALL, resolution=(1400, 800)))
    _write("nanodlp", t, backend="opencl", device=device)
    _check_nanodlp(t.path, benchy, t.spec, SETTINGS, backend="opencl", device=device)


@pytest.mark.parametrize("fmt", ["sl1", "nanodlp"])
@pytest.mark.parametrize("model", ["benchy", "nefertiti"])
def test_png_archives_on_the_12k_non_square_preset(tmp_path, device, request, fmt, model):
    """SL1 and NanoDLP at the Saturn 3 Ultra's 11520x5120 display of 0.019 x 0.024 mm pixels (mirrored in x):
    every written layer decodes to masks() exactly (24 layers spread over the model, 0.05 mm)."""
    from gpuslice.raster import with_printer

    res = request.getfixturevalue(model)
    spec = replace(with_printer("elegoo-saturn-3-ultra"), mirror_x=True)
    assert spec.px != spec.py and spec.shape == (5120, 11520)
    t = _target(tmp_path, f"m.{fmt}", res, spec)
    _write(fmt, t, backend="opencl", device=device)
    a = zr.read_sl1(t.path) if fmt == "sl1" else zr.read_nanodlp(t.path)
    assert len(a.layers) == res.n_layers == 24
    lit = 0
    for k, name in enumerate(a.layers):
        got = zr.png_layer(a.read(name))
        want = masks(res, spec, layers=[k], device=device)[0]
        assert got.shape == want.shape and np.array_equal(got, want), (k, int(np.count_nonzero(got != want)))
        lit += int(np.count_nonzero(want))
    assert lit > 1_000_000


def test_cli_sl1svg_prints_its_summary(tmp_path, capsys):
    """`raster -o x.sl1_svg` without -q: the summary counts its SVG layers (it ended in an internal error, KeyError
    'png_bytes', after writing the file)."""
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    assert main(["raster", str(stl), "-t", "1", "--no-progress", "-o", str(tmp_path / "x.sl1_svg")]) == 0
    out = capsys.readouterr().out
    assert "MB of layer images" in out and "wrote" in out and (tmp_path / "x.sl1_svg").is_file()


def test_sl1svg_refuses_z_samples(tmp_path, capsys):
    """Anti-aliasing in Z cannot reach an SVG of contours (it only changed the thumbnails): refused, nothing written."""
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    out = tmp_path / "x.sl1_svg"
    assert main(["raster", str(stl), "-t", "1", "--z-samples", "2", "--no-progress", "-o", str(out)]) == 2
    assert "x.sl1_svg: an SL1_SVG archive stores each layer's contours" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.stl"]


@pytest.mark.parametrize("flags, named", [
    (["--lift-speed", "30"], "--lift-speed 30"),
    (["--bottom-retract-speed", "90", "--bottom-light-pwm", "200"],
     "--bottom-retract-speed 90.0, --bottom-light-pwm 200"),
    (["--retract-height2", "1", "--retract-speed2", "40"], "--retract-height2 1"),
], ids=["lift-speed", "bottom", "retract-stage"])
def test_nanodlp_refuses_settings_it_cannot_store(tmp_path, capsys, flags, named):
    """A NanoDLP profile has lift heights and waits but no speeds and one light intensity: what it cannot store is
    refused before any work (it was dropped without a word), as SL1 does; the heights and waits it stores pass."""
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    out = tmp_path / "x.nanodlp"
    assert main(["raster", str(stl), "-t", "1", "--no-progress", "-q", "-o", str(out), *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"gpuslice: error: {out}: a NanoDLP plate stores lift heights") and named in err, err
    assert "\n" not in err and sorted(p.name for p in tmp_path.iterdir()) == ["cube.stl"]
    assert main(["raster", str(stl), "-t", "1", "--no-progress", "-q", "-o", str(out), "--lift-height", "3",
                 "--wait-after-lift", "2", "--light-pwm", "200"]) == 0
    assert zr.read_nanodlp(out).manifests["profile.json"]["WaitHeight"] == pytest.approx(3.0)


def test_nanodlp_refuses_adaptive_layers(tmp_path, torus):
    uneven = replace(torus, thickness=np.linspace(0.5, 1.5, torus.n_layers))
    with pytest.raises(ParameterError, match="one layer height"):
        _write("nanodlp", _target(tmp_path, "u.nanodlp", uneven, SMALL))
    assert not (tmp_path / "u.nanodlp").exists()


def test_sl1_refuses_adaptive_layers_and_names_the_preset_model(tmp_path, torus):
    """SL1 holds one layer height: adaptive layers are refused (no file), not written with the median height; with a
    Prusa preset the archive names the printer model the firmware checks."""
    uneven = replace(torus, thickness=np.linspace(0.5, 1.5, torus.n_layers))
    with pytest.raises(ParameterError, match="one layer height"):
        _write("sl1", _target(tmp_path, "u.sl1", uneven, SMALL))
    assert not (tmp_path / "u.sl1").exists()
    for fmt, name in (("sl1", "b.sl1"), ("sl1svg", "b.sl1_svg")):  # bottom layers it cannot hold: refused, not dropped
        t = replace(_target(tmp_path, name, torus, SMALL), settings=SETTINGS)
        with pytest.raises(ParameterError, match="--bottom-layers 3"):
            _write(fmt, t)
        assert not (tmp_path / name).exists()
    from gpuslice.raster.printers import find_printer
    from gpuslice.raster.spec import with_printer

    spec = with_printer("prusa-sl1")
    _write("sl1", _target(tmp_path, "p.sl1", torus, spec, printer="prusa-sl1"))
    with zipfile.ZipFile(tmp_path / "p.sl1") as z:
        config = dict(line.split(" = ", 1) for line in z.read("config.ini").decode().splitlines())
    assert config["printerModel"] == find_printer("prusa-sl1").machine == "SL1"
    assert config["printerVariant"] == "default"


# ---- command line --------------------------------------------------------------------------------------------------
def test_cli_writes_each_format_reproducibly(tmp_path, device, monkeypatch, capsys):
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 96, 48), stl)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    base = ["raster", str(stl), "-t", "0.5", "-q", "--no-progress"]
    small = ["--resolution", "900x900"]
    cases = [("a.sl1s", ["--printer", "prusa-sl1s"]), ("a.sl1_svg", small), ("a.nanodlp", small)]
    for name, extra in cases:
        digests = []
        for k in range(2):
            out = tmp_path / f"{k}{name}"
            assert main([*base, *extra, "-o", str(out)]) == 0, capsys.readouterr().err
            digests.append(out.read_bytes())
        assert digests[0] == digests[1], name
    assert zr.read_sl1(tmp_path / "0a.sl1s").config["printerModel"] == "SL1S"
    assert len(zr.read_sl1(tmp_path / "0a.sl1_svg", ".svg").layers) == 20
    assert len(zr.read_nanodlp(tmp_path / "0a.nanodlp").layers) == 20
    # an SL1S archive on another display is refused, one line, no file
    assert main([*base, *small, "-o", str(tmp_path / "bad.sl1s")]) == 2
    err = capsys.readouterr().err.strip()
    assert "1620x2560" in err and len(err.splitlines()) == 1 and not (tmp_path / "bad.sl1s").exists()


def test_thumbnails_keep_the_parts_shape_on_non_square_pixels():
    """A 10 x 10 mm square on 0.019 x 0.024 mm pixels (526 x 417 pixels) is drawn square in every archive's previews
    (the SL1 family, CTB, GOO and NanoDLP share this top view); on square pixels the map is not resampled."""
    import io

    from PIL import Image

    from gpuslice.raster.coverage import Tile
    from gpuslice.raster.sl1 import _Thumb

    for spec, (h, w) in ((RasterSpec(resolution=(1000, 800), pixel=0.019, pixel_y=0.024), (417, 526)),
                         (RasterSpec(resolution=(1000, 800), pixel=0.02), (500, 500))):
        thumb = _Thumb(spec, 2, step=1)
        thumb.add(Tile(1, 100, 100, np.full((h, w), 255, np.uint8)))
        img = np.asarray(Image.open(io.BytesIO(thumb.png((400, 400)))).convert("RGB")).astype(int)
        part = np.abs(img - np.array([40, 40, 40])).sum(axis=2) > 30
        ys, xs = np.nonzero(part)
        ratio = (ys.max() - ys.min() + 1) / (xs.max() - xs.min() + 1)
        assert ratio == pytest.approx(1.0, abs=0.03), (spec.py, ratio)


def test_an_existing_folder_named_like_an_archive_is_refused(tmp_path):
    # `raster -o d.goo` where d.goo is a folder wrote a PNG stack into it without a word (a helper's probe)
    from gpuslice.errors import ParameterError
    from gpuslice.raster.outputs import resin_format_for

    (tmp_path / "d.goo").mkdir()
    with pytest.raises(ParameterError, match=r"d\.goo: is a folder, but a .* is one file"):
        resin_format_for(tmp_path / "d.goo")
    assert resin_format_for(str(tmp_path / "d.goo") + "/").folder  # a trailing slash says folder: a PNG stack
    (tmp_path / "stack").mkdir()
    assert resin_format_for(tmp_path / "stack").folder
