"""Printer presets (issue 19): the built-in table against its sources, users' preset files, `gpuslice printers`, and
errors before any work (a format the printer cannot read, a broken preset)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile

import pytest

from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster.printers import PRESET_MAX_BYTES, PRINTERS, Printer, find_printer, load_printer_file
from gpuslice.raster.settings import PrintSettings
from gpuslice.raster.spec import RasterSpec, ResinOptions, with_printer

FAST = ["--backend", "numpy", "--raster-backend", "numpy", "--no-progress"]

WANTED = [
    "elegoo-mars-3", "elegoo-mars-4", "elegoo-mars-4-ultra", "elegoo-mars-5", "elegoo-mars-5-ultra",
    "elegoo-saturn-2", "elegoo-saturn-3", "elegoo-saturn-3-ultra", "elegoo-saturn-4", "elegoo-saturn-4-ultra",
    "elegoo-saturn-4-ultra-16k", "elegoo-jupiter", "anycubic-photon-mono-2", "anycubic-photon-mono-m5",
    "anycubic-photon-mono-m5s", "anycubic-photon-mono-m7", "anycubic-photon-mono-m7-pro",
    "anycubic-photon-mono-m7-max", "anycubic-photon-mono-x-6k", "anycubic-photon-mono-x-6ks",
    "phrozen-sonic-mini-8k", "phrozen-sonic-mini-8k-s", "phrozen-sonic-mighty-12k", "phrozen-sonic-mega-8k",
    "creality-halot-mage", "creality-halot-mage-pro", "creality-halot-one", "uniformation-gktwo",
    "uniformation-gkone", "prusa-sl1", "prusa-sl1s",
]
KEPT = ["generic-4k", "generic-2k", "prusa-sl1", "elegoo-mars", "elegoo-saturn", "anycubic-photon-mono-x"]

# display_pixels_x/y, display_width/height (mm), max_print_height as sn4k3/UVtools PrusaSlicer/printer/*.ini and
# PrusaSlicer's PrusaResearchSLA.ini give them: typed here from those files, not from printers.toml
SOURCES = {
    "elegoo-mars-3": ((4098, 2560), (143.43, 89.6), 175),
    "elegoo-mars-4-ultra": ((8520, 4320), (153.36, 77.76), 165),
    "elegoo-saturn-2": ((7680, 4320), (218.88, 123.12), 250),
    "elegoo-saturn-3-ultra": ((11520, 5120), (218.88, 122.88), 260),
    "elegoo-saturn-4-ultra-16k": ((15120, 6230), (211.68, 118.37), 220),
    "elegoo-jupiter": ((5448, 3064), (277.848, 156.264), 300),
    "anycubic-photon-mono-x-6k": ((5760, 3600), (198.15, 123.84), 245),
    "anycubic-photon-mono-m7": ((13312, 5120), (223.642, 126.976), 230),
    "anycubic-photon-mono-m7-max": ((6480, 3600), (298.08, 165.6), 300),
    "phrozen-sonic-mini-8k": ((7500, 3240), (165.0, 71.28), 180),
    "phrozen-sonic-mega-8k": ((7680, 4320), (330.24, 185.76), 400),
    "creality-halot-mage": ((7680, 4320), (228.096, 128.304), 230),
    "uniformation-gktwo": ((7680, 4320), (228.089, 128.3), 245),
    "prusa-sl1": ((2560, 1440), (120.96, 68.04), 150),
    "prusa-sl1s": ((2560, 1620), (128.0, 81.0), 150),
}


def test_table_has_the_current_printers_and_keeps_the_old_names():
    assert len(PRINTERS) >= 25
    missing = [n for n in WANTED + KEPT if n not in PRINTERS]
    assert not missing
    assert list(PRINTERS) == sorted(PRINTERS)


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_rows_match_their_sources(name):
    (nx, ny), (w, h), z = SOURCES[name]
    p = PRINTERS[name]
    assert p.resolution == (nx, ny) and p.build_height == z
    assert p.display_mm == pytest.approx((w, h), abs=0.01)  # pitch x pixels: the display within 0.01 mm


def test_every_row_is_usable_and_cites_a_source():
    for name, p in PRINTERS.items():
        spec = RasterSpec(**p.display())
        assert spec.display_mm == pytest.approx(p.display_mm), name
        assert p.source, name
        if not name.startswith("generic-"):
            assert p.formats and p.machine and p.build_height > 0, name
        PrintSettings().with_values(p.settings)


def test_non_square_pixels_and_native_formats():
    for name in ("elegoo-saturn-3-ultra", "anycubic-photon-mono-m5", "phrozen-sonic-mighty-12k"):
        p = PRINTERS[name]
        assert (p.pixel, p.pixel_y) == (0.019, 0.024)
    assert PRINTERS["elegoo-saturn-3-ultra"].native_format == "goo"
    assert PRINTERS["anycubic-photon-mono-x"].formats[0] == "pwmx"
    assert PRINTERS["anycubic-photon-mono-x-6k"].format_version == 516
    assert PRINTERS["anycubic-photon-mono-m5s"].format_version == 518
    assert PRINTERS["elegoo-mars-3"].formats == ("ctb",) and PRINTERS["elegoo-mars-3"].format_version == 4
    assert PRINTERS["phrozen-sonic-mini-8k-s"].native_format == "prz"
    gk = PRINTERS["uniformation-gktwo"]
    assert gk.reads("gktwo.ctb") and not gk.reads("ctb") and gk.reads("png")  # PNG stacks: always
    assert PRINTERS["generic-4k"].reads("anything")


def test_prusa_layers_are_portrait_pngs_as_the_firmware_shows_them():
    # Prusa's SL1 firmware (sla-fw) exposure screen: 1440 x 2560 px at 47.25 um; SL1S: 1620 x 2560 at 50 um
    sl1, sl1s = with_printer("prusa-sl1"), with_printer("prusa-sl1s")
    assert (sl1.png_size, sl1.px) == ((1440, 2560), 0.04725)
    assert (sl1s.png_size, sl1s.px) == ((1620, 2560), 0.05)
    assert sl1.bed_mm == pytest.approx((120.96, 68.04))
    assert ResinOptions(printer="prusa-sl1").settings().exposure == 6.0


def test_find_printer_forgives_case_and_spaces_and_suggests():
    assert find_printer("Elegoo Saturn 3 Ultra") is PRINTERS["elegoo-saturn-3-ultra"]
    assert find_printer("ELEGOO_MARS_3").name == "elegoo-mars-3"
    with pytest.raises(ParameterError, match="did you mean elegoo-saturn-3-ultra"):
        find_printer("elegoo-saturn-3-ultr")
    with pytest.raises(ParameterError, match="unknown printer 'zzz'"):
        find_printer("zzz")


def test_user_presets_toml_json_and_inherits(tmp_path):
    own = tmp_path / "my-printer.toml"
    own.write_text('resolution = [11520, 5120]\npixel = 0.019\npixel_y = 0.024\nbuild_height = 250\n'
                   'formats = ["goo"]\n[settings]\nexposure = 2.2\n')
    p = find_printer(str(own))
    assert (p.name, p.resolution, p.py, p.formats, p.settings) == ("my-printer", (11520, 5120), 0.024, ("goo",),
                                                                   {"exposure": 2.2})
    js = tmp_path / "j.json"
    js.write_text(json.dumps({"name": "jay", "resolution": [100, 200], "pixel": 0.1, "mirror_y": True}))
    assert load_printer_file(js) == Printer("jay", "jay", (100, 200), 0.1, mirror_y=True)
    child = tmp_path / "my-saturn.toml"
    child.write_text('inherits = "elegoo-saturn-3-ultra"\nbuild_height = 250\n[settings]\nexposure = 2.4\n')
    c, parent = find_printer(str(child)), PRINTERS["elegoo-saturn-3-ultra"]
    assert (c.name, c.resolution, c.pixel_y, c.formats, c.machine) == ("my-saturn", parent.resolution,
                                                                       parent.pixel_y, parent.formats, parent.machine)
    assert c.build_height == 250 and c.settings["exposure"] == 2.4
    assert ResinOptions(printer=str(child)).settings(bottom_layers=3).exposure == 2.4


def test_a_preset_file_rewritten_with_as_many_bytes_at_the_same_time_is_read_again(tmp_path):
    """The parsed preset is kept per content of the file: a rewrite with the same size and modification time (two
    writes within the file system's clock step) was served from the old parse."""
    own = tmp_path / "mine.toml"
    own.write_text("resolution = [11520, 5120]\npixel = 0.019\nbuild_height = 250\n")
    st = own.stat()
    assert find_printer(str(own)).build_height == 250
    own.write_text("resolution = [11520, 5120]\npixel = 0.019\nbuild_height = 190\n")
    os.utime(own, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert own.stat().st_size == st.st_size and own.stat().st_mtime_ns == st.st_mtime_ns
    assert find_printer(str(own)).build_height == 190


@pytest.mark.parametrize(("name", "text", "message"), [
    ("syntax.toml", "resolution = [1, 2\n", "not a valid TOML printer preset"),
    ("keys.toml", 'resolution = [10, 10]\npixel = 0.05\ncolour = "red"\n', "unknown printer preset key 'colour'"),
    ("need.toml", "pixel = 0.05\n", "printer preset needs 'resolution'"),
    ("px.toml", "resolution = [10, 10]\npixel = -1\n", "pixel must be a positive number of mm"),
    # a denormal pitch made the placement's 1 / pixel infinite: a model 'fitted' a display of no width, and the
    # archive was written (a helper's fuzzing); 1e308 of Z travel overflowed GOO's float32 field (internal error)
    ("tiny.json", '{"inherits": "generic-4k", "pixel": 5e-324}', "pixel must be a positive number of mm from 1e-06"),
    ("tinyy.json", '{"inherits": "generic-4k", "pixel_y": 1e-9}', "pixel_y must be a positive number of mm"),
    ("tall.json", '{"inherits": "generic-4k", "build_height": 1e308}', "build_height must be a number of mm"),
    ("exp.toml", "resolution = [10, 10]\npixel = 0.05\n[settings]\nexposure = 0\n", "exposure must be > 0"),
    ("set.toml", "resolution = [10, 10]\npixel = 0.05\n[settings]\nexposur = 2\n", "unknown print setting"),
    ("inh.toml", 'inherits = "elegoo-saturn-99"\n', "inherits unknown printer 'elegoo-saturn-99'"),
    ("arr.json", "[1, 2]", "must be a table of keys"),
    ("bad.json", "{", "not a valid JSON printer preset"),
])
def test_broken_presets_name_the_file(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ParameterError, match=message) as info:
        find_printer(str(path))
    assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)
    with pytest.raises(ParameterError, match="cannot read printer preset"):
        find_printer(str(tmp_path / "absent.toml"))


def test_printers_command_table_json_and_details(tmp_path, capsys):
    assert main(["printers"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:3] == ["name", "pixels", "pixel"]
    names = [line.split()[0] for line in lines[1:-1]]
    assert names == sorted(PRINTERS)
    row = lines[1 + names.index("elegoo-saturn-3-ultra")].split()
    assert row[1:3] == ["11520x5120", "19x24"] and "goo" in row and "218.88" in row and row[-1] != "*"
    # a native format gpuslice does not write is marked, and the footnote says what that printer gets
    assert lines[1 + names.index("uniformation-gktwo")].split()[-1] == "*"
    assert lines[1 + names.index("creality-halot-mage")].split()[-1] == "cxdlpv4"
    assert lines[1 + names.index("creality-halot-one")].split()[-1] == "cxdlp"
    assert lines[-1].startswith("* a format gpuslice does not write: a PNG stack")
    assert main(["printers", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert [d["name"] for d in data] == sorted(PRINTERS)
    sl1 = next(d for d in data if d["name"] == "prusa-sl1")
    assert sl1["resolution"] == [2560, 1440] and sl1["build_mm"] == [120.96, 68.04, 150.0] and sl1["portrait"]
    assert main(["printers", "anycubic-photon-mono-x-6k"]) == 0
    out = capsys.readouterr().out
    assert "pwmb (native pwmb version 516)" in out and "Photon Mono X 6K" in out and "UVtools" in out
    assert main(["printers", "anycubic-photon-mono-m7-pro"]) == 0
    out = capsys.readouterr().out
    assert "formats   pwsz\n" in out and "not written" not in out
    assert main(["printers", "uniformation-gktwo"]) == 0
    assert "gktwo.ctb (not written by gpuslice)" in capsys.readouterr().out
    own = tmp_path / "mine.json"
    own.write_text(json.dumps({"resolution": [100, 200], "pixel": 0.1, "settings": {"exposure": 2}}))
    assert main(["printers", str(own), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["settings"] == {"exposure": 2}
    assert main(["printers", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown printer 'nope'" in err and len(err.splitlines()) == 1


def test_printers_command_starts_without_opencl():
    code = ("import sys; from gpuslice.cli import main; rc = main(['printers']); "
            "assert rc == 0 and 'pyopencl' not in sys.modules, sorted(m for m in sys.modules if 'opencl' in m)")
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, timeout=120)


def _cube_stl(tmp_path):
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    return stl


@pytest.mark.parametrize(("printer", "output", "message"), [
    ("elegoo-saturn-3-ultra", "x.sl1", "printer elegoo-saturn-3-ultra reads goo, ctb, not sl1"),
    ("creality-halot-mage", "x.sl1", "reads cxdlpv4, not sl1"),
    ("creality-halot-mage", "x.cxdlp", "reads cxdlpv4, not cxdlp"),
    ("broken.toml", "x.sl1", "broken.toml: not a valid TOML printer preset"),
    ("exposure.toml", "x.sl1", "exposure.toml: exposure must be > 0"),
])
def test_raster_refuses_before_work_and_writes_nothing(tmp_path, capsys, printer, output, message):
    stl = _cube_stl(tmp_path)
    (tmp_path / "broken.toml").write_text("resolution = [\n")
    (tmp_path / "exposure.toml").write_text("resolution = [500, 500]\npixel = 0.05\n[settings]\nexposure = 0\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    if printer.endswith(".toml"):
        printer = str(tmp_path / printer)
    assert main(["raster", str(stl), "-t", "1", "--printer", printer, *FAST, "-o", str(tmp_path / output)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_raster_with_a_user_preset_file(tmp_path, capsys):
    stl = _cube_stl(tmp_path)
    preset = tmp_path / "mini.toml"
    preset.write_text('title = "a small display"\nresolution = [600, 500]\npixel = 0.05\npixel_y = 0.06\n'
                      'build_height = 100\nmirror_x = true\nformats = ["sl1"]\n[settings]\nexposure = 4.5\n')
    out = tmp_path / "cube.sl1"
    assert main(["raster", str(stl), "-t", "2", "--printer", str(preset), *FAST, "-q", "-o", str(out)]) == 0
    with zipfile.ZipFile(out) as z:
        cfg = dict(line.split(" = ", 1) for line in z.read("config.ini").decode().splitlines())
        ini = dict(line.split(" = ", 1) for line in z.read("prusaslicer.ini").decode().splitlines())
    assert float(cfg["expTime"]) == 4.5 and int(cfg["numFast"]) == 10
    assert (ini["display_pixels_x"], ini["display_pixels_y"], ini["display_mirror_x"]) == ("600", "500", "1")
    assert float(ini["display_height"]) == pytest.approx(30.0)
    # a PNG stack is fine for any printer, even one whose own format gpuslice does not write
    stack = tmp_path / "stack"
    assert main(["raster", str(stl), "-t", "5", "--printer", "creality-halot-one", *FAST, "-q",
                 "-o", f"{stack}/"]) == 0
    assert len(list(stack.iterdir())) == 4


def test_format_overrides_the_suffix(tmp_path, monkeypatch):
    """`raster --format NAME` writes that format whatever -o's suffix: the bytes the suffix would have made."""
    from photon_reader import read_photon

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    stl = _cube_stl(tmp_path)
    run = ["raster", str(stl), "-t", "2", *FAST, "-q"]
    assert main([*run, "--printer", "elegoo-saturn-3-ultra", "-o", str(tmp_path / "a.goo")]) == 0
    assert main([*run, "--printer", "elegoo-saturn-3-ultra", "--format", "goo", "-o", str(tmp_path / "a.bin")]) == 0
    assert (tmp_path / "a.bin").read_bytes() == (tmp_path / "a.goo").read_bytes()
    # a Photon Workshop file's machine comes from the format's name, not from the suffix
    assert main([*run, "--format", "pwmx", "-o", str(tmp_path / "b.dat")]) == 0
    assert main([*run, "-o", str(tmp_path / "b.pwmx")]) == 0
    assert (tmp_path / "b.dat").read_bytes() == (tmp_path / "b.pwmx").read_bytes()
    assert read_photon(tmp_path / "b.dat").machine["name"] == "Anycubic Photon Mono X"
    # a PNG stack into a folder named without the trailing slash: what `-o DIR/` writes
    assert main([*run, "--format", "png", "-o", str(tmp_path / "stack")]) == 0
    assert main([*run, "-o", f"{tmp_path / 'stack2'}/"]) == 0
    pngs = sorted(p.name for p in (tmp_path / "stack").iterdir())
    assert pngs and pngs == sorted(p.name for p in (tmp_path / "stack2").iterdir())
    assert all((tmp_path / "stack" / n).read_bytes() == (tmp_path / "stack2" / n).read_bytes() for n in pngs)


@pytest.mark.parametrize(("args", "message"), [
    (["--format", "goo", "-o", "{tmp}/out/"], "out/: names a folder, but a GOO file is one file"),
    (["--format", "pwmx", "--printer", "elegoo-saturn-3-ultra", "-o", "{tmp}/x.dat"],
     "printer elegoo-saturn-3-ultra reads goo, ctb, not pwmx"),
    (["--format", "png", "-o", "{tmp}/notes.txt"], "notes.txt: exists and is not a directory"),
    # a suffix that another format owns: GOO bytes in a file every program reads as a CTB
    (["--format", "goo", "-o", "{tmp}/part.ctb"], "part.ctb: a .ctb file is a CTB file, not the GOO file --format goo "
                                                  "writes (name it part.goo, or leave --format out)"),
    (["--format", "png", "-o", "{tmp}/part.goo"], "part.goo: a .goo file is a GOO file, not the PNG stack --format "
                                                  "png writes (name a folder DIR/, or leave --format out)"),
])
def test_format_refusals_write_nothing(tmp_path, capsys, args, message):
    stl = _cube_stl(tmp_path)
    (tmp_path / "notes.txt").write_text("a file of the user's\n")
    before = sorted(p.name for p in tmp_path.iterdir())
    args = [a.format(tmp=tmp_path) for a in args]
    assert main(["raster", str(stl), "-t", "2", *FAST, "-q", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_an_output_that_is_the_model_is_refused(tmp_path, capsys):
    """`--format` accepts any name, so `-o model.stl --format goo` would replace the model: refused, model intact."""
    stl = _cube_stl(tmp_path)
    before = stl.read_bytes()
    for args in (["raster", str(stl), "-t", "2", *FAST, "--format", "goo", "-o", str(stl)],
                 ["slice", str(stl), "-t", "2", "--backend", "numpy", "--format", "svg", "-o", str(stl)],
                 ["check", str(stl), "-t", "2", "--backend", "numpy", "--json", str(stl)]):
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "is the model" in err, err
    assert stl.read_bytes() == before


def test_a_preset_writes_the_file_version_its_source_cites():
    """Where a preset's source names a FILEVERSION (UVtools' profiles), that is the version written: the Photon Mono 2
    said FILEVERSION_517 and wrote 516."""
    import re

    from gpuslice.raster.photon import MACHINES
    from gpuslice.raster.printers import PRINTERS

    cited = 0
    for p in PRINTERS.values():
        m = re.search(r"FILEVERSION_(\d+)", p.source or "")
        if m is None:
            continue
        cited += 1
        assert p.format_version == int(m.group(1)), p.name
        native = p.formats[0]
        if native in MACHINES:
            assert MACHINES[native].version == p.format_version, (p.name, native)
    assert cited >= 5


def test_a_preset_that_is_not_a_regular_file_is_refused_at_once(tmp_path):
    # a FIFO was waited on forever and a link to /dev/zero read until memory ran out (a helper's probe)
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    with pytest.raises(ParameterError, match=r"pipe\.json: cannot read printer preset \(not a regular file\)"):
        load_printer_file(fifo)
    (tmp_path / "zero.toml").symlink_to("/dev/zero")
    with pytest.raises(ParameterError, match=r"zero\.toml: cannot read printer preset \(not a regular file\)"):
        load_printer_file(tmp_path / "zero.toml")
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (PRESET_MAX_BYTES + 1))
    with pytest.raises(ParameterError, match="is not one"):
        load_printer_file(big)



def test_format_png_takes_a_folder_named_like_an_archive(tmp_path):
    """`--format png -o out.goo/` names a folder (the trailing slash), as `-o out.goo/` alone does: not refused."""
    from gpuslice.raster.outputs import resin_format_for

    assert resin_format_for(f"{tmp_path}/out.goo/", "png").name == "png"
    assert resin_format_for(f"{tmp_path}/out.goo/").name == "png"
