"""Chitubox CTB files, unencrypted v2-v4 (issue 19): the writer (gpuslice/raster/ctb.py) read back by a separate
decoder written from the format description (tests/raster/ctb_reader.py): the format's own byte examples, a real
Chitubox file (tests/data/ctb/pyramid.ctb), header fields and the per-layer table for each version, every layer's
pixels against masks() after the 7-bit quantisation (small displays, and the 12K Saturn 3 Ultra preset with benchy and
nefertiti), previews, atomic and reproducible files, the command line."""

from __future__ import annotations

import datetime as dt
import hashlib
import sys
from pathlib import Path

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import load_mesh, shapes
from gpuslice.raster import PrintSettings, RasterSpec, ResinOptions, iter_tiles, masks, with_printer
from gpuslice.raster.ctb import MAX_RUN, rgb15_rle, rle7, rle7_batch, write_target
from gpuslice.raster.layers import iter_run_layers
from gpuslice.raster.outputs import ResinTarget
from gpuslice.raster.settings import layer_table, print_time_s, resin_ml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ctb_reader import canonical, decode_rle7, read_ctb, reference_runs  # noqa: E402

pytest.importorskip("PIL.Image")

DATA = Path(__file__).resolve().parents[1] / "data" / "ctb"
NOW = dt.datetime(2024, 1, 2, 3, 4, 5)
SATURN = "elegoo-saturn-3-ultra"


def _q(grey) -> np.ndarray:
    """What a CTB reader gets back for 8-bit greys: 7 bits stored (g >> 1), expanded to (g7 << 1) | 1, 0 stays 0."""
    g7 = np.asarray(grey, np.uint8) >> 1
    return np.where(g7 == 0, 0, (g7 << 1) | 1).astype(np.uint8)


# ---- the encodings, against the format description's examples ---------------------------------------------------
def test_rle7_examples_from_the_format_description():
    """catibo: 0x7F is one pixel of 127; 0xFF 0x2A is 42 pixels of 127; 0xFF 0xEF 0xFF 0xFF 0xFF is 268,435,455."""
    assert rle7([0], [1], [255], 1) == b"\x7f"
    assert rle7([0], [42], [255], 42) == b"\xff\x2a"
    assert rle7([0], [MAX_RUN], [254], MAX_RUN) == b"\xff\xef\xff\xff\xff"
    assert MAX_RUN == 268_435_455
    assert rle7([], [], [], 5) == b"\x80\x05"  # 5 blank pixels: a run of 0
    assert rle7([2], [1], [1], 5) == b"\x80\x05"  # grey 1 is 0 in 7 bits: merged into the blank


def test_rle7_every_length_class_and_merging():
    """Runs on both sides of each length-byte boundary (2^7, 2^14, 2^21), greys that merge once quantised (2 and 3,
    254 and 255), grey 1 (→ blank) and a blank longer than one 28-bit run: decoded as masks() would be."""
    lengths = [1, 2, 127, 128, 16383, 16384, 2**21 - 1, 2**21, 5]
    greys = [255, 2, 3, 254, 255, 1, 77, 200, 201]
    start, pos = [], 10
    for n in lengths:
        start.append(pos)
        pos += n + (0 if n == 2 else 3)  # touching neighbours (2 then 3 merge), else a gap
    n_pixels = pos + 1000
    data = rle7(start, lengths, greys, n_pixels)
    value, length = decode_rle7(data, n_pixels)
    assert int(length.sum()) == n_pixels and not np.any(value[1:] == value[:-1])  # neighbours merged
    s = np.cumsum(length) - length
    keep = value > 0
    got = canonical(s[keep], length[keep], (value[keep] << 1) | 1)
    g = _q(greys)
    want = canonical(*(np.asarray(a)[g > 0] for a in (start, lengths, g)))
    for a, b in zip(got, want, strict=True):
        assert np.array_equal(a, b)
    big = 2 * MAX_RUN + 7  # an empty layer of a display larger than one run holds
    assert decode_rle7(rle7([], [], [], big), big)[1].tolist() == [MAX_RUN, MAX_RUN, 7]


def test_rle7_of_layers_together_equals_one_by_one():
    """The writer's groups of layers (one set of numpy passes) give each layer's own bytes: blank layers, full ones
    (a last run never merges with the next layer's first), grey 1 (blank once quantised) at both ends, a blank longer
    than one record; overlapping runs are refused as one by one."""
    rng = np.random.default_rng(3)
    n_pixels = 120
    layers = []
    for k in range(10):
        cut = np.sort(rng.choice(np.arange(1, n_pixels), size=2 * (k + 1), replace=False))
        start, end = cut[0::2], cut[1::2]
        layers.append((start, end - start, rng.choice(np.array([1, 2, 3, 200, 254, 255], np.uint8), start.size)))
    layers[3] = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8))
    layers[4] = layers[5] = (np.array([0]), np.array([n_pixels]), np.array([255], np.uint8))
    layers[6] = (np.array([0, n_pixels - 1]), np.array([1, 1]), np.array([1, 1], np.uint8))
    offsets = np.concatenate(([0], np.cumsum([x[0].size for x in layers])))
    start, length, grey = (np.concatenate([x[i] for x in layers]) for i in range(3))
    assert rle7_batch(start, length, grey, offsets, n_pixels) == [rle7(*x, n_pixels) for x in layers]
    big = 2 * MAX_RUN + 7
    assert rle7_batch(np.array([5]), np.array([2]), np.array([9], np.uint8), np.array([0, 0, 1]), big) == [
        rle7([], [], [], big), rle7([5], [2], [9], big)]
    with pytest.raises(ParameterError, match="overlap"):
        rle7_batch(np.array([0, 3, 4]), np.array([2, 5, 1]), np.full(3, 255, np.uint8), np.array([0, 1, 3]), 20)
    with pytest.raises(ParameterError, match="overlap"):
        rle7([0, 3], [5, 1], [255, 255], 20)


def test_rgb15_examples_from_the_format_description():
    """catibo: 0xFFDF is one white pixel (R 15-11, G 10-6, B 4-0, bit 5 the run flag); a flagged word is followed by
    0x3nnn, nnn more copies (so 0xFFFF 0x302A is 43 pixels, as Chitubox's files decode); at most 0xFFF in a run."""
    white = np.full((1, 1, 3), 255, np.uint8)
    assert rgb15_rle(white) == bytes.fromhex("dfff")
    assert rgb15_rle(np.full((1, 43, 3), 255, np.uint8)) == bytes.fromhex("ffff2a30")
    assert rgb15_rle(np.full((1, 2, 3), 255, np.uint8)) == bytes.fromhex("dfffdfff")  # a pair: two plain words
    rgb = np.zeros((2, 5000, 3), np.uint8)
    rgb[1, 100] = (8, 16, 248)  # r 1, g 2, b 31
    words = np.frombuffer(rgb15_rle(rgb), "<u2").tolist()
    # 5100 black pixels (4095 + 1005), the blue one, 4899 black (4095 + 804)
    assert words == [0x20, 0x3FFE, 0x20, 0x33EC, (1 << 11) | (2 << 6) | 31, 0x20, 0x3FFE, 0x20, 0x3323]


# ---- a CTB written by Chitubox -------------------------------------------------------------------------------------
def test_reads_a_chitubox_file_and_encodes_its_layers_and_previews_alike():
    """pyramid.ctb (Chitubox 1.7.0, Elegoo Mars, from luizribeiro/mariner, MIT): the decoder reads its header and
    every layer (each exactly 1440 x 2560 pixels, the key's XOR undone), a pyramid: square, centred, shrinking. Our
    RLE7 encoder gives Chitubox's bytes for its pixels except where Chitubox left two equal 7-bit neighbours
    unmerged, and our RGB15 encoder gives its previews' bytes exactly."""
    f = read_ctb(DATA / "pyramid.ctb")
    h = f.header
    assert (h["magic"], h["version"], f.machine, f.shape, h["layer_count"]) == (0x12FD0086, 3, "ELEGOO MARS",
                                                                               (2560, 1440), 50)
    assert h["bed_x"] == pytest.approx(68.04) and h["bed_y"] == pytest.approx(120.96) and h["key"] != 0
    assert h["layer_height"] == pytest.approx(0.05) and h["total_height"] == pytest.approx(2.5)
    assert [e["z"] for e in f.layers] == pytest.approx(0.05 * np.arange(1, 51))
    pairs = zip(f.layers_ex, f.layers, strict=True)
    assert all(ex["copy"] == e and ex["total_size"] == 84 + e["size"] for ex, e in pairs)
    widths, same = [], 0
    for i in range(50):
        img = f.image(i)
        rows, cols = np.nonzero(img)
        if rows.size:
            h_, w_ = np.ptp(rows) + 1, np.ptp(cols) + 1
            assert abs(h_ - w_) <= 2 and abs((rows.min() + rows.max()) / 2 - 1280) < 4, i  # a centred square
            widths.append(w_)
        start, length, grey = f.runs(i)
        theirs = f.layer_bytes(i)
        ours = rle7(start, length, grey, 1440 * 2560)
        value, _ = f.segments(i)
        same += ours == theirs
        assert ours == theirs or np.any(value[1:] == value[:-1]), i
    assert len(widths) >= 45 and widths[0] > 100 and all(a >= b for a, b in zip(widths, widths[1:], strict=False))
    assert same >= 45
    for at, p in zip((h["large_preview"], h["small_preview"]), f.previews, strict=True):
        off, size = np.frombuffer(f.data[at + 8 : at + 16], "<u4")
        assert rgb15_rle(p.rgb) == f.data[off : off + size]
    assert [(p.width, p.height) for p in f.previews] == [(400, 300), (200, 125)]


# ---- small displays: header, table, pixels -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=0.5, backend="numpy")


SETTINGS = PrintSettings(bottom_layers=3, bottom_exposure=20.0, exposure=3.0, transition_layers=4, lift_height=4.0,
                         lift_speed=60.0, lift_height2=3.0, lift_speed2=180.0, retract_speed=200.0,
                         retract_height2=1.5, retract_speed2=50.0, bottom_lift_height=6.0, bottom_lift_speed=40.0,
                         wait_before_cure=0.5, wait_after_cure=0.25, wait_after_lift=0.75, light_pwm=200,
                         bottom_light_pwm=250, resin_density=1.2)
#: the same for one-stage files (v2, v3): the second stages at the first's speeds, which one stage holds exactly
SETTINGS_ONE = SETTINGS.with_values({"lift_speed2": 60.0, "retract_speed2": 200.0, "bottom_lift_speed2": 40.0})


def _preset(tmp_path, version: int | None, **extra) -> str:
    """A printer preset file whose native format is CTB (``version``: its format_version)."""
    keys = {"name": '"ctb-test"', "title": '"CTB test printer"', "resolution": "[900, 700]", "pixel": "0.05",
            "pixel_y": "0.07", "build_height": "180", "formats": '["ctb"]', "machine": '"CTB Test"', **extra}
    if version is not None:
        keys["format_version"] = str(version)
    lines = [f"{k} = {v}" for k, v in keys.items()]
    p = tmp_path / f"ctb-test-{version}.toml"
    p.write_text("\n".join(lines) + "\n")
    return str(p)


def _target(path, spec, res, settings=SETTINGS_ONE, options=None, now=NOW) -> ResinTarget:
    return ResinTarget(path=Path(path), spec=spec, options=options or ResinOptions(), result=res, name="torus",
                       now=now, workers=2, settings=settings)


@pytest.mark.parametrize("version", [2, 3, 4])
def test_header_and_layer_table_per_version(tmp_path, torus, version):
    """Every field the writer sets, for each version: from the preset (version, machine, Z), the display, the print
    settings (two-stage lift and retract and the waits in v4, folded into the light-off delay in v2/v3), the
    per-layer table (z = each layer's top, the exposure ramp) and v3's per-layer records."""
    options = ResinOptions(printer=_preset(tmp_path, version))
    spec = options.spec(gamma=1.0)
    out = tmp_path / "t.ctb"
    s = SETTINGS if version == 4 else SETTINGS_ONE
    stats = write_target(iter_tiles(torus, spec, backend="numpy"), _target(out, spec, torus, s, options=options))
    f = read_ctb(out)
    h, p, si, n = f.header, f.params, f.slicer, torus.n_layers
    assert stats["layers"] == n == h["layer_count"] == 20 and stats["format_version"] == version
    assert stats["ctb_bytes"] == out.stat().st_size
    assert (h["magic"], h["version"]) == ((0x12FD0106 if version == 4 else 0x12FD0086), version)
    assert (h["res_x"], h["res_y"], h["key"], h["level_sets"], h["projector"]) == (900, 700, 0, 1, 0)
    assert (h["bed_x"], h["bed_y"], h["bed_z"]) == pytest.approx((45.0, 49.0, 180.0))
    assert h["total_height"] == pytest.approx(10.0) and h["layer_height"] == pytest.approx(0.5)
    assert (h["exposure"], h["bottom_exposure"], h["bottom_layers"]) == (3.0, 20.0, 3)
    assert (h["pwm"], h["bottom_pwm"]) == (200, 250) and h["print_time"] == round(print_time_s(s, n))
    ml = resin_ml(torus.area, torus.thickness)
    assert p["volume_ml"] == pytest.approx(ml, rel=1e-6) and p["weight_g"] == pytest.approx(1.2 * ml, rel=1e-6)
    assert p["volume_ml"] == pytest.approx(2 * np.pi**2 * 15 * 25 / 1000, rel=0.02)  # the torus, V = 2π²Rr²
    assert f.machine == "CTB Test" and si["machine_size"] == 8 and p["bottom_layers"] == 3
    assert (si["aa_level"], si["aa_flag"], si["per_layer"], si["transition_layers"]) == (8, 0x0F, 0, 4)
    assert si["minutes"] == int((NOW - dt.datetime(1970, 1, 1)).total_seconds()) // 60
    # lifts: v2/v3 one stage (the lift's total at the first speed), v4 the total and the second stage apart
    assert (p["lift_height"], p["bottom_lift_height"]) == (7.0, 9.0)  # 4 + 3, 6 + 3 (bottom: no own second stage)
    assert (p["lift_speed"], p["bottom_lift_speed"], p["retract_speed"]) == (60.0, 40.0, 200.0)
    # light-off: v4 keeps the waits apart; v2/v3 hold lift + retract time + the waits (s)
    waits = 0.5 + 0.25 + 0.75
    off = (0.0, 0.0) if version == 4 else (7 / 60 * 60 + 7 / 200 * 60 + waits, 9 / 40 * 60 + 9 / 200 * 60 + waits)
    assert (p["light_off"], p["bottom_light_off"], h["light_off"]) == pytest.approx((off[0], off[1], off[0]))
    if version == 4:
        v4 = f.v4
        assert (si["lift_height2"], si["lift_speed2"], si["bottom_lift_height2"]) == (3.0, 180.0, 3.0)
        assert (si["retract_height2"], si["retract_speed2"]) == (1.5, 50.0)
        assert (v4["rest_after_retract"], v4["rest_before_lift"], v4["rest_after_lift"]) == (0.5, 0.25, 0.75)
        assert (v4["bottom_retract_speed"], v4["bottom_retract_speed2"], v4["bottom_retract_height2"]) == (
            200.0, 50.0, 1.5)
        assert (v4["last_layer"], v4["four1"], v4["four2"], v4["disclaimer_size"]) == (n - 1, 4.0, 4.0, 0)
        assert si["v4_offset"] > h["slicer_offset"] and h["layer_table"] > si["v4_offset"]
    else:
        assert f.v4 is None and (si["lift_height2"], si["retract_height2"], si["v4_offset"]) == (0.0, 0.0, 0)
    # the layer table, row by row
    t = layer_table(s, n)
    z = np.array([e["z"] for e in f.layers])
    assert np.allclose(z, np.cumsum(torus.thickness)) and z[-1] == pytest.approx(10.0)
    e = np.array([x["exposure"] for x in f.layers])
    assert np.allclose(e, t["exposure"]) and e[0] == e[2] == 20.0 and 20.0 > e[3] > e[6] > e[7] == 3.0
    lo = np.array([x["light_off"] for x in f.layers])
    assert np.allclose(lo, [off[1]] * 3 + [off[0]] * (n - 3))
    assert all(x["table_size"] == (36 if version == 2 else 84) and x["page"] == 0 for x in f.layers)
    offsets = np.array([x["offset"] for x in f.layers])
    assert offsets[0] > h["layer_table"] + 36 * n - 1 and np.all(np.diff(offsets) > 0)
    if version >= 3:
        ex = f.layers_ex
        assert all(x["copy"] == y and x["total_size"] == 84 + y["size"] for x, y in zip(ex, f.layers, strict=True))
        col = {k: np.array([x[k] for x in ex]) for k in ex[0] if k != "copy"}
        assert np.allclose(col["lift_height"], t["lift_height"] + t["lift_height2"])
        assert np.allclose(col["lift_speed"], t["lift_speed"]) and np.allclose(col["pwm"], t["light_pwm"])
        assert np.allclose(col["retract_speed"], t["retract_speed"])
        two = version == 4
        for ours, theirs in (("lift_height2", "lift_height2"), ("lift_speed2", "lift_speed2"),
                             ("retract_height2", "retract_height2"), ("retract_speed2", "retract_speed2"),
                             ("rest_before_lift", "wait_after_cure"), ("rest_after_lift", "wait_after_lift"),
                             ("rest_after_retract", "wait_before_cure")):
            assert np.allclose(col[ours], t[theirs] if two else 0.0), ours
    # pixels: every layer (also checked on their own below)
    ref = masks(torus, spec, backend="numpy", layers=[0, 10])
    assert np.array_equal(f.image(0), _q(ref[0])) and np.array_equal(f.image(10), _q(ref[1]))


def test_version_default_switch_and_errors(tmp_path, torus):
    """No CTB preset: v3; a CTB preset without a version: v3; the per-layer switch sets its byte (0x10 x version);
    an unknown version and a non-ASCII machine name are refused, naming the file, and nothing is left."""
    spec = RasterSpec(resolution=(900, 700), pixel=0.05, gamma=0.0)
    out = tmp_path / "d.ctb"
    write_target(iter_tiles(torus, spec, backend="numpy", clip=True),
                 _target(out, spec, torus, settings=PrintSettings()))
    f = read_ctb(out)
    assert (f.header["version"], f.machine, f.slicer["aa_level"], f.slicer["aa_flag"]) == (3, "", 1, 0x07)
    assert f.header["bed_z"] == pytest.approx(10.0) and f.params["light_off"] == 0.0  # no preset: the part's height
    options = ResinOptions(printer=_preset(tmp_path, None))
    on = PrintSettings(per_layer_settings=True)
    write_target(iter_tiles(torus, spec, backend="numpy", clip=True),
                 _target(out, spec, torus, settings=on, options=options))
    assert (read_ctb(out).header["version"], read_ctb(out).slicer["per_layer"]) == (3, 0x30)
    # layers of two thicknesses: each layer's z is its own (the header has one layer height), so the byte is set too
    th = np.tile([0.25, 0.5], 14)
    varied = slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 48, 24)), z=np.cumsum(th) - th / 2,
                        layer_thickness=th, backend="numpy")
    write_target(iter_tiles(varied, spec, backend="numpy", clip=True),
                 _target(out, spec, varied, settings=PrintSettings(), options=options))
    f = read_ctb(out)
    assert f.slicer["per_layer"] == 0x30 and [e["z"] for e in f.layers] == pytest.approx(np.cumsum(th), abs=1e-5)
    options = ResinOptions(printer=_preset(tmp_path, 5))
    with pytest.raises(ParameterError, match=r"x\.ctb: CTB version 5 is not written"):
        write_target(iter_tiles(torus, spec, backend="numpy", clip=True),
                     _target(tmp_path / "x.ctb", spec, torus, options=options))
    options = ResinOptions(printer=_preset(tmp_path, 4, machine='"Märs"'))
    with pytest.raises(ParameterError, match="ASCII"):
        write_target(iter(()), _target(tmp_path / "x.ctb", spec, torus, options=options))
    assert not (tmp_path / "x.ctb").exists() and sorted(p.suffix for p in tmp_path.iterdir()) == [
        ".ctb", ".toml", ".toml", ".toml"]


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_every_layer_equals_the_masks_after_quantisation(tmp_path, torus, gamma, request):
    """Every layer's pixels, decoded, equal masks() with greys quantised to 7 bits: from tiles (numpy) and, where
    there is an OpenCL device, from the rasteriser's runs (the command line's path)."""
    spec = RasterSpec(resolution=(900, 700), pixel=0.05, pixel_y=0.07, gamma=gamma)
    ref = masks(torus, spec, backend="numpy")
    sources = {"tiles": (lambda: iter_tiles(torus, spec, backend="numpy"), ref)}
    try:  # the OpenCL masks: the runs' float32 arithmetic (a grey may differ by 1 from numpy's)
        device = request.getfixturevalue("device")
        sources["runs"] = (lambda: iter_run_layers(torus, spec, device=device), masks(torus, spec, device=device))
    except pytest.skip.Exception:
        pass
    for kind, (layers, expected) in sources.items():
        out = tmp_path / f"{kind}.ctb"
        write_target(layers(), _target(out, spec, torus))
        f = read_ctb(out)
        for i in range(torus.n_layers):
            assert np.array_equal(f.image(i), _q(expected[i])), (kind, i)
    greys = np.unique(ref)
    assert set(greys) == {0, 255} if gamma == 0 else len(greys) > 100
    assert set(np.unique(f.image(5))) <= set(_q(greys))


def test_portrait_mirror_and_previews(tmp_path, torus):
    """Portrait: the header's resolution and bed size are the image's (width x height); a mirror sets the projector
    type; the previews (400x300, 200x125) show the part on a dark ground, inside the region before the parameters."""
    spec = RasterSpec(resolution=(1000, 800), pixel=0.05, pixel_y=0.07, portrait=True, mirror_x=True)
    out = tmp_path / "p.ctb"
    write_target(iter_tiles(torus, spec, backend="numpy"), _target(out, spec, torus))
    f = read_ctb(out)
    h = f.header
    assert (h["res_x"], h["res_y"], h["projector"]) == (800, 1000, 1)
    assert (h["bed_x"], h["bed_y"]) == pytest.approx((800 * 0.07, 1000 * 0.05))
    ref = masks(torus, spec, backend="numpy", layers=[4])[0]
    assert np.array_equal(f.image(4), _q(ref)) and ref.max() == 255
    big, small = f.previews
    assert (big.width, big.height, small.width, small.height) == (400, 300, 200, 125)
    assert big.rgb[150, 200].max() < 64 and big.rgb[150, 20:380].max() > 150  # the torus's hole, its ring
    assert small.rgb[62, 100].max() < 64 and small.rgb[62].max() > 150
    assert h["large_preview"] == 112 and h["small_preview"] > h["large_preview"] and h["params_offset"] > (
        h["small_preview"] + 32 + 2 * small.words - 2)


def test_atomic_and_reproducible(tmp_path, torus):
    """A failing layer source or a wrong layer count leaves no file; the same date gives the same bytes, another
    date changes only the date's field."""
    spec = RasterSpec(resolution=(900, 900), pixel=0.05)

    def broken():
        yield from iter_tiles(torus, spec, backend="numpy", layers=[0, 1])
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        write_target(broken(), _target(tmp_path / "x.ctb", spec, torus))
    with pytest.raises(ParameterError, match="y.ctb: expected 20 layers, got 2"):
        write_target(iter_tiles(torus, spec, backend="numpy", layers=[0, 1]), _target(tmp_path / "y.ctb", spec,
                                                                                     torus))
    assert list(tmp_path.iterdir()) == []
    data = []
    for k, now in enumerate((NOW, NOW, NOW + dt.timedelta(days=1))):
        out = tmp_path / f"a{k}.ctb"
        write_target(iter_tiles(torus, spec, backend="numpy"), _target(out, spec, torus, now=now))
        data.append(out.read_bytes())
    assert data[0] == data[1] and len(data[2]) == len(data[0])
    diff = np.flatnonzero(np.frombuffer(data[0], np.uint8) != np.frombuffer(data[2], np.uint8))
    at = read_ctb(tmp_path / "a0.ctb").header["slicer_offset"] + 40  # the minutes field
    assert diff.size and diff.min() >= at and diff.max() < at + 4


# ---- the command line and the 12K preset ---------------------------------------------------------------------------
def test_cli_saturn_ctb_reproducible(tmp_path, device, monkeypatch):
    """`raster MODEL --printer elegoo-saturn-3-ultra -o part.ctb`: v3 (its native format is GOO), the preset's
    display, machine, mirror and settings; the same bytes run after run with SOURCE_DATE_EPOCH; pixels as masks()."""
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    outs = [tmp_path / "a.ctb", tmp_path / "b.ctb"]
    for out in outs:
        assert main(["raster", str(stl), "-t", "0.5", "--printer", SATURN, "--no-progress", "-q", "-o",
                     str(out)]) == 0
    assert outs[0].read_bytes() == outs[1].read_bytes()
    f = read_ctb(outs[0])
    h = f.header
    spec = with_printer(SATURN)
    settings = ResinOptions(printer=SATURN).settings()
    assert (h["version"], h["res_x"], h["res_y"], f.machine) == (3, 11520, 5120, "Saturn 3 Ultra")
    assert (h["bed_x"], h["bed_y"], h["bed_z"]) == pytest.approx((218.88, 122.88, 260.0))
    assert h["projector"] == int(spec.mirror_x or spec.mirror_y) and h["layer_count"] == 20
    assert (h["bottom_layers"], h["exposure"], h["bottom_exposure"]) == (
        settings.bottom_layers, settings.exposure, settings.bottom_exposure)
    assert f.slicer["minutes"] == 1700000000 // 60
    mesh = load_mesh(str(stl))
    b = mesh.bounds
    ref = masks(slice_mesh(mesh, thickness=0.5), spec, layers=[10], bounds=(b[0, 0], b[0, 1], b[1, 0], b[1, 1]))[0]
    assert np.array_equal(f.image(10), _q(ref)) and ref.max() == 255


def _digest(runs) -> str:
    return hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in runs)).hexdigest()


@pytest.mark.parametrize(("name", "fit", "gamma"), [("benchy", 60.0, 1.0), ("nefertiti", 80.0, 0.0)])
def test_shared_meshes_every_layer_on_the_12k_preset(tmp_path, device, shared_results, name, fit, gamma):
    """Benchy and nefertiti on the 12K Saturn 3 Ultra (19 x 24 um pixels): every layer decoded from the file equals
    the rasteriser's runs (what masks() draws) after quantisation, compared as canonical runs (a digest per layer:
    ~1000 layers of 59 M pixels in seconds), and three layers pixel for pixel against the tiles masks() draws."""
    res, bounds = shared_results(name, fit)
    spec = with_printer(SATURN, gamma=gamma)
    cols = spec.shape[1]
    expected = []

    def layers():  # the writer's input, each layer's quantised canonical runs noted on the way
        for item in iter_run_layers(res, spec, device=device, bounds=bounds):
            r, j = item.runs, item.j
            a, b = int(r.layer_offsets[j]), int(r.layer_offsets[j + 1])
            start = r.row[a:b].astype(np.int64) * cols + r.x[a:b]
            g = _q(r.grey[a:b])
            keep = g > 0
            expected.append(_digest(canonical(start[keep], r.length[a:b][keep], g[keep])))
            yield item

    out = tmp_path / f"{name}.ctb"
    opts = ResinOptions(printer=SATURN)
    write_target(layers(), _target(out, spec, res, settings=opts.settings(), options=opts))
    f = read_ctb(out)
    got = [_digest(f.runs(i)) for i in range(len(f.layers))]
    assert len(got) == len(expected) == res.n_layers > 900
    bad = [i for i in range(res.n_layers) if got[i] != expected[i]]
    assert not bad, f"layers differ: {bad[:10]}"
    k = [0, res.n_layers // 3, 2 * res.n_layers // 3]
    for tile in iter_tiles(res, spec, layers=k, bounds=bounds, device=device):  # what masks() draws, box only
        want = reference_runs(tile.data, cols, tile.row0, tile.col0)
        assert [np.array_equal(a, b) for a, b in zip(f.runs(tile.index), want, strict=True)] == [True] * 3
        assert tile.data.max() == 255


# ---- the encoding kernels (kernels/ctb.cl) against their numpy twin ------------------------------------------------
def _group_images(rng, h: int, w: int, count: int) -> list[np.ndarray]:
    """Layers with grey ramps (neighbours equal after quantisation: one record), greys 1 (blank after it), blank
    layers first, inside and last, and lone pixels at both ends of the image."""
    imgs = []
    for k in range(count):
        img = rng.choice(np.array([0, 0, 255, 255, 1, 2, 3, 128, 129, 254], np.uint8), size=(h, w))
        img[rng.random((h, w)) < 0.2 * (k % 5)] = 0
        imgs.append(img)
    for k in (0, 9, count - 1):
        imgs[k][:] = 0
    imgs[4][:] = 0
    imgs[4][0, 0] = imgs[4][-1, -1] = 255
    imgs[5][:] = 255  # whole rows: touching across row ends, one record
    imgs[6][:, :] = np.arange(w, dtype=np.uint8)[None, :] // 2 + 1  # ramps: pairs of greys, one value each
    return imgs


def test_kernels_equal_the_twin_on_random_groups(device):
    from gpuslice.raster.ctb import CtbEncoder, rle7_runs

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from run_images import image_runs, runs_of

    enc = CtbEncoder.of(device)
    rng = np.random.default_rng(21)
    h, w = 11, 37
    imgs = _group_images(rng, h, w, 30)
    runs = runs_of(imgs)
    before = enc.fallbacks
    for a, b in ((0, 30), (0, 1), (3, 17), (4, 7), (9, 11), (29, 30), (5, 29)):
        got = rle7_runs(runs, a, b, w, h * w, device=device)
        assert got == rle7_runs(runs, a, b, w, h * w), (a, b)
        assert got == [rle7(*image_runs(imgs[k]), h * w) for k in range(a, b)]
    assert enc.fallbacks == before
    value, length = decode_rle7(rle7_runs(runs, 6, 7, w, h * w, device=device)[0], h * w)
    assert np.array_equal(np.repeat(value, length).reshape(h, w), imgs[6] >> 1)


def test_kernels_every_record_length_and_long_merges(device):
    """Records of every length class (1, 2-127, to 2^14 - 1, to 2^21 - 1, more) from single runs and gaps, and a
    record merging more runs than a work-item looks ahead over (a ramp of 200 pixels of one value): left to the twin,
    counted, the bytes still the twin's."""
    from gpuslice.raster.ctb import CtbEncoder, rle7_runs
    from gpuslice.raster.runs import Runs

    enc = CtbEncoder.of(device)
    lengths = np.array([1, 2, 127, 128, 0x3FFF, 0x4000, 0x1FFFFF, 0x200000, 3, 1])
    greys = np.array([255, 7, 255, 200, 255, 9, 254, 255, 9, 255], np.uint8)
    gaps = np.array([0, 1, 1, 127, 128, 0x3FFF, 0x4000, 0x1FFFFF, 0x200000, 0])
    start = np.cumsum(gaps + np.concatenate(([0], lengths[:-1])))
    cols = int(start[-1] + lengths[-1])
    runs = Runs(np.arange(1), np.array([0, lengths.size]), np.zeros(lengths.size, np.int32), start.astype(np.int32),
                lengths.astype(np.int32), greys, (1, cols))
    before = enc.fallbacks
    got = rle7_runs(runs, 0, 1, cols, cols, device=device)
    assert got == rle7_runs(runs, 0, 1, cols, cols) and enc.fallbacks == before
    value, length = decode_rle7(got[0], cols)
    assert np.array_equal(np.repeat(value, length), np.repeat(np.insert(greys >> 1, np.arange(10), 0),
                                                              np.insert(lengths, np.arange(10), gaps)))
    ramp = np.zeros((2, 300), np.uint8)
    ramp[0, 50:250] = 100 + np.arange(200) % 2  # 200 one-pixel runs, all of value 50
    runs = Runs(np.arange(1), np.array([0, 200]), np.zeros(200, np.int32), np.arange(50, 250, dtype=np.int32),
                np.ones(200, np.int32), ramp[0, 50:250].copy(), ramp.shape)
    assert enc.encode(runs, 0, 1, 300, 600) is None and enc.fallbacks == before + 1
    assert rle7_runs(runs, 0, 1, 300, 600, device=device) == rle7_runs(runs, 0, 1, 300, 600)


def test_writer_with_the_kernels_writes_the_twins_file(tmp_path, torus, device):
    from dataclasses import replace

    for gamma in (1.0, 0.0):
        spec = RasterSpec(resolution=(900, 700), pixel=0.05, gamma=gamma)
        files = []
        for dev in (device, None):
            out = tmp_path / f"t{gamma:g}{dev is None}.ctb"
            write_target(iter_run_layers(torus, spec, device=device, clip=True), replace(_target(out, spec, torus),
                                                                                      device=dev))
            files.append(out.read_bytes())
        assert files[0] == files[1]
