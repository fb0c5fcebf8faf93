"""Elegoo GOO files (issue 19): the writer (gpuslice/raster/goo.py) read back by a separate decoder written from
Elegoo's spec (tests/raster/goo_reader.py): chunk bytes against the spec's own examples, header fields and the
per-layer table, every layer's pixels against masks() (small displays, and the 12K Saturn 3 Ultra preset with
benchy and nefertiti), atomic and reproducible files, the command line, and .prz."""

from __future__ import annotations

import datetime as dt
import hashlib
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import load_mesh, shapes
from gpuslice.raster import PrintSettings, RasterSpec, ResinOptions, iter_tiles, masks, with_printer
from gpuslice.raster.goo import HEADER_SIZE, MAX_RUN, encode_runs, encode_segments, write_goo
from gpuslice.raster.layers import batch_image_segments, image_segments, iter_run_layers
from gpuslice.raster.outputs import ResinTarget
from gpuslice.raster.settings import layer_table, print_time_s, resin_ml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from goo_reader import (  # noqa: E402
    ENDING,
    canonical_runs,
    decode_runs,
    layer_mask,
    layer_runs,
    read_goo,
)
from run_images import image_runs, runs_of  # noqa: E402

pytest.importorskip("PIL.Image")

NOW = dt.datetime(2024, 1, 2, 3, 4, 5)
SATURN = "elegoo-saturn-3-ultra"


def _checksum(body: bytes) -> int:
    return ~sum(body) & 0xFF


# ---- the chunk encoding ------------------------------------------------------------------------------------------
def test_chunks_match_the_spec_examples():
    """The spec's worked examples: 0b00111111 0x55 0x56 0x57 is 0x555657F blank pixels, 0b01110101 0xAA 0xBB 0xCC
    0x15 is 0xBBCC155 pixels of grey 0xAA, 0b00000101 is 5 blank pixels; data = 0x55, chunks, ~sum."""
    body = bytes([0b00111111, 0x55, 0x56, 0x57])
    assert encode_runs([], [], [], 0x555657F) == b"\x55" + body + bytes([_checksum(body)])
    body = bytes([0b01110101, 0xAA, 0xBB, 0xCC, 0x15])
    assert encode_runs([0], [0xBBCC155], [0xAA], 0xBBCC155) == b"\x55" + body + bytes([_checksum(body)])
    assert encode_runs([], [], [], 5) == bytes([0x55, 0b00000101, _checksum(b"\x05")])
    # 16 blank (12-bit length: 0x10 then 16 >> 4), 5 white (0xC5), 1 of grey 0x80 (0x41 0x80), 2 blank to the end
    body = bytes([0x10, 0x01, 0xC5, 0x41, 0x80, 0x02])
    assert encode_runs([16, 21], [5, 1], [255, 0x80], 24) == b"\x55" + body + bytes([_checksum(body)])


def test_random_images_round_trip():
    rng = np.random.default_rng(19)
    for h, w in ((1, 1), (3, 17), (37, 53), (64, 300)):
        img = rng.choice(np.array([0, 0, 0, 255, 255, 1, 17, 128, 254], np.uint8), size=(h, w))
        img[rng.random((h, w)) < 0.3] = 0
        img[h // 2] = 255  # a whole row: touches the next row's run when that starts at column 0
        data = encode_runs(*image_runs(img), h * w)
        length, grey = decode_runs(np.frombuffer(data, np.uint8), h * w)
        assert np.array_equal(np.repeat(grey, length).reshape(h, w), img)
    blank = encode_runs(*image_runs(np.zeros((4, 4), np.uint8)), 16)
    assert blank == bytes([0x55, 0x10, 0x01, _checksum(b"\x10\x01")])


def test_images_encoded_together_equal_one_by_one():
    """Several layers encoded in one set of numpy passes (the writer's groups) give each layer's own bytes: blank
    layers, layers full to both ends (a run ending an image never joins the next image's first run), touching runs
    of one grey across a row end (joined), and blank gaps longer than one chunk holds."""
    rng = np.random.default_rng(7)
    h, w = 9, 23
    imgs = []
    for k in range(12):
        img = rng.choice(np.array([0, 0, 255, 255, 3, 128], np.uint8), size=(h, w))
        img[rng.random((h, w)) < 0.4 * (k % 3)] = 0
        imgs.append(img)
    imgs[2][:] = 0
    imgs[5][:] = 255
    imgs[6][:] = 255
    imgs[7][0, 0] = imgs[7][-1, -1] = 255
    runs = [image_runs(img) for img in imgs]
    offsets = np.concatenate(([0], np.cumsum([r[0].size for r in runs])))
    start, length, grey = (np.concatenate([r[i] for r in runs]) for i in range(3))
    n, v, seg = batch_image_segments(start, length, grey, offsets, h * w)
    for k, r in enumerate(runs):
        n1, v1 = image_segments(*r, h * w)
        assert np.array_equal(n[seg[k] : seg[k + 1]], n1) and np.array_equal(v[seg[k] : seg[k + 1]], v1)
    assert encode_segments(n, v, seg) == [encode_runs(*r, h * w) for r in runs]
    big = 2 * MAX_RUN + 40  # blank gaps split into chunks, in every image of the group
    long_runs = [(np.array([5]), np.array([3]), np.array([255], np.uint8)), (np.zeros(0, np.int64),) * 2
                 + (np.zeros(0, np.uint8),), (np.array([MAX_RUN + 9]), np.array([1]), np.array([17], np.uint8))]
    offsets = np.concatenate(([0], np.cumsum([r[0].size for r in long_runs])))
    start, length, grey = (np.concatenate([r[i] for r in long_runs]) for i in range(3))
    assert encode_segments(*batch_image_segments(start, length, grey, offsets, big)) == [
        encode_runs(*r, big) for r in long_runs]


def test_run_lengths_at_every_width_and_long_gaps():
    """Lengths on both sides of 4, 12, 20 and 28 bits, and a blank tail longer than one chunk holds (split)."""
    lengths = np.array([15, 16, 4095, 4096, 0xFFFFF, 0x100000, MAX_RUN, 1, 2, 3])
    greys = np.array([255, 7, 255, 200, 255, 1, 255, 254, 255, 9], np.uint8)
    gaps = np.array([0, 1, 15, 16, 4095, 4096, 0x100000, 17, 1, 2])
    start = np.cumsum(gaps + np.concatenate(([0], lengths[:-1])))
    n_pixels = int(start[-1] + lengths[-1]) + 2 * MAX_RUN + 5
    length, grey = decode_runs(np.frombuffer(encode_runs(start, lengths, greys, n_pixels), np.uint8), n_pixels)
    assert length.max() <= MAX_RUN and length.sum() == n_pixels
    got = canonical_runs(np.cumsum(length) - length, length, grey)
    assert np.array_equal(got, canonical_runs(start, lengths, greys))


def test_reader_decodes_grey_differences():
    """The decoder also reads the difference chunks (type 2) other slicers write: the spec's four examples after a
    grey of 0x80: +1 once, +2 for 0xFF pixels, -1 once, -2 for 0xEE pixels."""
    body = bytes([0x41, 0x80, 0x81, 0x92, 0xFF, 0xA1, 0xB2, 0xEE])
    length, grey = decode_runs(np.frombuffer(b"\x55" + body + bytes([_checksum(body)]), np.uint8))
    assert length.tolist() == [1, 1, 0xFF, 1, 0xEE]
    assert grey.tolist() == [0x80, 0x81, 0x83, 0x82, 0x80]


# ---- small displays: header, table, pixels -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=0.5, backend="numpy")


SETTINGS = PrintSettings(bottom_layers=3, bottom_exposure=20.0, exposure=3.0, transition_layers=4, lift_height=4.0,
                         lift_speed=70.0, lift_height2=3.0, lift_speed2=210.0, retract_speed=220.0,
                         retract_height2=1.5, retract_speed2=60.0, bottom_lift_height=6.0, bottom_lift_speed=45.0,
                         wait_before_cure=1.25, wait_after_cure=0.5, wait_after_lift=0.75, light_pwm=200,
                         bottom_light_pwm=180, per_layer_settings=True, resin_density=1.25)


def _target(path, spec, res, settings=SETTINGS, options=None, now=NOW) -> ResinTarget:
    return ResinTarget(path=Path(path), spec=spec, options=options or ResinOptions(), result=res, name="torus",
                       now=now, workers=2, settings=settings)


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_header_table_and_pixels(tmp_path, torus, gamma):
    spec = RasterSpec(resolution=(900, 700), pixel=0.05, pixel_y=0.07, gamma=gamma)  # non-square pixels
    out = tmp_path / "t.goo"
    stats = write_goo(iter_tiles(torus, spec, backend="numpy"), _target(out, spec, torus))
    goo = read_goo(out)
    h, s, n = goo.header, SETTINGS, torus.n_layers
    assert stats["layers"] == n == h["total_layers"] == len(goo.layers) == 20 and stats["goo_bytes"] == goo.size
    assert (h["version"], h["layer_content_offset"], h["gray_scale_level"]) == ("V3.0", HEADER_SIZE, True)
    assert (h["software_info"], h["file_time"], h["profile_name"]) == ("gpuslice", "2024-01-02 03:04:05", "torus")
    assert (h["x_resolution"], h["y_resolution"], h["x_mirror"], h["y_mirror"]) == (900, 700, False, False)
    assert h["x_size"] == pytest.approx(45.0) and h["y_size"] == pytest.approx(49.0)
    assert h["z_size"] == pytest.approx(10.0)  # no preset: the part's height
    assert h["layer_thickness"] == pytest.approx(0.5) and h["anti_aliasing_level"] == (8 if gamma else 1)
    assert (h["exposure_time"], h["bottom_exposure_time"]) == (3.0, 20.0)
    assert (h["bottom_layers"], h["transition_layers"], h["advance_mode"]) == (3, 4, True)
    assert (h["bottom_light_pwm"], h["light_pwm"], h["exposure_delay_mode"], h["turn_off_time"]) == (180, 200, True, 0)
    assert h["printing_time"] == round(print_time_s(s, n))
    ml = resin_ml(torus.area, torus.thickness)
    assert h["total_volume"] == pytest.approx(ml * 1000, rel=1e-6)  # mm³
    assert h["total_weight"] == pytest.approx(ml * 1.25, rel=1e-6)  # g
    assert h["total_volume"] == pytest.approx(2 * np.pi**2 * 15 * 25, rel=0.02)  # the torus, V = 2π²Rr²
    # global settings: the bottom layers' and the normal layers' rows of the layer table
    t = layer_table(s, n)
    for prefix, row in (("bottom_", 0), ("", n - 1)):
        assert h[f"{prefix}lift_distance"] == pytest.approx(t["lift_height"][row])
        assert h[f"{prefix}lift_speed"] == pytest.approx(t["lift_speed"][row])
        assert h[f"{prefix}second_lift_distance"] == pytest.approx(t["lift_height2"][row])
        assert h[f"{prefix}second_lift_speed"] == pytest.approx(t["lift_speed2"][row])
        assert h[f"{prefix}retract_distance"] == pytest.approx(t["retract_height"][row])
        assert h[f"{prefix}retract_speed"] == pytest.approx(t["retract_speed"][row])
        assert h[f"{prefix}second_retract_distance"] == pytest.approx(t["retract_height2"][row])
        assert h[f"{prefix}second_retract_speed"] == pytest.approx(t["retract_speed2"][row])
        assert h[f"{prefix}before_lift_time"] == pytest.approx(t["wait_after_cure"][row])
        assert h[f"{prefix}after_lift_time"] == pytest.approx(t["wait_after_lift"][row])
        assert h[f"{prefix}after_retract_time"] == pytest.approx(t["wait_before_cure"][row])
    assert h["bottom_lift_distance"] == 6.0 and h["lift_distance"] == 4.0  # the two rows differ
    # each layer's definition: the table, row by row (the transition ramp included)
    d = {k: np.array([layer.definition[k] for layer in goo.layers]) for k in goo.layers[0].definition}
    pairs = {"layer_exposure_time": "exposure", "lift_distance": "lift_height", "lift_speed": "lift_speed",
             "second_lift_distance": "lift_height2", "second_lift_speed": "lift_speed2",
             "retract_distance": "retract_height", "retract_speed": "retract_speed",
             "second_retract_distance": "retract_height2", "second_retract_speed": "retract_speed2",
             "before_lift_time": "wait_after_cure", "after_lift_time": "wait_after_lift",
             "after_retract_time": "wait_before_cure", "light_pwm": "light_pwm"}
    for ours, theirs in pairs.items():
        assert np.allclose(d[ours], t[theirs], rtol=1e-6), ours
    e = d["layer_exposure_time"]
    assert e[0] == e[2] == 20.0 and e[7] == 3.0 and 20.0 > e[3] > e[4] > e[5] > e[6] > 3.0  # the ramp
    assert np.allclose(d["layer_position_z"], np.cumsum(torus.thickness)) and not d["pause_flag"].any()
    assert np.allclose(d["pause_position_z"], 10.0) and not d["layer_off_time"].any()
    # every layer's pixels, as masks() draws them: 8-bit greys stored as they are
    ref = masks(torus, spec, backend="numpy")
    for i in range(n):
        assert np.array_equal(layer_mask(goo, i), ref[i]), i
    if gamma == 0:
        assert set(np.unique(ref)) == {0, 255}
    else:
        assert len(np.unique(ref)) > 100
    # previews: the part, lit, on a dark ground
    small, big = goo.previews
    assert small.shape == (116, 116, 3) and big.shape == (290, 290, 3)
    assert big[145, 145].max() < 64 and big[145, 20:270].max() > 150  # the torus's hole in the middle, its ring


def test_portrait_mirrors_and_the_header_resolution(tmp_path, torus):
    """The header's resolution and size are the image's (the PNG's width and height): portrait swaps them."""
    spec = RasterSpec(resolution=(1000, 800), pixel=0.05, pixel_y=0.07, portrait=True, mirror_x=True, mirror_y=True)
    out = tmp_path / "p.goo"
    write_goo(iter_tiles(torus, spec, backend="numpy"), _target(out, spec, torus))
    h = read_goo(out).header
    assert (h["x_resolution"], h["y_resolution"], h["x_mirror"], h["y_mirror"]) == (800, 1000, True, True)
    assert h["x_size"] == pytest.approx(800 * 0.07) and h["y_size"] == pytest.approx(1000 * 0.05)
    goo = read_goo(out)
    ref = masks(torus, spec, backend="numpy", layers=[0, 10])
    assert np.array_equal(layer_mask(goo, 0), ref[0]) and np.array_equal(layer_mask(goo, 10), ref[1])


def test_written_atomically(tmp_path, torus):
    spec = RasterSpec(resolution=(900, 900), pixel=0.05)

    def broken():
        yield from iter_tiles(torus, spec, backend="numpy", layers=[0, 1])
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        write_goo(broken(), _target(tmp_path / "x.goo", spec, torus))
    with pytest.raises(ParameterError, match="expected 20 layers, got 2"):
        write_goo(iter_tiles(torus, spec, backend="numpy", layers=[0, 1]), _target(tmp_path / "y.goo", spec, torus))
    with pytest.raises(ParameterError, match="65535"):
        big = RasterSpec(resolution=(70000, 900), pixel=0.05)
        write_goo(iter(()), _target(tmp_path / "z.goo", big, torus))
    assert list(tmp_path.iterdir()) == []


def test_bytes_reproducible_with_a_fixed_date(tmp_path, torus):
    spec = RasterSpec(resolution=(900, 900), pixel=0.05)
    digests = []
    for k in range(2):
        out = tmp_path / f"a{k}.goo"
        write_goo(iter_tiles(torus, spec, backend="numpy"), _target(out, spec, torus))
        digests.append(hashlib.sha256(out.read_bytes()).hexdigest())
    assert digests[0] == digests[1]
    assert out.read_bytes().endswith(ENDING)


# ---- the command line and the 12K preset ---------------------------------------------------------------------------
def _torus_stl(tmp_path) -> Path:
    p = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), p)
    return p


def test_cli_saturn_goo_prz_reproducible(tmp_path, device, capsys, monkeypatch):
    """`raster -o part.goo --printer elegoo-saturn-3-ultra`: the preset's display, machine and settings in the
    header; the same bytes run after run with SOURCE_DATE_EPOCH; .prz is the same layout (the same bytes), refused
    for this printer (it reads goo and ctb)."""
    stl = _torus_stl(tmp_path)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")  # 2023-11-14 22:13:20 UTC
    args = ["raster", str(stl), "-t", "0.5", "--printer", SATURN, "--no-progress", "-q"]
    outs = [tmp_path / "a.goo", tmp_path / "b.goo"]
    for out in outs:
        assert main([*args, "-o", str(out)]) == 0
    assert outs[0].read_bytes() == outs[1].read_bytes()
    capsys.readouterr()
    assert main([*args, "-o", str(tmp_path / "c.prz")]) == 2
    assert "reads goo, ctb, not prz" in capsys.readouterr().err and not (tmp_path / "c.prz").exists()
    plain = ["raster", str(stl), "-t", "1", "--resolution", "900x900", "--no-progress", "-q"]
    assert main([*plain, "-o", str(tmp_path / "d.goo")]) == 0 and main([*plain, "-o", str(tmp_path / "d.prz")]) == 0
    assert (tmp_path / "d.goo").read_bytes() == (tmp_path / "d.prz").read_bytes()
    goo = read_goo(outs[0])
    h = goo.header
    spec = with_printer(SATURN)
    assert (h["x_resolution"], h["y_resolution"]) == spec.png_size == (11520, 5120)
    assert h["x_size"] == pytest.approx(218.88) and h["y_size"] == pytest.approx(122.88)
    assert h["z_size"] == pytest.approx(260.0) and h["printer_name"] == "Saturn 3 Ultra"
    settings = ResinOptions(printer=SATURN).settings()
    assert (h["bottom_layers"], h["exposure_time"], h["bottom_exposure_time"]) == (
        settings.bottom_layers, settings.exposure, settings.bottom_exposure)
    assert h["file_time"] == "2023-11-14 22:13:20" and h["total_layers"] == len(goo.layers) == 20
    mesh = load_mesh(str(stl))
    res = slice_mesh(mesh, thickness=0.5)
    b = mesh.bounds
    ref = masks(res, spec, layers=[10], bounds=(b[0, 0], b[0, 1], b[1, 0], b[1, 1]))[0]
    assert np.array_equal(layer_mask(goo, 10), ref) and ref.max() == 255


def test_cli_errors_leave_nothing(tmp_path, device, capsys):
    stl = _torus_stl(tmp_path)
    args = ["raster", str(stl), "-t", "1", "--no-progress", "-q"]
    for extra, msg in ((["-o", str(tmp_path / "no" / "part.goo"), "--printer", SATURN], "does not exist"),
                       (["-o", str(tmp_path / "w.goo"), "--resolution", "70000x1000"], "65535")):
        assert main([*args, *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["torus.stl"]


# ---- shared meshes on the 12K Saturn 3 Ultra: every layer ----------------------------------------------------------
def _digest(runs: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(runs).tobytes()).hexdigest()


@pytest.mark.parametrize(("name", "fit"), [("benchy", 60.0), ("nefertiti", 80.0)])
@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_shared_meshes_every_layer_on_the_12k_preset(tmp_path, device, shared_results, name, fit, gamma):
    """Every layer decoded from the file equals the rasteriser's runs (what masks() draws), compared as canonical
    runs (a digest per layer, so that ~1000 layers of 59 M pixels take seconds), and two layers pixel for pixel."""
    res, bounds = shared_results(name, fit)
    spec = with_printer(SATURN, gamma=gamma)
    cols = spec.shape[1]
    expected = []

    def layers():  # the writer's input, with each layer's canonical runs noted on the way
        for item in iter_run_layers(res, spec, device=device, bounds=bounds):
            r, j = item.runs, item.j
            a, b = int(r.layer_offsets[j]), int(r.layer_offsets[j + 1])
            start = r.row[a:b].astype(np.int64) * cols + r.x[a:b]
            expected.append(_digest(canonical_runs(start, r.length[a:b], r.grey[a:b])))
            yield item

    out = tmp_path / f"{name}.goo"
    opts = ResinOptions(printer=SATURN)
    write_goo(layers(), _target(out, spec, res, settings=opts.settings(), options=opts))
    goo = read_goo(out)
    n_pixels = spec.shape[0] * spec.shape[1]
    got = [_digest(layer_runs(layer, n_pixels)) for layer in goo.layers]
    assert len(got) == len(expected) == res.n_layers > 900
    bad = [i for i in range(res.n_layers) if got[i] != expected[i]]
    assert not bad, f"layers differ: {bad[:10]}"
    k = [res.n_layers // 3, 2 * res.n_layers // 3]
    ref = masks(res, spec, layers=k, bounds=bounds, device=device)
    for i, m in zip(k, ref, strict=True):
        assert np.array_equal(layer_mask(goo, i), m) and m.max() == 255, i


def test_text_fields_are_cut_at_a_character_boundary():
    """A long non-ASCII name is cut to fit its field without splitting a UTF-8 character."""
    from gpuslice.raster.goo import _text

    for name in ("é" * 40, "a" + "€" * 40, "plain"):
        b = _text(name, 32)
        assert len(b) <= 31 and name.startswith(b.decode("utf-8"))  # decodes: no half character left
    assert len(_text("é" * 40, 32)) == 30 and len(_text("a" + "€" * 40, 32)) == 31


# ---- the encoding kernels (kernels/goo.cl) against their numpy twin ------------------------------------------------
def test_kernels_equal_the_twin_on_random_groups(device):
    """Groups of layers (any first entry, blank layers first, inside and last, full layers, lone pixels at both ends
    of the image, every grey): the kernels' bytes equal the numpy twin's, layer by layer, with no group left to it."""
    from gpuslice.raster.goo import GooEncoder, encode_batch

    enc = GooEncoder.of(device)
    rng = np.random.default_rng(20)
    h, w = 13, 41
    imgs = []
    for k in range(40):
        img = rng.choice(np.array([0, 0, 255, 255, 1, 2, 128, 254], np.uint8), size=(h, w))
        img[rng.random((h, w)) < 0.2 * (k % 5)] = 0
        img[:, ::7] = 0  # no row full to its end: rows never touch with one grey
        imgs.append(img)
    for k in (0, 9, 10, 39):
        imgs[k][:] = 0
    imgs[20][:] = 0
    imgs[20][0, 0] = imgs[20][-1, -1] = 255
    imgs[21][:] = 0
    imgs[21][:, 1:-1] = 200  # rows of one grey, never touching across a row end
    runs = runs_of(imgs)
    before = enc.fallbacks
    for a, b in ((0, 40), (0, 1), (3, 17), (9, 11), (20, 22), (39, 40), (5, 39)):
        got = encode_batch(runs, a, b, w, h * w, device=device)
        assert got == encode_batch(runs, a, b, w, h * w), (a, b)
        assert got == [encode_runs(*image_runs(imgs[k]), h * w) for k in range(a, b)]
    assert enc.fallbacks == before
    length, grey = decode_runs(np.frombuffer(encode_batch(runs, 21, 22, w, h * w, device=device)[0], np.uint8))
    assert np.array_equal(np.repeat(grey, length).reshape(h, w), imgs[21])


def test_kernels_write_every_length_width(device):
    """One long row: runs and blank gaps on both sides of 4, 12 and 20 bits of length, a run at pixel 0 and one
    ending the image (no tail): the kernels' bytes equal the twin's and decode to the runs."""
    from gpuslice.raster.goo import encode_batch
    from gpuslice.raster.runs import Runs

    lengths = np.array([15, 16, 4095, 4096, 0xFFFFF, 0x100000, 1, 2, 3, 17])
    greys = np.array([255, 7, 255, 200, 255, 1, 254, 255, 9, 255], np.uint8)
    gaps = np.array([0, 1, 15, 16, 4095, 4096, 0x100000, 0xFFFFF, 2, 5])
    start = np.cumsum(gaps + np.concatenate(([0], lengths[:-1])))
    cols = int(start[-1] + lengths[-1])
    runs = Runs(np.arange(1), np.array([0, lengths.size]), np.zeros(lengths.size, np.int32), start.astype(np.int32),
                lengths.astype(np.int32), greys, (1, cols))
    got = encode_batch(runs, 0, 1, cols, cols, device=device)
    assert got == encode_batch(runs, 0, 1, cols, cols)
    length, grey = decode_runs(np.frombuffer(got[0], np.uint8), cols)
    assert np.array_equal(canonical_runs(np.cumsum(length) - length, length, grey),
                          canonical_runs(start, lengths, greys))


def test_kernels_leave_touching_runs_to_the_twin(device):
    """A row full to its end and the next row starting with the same grey are one chunk in the twin's bytes: the
    kernels see it and hand the group to the twin (counted), so the bytes stay the twin's."""
    from gpuslice.raster.goo import GooEncoder, encode_batch

    enc = GooEncoder.of(device)
    img = np.zeros((4, 9), np.uint8)
    img[1, 3:] = 255
    img[2, :4] = 255
    runs = runs_of([img, np.zeros_like(img)])
    before = enc.fallbacks
    assert enc.encode(runs, 0, 2, 9, 36) is None and enc.fallbacks == before + 1
    got = encode_batch(runs, 0, 2, 9, 36, device=device)
    assert got == encode_batch(runs, 0, 2, 9, 36) and got[0] == encode_runs(*image_runs(img), 36)


def test_writer_with_the_kernels_writes_the_twins_file(tmp_path, torus, device):
    """The same GOO file, byte for byte, with the layers encoded on the device (the pipeline's default) and by numpy,
    at gamma 1 and 0."""
    for gamma in (1.0, 0.0):
        spec = RasterSpec(resolution=(900, 700), pixel=0.05, gamma=gamma)
        files = []
        for dev in (device, None):
            out = tmp_path / f"t{gamma:g}{dev is None}.goo"
            target = replace(_target(out, spec, torus), device=dev)
            write_goo(iter_run_layers(torus, spec, device=device, clip=True), target)
            files.append(out.read_bytes())
        assert files[0] == files[1]
