"""Anycubic's zip archives (gpuslice.raster.anycubic_zip: .pm7, .pm7m, .pwsz), read back with the tests' own reader
(anycubic_zip_reader.py): every layer against the rasteriser after PW0's documented 4-bit quantisation, the print
settings in the resin's JSON and the per-layer table, the scene and volume binaries, the previews, real meshes on the
M7's non-square 13312x5120 display, the command line, reproducibility and errors."""

from __future__ import annotations

import datetime as dt
import hashlib
from pathlib import Path

import numpy as np
import pytest
from anycubic_zip_reader import read_anycubic_zip
from run_images import quantised_runs

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import PrintSettings, RasterSpec, ResinOptions, iter_tiles, masks
from gpuslice.raster.anycubic_zip import ZIP_MACHINES, write_target
from gpuslice.raster.layers import iter_run_layers, pixel_runs
from gpuslice.raster.nanodlp import polygon_areas
from gpuslice.raster.outputs import RESIN_FORMATS, ResinTarget, resin_format_for
from gpuslice.raster.printers import PRINTERS
from gpuslice.raster.settings import layer_table, print_time_s, resin_ml

SPEC = RasterSpec(resolution=(1200, 900), pixel=0.05)
SETTINGS = PrintSettings(bottom_layers=3, bottom_exposure=25.0, exposure=2.5, transition_layers=4, lift_height=6.0,
                         lift_speed=90.0, retract_speed=180.0, wait_before_cure=1.5, wait_after_cure=0.5,
                         wait_after_lift=0.25, bottom_wait_before_cure=3.0, bottom_lift_height=8.0,
                         bottom_lift_speed=60.0, resin_density=1.25)
NOW = dt.datetime(2026, 1, 2, 3, 4, 6)


def q(grey: np.ndarray) -> np.ndarray:
    """PW0's documented quantisation: 4 bits kept (grey >> 4), read back as 17 times that."""
    return (np.asarray(grey).astype(np.int64) >> 4) * 17


def target(path, res, spec=SPEC, settings=SETTINGS, options: ResinOptions | None = None, now=NOW) -> ResinTarget:
    return ResinTarget(Path(path), spec, options or ResinOptions(), res, "part", settings=settings, now=now)


@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=0.5, backend="numpy")


@pytest.mark.parametrize("gamma", [1.0, 0.0])
@pytest.mark.parametrize("suffix", ["pm7", "pm7m", "pwsz"])
def test_torus_layers_settings_and_tables(tmp_path, torus, gamma, suffix):
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05, gamma=gamma)
    out = tmp_path / f"part.{suffix}"
    stats = write_target(iter_tiles(torus, spec, backend="numpy"), target(out, torus, spec))
    f = read_anycubic_zip(out)
    n = torus.n_layers
    assert stats["layers"] == n == len(f.layers) == 20
    names = f.zf.namelist()
    assert sorted(x for x in names if x.startswith("layer_images/")) == sorted(
        f"layer_images/layer_{i}.pw0Img" for i in range(n))
    assert all(i.compress_type == 8 for i in f.zf.infolist())  # every member deflated, as Photon Workshop's
    ref = masks(torus, spec, backend="numpy")
    for i in range(n):
        assert np.array_equal(f.layer_image(i), q(ref[i])), i
    greys = bool(np.any((q(ref) > 0) & (q(ref) < 255)))
    assert greys == (gamma != 0)
    m, machine = f.machine, ZIP_MACHINES[suffix]
    assert (m["name"], m["key_suffix"], m["key_image_format"]) == (machine.name, suffix, "pw0Img")
    assert (m["res_x"], m["res_y"], m["xy_pixel"], m["xy_pixel_y"]) == (1200, 900, 50.0, 50.0)
    assert (m["print_xsize"], m["print_ysize"], m["print_zsize"]) == (60.0, 45.0, machine.height)
    assert m["raster_antialiasing"] == (16 if greys else 1)
    assert m["child_screen"] == [{"x": 0, "y": 0, "width": 1200, "height": 900}]
    p, x = f.resin["slicepara"], f.resin["slice_extpara"]
    assert (p["bott_layers"], p["bott_time"], p["exposure_time"], x["transition_layercount"]) == (3, 25.0, 2.5, 4)
    assert (p["off_time"], p["wait_before_lift"], p["wait_after_lift"]) == (1.5, 0.5, 0.25)
    assert (p["bott_off_time"], p["bott_wait_before_lift"], p["bott_wait_after_lift"]) == (3.0, 0.5, 0.25)
    assert (p["zthick"], p["zup_height"], p["zup_speed"], p["zdown_speed"]) == (0.5, 6.0, 1.5, 3.0)
    assert p["use_indivi_layerpara"] == 0 and x["multi_state_used"] == 0
    assert x["multi_state_paras"]["bott_0"] == {"height": 8.0, "up_speed": 1.0, "down_speed": 0.0}
    assert x["multi_state_paras"]["normal_0"] == {"height": 6.0, "up_speed": 1.5, "down_speed": 0.0}
    assert x["multi_state_paras"]["normal_1"] == {"height": 0.0, "up_speed": 0.0, "down_speed": 3.0}
    t = layer_table(SETTINGS, n)
    assert [r["exposure_time"] for r in f.layers] == pytest.approx(list(t["exposure"]))
    assert [r["layer_index"] for r in f.layers] == list(range(n))
    assert [r["layer_minheight"] for r in f.layers] == pytest.approx(list(np.arange(n) * 0.5))
    assert [r["layer_thickness"] for r in f.layers] == [0.5] * n
    assert [r["zup_height"] for r in f.layers] == [8.0] * 3 + [6.0] * (n - 3)
    assert [r["zup_speed"] for r in f.layers] == [1.0] * 3 + [1.5] * (n - 3)
    vol = resin_ml(torus.area, torus.thickness)
    info = f.print_info
    assert info["model_layers_count"] == n and info["print_time"] == pytest.approx(print_time_s(SETTINGS, n), abs=0.01)
    assert info["volume"] == pytest.approx(vol, abs=1e-3) and info["weight"] == pytest.approx(1.25 * vol, abs=1e-3)
    assert f.software["mark"] == "gpuslice"
    # scene.slice: one record a layer, its top Z, area, polygon count and largest polygon, the lit pixels' box
    sc = f.scene
    assert sc["count"] == n and sc["box"][2] == 0.0 and sc["box"][5] == pytest.approx(10.0)
    rec = sc["records"]
    assert np.allclose(rec["z"], 0.5 * np.arange(1, n + 1)) and np.allclose(rec["area"], torus.area, atol=1e-3)
    layer, area = polygon_areas(torus)
    import gpuslice.raster.nanodlp as nanodlp

    chunk = nanodlp.AREA_CHUNK_POINTS
    try:  # whole loops a few points at a time (memory bounded: a helper's audit), the same areas bit for bit
        nanodlp.AREA_CHUNK_POINTS = 5
        assert np.array_equal(polygon_areas(torus)[1], area)
    finally:
        nanodlp.AREA_CHUNK_POINTS = chunk
    assert np.array_equal(rec["objects"], np.bincount(layer, minlength=n)) and np.all(rec["objects"] == 1)
    assert np.allclose(rec["largest"], area[np.argsort(layer)], rtol=1e-5)
    assert np.allclose(sc["box"][:2], (-20, -20), atol=0.06) and np.allclose(sc["box"][3:5], (20, 20), atol=0.06)
    for i in (0, 10, n - 1):  # each layer's box holds its lit pixels, within a pixel
        r, c = np.nonzero(f.layer_image(i))
        box = (c.min() * 0.05 - 30, r.min() * 0.05 - 22.5, (c.max() + 1) * 0.05 - 30, (r.max() + 1) * 0.05 - 22.5)
        assert np.allclose([rec["xmin"][i], rec["ymin"][i], rec["xmax"][i], rec["ymax"][i]], box, atol=1e-4)
    v = f.volumes
    assert (v["magic"], v["step"], v["one"]) == (0x20251024, pytest.approx(0.2), 1)
    assert list(v["records"]["layer"]) == list(range(n)) and np.allclose(v["records"]["thickness"], 0.5)
    assert float(v["records"]["volume"].sum()) == pytest.approx(1000 * vol, rel=1e-5)


def test_two_stage_motion_and_per_layer_switch(tmp_path, torus):
    s = PrintSettings(lift_height=2.0, lift_speed=30.0, lift_height2=4.0, lift_speed2=180.0, retract_speed=240.0,
                      retract_height2=2.0, retract_speed2=45.0, per_layer_settings=True)
    out = tmp_path / "two.pwsz"
    write_target(iter_tiles(torus, SPEC, backend="numpy"), target(out, torus, settings=s))
    f = read_anycubic_zip(out)
    x, p = f.resin["slice_extpara"], f.resin["slicepara"]
    assert x["multi_state_used"] == 1 and p["use_indivi_layerpara"] == 1
    assert x["multi_state_paras"]["normal_0"] == {"height": 2.0, "up_speed": 0.5, "down_speed": 0.75}
    assert x["multi_state_paras"]["normal_1"] == {"height": 4.0, "up_speed": 3.0, "down_speed": 4.0}
    assert p["zup_height"] == 6.0 and [r["zup_height"] for r in f.layers] == [6.0] * torus.n_layers
    bad = PrintSettings(lift_height=2.0, lift_height2=4.0, lift_speed2=180.0, retract_height2=1.0,
                        retract_speed2=45.0)
    with pytest.raises(ParameterError, match=r"bad\.pwsz: .*retract-height2 1 cannot be written"):
        write_target(iter_tiles(torus, SPEC, backend="numpy"), target(tmp_path / "bad.pwsz", torus, settings=bad))
    assert not (tmp_path / "bad.pwsz").exists()


def test_previews_show_the_part(tmp_path, torus):
    out = tmp_path / "p.pm7"
    write_target(iter_tiles(torus, SPEC, backend="numpy"), target(out, torus))
    f = read_anycubic_zip(out)
    for i, size in enumerate(((224, 168), (336, 252), (800, 600))):
        img = f.preview(i)
        assert img.size == size and img.mode == "RGBA"
        a = np.asarray(img.convert("RGB")).astype(int)
        part = a[..., 0] > a[..., 2] + 40  # orange on a dark grey background
        h, w = part.shape
        assert part.mean() > 0.1 and not part[h // 2, w // 2] and part[h // 2].any()  # the torus's hole


def test_runs_and_tiles_write_the_same_archive(tmp_path, torus, device):
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05, gamma=1.0)
    a, b = tmp_path / "a.pm7", tmp_path / "b.pm7"
    write_target(iter_tiles(torus, spec, backend="numpy"), target(a, torus, spec))
    write_target(iter_run_layers(torus, spec, device=device), target(b, torus, spec))
    fa, fb = read_anycubic_zip(a), read_anycubic_zip(b)
    # the rasterisers may differ by one grey level on a boundary pixel (raster/coverage.py); the codes are the same
    # wherever the quantised pixels are
    for i in range(torus.n_layers):
        ia, ib = fa.layer_image(i), fb.layer_image(i)
        assert np.count_nonzero(ia != ib) <= 0.01 * max(1, np.count_nonzero(ia)), i
    tiles = iter_tiles(torus, spec, backend="opencl", device=device)  # the same runs as bitmaps: the same bytes
    c = tmp_path / "c.pm7"
    write_target(tiles, target(c, torus, spec))
    assert c.read_bytes() == b.read_bytes()


def test_registry_and_presets():
    zips = {f.name: f for f in RESIN_FORMATS.values() if f.writer == "anycubic_zip:write_target"}
    assert set(zips) == set(ZIP_MACHINES) == {"pm7", "pm7m", "pwsz"}
    for s, m in ZIP_MACHINES.items():
        assert resin_format_for(f"x.{s.upper()}") is zips[s] and m.name.removeprefix("Anycubic ") in zips[s].title
        preset = next(p for p in PRINTERS.values() if s in p.formats)  # the preset of the printer that reads it
        assert tuple(preset.resolution) == m.resolution and preset.machine == m.name
        assert preset.resolution[0] * preset.pixel == pytest.approx(m.display[0], abs=1e-3)
        assert preset.resolution[1] * (preset.pixel_y or preset.pixel) == pytest.approx(m.display[1], abs=1e-3)


# ---- the M7's own display ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_shared_meshes_on_the_m7_display_every_layer(tmp_path, shared_results, device, gamma):
    """benchy (60 mm) and nefertiti (80 mm) at 0.05 mm on the M7 Pro's 13312x5120 display of 0.0168 x 0.0248 mm
    pixels (non-square): every layer decodes to the runs the writer was given, quantised; three whole layers equal
    gpuslice.raster.masks() quantised."""
    spec = RasterSpec(resolution=(13312, 5120), pixel=0.0168, pixel_y=0.0248, gamma=gamma, mirror_x=True)
    cols = spec.shape[1]
    for name, fit in (("benchy", 60.0), ("nefertiti", 80.0)):
        res, bounds = shared_results(name, fit)
        want: dict[int, str] = {}

        def layers(res=res, bounds=bounds, want=want):
            for item in iter_run_layers(res, spec, device=device, bounds=bounds):
                start, length, grey = pixel_runs(item, cols)
                img_runs = quantised_runs(start, length, grey, q)
                want[item.index] = hashlib.sha1(b"".join(a.tobytes() for a in img_runs)).hexdigest()
                yield item

        out = tmp_path / f"{name}.pwsz"
        t = ResinTarget(out, spec, ResinOptions(printer="anycubic-photon-mono-m7-pro"), res, name,
                        settings=PrintSettings(), now=NOW, bounds=bounds)
        write_target(layers(), t)
        f = read_anycubic_zip(out)
        assert len(f.layers) == res.n_layers == len(want) and f.machine["name"] == "Anycubic Photon Mono M7 Pro"
        assert (f.machine["xy_pixel"], f.machine["xy_pixel_y"]) == (16.8, 24.8)
        from photon_reader import decode_pw0

        for i in range(res.n_layers):
            code = np.frombuffer(f.zf.read(f"layer_images/layer_{i}.pw0Img"), np.uint8)
            got = decode_pw0(code, 13312 * 5120)
            assert hashlib.sha1(b"".join(np.asarray(a, np.int64).tobytes() for a in got)).hexdigest() == want[i], i
        some = [0, res.n_layers // 2, res.n_layers - 1]
        for k, m in enumerate(masks(res, spec, backend="opencl", device=device, layers=some, bounds=bounds)):
            assert np.array_equal(f.layer_image(some[k]), q(m)), (name, some[k])


# ---- command line, reproducibility, errors -------------------------------------------------------------------------
def test_cli_preset_writes_reproducible_archives(tmp_path, device, monkeypatch, capsys):
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    args = ["raster", str(stl), "-t", "0.5", "--printer", "anycubic-photon-mono-m7-max", "--no-progress",
            "--bottom-layers", "2", "--exposure", "3"]
    assert main([*args, "-o", str(tmp_path / "a.pm7m")]) == 0
    assert "wrote" in capsys.readouterr().out
    assert main([*args, "-q", "-o", str(tmp_path / "b.pm7m")]) == 0
    assert (tmp_path / "a.pm7m").read_bytes() == (tmp_path / "b.pm7m").read_bytes()
    f = read_anycubic_zip(tmp_path / "a.pm7m")
    assert len(f.layers) == 20 and f.resin["slicepara"]["bott_layers"] == 2 and f.layers[19]["exposure_time"] == 3.0
    assert (f.machine["res_x"], f.machine["res_y"], f.machine["print_zsize"]) == (6480, 3600, 300.0)
    img = f.layer_image(10)
    assert img[1800, 3240] == 0 and img.max() == 255  # the torus's hole at the display's centre


def test_a_display_not_the_machines_is_refused(tmp_path, capsys):
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    base = ["raster", str(stl), "-t", "0.5", "--no-progress"]
    assert main([*base, "-o", str(tmp_path / "a.pm7")]) == 2  # the default 3840x2400 display: not the M7's
    err = capsys.readouterr().err
    assert "a.pm7: a .pm7 file is for the Anycubic Photon Mono M7, whose display is 13312x5120" in err
    assert err.count("\n") == 1
    assert main([*base, "--printer", "elegoo-saturn-3-ultra", "-o", str(tmp_path / "b.pwsz")]) == 2
    assert "elegoo-saturn-3-ultra" in capsys.readouterr().err  # a format the preset's printer does not read
    assert sorted(p.name for p in tmp_path.iterdir()) == ["torus.stl"]


def test_errors_leave_no_file(tmp_path, torus):
    def broken():
        yield from iter_tiles(torus, SPEC, backend="numpy", layers=[0, 1])
        raise ParameterError("stop")

    with pytest.raises(ParameterError, match="stop"):
        write_target(broken(), target(tmp_path / "b.pm7", torus))
    with pytest.raises(ParameterError, match="expected 20 layers, got 2"):
        write_target(iter_tiles(torus, SPEC, backend="numpy", layers=[0, 1]), target(tmp_path / "c.pm7", torus))
    with pytest.raises(ParameterError, match=r"x\.pwx: not an Anycubic zip suffix"):
        write_target(iter([]), target(tmp_path / "x.pwx", torus))
    assert list(tmp_path.iterdir()) == []
