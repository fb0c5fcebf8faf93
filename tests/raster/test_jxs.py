"""UniFormation GKone ``.jxs`` archives (gpuslice.raster.jxs), read back with the tests' own reader (jxs_reader.py):
every layer's RGB-packed PNG against the rasteriser (8-bit greys: exact), config.ini, the print program replayed
(the platform's height, exposure, PWM and waits of every layer), the refusals and the command line."""

from __future__ import annotations

import datetime as dt
import struct
from pathlib import Path

import numpy as np
import pytest
from jxs_reader import read_jxs, replay

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import PrintSettings, ResinOptions, iter_tiles, masks
from gpuslice.raster.jxs import program, program_seconds, rgb_packed, write_target
from gpuslice.raster.layers import iter_run_layers, pixel_runs
from gpuslice.raster.outputs import ResinTarget, resin_format_for
from gpuslice.raster.settings import layer_table

NOW = dt.datetime(2026, 11, 25, 12, 0)
GKONE = "uniformation-gkone"
SETTINGS = PrintSettings(bottom_layers=2, bottom_exposure=20.0, exposure=2.5, transition_layers=3, lift_height=4.0,
                         lift_speed=90.0, lift_height2=2.0, lift_speed2=240.0, bottom_lift_height=6.0,
                         bottom_lift_speed=60.0, retract_speed=180.0, retract_height2=1.5, retract_speed2=60.0,
                         wait_before_cure=1.5, bottom_wait_before_cure=8.0, wait_after_cure=0.5, wait_after_lift=0.25,
                         light_pwm=200, bottom_light_pwm=250)


def target(path, res, settings=SETTINGS, gamma: float = 1.0, **kw) -> ResinTarget:
    opts = ResinOptions(printer=GKONE)
    return ResinTarget(Path(path), opts.spec(gamma=gamma), opts, res, "part", settings=settings, now=NOW, workers=2,
                       **kw)


@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=0.5, backend="numpy")


def test_rgb_packed_png_holds_the_grey_rows():
    """Three grey pixels side by side are one RGB pixel (R the first): Pillow reads the repacked PNG so."""
    import io

    from PIL import Image

    from gpuslice.raster.coverage import Tile
    from gpuslice.raster.png import PngEncoder

    img = np.arange(6 * 9, dtype=np.uint8).reshape(6, 9) * 4
    png = PngEncoder(9, 6, 1, "zlib").encode(Tile(0, 0, 0, img))
    rgb = np.asarray(Image.open(io.BytesIO(rgb_packed(png, 9, 6))))
    assert rgb.shape == (6, 3, 3) and np.array_equal(rgb.reshape(6, 9), img)
    with pytest.raises(ValueError):
        rgb_packed(png, 8, 6)


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_torus_every_layer_config_and_program(tmp_path, torus, gamma):
    out = tmp_path / "part.jxs"
    t = target(out, torus, gamma=gamma)
    stats = write_target(iter_tiles(torus, t.spec, backend="numpy"), t)
    f = read_jxs(out)
    n = torus.n_layers
    c = f.config
    assert stats["layers"] == n == f.n_layers == f.control["total_slices"] == 20
    assert (c["Action"], c["FirstLayerTime"], c["LayerTime"], c["NumBottomLayers"], c["layerHeight"]) == (
        "print", "20000", "2500", "2", "0.5")
    assert (c["LiftDistance1"], c["LiftFeedrate1"], c["LiftDistance2"], c["LiftFeedrate2"]) == ("4", "90", "2", "240")
    assert (c["BottomLiftFeedrate"], c["RetractFeedrate"], c["ZMoveTimeCompensation"],
            c["ZMoveTimeCompensationBottom"], c["OnLightCode"]) == ("60", "180", "1500", "8000", "M106 S200")
    assert float(c["UsedMaterial"]) == pytest.approx(stats["resin_ml"], abs=1e-3) and c["nJobName"] == "part"
    assert c["GcodeFooter"].startswith("G0 Z") and c["ApplicationName"].startswith("gpuslice")
    # the time stated: the program's delays less the layers' rises (0.5 mm each here, at 60-90 mm/min) and the end
    acts = f.control["action_list"]
    assert f.control["total_time"] == pytest.approx(stats["print_time_s"], abs=1e-3)
    assert 0 < program_seconds(acts) - f.control["total_time"] < n * 0.5 / 60 * 60 + 245 / 60 * 60 + 5
    # the program, replayed: each layer shown, then exposed at its top, at its PWM, for its (ramped) exposure
    table = layer_table(SETTINGS, n)
    steps = replay(f.control["action_list"])
    assert [s["layerno"] for s in steps] == list(range(1, n + 1))
    for i, s in enumerate(steps):
        assert s["z"] == pytest.approx(0.5 * (i + 1), abs=1e-6), i
        assert (s["pwm"], s["exposure_ms"]) == (250 if i < 2 else 200, round(table["exposure"][i] * 1000)), i
        assert s["moved_then_waited"] and s["waits"] == [250, 8000 if i < 2 else 1500], i
    assert f.control["action_list"][-1] == ["gcode", "M18"]
    for i in range(n):  # (one layer at a time: a 4920x2880 mask is 14 MB)
        img = f.layer_image(i)
        assert img.shape == (2880, 4920)
        assert np.array_equal(img, masks(torus, t.spec, backend="numpy", layers=[i])[0]), i


def test_program_moves_add_up_to_every_layers_top():
    """Thin layers (0.0125 mm: tops that 3-decimal moves cannot each hold) and a lift with only its second stage:
    the relative moves, replayed, put every layer at its top to the micrometre (before, each move rounded on its own
    left the last layer 0.32 mm low); a move's delay is its time plus UVtools' margins."""
    th = np.full(1920, 0.0125)
    top = np.cumsum(th)
    for s in (SETTINGS, PrintSettings(lift_height=0.0, lift_height2=3.0, lift_speed2=120.0, bottom_lift_height=0.0,
                                      bottom_lift_height2=3.0, retract_speed=120.0)):
        acts = program(s, top, 245.0)
        steps = replay(acts)
        z = np.array([st["z"] for st in steps])
        assert np.abs(z - top).max() <= 0.0005 + 1e-9 and z[-1] == pytest.approx(24.0, abs=1e-9)  # (1 µm grid)
        assert acts[-1] == ["gcode", "M18"] and program_seconds(acts) > 1920 * s.exposure
    acts = program(PrintSettings(lift_height=0.0, lift_height2=3.0, lift_speed2=120.0, bottom_lift_height=0.0,
                                 bottom_lift_height2=3.0), top[:1], 245.0)
    moves = [a for a in acts if a[0] == "gcode" and a[1].startswith("G0")]
    assert moves[0] == ["gcode", "G0 Z3.012 F120"]  # (one move: the rise, 0.0125 on the 1 µm grid, and the stage)
    i = acts.index(moves[0])
    assert acts[i + 1] == ["delay", round((0.75 + 3.012 / 2.0 + 0.75) * 1000)]


def test_runs_and_tiles_write_the_same_file(tmp_path, torus, device):
    a, b = tmp_path / "a.jxs", tmp_path / "b.jxs"
    ta, tb = target(a, torus, device=device), target(b, torus, device=device)
    write_target(iter_tiles(torus, ta.spec, backend="opencl", device=device), ta)
    write_target(iter_run_layers(torus, tb.spec, device=device), tb)
    fa, fb = read_jxs(a), read_jxs(b)
    for i in (0, 7, 19):  # (the PNGs' deflate streams may differ: the pixels may not)
        assert np.array_equal(fa.layer_image(i), fb.layer_image(i)), i
    assert fa.control == fb.control and fa.config == fb.config


def test_another_display_is_refused_before_any_work(tmp_path, torus, capsys):
    opts = ResinOptions(printer="generic-4k")
    t = ResinTarget(tmp_path / "x.jxs", opts.spec(), opts, torus, "part", settings=SETTINGS)
    with pytest.raises(ParameterError, match=r"x\.jxs: a \.jxs file is for the UniFormation GKone's 4920x2880"):
        write_target(iter([]), t)
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    assert main(["raster", str(stl), "-t", "0.5", "--no-progress", "-o", str(tmp_path / "y.jxs")]) == 2
    assert "y.jxs: a .jxs file is for the UniFormation GKone's" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["torus.stl"]
    assert resin_format_for("a.JXS").name == "jxs"


def test_cli_writes_a_gkone_archive_with_the_presets_settings(tmp_path, device, capsys):
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    out = tmp_path / "a.jxs"
    assert main(["raster", str(stl), "-t", "0.5", "--no-progress", "--printer", GKONE, "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    f = read_jxs(out)
    assert f.n_layers == 20 and f.config["ZMoveTimeCompensationBottom"] == "8000"
    steps = replay(f.control["action_list"])
    assert [s["z"] for s in steps] == pytest.approx(0.5 * np.arange(1, 21), abs=1e-6)


def test_benchy_every_layer_on_the_gkone(tmp_path, shared_results, device):
    """benchy (60 mm) at 0.05 mm on the GKone's display (mirrored in y): every layer's PNG is RGB at a third of the
    width, every 10th holds the lit pixels and greys of the runs the writer was given (the pixels are the PNG stack's,
    checked on every layer there), and three layers equal what masks() draws."""
    res, bounds = shared_results("benchy", 60.0)
    opts = ResinOptions(printer=GKONE)
    spec = opts.spec()
    cols = spec.shape[1]
    want = {}

    def layers():
        for item in iter_run_layers(res, spec, device=device, bounds=bounds):
            start, length, grey = pixel_runs(item, cols)
            want[item.index] = (int(length.sum()), int((length * grey.astype(np.int64)).sum()))
            yield item

    out = tmp_path / "benchy.jxs"
    write_target(layers(), ResinTarget(out, spec, opts, res, "benchy", settings=opts.settings(), now=NOW, workers=2,
                                       device=device))
    f = read_jxs(out)
    assert f.n_layers == res.n_layers == len(want)
    for i in range(res.n_layers):  # every layer an RGB PNG a third as wide; every 10th inflated (30 ms each)
        assert f.zf.read(f"{i:05d}.png")[16:26] == struct.pack(">IIBB", 1640, 2880, 8, 2), i
        if i % 10 == 0:
            img = f.layer_quick(i)
            assert (int(np.count_nonzero(img)), int(img.sum(dtype=np.int64))) == want[i], i
    some = [0, res.n_layers // 2, res.n_layers - 1]
    for k, m in enumerate(masks(res, spec, backend="opencl", device=device, layers=some, bounds=bounds)):
        assert np.array_equal(f.layer_image(some[k]), m), some[k]
