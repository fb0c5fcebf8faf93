"""What a user's audit of the resin workflow found (twenty-first session), through the command line as a user runs
it: layers of several thicknesses turn every archive's per-layer switch on (the printer must follow each layer's
height), an archive naming a printer refuses another orientation or mirror than its display's, and a mesh whose
open chains leave layers unfilled is warned about (stderr, the report, the batch table)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from anycubic_zip_reader import read_anycubic_zip
from ctb_reader import read_ctb
from cxdlpv4_reader import read_cxdlpv4
from goo_reader import read_goo
from photon_reader import read_photon

from gpuslice.batch.report import format_summary
from gpuslice.cli import main

#: suffix, a printer reading it, and the per-layer switch as the tests' reader finds it in the file
SWITCHES = {
    ".goo": ("elegoo-mars-4", lambda p: read_goo(p).header["advance_mode"]),
    ".pm3n": ("anycubic-photon-mono-2", lambda p: read_photon(p).header["per_layer"]),
    ".pm7": ("anycubic-photon-mono-m7", lambda p: read_anycubic_zip(p).resin["slicepara"]["use_indivi_layerpara"]),
    ".ctb": ("elegoo-mars-3", lambda p: read_ctb(p).slicer["per_layer"]),
    ".cxdlpv4": ("creality-halot-mage", lambda p: read_cxdlpv4(p).slicer["per_layer"]),
}


@pytest.fixture(scope="module")
def box_stl(tmp_path_factory) -> Path:
    """A 10 × 8 × 3 mm box, as an STL file."""
    path = tmp_path_factory.mktemp("audit") / "box.stl"
    trimesh.creation.box((10.0, 8.0, 3.0)).export(path)
    return path


@pytest.mark.parametrize("suffix", sorted(SWITCHES))
def test_layers_of_several_thicknesses_turn_the_per_layer_switch_on(tmp_path, box_stl, capsys, suffix):
    """A thicker first layer (or adaptive layers): the header's one layer height is wrong for some layers, so the
    printer must read each layer's own; uniform layers leave the switch off (its default: some firmware freezes)."""
    printer, switch = SWITCHES[suffix]
    on, off = tmp_path / f"first{suffix}", tmp_path / f"uniform{suffix}"
    base = ["raster", str(box_stl), "--printer", printer, "-t", "0.5", "-q", "--no-progress"]
    assert main([*base, "--first-layer", "1.0", "-o", str(on)]) == 0
    assert main([*base, "-o", str(off)]) == 0
    assert bool(switch(on)) and not bool(switch(off))
    assert main([*base, "--per-layer-settings", "-o", str(off)]) == 0  # asked for: on, whatever the layers
    assert bool(switch(off))


@pytest.mark.parametrize("flags", [["--portrait"], ["--no-mirror-x"], ["--mirror-y"]])
@pytest.mark.parametrize("suffix", [".goo", ".ctb"])
def test_an_archive_naming_a_printer_refuses_another_orientation_or_mirror(tmp_path, box_stl, capsys, flags,
                                                                          suffix):
    """Mars 4 and Mars 3 are landscape with the columns mirrored: an unmirrored or portrait image would print
    mirrored or not at all, under the printer's own name."""
    printer = SWITCHES[suffix][0]
    out = tmp_path / f"x{suffix}"
    code = main(["raster", str(box_stl), "--printer", printer, "-t", "0.5", "-q", *flags, "-o", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and not out.exists() and "\n" not in err
    assert f"printer {printer}'s display is landscape, mirror x, not " in err
    # the same flags for a PNG stack (no printer named) are the user's to set
    assert main(["raster", str(box_stl), "--printer", printer, "-t", "0.5", "-q", *flags,
                 "-o", str(tmp_path / "png") + "/"]) == 0


def test_the_preset_orientation_given_again_is_accepted(tmp_path, box_stl):
    out = tmp_path / "x.goo"
    assert main(["raster", str(box_stl), "--printer", "elegoo-mars-4", "-t", "0.5", "-q", "--landscape",
                 "--mirror-x", "--no-mirror-y", "-o", str(out)]) == 0
    h = read_goo(out).header
    assert (h["x_mirror"], h["y_mirror"]) == (1, 0)


@pytest.fixture(scope="module")
def open_box_stl(tmp_path_factory) -> Path:
    """The box without its two +x facets: open edges round a hole in the wall, so every layer has one open chain
    (and nothing the layer's polygons could fill)."""
    m = trimesh.creation.box((10.0, 8.0, 3.0))
    keep = ~np.isclose(m.triangles_center[:, 0], 5.0)
    assert keep.sum() == 10
    path = tmp_path_factory.mktemp("audit") / "open_box.stl"
    trimesh.Trimesh(m.vertices, m.faces[keep], process=False).export(path)
    return path


def test_open_chains_are_warned_about_and_reported(tmp_path, open_box_stl, box_stl, capsys):
    out, report = tmp_path / "o.goo", tmp_path / "o.json"
    assert main(["raster", str(open_box_stl), "--printer", "elegoo-mars-4", "-t", "0.5", "-q", "-o", str(out),
                 "--exposure", "2.5", "--report", str(report), "--no-fill-holes"]) == 0  # (filled, its hole closes)
    err = capsys.readouterr().err.strip().splitlines()
    warning = [line for line in err if line.startswith("gpuslice: warning: ")]
    assert len(warning) == 1
    assert "open_box.stl: 6 open chains in 6 layers (layers 0-5)" in warning[0] and "o.goo" in warning[0]
    rep = json.loads(report.read_text())
    assert rep["open_chains"] == 6 and rep["repairs"]["open_chains"] == 6
    # the layer images' size under one name whatever the format (a GOO's were png_bytes only)
    assert rep["image_bytes"] == rep["png_bytes"] > 0
    # a closed box: no warning, and the report says none
    assert main(["raster", str(box_stl), "--printer", "elegoo-mars-4", "-t", "0.5", "-q", "-o", str(out),
                 "--exposure", "2.5", "--report", str(report)]) == 0
    assert "warning" not in capsys.readouterr().err
    assert json.loads(report.read_text())["open_chains"] == 0


def test_the_batch_table_warns_of_open_chains():
    base = {"status": "done", "facets": 10, "layers": 6, "timings_s": {"total": 0.1}}
    report = {"models": [{**base, "model": "open.stl", "open_chains": 6}, {**base, "model": "closed.stl",
                                                                          "open_chains": 0}],
              "summary": {"models": 2, "done": 2, "skipped": 0, "failed": 0, "not_run": 0, "wall_s": 0.2,
                          "models_per_s": 10.0, "mode": "local", "workers": 1, "workers_lost": 0, "retries": 0}}
    lines = format_summary(report).splitlines()
    row = {line.split()[0]: line for line in lines[1:3]}
    assert row["open.stl"].endswith("warning: 6 open chains (the mesh is not closed there; a resin layer leaves them "
                                    "unfilled)")
    assert "warning" not in row["closed.stl"]


def _prusaslicer_estimate(n: int, first: float, exp: float, fade: int, tilt: float) -> float:
    """PrusaSlicer's SLA estimate, as its ``merge_slices_and_eval_stats`` walks the layers: layers 0-2 at the
    initial exposure, then a fading time stepped down by (initial - exposure) / (fade + 1) while it is above the
    exposure, then the exposure; one fast tilt per layer."""
    step, t, total = (first - exp) / (fade + 1), first, 0.0
    for i in range(n):
        if i < 3:
            total += first
        elif t > exp + 1e-12:
            t -= step
            total += t
        else:
            total += exp
    return total + n * tilt


@pytest.mark.parametrize(("n", "first", "exp", "fade"), [(0, 35.0, 6.0, 10), (2, 35.0, 6.0, 10), (40, 35.0, 6.0, 10),
                                                         (12, 35.0, 6.0, 10), (40, 6.0, 8.0, 5), (40, 20.0, 2.0, 0)])
def test_the_sl1_estimate_counts_the_fade_layers(n, first, exp, fade):
    """SL1's printTime left the fade out (every layer after the first at expTime): 145 s short on a small cube."""
    from gpuslice.raster.sl1 import SL1Info, sl1_print_time

    info = SL1Info(exposure_time=exp, initial_exposure_time=first, faded_layers=fade, tilt_time=5.0)
    assert sl1_print_time(info, n) == pytest.approx(_prusaslicer_estimate(n, first, exp, fade, 5.0))


@pytest.mark.parametrize(("printer", "suffix", "flags", "words"), [
    ("prusa-sl1", ".sl1", ["--lift-height", "3", "--wait-before-cure", "3"],
     ("an SL1 archive stores no lift, retract, rest", "--lift-height 3", "--wait-before-cure 3")),
    ("prusa-sl1", ".sl1", ["--light-pwm", "100"], ("an SL1 archive", "--light-pwm 100")),
    ("prusa-sl1s", ".sl1s", ["--retract-speed", "300"], ("an SL1 archive", "--retract-speed 300")),
    ("anycubic-photon-mono-x", ".pwmx", ["--light-pwm", "100"], ("a Photon Workshop file stores no light intensity",
                                                                 "--light-pwm 100")),
    ("anycubic-photon-mono-m7", ".pm7", ["--bottom-light-pwm", "90"], ("an Anycubic zip archive stores no light",
                                                                       "--bottom-light-pwm 90")),
])
def test_settings_a_format_cannot_store_are_refused_not_dropped(tmp_path, box_stl, capsys, printer, suffix, flags,
                                                                 words):
    """SL1 wrote --lift-height 3 --wait-before-cure 3 --light-pwm 100 nowhere, with exit 0; Photon Workshop and the
    M7 zip dropped --light-pwm. Refused before any work, nothing written; without them the file is written."""
    out = tmp_path / f"x{suffix}"
    base = ["raster", str(box_stl), "--printer", printer, "-t", "0.5", "-q", "--no-progress", "-o", str(out)]
    assert main([*base, *flags]) == 2 and not out.exists()
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and all(w in err for w in words), err
    assert main(base) == 0 and out.exists()


RAMPS = {
    ".goo": lambda p: read_goo(p).header["transition_layers"],
    ".ctb": lambda p: read_ctb(p).slicer["transition_layers"],
    ".pm3n": lambda p: read_photon(p).header["transition_layers"],
    ".pm7": lambda p: read_anycubic_zip(p).resin["slice_extpara"]["transition_layercount"],
    ".cxdlpv4": lambda p: read_cxdlpv4(p).slicer["transition_layers"],
}


@pytest.mark.parametrize("suffix", sorted(RAMPS))
def test_the_header_states_a_ramp_only_where_the_layers_have_one(tmp_path, box_stl, suffix):
    """--bottom-exposure 2 --exposure 10 --transition-layers 5: no layer ramps (the exposure steps only down), yet
    the header said 5 transition layers, which a firmware computing its own ramp would follow."""
    printer, read = SWITCHES[suffix][0], RAMPS[suffix]
    base = ["raster", str(box_stl), "--printer", printer, "-t", "0.25", "-q", "--no-progress", "--exposure", "10",
            "--transition-layers", "5"]
    up, down = tmp_path / f"up{suffix}", tmp_path / f"down{suffix}"
    assert main([*base, "--bottom-exposure", "2", "-o", str(up)]) == 0
    assert main([*base, "--bottom-exposure", "30", "-o", str(down)]) == 0
    assert (read(up), read(down)) == (0, 5)


def test_keep_xy_says_where_the_model_and_the_display_are(tmp_path, box_stl, capsys):
    """The box centred on its origin with --keep-xy: "does not fit on the display (143.43 x 89.60 mm)" for a 10 mm
    part left the user to guess that it hangs off the display's x = 0 edge."""
    out = tmp_path / "k.ctb"
    assert main(["raster", str(box_stl), "--keep-xy", "--printer", "elegoo-mars-3", "-t", "0.5", "-q",
                 "-o", str(out)]) == 2 and not out.exists()
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--keep-xy keeps its own x -5.00 to 5.00 and y -4.00 to 4.00 mm" in err
    assert "the display spans x 0 to 143.43 and y 0 to 89.60 mm" in err


def test_a_preset_without_exposures_warns_of_the_generic_ones(tmp_path, box_stl, capsys):
    """Elegoo's presets carry no exposures: 10 s a layer and one 15 s bottom layer (PrusaSlicer's SL1 material) went
    into a Mars 4 file without a word; a mono LCD needs a fraction of that."""
    base = ["raster", str(box_stl), "-t", "0.5", "-q", "--no-progress"]
    assert main([*base, "--printer", "elegoo-mars-4", "-o", str(tmp_path / "a.goo")]) == 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("gpuslice: warning: ") and "\n" not in err
    assert "a.goo: printer elegoo-mars-4's preset holds no exposures, so its layers get the generic 10 s" in err
    for extra, out in ((["--printer", "elegoo-mars-4", "--exposure", "2.5"], "b.goo"),
                       (["--printer", "prusa-sl1"], "b.sl1"),
                       (["--printer", "elegoo-mars-4"], "stack/")):  # (a PNG stack stores no exposures)
        assert main([*base, *extra, "-o", str(tmp_path / out) + ("/" if out.endswith("/") else "")]) == 0
        assert "warning" not in capsys.readouterr().err


def test_an_archive_without_a_printer_says_it_names_none(tmp_path, box_stl, capsys):
    """`raster part.stl -o part.goo` wrote a GOO for a generic 3840x2400 display with an empty machine name, without a
    word; a PNG stack or a Photon Workshop file (its suffix names the machine) is not warned about."""
    base = ["raster", str(box_stl), "-t", "0.5", "-q", "--no-progress"]
    assert main([*base, "-o", str(tmp_path / "a.goo")]) == 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("gpuslice: warning: ") and "\n" not in err
    assert "a.goo names no printer (no --printer) and holds a generic 3840x2400 display of 0.05 mm pixels" in err
    for out in (tmp_path / "stack", tmp_path / "b.pwmx"):  # (the Photon Mono X mirrors x)
        assert main([*base, "--mirror-x", "-o", f"{out}/" if out.suffix == "" else str(out)]) == 0
        assert "warning" not in capsys.readouterr().err


def test_a_photon_file_without_a_printer_says_when_its_machine_mirrors(tmp_path, box_stl, capsys):
    """Without --printer a .pwmx (the Photon Mono X, whose display mirrors x) was written unmirrored without a word:
    the part prints mirrored. The preset that writes the suffix natively says how its display is."""
    assert main(["raster", str(box_stl), "-t", "0.5", "-q", "-o", str(tmp_path / "a.pwmx")]) == 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("gpuslice: warning: ") and "\n" not in err
    assert ("a.pwmx is written landscape, but the Anycubic Photon Mono X's display, which its suffix names, is "
            "landscape, mirror x" in err and "--printer anycubic-photon-mono-x" in err)


def test_the_m5s_takes_layers_of_several_thicknesses_only_when_per_layer_is_asked(tmp_path, box_stl, capsys):
    """A thicker first layer turns the per-layer switch on, and the M5s firmware never ends the first layer with it on
    (UVtools): refused, naming the file, unless --per-layer-settings asks for it; one thickness writes as before."""
    base = ["raster", str(box_stl), "--printer", "anycubic-photon-mono-m5s", "-t", "0.5", "-q", "--no-progress",
            "--exposure", "2.5"]
    out = tmp_path / "x.pm5s"
    assert main([*base, "--first-layer", "1.0", "-o", str(out)]) == 2 and not out.exists()
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "x.pm5s: layers of several thicknesses need the per-layer settings on" in err
    assert main([*base, "--first-layer", "1.0", "--per-layer-settings", "-o", str(out)]) == 0
    assert read_photon(out).header["per_layer"] == 1
    assert main([*base, "-o", str(out)]) == 0 and read_photon(out).header["per_layer"] == 0


def test_a_second_stage_speed_without_its_height_is_refused():
    """--lift-speed2 300 without --lift-height2 (or --retract-speed2 without --retract-height2) was dropped without a
    word; a bottom speed inherited from the normal one, or a normal one the bottom layers' own stage uses, is fine."""
    from gpuslice.errors import ParameterError
    from gpuslice.raster import PrintSettings

    for kw, words in (({"lift_speed2": 300.0}, "lift_speed2 300 mm/min"),
                      ({"retract_speed2": 30.0}, "retract_speed2 30 mm/min"),
                      ({"lift_height2": 2.0, "lift_speed2": 200.0, "bottom_lift_height2": 0.0,
                        "bottom_lift_speed2": 100.0}, "bottom_lift_speed2 100 mm/min")):
        with pytest.raises(ParameterError, match=words):
            PrintSettings(**kw)
    PrintSettings(lift_height2=0.5, lift_speed2=120.0, bottom_lift_height2=0.0)  # (the bottom inherits, unused)
    PrintSettings(lift_speed2=120.0, bottom_lift_height2=2.0)  # (the bottom layers' stage at --lift-speed2)


@pytest.mark.parametrize("printer", ["prusa-sl1", "anycubic-photon-mono-m5s", "elegoo-mars-3"])
def test_a_part_exactly_the_display_fits(tmp_path, printer, capsys):
    """A part exactly the preset's display size: its float32 points lie a step over it on some presets (68.04 rounds
    up), and it was refused with "the model (120.96 x 68.04 mm) does not fit on the display (120.96 x 68.04 mm)";
    a part 2 µm larger is still refused, saying by how much."""
    from gpuslice.raster import ResinOptions

    w, h = sorted(ResinOptions(printer=printer).spec().bed_mm, reverse=True)
    for extra, code in ((0.0, 0), (0.002, 2)):
        stl = tmp_path / f"d{extra}.stl"
        trimesh.creation.box(bounds=[[0, 0, 0], [w + extra, h, 0.1]]).export(stl)
        capsys.readouterr()
        assert main(["raster", str(stl), "--printer", printer, "-t", "0.05", "-q", "--no-progress", "-o",
                     f"{tmp_path / f'd{extra}'}/"]) == code
        if code:
            assert "pixels past an edge" in capsys.readouterr().err
