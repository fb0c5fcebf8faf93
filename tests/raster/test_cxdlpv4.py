"""Creality Halot Mage ``.cxdlpv4`` files (gpuslice.raster.cxdlpv4), read back with the tests' own reader
(cxdlpv4_reader.py): every layer of a torus and of real meshes against the rasteriser after the 7-bit quantisation,
the header, settings, per-layer records, previews and checksum, the refusals, and the command line."""

from __future__ import annotations

import datetime as dt
import hashlib
from pathlib import Path

import numpy as np
import pytest
from ctb_reader import canonical, reference_runs
from cxdlpv4_reader import read_cxdlpv4
from scipy import ndimage

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import PrintSettings, ResinOptions, iter_tiles, masks
from gpuslice.raster.cxdlpv4 import refuse_layers, refuse_settings, write_target
from gpuslice.raster.layers import iter_run_layers
from gpuslice.raster.outputs import ResinTarget, resin_format_for
from gpuslice.raster.printers import PRINTERS
from gpuslice.raster.settings import layer_table, print_time_s

NOW = dt.datetime(2026, 11, 25, 12, 0)
SETTINGS = PrintSettings(bottom_layers=2, bottom_exposure=25.0, exposure=2.4, transition_layers=3, lift_height=4.0,
                         lift_speed=90.0, lift_height2=2.0, lift_speed2=240.0, bottom_lift_height=6.0,
                         bottom_lift_speed=60.0, retract_speed=180.0, retract_height2=1.5, retract_speed2=60.0,
                         wait_before_cure=1.5, wait_after_cure=0.5, wait_after_lift=0.25, light_pwm=200,
                         bottom_light_pwm=250)


def preset_file(tmp_path, code: str = "CL-103", mirror: bool = True) -> str:
    p = tmp_path / "mage.toml"
    p.write_text(f'name = "test-mage"\nresolution = [1200, 900]\npixel = 0.05\nbuild_height = 230\n'
                 f'mirror_x = {str(mirror).lower()}\nformats = ["cxdlpv4"]\nmachine = "{code}"\n')
    return str(p)


def target(path, res, options, settings=SETTINGS, gamma: float = 1.0) -> ResinTarget:
    spec = options.spec(gamma=gamma)
    return ResinTarget(Path(path), spec, options, res, "part", settings=settings, now=NOW, workers=2)


@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=0.5, backend="numpy")


def largest_4(img: np.ndarray) -> int:
    lab, n = ndimage.label(img > 0)  # (4-connected: scipy's default structure)
    return int(np.bincount(lab.ravel())[1:].max()) if n else 0


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_torus_every_layer_header_settings_and_checksum(tmp_path, torus, gamma):
    opts = ResinOptions(printer=preset_file(tmp_path))
    out = tmp_path / "part.cxdlpv4"
    t = target(out, torus, opts, gamma=gamma)
    stats = write_target(iter_tiles(torus, t.spec, backend="numpy"), t)
    f = read_cxdlpv4(out)  # (checks the magic and the checksum)
    n = torus.n_layers
    h, p, s = f.header, f.params, f.slicer
    assert stats["layers"] == n == f.n_layers == h["layer_count"] == 20 and f.version == 4 == stats["format_version"]
    assert (f.model, h["res_x"], h["res_y"], h["projector"], h["key"]) == ("CL-103", 1200, 900, 1, 0)
    assert (h["bed_x"], h["bed_y"], h["bed_z"], h["layer_height"]) == pytest.approx((60.0, 45.0, 230.0, 0.5))
    assert h["print_height"] == pytest.approx(10.0) and h["bottom_layers"] == p["bottom_layers"] == 2
    # the anti-aliasing level in the slicer info; the header's level count stays 1 (UVtools' writer leaves it so)
    assert (h["aa_level"], s["aa_level"], h["pwm"], h["bottom_pwm"]) == (1, 8 if gamma else 1, 200, 250)
    assert h["print_time"] == round(print_time_s(SETTINGS, n))
    # the print parameters: lift totals (both stages), speeds in mm/min, no light-off delay (the rests have fields)
    assert (p["bottom_lift_height"], p["bottom_lift_speed"], p["lift_height"], p["lift_speed"], p["retract_speed"]) \
        == pytest.approx((8.0, 60.0, 6.0, 90.0, 180.0))
    assert (p["exposure"], p["bottom_exposure"], p["light_off"], p["bottom_light_off"]) == pytest.approx(
        (2.4, 25.0, 0.0, 0.0))
    assert p["volume_ml"] == pytest.approx(stats["resin_ml"], rel=1e-6) and stats["resin_ml"] > 0
    assert (s["lift_height2"], s["lift_speed2"], s["bottom_lift_height2"], s["bottom_lift_speed2"]) == (2, 240, 2, 240)
    assert (s["retract_height2"], s["retract_speed2"]) == (1.5, 60.0)
    assert (s["rest_after_retract"], s["rest_before_lift"], s["rest_after_lift"], s["rest_after_lift2"]) == (
        1.5, 0.5, 0.25, 0.25)
    assert (s["exposure"], s["bottom_exposure"]) == pytest.approx((2.4, 25.0))
    assert (s["transition_layers"], s["per_layer"], s["software"]) == (3, 0, 0)
    assert s["minutes"] == int((NOW - dt.datetime(1970, 1, 1)).total_seconds() // 60)
    # per layer: z (the layer's top), the exposure ramp, each layer's own record
    table = layer_table(SETTINGS, n)
    ref = masks(torus, t.spec, backend="numpy")
    for i, layer in enumerate(f.layers):
        assert layer["z"] == pytest.approx(0.5 * (i + 1)) and layer["exposure"] == pytest.approx(table["exposure"][i])
        ex = layer["ex"]
        assert (ex["lift_height"], ex["lift_speed"], ex["retract_speed"], ex["pwm"]) == pytest.approx(
            (table["lift_height"][i] + table["lift_height2"][i], table["lift_speed"][i], 180.0,
             250.0 if i < 2 else 200.0))
        assert (ex["rest_after_retract"], ex["rest_before_lift"], ex["rest_after_lift"]) == (1.5, 0.5, 0.25)
        img = f.layer_image(i)
        q = ref[i] >> 1
        assert np.array_equal(img, np.where(q == 0, 0, (q << 1) | 1)), i  # 7 bits a pixel
        assert layer["largest_area"] == round(largest_4(img) * 0.05 * 0.05 * 1000), i
    assert f.layers[2]["exposure"] > 2.4 + 1e-3 and f.layers[5]["exposure"] == pytest.approx(2.4)  # the ramp
    small, large = f.previews
    assert small.shape == (120, 120, 3) and large.shape == (300, 300, 3)
    part = large[..., 0].astype(int) > large[..., 2].astype(int) + 64  # orange part on a dark background
    assert part.mean() > 0.2 and not part[150, 150] and part[150].any()  # the hole


def test_runs_and_tiles_write_the_same_file(tmp_path, torus, device):
    opts = ResinOptions(printer=preset_file(tmp_path))
    a, b = tmp_path / "a.cxdlpv4", tmp_path / "b.cxdlpv4"
    ta, tb = target(a, torus, opts), target(b, torus, opts)
    write_target(iter_tiles(torus, ta.spec, backend="opencl", device=device), ta)
    write_target(iter_run_layers(torus, tb.spec, device=device), tb)
    assert a.read_bytes() == b.read_bytes()


def test_bottom_values_only_per_layer_records_hold_are_refused_unless_per_layer(tmp_path, torus):
    opts = ResinOptions(printer=preset_file(tmp_path))
    for change, flag in (({"bottom_retract_speed": 120.0}, "--retract-speed"),
                         ({"bottom_wait_before_cure": 3.0}, "--wait-before-cure"),
                         ({"bottom_wait_after_lift": 1.0}, "--wait-after-lift"),
                         ({"bottom_retract_height2": 0.5}, "--retract-height2")):
        s = PrintSettings(**{**SETTINGS.__dict__, **change})
        with pytest.raises(ParameterError, match=f"x.cxdlpv4: a .cxdlpv4 file holds one {flag} for bottom and normal "
                                                 "layers unless per-layer settings are on"):
            write_target(iter([]), target(tmp_path / "x.cxdlpv4", torus, opts, s))
        per_layer = PrintSettings(**{**SETTINGS.__dict__, **change, "per_layer_settings": True})
        refuse_layers(tmp_path / "x.cxdlpv4", per_layer, torus.thickness)  # (held: per-layer records)
        refuse_settings(tmp_path / "x.cxdlpv4", "cxdlpv4", opts, s)  # (the layers are another check's)
        refuse_layers(tmp_path / "x.cxdlpv4", s, np.array([0.5, 1.0]))  # (several thicknesses: the switch is on)
    for options in (ResinOptions(), ResinOptions(printer="generic-4k")):
        with pytest.raises(ParameterError, match="x.cxdlpv4: a .cxdlpv4 file carries its printer's model code"):
            refuse_settings(tmp_path / "x.cxdlpv4", "cxdlpv4", options, SETTINGS)
    assert not (tmp_path / "x.cxdlpv4").exists()


def test_bottom_values_of_layers_of_several_thicknesses_are_held(tmp_path):
    """A thicker first layer turns the per-layer switch on by itself: the bottom layers' own values are written
    (they were refused, asking for --per-layer-settings, which changed nothing in the file)."""
    res = slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 48, 24)), thickness=0.5, first_layer=1.0,
                     backend="numpy")
    s = PrintSettings(**{**SETTINGS.__dict__, "bottom_retract_speed": 120.0, "bottom_wait_before_cure": 3.0})
    out = tmp_path / "v.cxdlpv4"
    opts = ResinOptions(printer=preset_file(tmp_path))
    write_target(iter_tiles(res, opts.spec(), backend="numpy"), target(out, res, opts, s))
    got = read_cxdlpv4(out)
    assert got.slicer["per_layer"] == 1
    explicit = tmp_path / "e.cxdlpv4"
    s_on = PrintSettings(**{**s.__dict__, "per_layer_settings": True})
    write_target(iter_tiles(res, opts.spec(), backend="numpy"), target(explicit, res, opts, s_on))
    assert explicit.read_bytes() == out.read_bytes()


def test_per_layer_settings_flag_and_each_bottom_layers_own_values(tmp_path, torus):
    s = PrintSettings(**{**SETTINGS.__dict__, "bottom_retract_speed": 120.0, "bottom_wait_before_cure": 3.0,
                         "per_layer_settings": True})
    out = tmp_path / "p.cxdlpv4"
    write_target(iter_tiles(torus, ResinOptions(printer=preset_file(tmp_path)).spec(), backend="numpy"),
                 target(out, torus, ResinOptions(printer=preset_file(tmp_path)), s))
    f = read_cxdlpv4(out)
    assert f.slicer["per_layer"] == 1
    ex = [layer["ex"] for layer in f.layers]
    assert [e["retract_speed"] for e in ex[:3]] == [120.0, 120.0, 180.0]
    assert [e["rest_after_retract"] for e in ex[:3]] == [3.0, 3.0, 1.5]


def test_layers_of_several_thicknesses_set_the_per_layer_flag_and_a_y_mirror_the_projector(tmp_path):
    """Adaptive layers: each layer's z is its own, which the printer follows with the per-layer flag set (as UVtools
    sets it); a display mirrored in y is marked mirrored too."""
    th = np.tile([0.2, 0.4], 26)
    top = np.cumsum(th)
    res = slice_mesh(mesh_from_triangles(shapes.icosphere(8.0, 3)), z=top - th / 2, layer_thickness=th,
                     backend="numpy")
    th = np.asarray(res.thickness)
    assert np.ptp(th) > 0.1
    p = tmp_path / "m.toml"
    p.write_text('name = "m"\nresolution = [400, 400]\npixel = 0.05\nbuild_height = 100\nmirror_y = true\n'
                 'machine = "CL-103"\n')
    opts = ResinOptions(printer=str(p))
    t = target(tmp_path / "a.cxdlpv4", res, opts)
    write_target(iter_tiles(res, t.spec, backend="numpy"), t)
    f = read_cxdlpv4(tmp_path / "a.cxdlpv4")
    assert f.slicer["per_layer"] == 1 and f.header["projector"] == 1
    assert [layer["z"] for layer in f.layers] == pytest.approx(np.cumsum(th), abs=1e-5)


def test_registry_and_presets():
    fmt = resin_format_for("x.CXDLPV4")
    assert fmt.name == "cxdlpv4" and fmt.writer == "cxdlpv4:write_target"
    mages = [p for p in PRINTERS.values() if "cxdlpv4" in p.formats]
    assert sorted(p.name for p in mages) == ["creality-halot-mage", "creality-halot-mage-pro"]
    assert sorted(p.machine for p in mages) == ["CL-103", "CL-103L"]
    for p in mages:  # their default settings are ones the format holds
        opts = ResinOptions(printer=p.name)
        refuse_settings(Path("x.cxdlpv4"), "cxdlpv4", opts, opts.settings(), opts.spec())


# ---- real meshes ----------------------------------------------------------------------------------------------------
def _digest(runs) -> str:
    return hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in runs)).hexdigest()


@pytest.mark.parametrize(("name", "fit", "gamma"), [("benchy", 60.0, 1.0), ("nefertiti", 80.0, 0.0)])
def test_shared_meshes_every_layer_on_the_mage(tmp_path, shared_results, device, name, fit, gamma):
    """benchy (60 mm) and nefertiti (80 mm) at 0.05 mm on the Halot Mage's 7680x4320 display (mirrored in x): every
    layer decoded from the file equals the rasteriser's runs after the 7-bit quantisation (a digest per layer), and
    three layers pixel for pixel against what masks() draws."""
    res, bounds = shared_results(name, fit)
    opts = ResinOptions(printer="creality-halot-mage")
    spec = opts.spec(gamma=gamma)
    cols = spec.shape[1]
    expected = []

    def layers():
        for item in iter_run_layers(res, spec, device=device, bounds=bounds):
            r, j = item.runs, item.j
            a, b = int(r.layer_offsets[j]), int(r.layer_offsets[j + 1])
            g7 = r.grey[a:b] >> 1
            keep = g7 > 0
            start = r.row[a:b].astype(np.int64) * cols + r.x[a:b]
            expected.append(_digest(canonical(start[keep], r.length[a:b][keep], (g7[keep] << 1) | 1)))
            yield item

    out = tmp_path / f"{name}.cxdlpv4"
    t = ResinTarget(out, spec, opts, res, name, settings=opts.settings(), now=NOW, workers=2, device=device)
    write_target(layers(), t)
    f = read_cxdlpv4(out)
    assert f.model == "CL-103L" and f.header["projector"] == 1 and f.n_layers == res.n_layers == len(expected)
    bad = [i for i in range(res.n_layers) if _digest(f.runs(i)) != expected[i]]
    assert not bad, f"layers differ: {bad[:10]}"
    some = [0, res.n_layers // 2, res.n_layers - 1]
    for tile in iter_tiles(res, spec, layers=some, bounds=bounds, device=device):
        want = reference_runs(tile.data, cols, tile.row0, tile.col0)
        assert [np.array_equal(a, b) for a, b in zip(f.runs(tile.index), want, strict=True)] == [True] * 3


def test_cli_writes_a_mage_file_and_refuses_without_a_preset(tmp_path, device, capsys):
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    base = ["raster", str(stl), "-t", "0.5", "--no-progress"]
    assert main([*base, "--printer", "creality-halot-mage-pro", "--exposure", "2.2", "-o",
                 str(tmp_path / "a.cxdlpv4")]) == 0
    assert "wrote" in capsys.readouterr().out
    f = read_cxdlpv4(tmp_path / "a.cxdlpv4")
    assert (f.model, f.header["res_x"], f.header["res_y"], f.n_layers) == ("CL-103", 7680, 4320, 20)
    assert f.params["exposure"] == pytest.approx(2.2)
    assert main([*base, "-o", str(tmp_path / "b.cxdlpv4")]) == 2
    err = capsys.readouterr().err
    assert "b.cxdlpv4: a .cxdlpv4 file carries its printer's model code" in err and err.count("\n") == 1
    assert main([*base, "--printer", "creality-halot-one", "-o", str(tmp_path / "c.cxdlpv4")]) == 2
    assert "c.cxdlpv4" in capsys.readouterr().err  # (the Halot One reads .cxdlp, not v4)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.cxdlpv4", "torus.stl"]


def test_bottom_values_of_uniform_layers_are_refused_before_slicing(tmp_path, monkeypatch, capsys):
    """Uniform layers (no --adaptive, no other --first-layer) keep the per-layer switch off: the refusal comes
    before the slicing, as it did before the writer learnt to take layers of several thicknesses (a review)."""
    import gpuslice.pipeline

    stl = tmp_path / "cube.stl"
    assert main(["shape", "cube", "-o", str(stl)]) == 0

    def no_slicing(*args, **kwargs):
        raise AssertionError("sliced before the refusal")

    monkeypatch.setattr(gpuslice.pipeline, "_slice", no_slicing)
    capsys.readouterr()
    out = tmp_path / "x.cxdlpv4"
    assert main(["raster", str(stl), "--printer", preset_file(tmp_path), "-t", "0.5", "-q", "--no-progress",
                 "--bottom-retract-speed", "120", "-o", str(out)]) == 2
    assert "holds one --retract-speed for bottom and normal layers" in capsys.readouterr().err
    assert not out.exists()
