"""Print settings (issue 19): the bottom/transition ramp, two-stage lift and retract, waits, print time and resin
volume by hand, validation, and a preset's settings overridden by the command line."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster.settings import (
    LAYER_COLUMNS,
    PrintSettings,
    format_duration,
    layer_table,
    layer_times,
    print_time_s,
    resin_ml,
    transition_step,
)
from gpuslice.raster.spec import ResinOptions

# a numpy-only run: no OpenCL device needed, small and fast
FAST = ["--backend", "numpy", "--raster-backend", "numpy", "--no-progress"]


def test_bottom_and_transition_ramp_by_hand():
    s = PrintSettings(bottom_layers=2, bottom_exposure=30.0, exposure=2.5, transition_layers=4)
    t = layer_table(s, 9)
    assert set(t) == set(LAYER_COLUMNS) and all(c.shape == (9,) for c in t.values())
    # step (30 - 2.5) / 5 = 5.5 s: 24.5, 19, 13.5, 8, then the normal 2.5 s
    assert t["exposure"].tolist() == [30.0, 30.0, 24.5, 19.0, 13.5, 8.0, 2.5, 2.5, 2.5]
    assert t["bottom"].tolist() == [True, True] + [False] * 7
    assert t["light_pwm"].dtype == np.int64


def test_transition_step_is_rounded_clamped_and_only_downwards():
    s = PrintSettings(bottom_layers=1, bottom_exposure=35.0, exposure=6.0, transition_layers=10)
    assert transition_step(s) == 2.64  # 29 / 11 = 2.6363... to 0.01 s, as UVtools
    e = layer_table(s, 14)["exposure"]
    assert e[1:11] == pytest.approx(35.0 - 2.64 * np.arange(1, 11))
    assert e[11:].tolist() == [6.0] * 3 and e.min() >= 6.0
    # more transition layers than the ramp has 0.01 s steps for: clamped at the normal exposure, never below
    s = PrintSettings(bottom_layers=0, bottom_exposure=2.2, exposure=2.0, transition_layers=50)
    assert transition_step(s) == 0.0  # 0.2 / 51 rounds to 0: no ramp
    assert layer_table(s, 60)["exposure"].tolist() == [2.0] * 60
    # a bottom exposure shorter than the normal one: no ramp up (Chitubox/UVtools ramp down only)
    s = PrintSettings(bottom_layers=1, bottom_exposure=1.0, exposure=3.0, transition_layers=3)
    assert layer_table(s, 6)["exposure"].tolist() == [1.0, 3.0, 3.0, 3.0, 3.0, 3.0]
    # fewer layers than bottom + transition: still well defined
    assert layer_table(PrintSettings(bottom_layers=5), 3)["exposure"].tolist() == [15.0] * 3
    assert layer_table(PrintSettings(), 0)["exposure"].shape == (0,)


def test_two_stage_lift_retract_and_bottom_twins():
    s = PrintSettings(bottom_layers=1, transition_layers=0, lift_height=3.0, lift_speed=60.0, lift_height2=4.0,
                      lift_speed2=240.0, retract_speed=300.0, retract_height2=2.0, retract_speed2=30.0,
                      bottom_lift_height=6.0, bottom_lift_speed=120.0, bottom_retract_height2=1.0,
                      bottom_wait_before_cure=3.0, wait_before_cure=0.5)
    assert s.retract_height == 5.0  # the lift's 3 + 4 mm come back: 5 fast, then 2 slow
    assert s.bottom_retract_height == 9.0  # 6 + 4 - 1
    t = layer_table(s, 2)
    assert t["lift_height"].tolist() == [6.0, 3.0] and t["lift_speed"].tolist() == [120.0, 60.0]
    assert t["lift_height2"].tolist() == [4.0, 4.0]  # no bottom twin given: the normal value
    assert t["retract_height"].tolist() == [9.0, 5.0] and t["retract_height2"].tolist() == [1.0, 2.0]
    assert t["wait_before_cure"].tolist() == [3.0, 0.5]
    for k in (0, 1):  # every layer returns exactly what it lifted
        assert t["retract_height"][k] + t["retract_height2"][k] == t["lift_height"][k] + t["lift_height2"][k]


def test_layer_times_and_print_time_by_hand():
    s = PrintSettings(bottom_layers=2, bottom_exposure=20.0, exposure=2.0, transition_layers=2,
                      lift_height=4.0, lift_speed=80.0, lift_height2=2.0, lift_speed2=240.0,
                      retract_speed=180.0, retract_height2=1.0, retract_speed2=60.0,
                      bottom_lift_height=8.0, bottom_lift_speed=60.0,
                      wait_before_cure=1.0, wait_after_cure=0.5, wait_after_lift=0.25, bottom_wait_after_cure=2.0)
    # normal layer moves: lift 4/80 min = 3 s, 2/240 min = 0.5 s; retract (4 + 2 - 1)/180 min = 5/3 s, 1/60 min = 1 s
    normal_moves = 3.0 + 0.5 + 5.0 / 3.0 + 1.0
    # bottom layer moves: lift 8/60 min = 8 s, 0.5 s; retract (8 + 2 - 1)/180 min = 3 s, 1 s
    bottom_moves = 8.0 + 0.5 + 3.0 + 1.0
    # exposures: 20, 20 (bottom), step (20 - 2) / 3 = 6: 14, 8 (transition), then 2
    exposures = [20.0, 20.0, 14.0, 8.0, 2.0, 2.0, 2.0]
    expected = [e + 1.0 + 2.0 + 0.25 + bottom_moves for e in exposures[:2]]
    expected += [e + 1.0 + 0.5 + 0.25 + normal_moves for e in exposures[2:]]
    assert layer_times(s, 7) == pytest.approx(expected)
    assert print_time_s(s, 7) == pytest.approx(sum(expected))
    assert print_time_s(s, 0) == 0.0


def test_format_duration():
    assert format_duration(0) == "0:00" and format_duration(59) == "0:01" and format_duration(5430) == "1:31"
    assert format_duration(36000) == "10:00"


@pytest.mark.parametrize(("tri", "volume_mm3"), [
    (shapes.box((0, 0, 0), (10, 20, 5)), 1000.0),
    (shapes.hollow_box(20.0, 10.0), 20.0**3 - 10.0**3),  # the cavity is no resin
])
def test_resin_ml_is_the_solid_volume(tri, volume_mm3):
    res = slice_mesh(mesh_from_triangles(tri), thickness=0.05, backend="numpy")
    assert resin_ml(res.area, res.thickness) == pytest.approx(volume_mm3 / 1000.0, rel=1e-9)
    assert resin_ml(np.array([np.inf]), np.array([1.0])) == 0.0  # a bad area never gives NaN volumes


@pytest.mark.parametrize(("values", "param", "text"), [
    ({"exposure": 0}, "exposure", "exposure must be > 0"),
    ({"bottom_exposure": float("nan")}, "bottom_exposure", "bottom_exposure must be > 0"),
    ({"bottom_layers": -1}, "bottom_layers", "whole number of layers"),
    ({"transition_layers": 2.5}, "transition_layers", "whole number of layers"),
    ({"bottom_layers": True}, "bottom_layers", "whole number of layers"),
    ({"lift_speed": 0}, "lift_speed", "lift_speed must be > 0"),
    ({"bottom_retract_speed": -5}, "bottom_retract_speed", "bottom_retract_speed must be > 0"),
    ({"wait_after_lift": -1}, "wait_after_lift", ">= 0"),
    ({"light_pwm": 0}, "light_pwm", "from 1 to 255"),
    ({"bottom_light_pwm": 256}, "bottom_light_pwm", "from 1 to 255"),
    ({"resin_density": 0}, "resin_density", "> 0"),
    ({"exposure": 1e9}, "exposure", "exposure must be at most 3600 s"),  # (was an internal error in CTB/Photon)
    ({"bottom_wait_after_cure": 4000.0}, "bottom_wait_after_cure", "at most 3600 s"),
    ({"lift_height": 2000.0}, "lift_height", "at most 1000 mm"),
    ({"retract_speed2": 1e6}, "retract_speed2", "at most 60000 mm/min"),
    # contradictions
    ({"lift_height2": 3.0}, "lift_speed2", "lift_speed2 must be > 0 mm/min when lift_height2 is set"),
    ({"retract_height2": 1.0}, "retract_speed2", "when retract_height2 is set"),
    ({"retract_height2": 6.0, "retract_speed2": 30.0}, "retract_height2", "longer than the lift it returns"),
    ({"bottom_lift_height": 2.0, "retract_height2": 3.0, "retract_speed2": 30.0, "lift_height": 4.0},
     "bottom_retract_height2", "bottom_retract_height2 (3 mm) is longer than the lift"),
])
def test_validation_errors(values, param, text):
    with pytest.raises(ParameterError, match=text.replace("(", r"\(").replace(")", r"\)")) as info:
        PrintSettings().with_values(values)
    assert param in info.value.params


def test_unknown_and_derived_settings_are_refused():
    with pytest.raises(ParameterError, match="unknown print setting 'exposur'"):
        PrintSettings().with_values({"exposur": 2.0})
    with pytest.raises(ParameterError, match="retract_height is not a setting: the retract returns the whole lift"):
        PrintSettings().with_values({"retract_height": 2.0})
    assert PrintSettings().with_values({"exposure": None}) == PrintSettings()  # None: not given


def test_preset_settings_overridden_by_given_values():
    opts = ResinOptions(printer="prusa-sl1")
    preset = opts.settings()
    assert (preset.exposure, preset.bottom_exposure) == (6.0, 35.0)  # PrusaSlicer's default SL1 material
    mine = opts.settings(exposure=3.0, lift_height=None)
    assert (mine.exposure, mine.bottom_exposure, mine.lift_height) == (3.0, 35.0, PrintSettings().lift_height)
    with pytest.raises(ParameterError, match="exposure must be > 0"):
        opts.settings(exposure=0.0)


def _cube_stl(tmp_path):
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)  # 20 mm cube: 8 ml
    return stl


def _small_preset(tmp_path, **settings) -> str:
    lines = ['resolution = [500, 500]', 'pixel = 0.05', 'build_height = 100', 'formats = ["sl1"]', "[settings]"]
    lines += [f"{k} = {v}" for k, v in settings.items()]
    path = tmp_path / "small.toml"
    path.write_text("\n".join(lines) + "\n")
    return str(path)


def test_cli_preset_settings_overridden_and_estimates_reported(tmp_path, capsys):
    stl = _cube_stl(tmp_path)
    preset = _small_preset(tmp_path, bottom_layers=2, bottom_exposure=10.0, exposure=4.0, transition_layers=0,
                           lift_height=5.0, lift_speed=60.0, retract_speed=300.0)
    out, rep = tmp_path / "cube.sl1", tmp_path / "r.json"
    args = ["raster", str(stl), "-t", "1", "--printer", preset, *FAST, "--report", str(rep), "--exposure", "3"]
    # SL1 holds one bottom layer: refused with the preset's two, written with one
    assert main([*args, "-o", str(out)]) == 2 and not out.exists()
    assert "--bottom-layers 2" in capsys.readouterr().err
    assert main([*args, "-o", str(out), "--bottom-layers", "1"]) == 0
    with zipfile.ZipFile(out) as z:
        cfg = dict(line.split(" = ", 1) for line in z.read("config.ini").decode().splitlines())
    assert (float(cfg["expTime"]), float(cfg["expTimeFirst"])) == (3.0, 10.0)  # the flag wins, the preset stays
    # SL1's estimate is its config.ini's (exposures and tilts), printed and reported alike
    assert json.loads(rep.read_text())["print_time_s"] == pytest.approx(float(cfg["printTime"]))
    capsys.readouterr()
    assert main([*args, "-o", f"{tmp_path / 'stack'}/"]) == 0  # a PNG stack: the settings' own estimate
    # 20 layers: 2 x 10 s + 18 x 3 s of light, and each layer lifts 5 mm at 60 mm/min (5 s), retracts at 300 (1 s)
    expected = 2 * 10.0 + 18 * 3.0 + 20 * (5.0 + 1.0)
    report = json.loads(rep.read_text())
    assert report["layers"] == 20 and report["print_time_s"] == pytest.approx(expected)
    assert report["resin_ml"] == pytest.approx(8.0, rel=1e-6) and report["resin_g"] == pytest.approx(8.8, rel=1e-6)
    line = capsys.readouterr().out.strip()
    assert "print about 0:03 (h:mm), 8.0 ml of resin" in line  # 194 s


@pytest.mark.parametrize(("flags", "flag"), [(["--exposure", "0"], "--exposure"),
                                             (["--bottom-exposure", "-2"], "--bottom-exposure"),
                                             (["--lift-height2", "2"], "--lift-speed2"),
                                             (["--light-pwm", "300"], "--light-pwm")])
def test_cli_bad_settings_fail_before_work(tmp_path, capsys, flags, flag):
    stl = _cube_stl(tmp_path)
    out = tmp_path / "cube.sl1"
    assert main(["raster", str(stl), "-t", "1", "--resolution", "500x500", *FAST, "-o", str(out), *flags]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("gpuslice: error:") and flag in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.stl"]  # nothing written, not even a temporary


def test_a_print_time_no_archive_holds_is_refused_before_writing(tmp_path, capsys):
    """Settings each within bounds, but a print time over an archive's 32-bit field (136 years): one line, exit 2,
    nothing written (a CTB or Photon file ended in an internal error, GOO clamped it, SL1 wrote it)."""
    stl = _cube_stl(tmp_path)
    for suffix in ("ctb", "sl1"):
        out = tmp_path / f"cube.{suffix}"
        args = ["raster", str(stl), "-t", "0.01", "--resolution", "500x500", *FAST, "--lift-speed", "0.0001",
                "--bottom-layers", "1", "-o", str(out)]
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        # (SL1 stores no lift: its own refusal comes first, before any estimate)
        why = "years" if suffix == "ctb" else "--lift-speed 0.0001 cannot be written"
        assert len(err.splitlines()) == 1 and f"cube.{suffix}: " in err and why in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.stl"]


def test_a_resin_denser_than_any_is_refused():
    """--resin-density 1e308 overflowed the archives' float32 mass fields (an internal error after the slicing)."""
    with pytest.raises(ParameterError, match="resin_density must be at most 100 g/ml"):
        PrintSettings(resin_density=1e308)
    assert PrintSettings(resin_density=22.6).resin_density == 22.6


@pytest.mark.parametrize("flag", ["--lift-speed", "--retract-speed", "--bottom-lift-speed"])
@pytest.mark.parametrize("command", ["raster", "check"])
def test_a_speed_too_slow_for_any_estimate_is_refused(tmp_path, capsys, flag, command):
    """A denormal speed (5e-324 mm/min) made a move's time infinite: numpy's overflow warning, then "inf years"
    (raster) or an internal error (check)."""
    import warnings

    stl = _cube_stl(tmp_path)
    out = ["-o", str(tmp_path / "cube.goo")] if command == "raster" else []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast = FAST if command == "raster" else ["--backend", "numpy"]
        assert main([command, str(stl), "-t", "1", "--printer", "elegoo-saturn-3-ultra", *fast, flag, "5e-324",
                     *out]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{flag} must be at least 1e-06 mm/min" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.stl"]


def test_model_taller_than_the_printer_is_refused_before_slicing(tmp_path, capsys):
    """A model taller than the preset's build height: one line naming the file, exit 2, nothing written."""
    from gpuslice.cli import main
    from gpuslice.mesh import shapes
    from gpuslice.raster.printers import find_printer

    p = find_printer("elegoo-saturn-3-ultra")
    assert p.build_height > 0
    stl = tmp_path / "tall.stl"
    shapes.write_stl(shapes.box((0, 0, 0), (10, 10, p.build_height + 5)), stl)
    out = tmp_path / "tall"
    code = main(["raster", str(stl), "--printer", "elegoo-saturn-3-ultra", "-o", f"{out}/", "-q", "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "tall.stl" in err and "build height" in err
    assert not out.exists() and not list(tmp_path.glob("tall*tmp*"))
