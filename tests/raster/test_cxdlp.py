"""Creality Halot .cxdlp files (gpuslice.raster.cxdlp), read back with the tests' own reader (cxdlp_reader.py): the
vertical lines against a brute-force scan of bitmaps, the per-layer area against scipy's labelling, every layer of a
torus and of real meshes against the rasteriser (8-bit greys: exact), the header, settings and checksums of both
versions, the refusals, the command line, and a file Chitubox wrote."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from cxdlp_reader import read_cxdlp
from scipy import ndimage

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import PrintSettings, RasterSpec, ResinOptions, Tile, iter_tiles, masks
from gpuslice.raster.cxdlp import column_lines, largest_regions, write_target
from gpuslice.raster.layers import iter_run_layers, pixel_runs
from gpuslice.raster.outputs import ResinTarget, resin_format_for
from gpuslice.raster.printers import PRINTERS

SETTINGS = PrintSettings(bottom_layers=3, bottom_exposure=30.0, exposure=2.5, transition_layers=0, lift_height=5.0,
                         lift_speed=120.0, bottom_lift_height=7.0, bottom_lift_speed=60.0, retract_speed=180.0,
                         wait_before_cure=2.0, light_pwm=200, bottom_light_pwm=250)


def preset_file(tmp_path, version: int | None = None, code: str = "CL-79") -> str:
    p = tmp_path / f"halot{version}.toml"
    v = f"format_version = {version}\n" if version else ""
    p.write_text(f'name = "test-halot"\nresolution = [1200, 900]\npixel = 0.05\nbuild_height = 160\n'
                 f'formats = ["cxdlp"]\n{v}machine = "{code}"\n')
    return str(p)


def target(path, res, spec, options, settings=SETTINGS) -> ResinTarget:
    return ResinTarget(Path(path), spec, options, res, "part", settings=settings)


@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=0.5, backend="numpy")


def brute_lines(img: np.ndarray) -> np.ndarray:
    """(x, y0, y1, grey) of every maximal vertical run of one non-zero grey, by scanning each column."""
    out = []
    for x in range(img.shape[1]):
        col = img[:, x]
        y = 0
        while y < col.size:
            if col[y] == 0:
                y += 1
                continue
            y1 = y
            while y1 + 1 < col.size and col[y1 + 1] == col[y]:
                y1 += 1
            out.append((x, y, y1, int(col[y])))
            y = y1 + 1
    return np.array(out, np.int64).reshape(-1, 4)


def largest_4(img: np.ndarray) -> int:
    lab, n = ndimage.label(img > 0)  # (4-connected: scipy's default structure)
    return int(np.bincount(lab.ravel())[1:].max()) if n else 0


@pytest.mark.parametrize("seed", range(5))
def test_lines_and_areas_equal_a_brute_force_scan(seed):
    """Random layers (greys changing down a column, single pixels, runs touching in a row with two greys, rows that
    are blank, a full column) in one group: the lines equal a column-by-column scan, the areas scipy's labelling."""
    rng = np.random.default_rng(seed)
    rows, cols = 37, 41
    imgs = []
    for k in range(6):
        img = np.zeros((rows, cols), np.uint8)
        for _ in range(12):
            r, c = rng.integers(rows), rng.integers(cols)
            img[r : r + rng.integers(1, 15), c : c + rng.integers(1, 20)] = rng.choice([255, 128, 7, 255, 1])
        img[rng.random((rows, cols)) < 0.05 * k] = 0
        img[:, rng.integers(cols)] = 255 if k % 2 else 0
        imgs.append(img)
    imgs[2][:] = 0  # a blank layer
    runs = [pixel_runs(Tile(k, 0, 0, img), cols) for k, img in enumerate(imgs)]
    offsets = np.concatenate(([0], np.cumsum([r[0].size for r in runs])))
    start, length, grey = (np.concatenate([r[i] for r in runs]) for i in range(3))
    off, x, y0, y1, g = column_lines(start, length, grey, offsets, cols)
    area = largest_regions(start, length, offsets, cols)
    for k, img in enumerate(imgs):
        got = np.stack([x, y0, y1, g.astype(np.int64)], 1)[off[k] : off[k + 1]]
        assert np.array_equal(got, brute_lines(img)), k
        assert area[k] == largest_4(img), k


@pytest.mark.parametrize("version", [3, 2])
@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_torus_every_layer_header_and_checksum(tmp_path, torus, version, gamma):
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05, gamma=gamma)
    out = tmp_path / "part.cxdlp"
    stats = write_target(iter_tiles(torus, spec, backend="numpy"),
                         target(out, torus, spec, ResinOptions(printer=preset_file(tmp_path, version))))
    f = read_cxdlp(out)  # (checks the checksum, every CRLF and the length)
    n = torus.n_layers
    assert stats["layers"] == n == f.n_layers == 20 and stats["format_version"] == version == f.version
    assert (f.model, f.res_x, f.res_y, f.display_mm, f.layer_height) == ("CL-79", 1200, 900, (60.0, 45.0), 0.5)
    assert f.block[:4] == (160).to_bytes(4, "big") and f.footer == b"CXSW3D\0"
    assert f.settings == {"exposure_tenths": 25, "wait_before_cure": 2, "bottom_exposure": 30, "bottom_layers": 3,
                          "bottom_lift_height": 7, "bottom_lift_speed": 1, "lift_height": 5, "lift_speed": 2,
                          "retract_speed": 3, "bottom_light_pwm": 250, "light_pwm": 200}
    if version == 3:
        assert f.info["software"].startswith("gpuslice") and f.info["aa_enabled"] == int(gamma != 0)
    else:
        assert f.info is None
    ref = masks(torus, spec, backend="numpy")
    for i in range(n):
        img = f.layer_image(i)
        assert np.array_equal(img, ref[i]), i  # 8-bit greys: exact
        assert f.layers[i]["area"] == f.areas[i] == largest_4(ref[i]), i
        lines = f.layers[i]["lines"]
        assert np.array_equal(lines, brute_lines(ref[i])), i  # sorted by column then row, maximal runs
    p = f.previews[2].astype(np.int64)
    part = (p >> 11) > (p & 31) + 8  # orange (red high, blue low) on a dark grey background
    assert part.mean() > 0.2 and not part[145, 145] and part[145].any() and p[145, 145] == p[0, 0]  # the hole


def test_runs_and_tiles_write_the_same_file(tmp_path, torus, device):
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05)
    opts = ResinOptions(printer=preset_file(tmp_path))
    a, b = tmp_path / "a.cxdlp", tmp_path / "b.cxdlp"
    write_target(iter_tiles(torus, spec, backend="opencl", device=device), target(a, torus, spec, opts))
    write_target(iter_run_layers(torus, spec, device=device), target(b, torus, spec, opts))
    assert a.read_bytes() == b.read_bytes()


def test_what_the_format_cannot_hold_is_refused(tmp_path, torus):
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05)
    opts = ResinOptions(printer=preset_file(tmp_path))
    cases = [
        (ResinOptions(), {}, "give a Creality Halot --printer preset"),
        (ResinOptions(printer="generic-4k"), {}, "give a Creality Halot --printer preset"),
        (ResinOptions(printer=preset_file(tmp_path, 4)), {}, "versions 2 and 3, not 4"),
        (opts, {"transition_layers": 5}, "--transition-layers 5 (no exposure ramp"),
        (opts, {"lift_speed": 65.0}, "--lift-speed 65 mm/min (whole mm/s"),
        (opts, {"wait_before_cure": 0.0}, "--wait-before-cure 0 s (whole seconds, at least 1"),
        (opts, {"exposure": 2.55}, "--exposure 2.55 s (tenths"),
        (opts, {"lift_height2": 3.0, "lift_speed2": 240.0}, "one lift stage"),
        (opts, {"lift_height2": 0.5, "lift_speed2": 120.0, "bottom_lift_height2": 0.0},
         "--lift-height 5.5 mm, both stages"),
        (opts, {"wait_after_cure": 1.0}, "--wait-after-cure"),
        (opts, {"bottom_retract_speed": 120.0}, "one retract speed"),
    ]
    for options, change, message in cases:
        s = PrintSettings(**{**{k: getattr(SETTINGS, k) for k in ("bottom_layers", "bottom_exposure", "exposure",
                                                                     "transition_layers", "lift_height", "lift_speed",
                                                                     "bottom_lift_height", "bottom_lift_speed",
                                                                     "retract_speed", "wait_before_cure")},
                             **change})
        with pytest.raises(ParameterError, match=f"x.cxdlp: .*{message}".replace("(", r"\(").replace(")", r"\)")):
            write_target(iter_tiles(torus, spec, backend="numpy"), target(tmp_path / "x.cxdlp", torus, spec, options,
                                                                          s))
    assert not (tmp_path / "x.cxdlp").exists()


def test_registry_and_presets():
    fmt = resin_format_for("x.CXDLP")
    assert fmt.name == "cxdlp" and fmt.writer == "cxdlp:write_target"
    halots = [p for p in PRINTERS.values() if "cxdlp" in p.formats]
    assert len(halots) == 8 and len({p.machine for p in halots}) == 8  # each its own model code
    for p in halots:  # every Halot preset's own settings are ones the format holds (no refusal)
        from gpuslice.raster.cxdlp import refuse_settings

        opts = ResinOptions(printer=p.name)
        refuse_settings(Path("x.cxdlp"), "cxdlp", opts, opts.settings(), opts.spec())
    for name in ("creality-halot-mage", "creality-halot-mage-pro"):
        assert PRINTERS[name].formats == ("cxdlpv4",)  # another layout, not written


# ---- real meshes ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_shared_meshes_on_the_sky_plus_every_layer(tmp_path, shared_results, device, gamma):
    """benchy (60 mm) and nefertiti (80 mm) at 0.05 mm on the Halot Sky Plus's 5760x3600 display: every layer's lines
    hold the pixels and greys of the runs the writer was given; three whole layers equal gpuslice.raster.masks()."""
    spec = RasterSpec(resolution=(5760, 3600), pixel=0.0344, gamma=gamma)
    cols = spec.shape[1]
    for name, fit in (("benchy", 60.0), ("nefertiti", 80.0)):
        res, bounds = shared_results(name, fit)
        want = {}

        def layers(res=res, bounds=bounds, want=want):
            for item in iter_run_layers(res, spec, device=device, bounds=bounds):
                start, length, grey = pixel_runs(item, cols)
                want[item.index] = (int(length.sum()), int((length * grey).sum()))
                yield item

        out = tmp_path / f"{name}.cxdlp"
        write_target(layers(), target(out, res, spec, ResinOptions(printer="creality-halot-sky-plus"),
                                      ResinOptions(printer="creality-halot-sky-plus").settings()))
        f = read_cxdlp(out)
        assert f.n_layers == res.n_layers == len(want) and f.model == "CL-92"
        for i in range(res.n_layers):
            lines = f.layers[i]["lines"]
            n = lines[:, 2] - lines[:, 1] + 1
            assert (int(n.sum()), int((n * lines[:, 3]).sum())) == want[i], i
        some = [0, res.n_layers // 2, res.n_layers - 1]
        for k, m in enumerate(masks(res, spec, backend="opencl", device=device, layers=some, bounds=bounds)):
            assert np.array_equal(f.layer_image(some[k]), m), (name, some[k])
            assert f.areas[some[k]] == largest_4(m), (name, some[k])


def test_cli_writes_a_halot_file_and_refuses_without_a_preset(tmp_path, device, capsys):
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    base = ["raster", str(stl), "-t", "0.5", "--no-progress"]
    assert main([*base, "--printer", "creality-halot-one", "--exposure", "3", "-o", str(tmp_path / "a.cxdlp")]) == 0
    assert "wrote" in capsys.readouterr().out
    f = read_cxdlp(tmp_path / "a.cxdlp")
    assert (f.model, f.res_x, f.res_y, f.n_layers, f.settings["exposure_tenths"]) == ("CL-60", 1620, 2560, 20, 30)
    assert main([*base, "-o", str(tmp_path / "b.cxdlp")]) == 2
    err = capsys.readouterr().err
    assert "b.cxdlp: a .cxdlp file carries its printer's model code" in err and err.count("\n") == 1
    assert main([*base, "--printer", "creality-halot-one", "--lift-speed", "65", "-o", str(tmp_path / "c.cxdlp")]) == 2
    assert "--lift-speed 65 mm/min" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.cxdlp", "torus.stl"]


FOREIGN = os.environ.get("GPUSLICE_FOREIGN_ARCHIVES")


@pytest.mark.skipif(not FOREIGN, reason="set GPUSLICE_FOREIGN_ARCHIVES to a folder holding a .cxdlp another program "
                    "wrote (futurelink/msla-imaging's Example_HALOT_ONE_PLUS.cxdlp: public, with no licence to copy "
                    "it here)")
def test_a_file_chitubox_wrote_reads_back():
    """The test decoder reads a Halot One Plus file Chitubox wrote: its checksum (v3 CRC-32) holds, the header is
    the One Plus's, and its area table is what the writer puts there, each layer's largest 4-connected region."""
    files = sorted(Path(FOREIGN).glob("*.cxdlp"))
    assert files, f"no .cxdlp file in {FOREIGN}"
    for path in files:
        f = read_cxdlp(path)
        assert f.version in (2, 3) and f.model.startswith("CL") and f.n_layers > 0
        preset = next(p for p in PRINTERS.values() if p.machine == f.model)
        assert (f.res_x, f.res_y) == tuple(preset.resolution)
        assert f.display_mm == pytest.approx((preset.resolution[0] * preset.pixel, preset.resolution[1] * preset.pixel))
        assert f.layer_height > 0 and f.settings["exposure_tenths"] > 0
        for i in (0, f.n_layers // 2, f.n_layers - 1):
            img = f.layer_image(i)
            assert f.layers[i]["area"] == f.areas[i] == largest_4(img), (path.name, i)
            lines = f.layers[i]["lines"]
            assert np.array_equal(lines, brute_lines(img)) or np.array_equal(
                lines[np.lexsort((lines[:, 1], lines[:, 0]))], lines), (path.name, i)


def test_a_second_lift_stage_at_the_first_ones_speed_is_one_longer_lift(tmp_path, torus):
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05)
    s = PrintSettings(transition_layers=0, wait_before_cure=1.0, lift_height=4.0, lift_speed=120.0, lift_height2=3.0,
                      lift_speed2=120.0, bottom_lift_height=6.0, bottom_lift_speed=60.0, bottom_lift_height2=0.0,
                      retract_speed=120.0)
    out = tmp_path / "two.cxdlp"
    write_target(iter_tiles(torus, spec, backend="numpy"), target(out, torus, spec,
                                                                  ResinOptions(printer=preset_file(tmp_path)), s))
    f = read_cxdlp(out)
    assert (f.settings["lift_height"], f.settings["lift_speed"], f.settings["bottom_lift_height"]) == (7, 2, 6)
