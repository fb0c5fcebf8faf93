"""Anycubic Photon Workshop files (gpuslice.raster.photon), read back with the tests' own reader (photon_reader.py):
the PW0 codec against the documented 4-bit quantisation, every table of every version, the print settings, every
layer of real meshes on a 12K display against the rasteriser, the command line, reproducibility and errors."""

from __future__ import annotations

import hashlib
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from photon_reader import decode_pw0, read_photon
from run_images import quantised_runs

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import PrintSettings, RasterSpec, ResinOptions, Tile, iter_tiles, masks
from gpuslice.raster.layers import iter_run_layers, pixel_runs
from gpuslice.raster.outputs import RESIN_FORMATS, ResinTarget, resin_format_for
from gpuslice.raster.photon import MACHINES, encode_pw0, encode_pw0_batch, write_target
from gpuslice.raster.settings import layer_table, print_time_s, resin_ml

SPEC = RasterSpec(resolution=(1200, 900), pixel=0.05)  # 60 x 45 mm: the torus (40 mm) fits
SETTINGS = PrintSettings(bottom_layers=3, bottom_exposure=25.0, exposure=2.5, transition_layers=4, lift_height=6.0,
                         lift_speed=90.0, retract_speed=180.0, wait_before_cure=1.5, bottom_lift_height=8.0,
                         bottom_lift_speed=60.0, resin_density=1.25)


def q(grey: np.ndarray) -> np.ndarray:
    """The documented quantisation: 4 bits kept (grey >> 4), read back as 17 times that."""
    return (np.asarray(grey).astype(np.int64) >> 4) * 17


def target(path, res, spec=SPEC, settings=SETTINGS, options: ResinOptions | None = None) -> ResinTarget:
    return ResinTarget(Path(path), spec, options or ResinOptions(), res, "part", settings=settings)


@pytest.fixture(scope="module")
def torus():
    return slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 96, 48)), thickness=0.5, backend="numpy")


# ---- the PW0 codec ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_pw0_round_trip_random_layers(seed):
    """Random layers (long blank and full stretches, grey runs longer than 15, single pixels, rows touching) decode
    to the quantised greys exactly, with the records the format allows."""
    rng = np.random.default_rng(seed)
    h, w = 23, 6000
    img = np.zeros((h, w), np.uint8)
    for _ in range(60):
        r, c = rng.integers(h), rng.integers(w)
        img[r, c : c + rng.integers(1, 9000)] = rng.choice([255, 254, 240, 239, 128, 17, 16, 15, 1, 200])
    img[rng.integers(h), :] = 255  # a full row: runs touch across the row ends
    img[5, 100:200] = rng.integers(0, 256, 100)  # every grey
    cols = w + 7
    tile = Tile(0, 2, 3, img)
    data, lit, mid = encode_pw0(*pixel_runs(tile, cols), (h + 4) * cols)
    start, length, grey = decode_pw0(np.frombuffer(data, np.uint8), (h + 4) * cols)
    ref = np.zeros((h + 4, cols), np.int64)
    ref[2 : 2 + h, 3 : 3 + w] = q(img)
    got = np.zeros(ref.size, np.int64)
    for s, n, g in zip(start.tolist(), length.tolist(), grey.tolist(), strict=True):
        got[s : s + n] = g
    assert np.array_equal(got.reshape(ref.shape), ref)
    assert lit == np.count_nonzero(ref) and mid == bool(np.any((ref > 0) & (ref < 255)))
    assert len(data) <= 2 * ((h + 4) * cols // 4095 + 2 * len(start) + 2) + int(np.sum(length[grey % 255 > 0]))


def test_pw0_records_and_limits():
    n = 3 * 4095 + 10
    data, lit, mid = encode_pw0(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8), n)
    assert data == bytes.fromhex("0fff") * 3 + bytes([0x00, 10]) and lit == 0 and not mid  # blank: 12-bit counts
    data, lit, mid = encode_pw0(np.array([0, 40]), np.array([40, 5000]), np.array([0x95, 0xF3], np.uint8), 5040)
    assert data == bytes([0x9F, 0x9F, 0x9A, 0xFF, 0xFF]) + bytes([0xF0 | (905 >> 8), 905 & 0xFF])  # grey 9: 15+15+10
    assert lit == 5040 and mid
    data, _, _ = encode_pw0(np.array([3]), np.array([4]), np.array([7], np.uint8), 10)  # 7 >> 4 = 0: blank
    assert data == bytes([0x00, 10])
    with pytest.raises(ValueError, match="covers"):
        decode_pw0(np.frombuffer(bytes([0x00, 9]), np.uint8), 10)


def test_pw0_layers_together_equal_one_by_one():
    """The writer's groups (one set of numpy passes) give each layer's bytes, lit count and middle-grey flag, and the
    box of its lit pixels: blank layers, greys blank once quantised, full layers touching the next one."""
    rng = np.random.default_rng(11)
    cols, rows = 37, 5
    n_pixels = cols * rows
    layers = []
    for k in range(9):  # runs as the rasteriser gives them: never across a row end
        img = rng.choice(np.array([0, 3, 16, 128, 240, 255], np.uint8), size=(rows, cols))
        img[rng.random((rows, cols)) < 0.1 * k] = 0
        layers.append(pixel_runs(Tile(k, 0, 0, img), cols))
    layers[2] = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8))
    layers[3] = (np.array([4, 9]), np.array([2, 3]), np.array([7, 15], np.uint8))  # lit by nothing once quantised
    layers[4] = layers[5] = (np.array([0]), np.array([n_pixels]), np.array([255], np.uint8))
    offsets = np.concatenate(([0], np.cumsum([x[0].size for x in layers])))
    start, length, grey = (np.concatenate([x[i] for x in layers]) for i in range(3))
    data, lit, mid, box = encode_pw0_batch(start, length, grey, offsets, n_pixels, cols)
    for k, x in enumerate(layers):
        assert (data[k], int(lit[k]), bool(mid[k])) == encode_pw0(*x, n_pixels)
        img = np.zeros(n_pixels, np.uint8)
        for s0, n0, g0 in zip(*x, strict=True):
            img[s0 : s0 + n0] = g0 >> 4
        r, c = np.nonzero(img.reshape(rows, cols))
        want = (r.min(), c.min(), r.max(), c.max()) if r.size else (-1, -1, -1, -1)
        assert tuple(box[k]) == want


# ---- the tables ----------------------------------------------------------------------------------------------------
def check_layout(f, version: int) -> None:
    """The file mark's table count, each table where the mark says, the images contiguous up to the end."""
    tables = {1: 4, 515: 5, 516: 8, 517: 9, 518: 11}[version]
    assert f.version == version and f.n_tables == tables
    assert f.header_length == {1: 80, 515: 80, 516: 84, 517: 92, 518: 96}[version]
    assert (f.colors is not None) == (version >= 515)
    assert (f.machine is not None) == (f.extra is not None) == (version >= 516)
    assert (f.software is not None) == (f.model is not None) == (version >= 517)
    assert (f.sublayers is not None) == (f.preview2 is not None) == (version >= 518)
    addr = np.array([d["address"] for d in f.layers])
    size = np.array([d["length"] for d in f.layers])
    assert addr[0] == f.addresses["images"] and np.all(addr[1:] == addr[:-1] + size[:-1])
    assert addr[-1] + size[-1] == len(f.data)
    assert f.layerdef_length == 4 + 32 * len(f.layers)
    assert (f.preview["width"], f.preview["height"]) == (224, 168)
    assert f.preview["length"] == (75276 if version == 1 else 75292)  # Photon Workshop's 515/516 files: 75292
    if version >= 516:
        assert f.extra["length"] == 24 and f.extra["bottom_count"] == f.extra["normal_count"] == 2
        assert f.machine["length"] == (224 if version >= 518 else 156) and f.machine["image_format"] == "pw0Img"
        assert f.machine["max_aa"] == 16 and f.machine["background"] == 6506241
    if version >= 518:
        sub = f.sublayers["records"]
        assert f.sublayers["count"] == len(f.layers) and np.array_equal(sub["address"], addr)
        assert np.array_equal(sub["nonzero"], [d["nonzero"] for d in f.layers])
        assert (f.preview2["width"], f.preview2["height"]) == (320, 190)


@pytest.mark.parametrize("gamma", [1.0, 0.0])
@pytest.mark.parametrize("suffix", ["pwmx", "pm5", "pm5s", "pwmo"])
def test_torus_layers_and_header(tmp_path, torus, gamma, suffix):
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05, gamma=gamma)
    out = tmp_path / f"part.{suffix}"
    stats = write_target(iter_tiles(torus, spec, backend="numpy"), target(out, torus, spec))
    f = read_photon(out)
    machine = MACHINES[suffix]
    check_layout(f, machine.version)
    n = torus.n_layers
    assert stats["layers"] == len(f.layers) == n == 20 and stats["photon_bytes"] == out.stat().st_size
    ref = masks(torus, spec, backend="numpy")
    for i in range(n):
        img = f.layer_image(i)
        assert np.array_equal(img, q(ref[i])), i
        assert f.layers[i]["nonzero"] == np.count_nonzero(img)
    greys = bool(np.any((q(ref) > 0) & (q(ref) < 255)))
    assert greys == (gamma != 0)
    h, t = f.header, layer_table(SETTINGS, n)
    assert (h["res_x"], h["res_y"], h["pixel_um"]) == (1200, 900, pytest.approx(50.0))
    assert h["antialiasing"] == (16 if greys else 1)
    assert f.colors["grey"] == ([255] * 16 if not greys else [15, 31, 47, 63, 79, 95, 111, 127, 143, 159, 175, 191,
                                                              207, 223, 239, 255])
    assert h["layer_height"] == pytest.approx(0.5) and h["bottom_layers"] == 3 and h["transition_layers"] == 4
    assert (h["exposure"], h["bottom_exposure"], h["wait_before_cure"]) == (2.5, 25.0, 1.5)
    assert (h["lift_height"], h["lift_speed"], h["retract_speed"]) == (6.0, pytest.approx(1.5), pytest.approx(3.0))
    assert h["print_time"] == round(print_time_s(SETTINGS, n)) and h["per_layer"] == 0 and h["currency"] == 0x24
    vol = resin_ml(torus.area, torus.thickness)
    assert h["volume_ml"] == pytest.approx(vol, rel=1e-6) and h["weight_g"] == pytest.approx(1.25 * vol, rel=1e-6)
    assert vol == pytest.approx(2 * np.pi**2 * 15 * 25 / 1000, rel=0.02)  # the torus's own volume
    exposure = [d["exposure"] for d in f.layers]
    assert exposure == pytest.approx(list(t["exposure"])) and exposure[:3] == [25.0] * 3 and exposure[-1] == 2.5
    assert [d["lift_height"] for d in f.layers] == [8.0] * 3 + [6.0] * (n - 3)
    assert [d["lift_speed"] for d in f.layers] == pytest.approx([1.0] * 3 + [1.5] * (n - 3))
    assert [d["thickness"] for d in f.layers] == pytest.approx([0.5] * n)
    if machine.version >= 516:
        assert h["advanced_mode"] == 0  # one lift stage: Photon Workshop's basic-mode EXTRA
        assert f.extra["bottom"] == [(8.0, 1.0, 0.0), (0.0, 0.0, 3.0)]
        assert f.extra["normal"] == [(6.0, 1.5, 0.0), (0.0, 0.0, 3.0)]
        m = f.machine
        assert (m["name"], m["machine_z"], m["max_version"]) == (machine.name, machine.height, machine.version)
        assert (m["display_width"], m["display_height"]) == (pytest.approx(60.0), pytest.approx(45.0))
    if machine.version >= 517:
        assert f.software["name"] == "gpuslice" and f.software["length"] == 164
        lo, hi = f.model["min"], f.model["max"]  # the torus (40 mm across) in the display's middle
        assert np.allclose(lo, (-20, -20, 0), atol=0.06) and np.allclose(hi, (20, 20, 10), atol=0.06)
    if machine.version >= 518:
        assert (f.machine["res_x"], f.machine["res_y"]) == (1200, 900)
        assert f.machine["pixel_width_um"] == f.machine["pixel_height_um"] == pytest.approx(50.0)


def test_runs_and_tiles_write_the_same_file(tmp_path, torus, device):
    """The same pixels as tiles (bitmaps) or as runs: the same bytes."""
    spec = RasterSpec(resolution=(1200, 900), pixel=0.05, gamma=1.0)
    a, b = tmp_path / "a.pm3", tmp_path / "b.pm3"
    write_target(iter_tiles(torus, spec, backend="opencl", device=device), target(a, torus, spec))  # runs → tiles
    write_target(iter_run_layers(torus, spec, device=device), target(b, torus, spec))
    assert a.read_bytes() == b.read_bytes()


def test_preview_shows_the_part(tmp_path, torus):
    out = tmp_path / "p.pm5s"
    write_target(iter_tiles(torus, SPEC, backend="numpy"), target(out, torus))
    for p in (read_photon(out).preview, read_photon(out).preview2):
        v = p["rgb565"]
        r, b = v >> 11, v & 31
        part = r > b + 8  # orange: red high, blue low; the background is grey
        hh, ww = v.shape
        assert part.mean() > 0.2 and not part[hh // 2, ww // 2]  # the torus's hole is in the middle
        assert part[hh // 2].any() and v[0, 0] == 0x5ACB  # Photon Workshop's background grey


@pytest.mark.parametrize("version", [1, 515, 516, 517, 518])
def test_every_version_and_the_preset(tmp_path, torus, version):
    preset = tmp_path / "my.toml"
    preset.write_text(f'name = "my"\nresolution = [1200, 900]\npixel = 0.05\nbuild_height = 123.5\n'
                      f'formats = ["pwmx"]\nformat_version = {version}\nmachine = "Bench Printer"\n')
    out = tmp_path / "v.pwmx"
    stats = write_target(iter_tiles(torus, SPEC, backend="numpy"),
                         target(out, torus, options=ResinOptions(printer=str(preset))))
    f = read_photon(out)
    check_layout(f, version)
    assert stats["format_version"] == version and stats["machine"] == "Bench Printer"
    if version >= 516:
        assert (f.machine["name"], f.machine["machine_z"]) == ("Bench Printer", 123.5)
    ref = masks(torus, SPEC, backend="numpy", layers=[0, 10, 19])
    for k, i in enumerate((0, 10, 19)):
        assert np.array_equal(f.layer_image(i), q(ref[k]))


def test_two_stage_motion_and_waits(tmp_path, torus):
    s = PrintSettings(lift_height=2.0, lift_speed=60.0, lift_height2=5.0, lift_speed2=240.0, retract_speed=300.0,
                      retract_height2=2.0, retract_speed2=90.0, bottom_lift_height=3.0, bottom_lift_speed=30.0,
                      bottom_retract_height2=3.0, bottom_retract_speed=120.0, wait_before_cure=1.0,
                      wait_after_cure=0.5, wait_after_lift=0.25)  # (the slow retract: each group's first stage)
    out = tmp_path / "t.pm3"
    write_target(iter_tiles(torus, SPEC, backend="numpy"), target(out, torus, settings=s))
    f = read_photon(out)
    h = f.header
    assert h["advanced_mode"] == 1 and h["wait_before_cure"] == 1.75  # the three waits in the one the format has
    assert (h["lift_height"], h["lift_speed"], h["retract_speed"]) == (7.0, 1.0, 5.0)
    assert f.extra["normal"] == [(2.0, 1.0, 1.5), (5.0, 4.0, 5.0)]  # (height, lift, retract): slow, then fast
    assert f.extra["bottom"] == [(3.0, 0.5, 1.5), (5.0, 4.0, 2.0)]
    assert [d["lift_height"] for d in f.layers[:2]] == [8.0, 7.0]  # the bottom layer's lift, then the normal one
    assert [d["lift_speed"] for d in f.layers[:2]] == [0.5, 1.0]
    with pytest.raises(ParameterError, match="rest the same before every layer"):
        write_target(iter([]), target(tmp_path / "w.pm3", torus, settings=s.with_values({"bottom_wait_after_cure":
                                                                                          2.0})))
    # a slow retract other than the first stage's height has nowhere to go: refused, not changed (it was written
    # as the first stage's 3 mm)
    with pytest.raises(ParameterError, match=r"slow retract is its first lift stage \(--bottom-lift-height 3 mm\); "
                                             r"--bottom-retract-height2 2 cannot"):
        write_target(iter([]), target(tmp_path / "r.pm3", torus, settings=s.with_values({"bottom_retract_height2":
                                                                                          2.0})))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.pm3"]


def test_settings_a_file_cannot_store_are_refused_before_any_work(tmp_path, capsys):
    """A second lift stage at its own speed in a CTB v3 file (one stage), or a slow retract other than a Photon
    file's first stage: a one-line error from the command before slicing, nothing written (they were folded into
    one stage, so the file moved otherwise than asked and its print time was not the one printed)."""
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    base = ["raster", str(stl), "-t", "0.5", "--no-progress", "--lift-height", "3", "--lift-height2", "4",
            "--lift-speed2", "180"]
    assert main([*base, "--printer", "elegoo-saturn", "-o", str(tmp_path / "a.ctb")]) == 2
    err = capsys.readouterr().err
    assert "a.ctb: a CTB v3 file has one lift and one retract stage; --lift-height2 4 at --lift-speed2 180" in err
    assert main([*base, "--printer", "anycubic-photon-mono-x", "--retract-height2", "1.5", "--retract-speed2", "50",
                 "-o", str(tmp_path / "b.pwmx")]) == 2
    assert "--retract-height2 1.5 cannot be written" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["torus.stl"]
    from gpuslice.pipeline import ResinOutput  # the refusal is the output's, made before the device or the mesh
    from gpuslice.raster import ResinOptions

    opts = ResinOptions(printer="elegoo-saturn")
    with pytest.raises(ParameterError, match="a CTB v3 file has one lift"):
        ResinOutput("x.ctb", "ctb", opts.spec(), opts, opts.settings(lift_height2=4.0, lift_speed2=180.0))
    assert main([*base, "--printer", "elegoo-mars-3", "-q", "-o", str(tmp_path / "c.ctb")]) == 0  # CTB v4: two
    # (the preset's bottom layers lift 8 mm, UVtools' value: their first stage is given 3 mm too)
    assert main([*base, "--printer", "anycubic-photon-mono-x", "--retract-height2", "3", "--retract-speed2", "50",
                 "--bottom-lift-height", "3", "-q", "-o", str(tmp_path / "d.pwmx")]) == 0


def test_registry_names_every_machine():
    photon = {f.name: f for f in RESIN_FORMATS.values() if f.writer == "photon:write_target"}
    assert set(photon) == set(MACHINES)
    for s, m in MACHINES.items():
        assert photon[s].suffixes == (f".{s}",) and resin_format_for(f"x.{s.upper()}") is photon[s]
        assert m.name.removeprefix("Anycubic ") in photon[s].title
        assert m.version in (516, 517, 518) and m.display[0] / m.resolution[0] < 0.06


# ---- real meshes on a 12K display ----------------------------------------------------------------------------------
SPEC12K = {"resolution": (11520, 5120), "pixel": 0.019, "pixel_y": 0.024}


@pytest.fixture(scope="module", params=[("benchy", 60.0, "pm5s"), ("nefertiti", 80.0, "pm5")], ids=lambda p: p[0])
def shared_case(request, shared_meshes, device):
    import trimesh

    name, fit, suffix = request.param
    m = trimesh.load(shared_meshes / f"{name}.stl", force="mesh")
    return slice_mesh(mesh_from_triangles(m.vertices[m.faces], fit=fit), thickness=0.05, backend="opencl"), suffix


def normalised(start, length, grey):
    """Runs after the quantisation: blank ones dropped, touching ones of one grey merged."""
    return quantised_runs(start, length, grey, q)


def digest(runs) -> str:
    return hashlib.sha1(b"".join(np.ascontiguousarray(a, np.int64).tobytes() for a in runs)).hexdigest()


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_shared_meshes_12k_every_layer(tmp_path, shared_case, device, gamma):
    """Every layer of the file decodes to the runs the writer was given (the rasteriser's, as masks() draws them),
    quantised; a few whole layers equal gpuslice.raster.masks() quantised."""
    res, suffix = shared_case
    spec = RasterSpec(**SPEC12K, gamma=gamma)
    cols = spec.shape[1]
    want: dict[int, tuple[str, int]] = {}

    def layers():  # what the writer gets, its quantised runs remembered by digest (not kept: 12K layers are big)
        for item in iter_run_layers(res, spec, device=device):
            runs = normalised(*pixel_runs(item, cols))
            want[item.index] = digest(runs), int(runs[1].sum())
            yield item

    out = tmp_path / f"part.{suffix}"
    write_target(layers(), target(out, res, spec, PrintSettings()))
    f = read_photon(out)
    check_layout(f, MACHINES[suffix].version)
    assert sorted(want) == list(range(res.n_layers)) and len(f.layers) == res.n_layers
    for i in range(res.n_layers):
        assert (digest(f.layer_runs(i)), f.layers[i]["nonzero"]) == want[i], i
    some = [0, res.n_layers // 2, res.n_layers - 1]
    for k, m in enumerate(masks(res, spec, backend="opencl", device=device, layers=some)):
        assert np.array_equal(f.layer_image(some[k]), q(m)), some[k]
    assert (f.header["res_x"], f.header["res_y"]) == (11520, 5120)
    assert f.header["antialiasing"] == (16 if gamma else 1)


# ---- command line, reproducibility, errors -------------------------------------------------------------------------
def test_cli_writes_reproducible_files(tmp_path, device, monkeypatch, capsys):
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    args = ["raster", str(stl), "-t", "0.5", "--resolution", "3840x2400", "--pixel", "0.05", "--no-progress",
            "--bottom-layers", "2", "--exposure", "3"]  # (the Photon Mono X's display)
    assert main([*args, "-o", str(tmp_path / "a.pwmx")]) == 0
    assert "wrote" in capsys.readouterr().out
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    assert main([*args, "-q", "-o", str(tmp_path / "b.pwmx")]) == 0
    assert (tmp_path / "a.pwmx").read_bytes() == (tmp_path / "b.pwmx").read_bytes()  # no date in the format
    f = read_photon(tmp_path / "a.pwmx")
    assert len(f.layers) == 20 and f.header["bottom_layers"] == 2 and f.header["exposure"] == 3.0
    assert f.layer_image(10)[1200, 1920] == 0 and f.layer_image(10).max() == 255  # the hole at the display centre


def test_a_display_not_the_machines_is_refused(tmp_path, capsys):
    """The suffix names the machine (its name is in the file, and its firmware checks the display): another display
    is a one-line error before any work, nothing written; a preset's display overridden the same."""
    stl = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), stl)
    base = ["raster", str(stl), "-t", "0.5", "--no-progress"]
    assert main([*base, "-o", str(tmp_path / "a.pm5s")]) == 2  # the default 3840x2400 display: not the M5s's
    err = capsys.readouterr().err
    assert "a.pm5s: a .pm5s file is for the Anycubic Photon Mono M5s, whose display is 11520x5120 px of 0.019 x 0.024" \
        in err and err.count("\n") == 1
    assert main([*base, "--printer", "anycubic-photon-mono-m5s", "--resolution", "3840x2400",
                 "-o", str(tmp_path / "b.pm5s")]) == 2
    assert "printer anycubic-photon-mono-m5s's display is 11520x5120" in capsys.readouterr().err
    assert main([*base, "--printer", "elegoo-saturn-3-ultra", "--pixel", "0.05", "-o", str(tmp_path / "c.goo")]) == 2
    assert "not the 11520x5120 px of 0.05 x 0.024 mm asked" in capsys.readouterr().err
    # a preset that names no machine (generic-4k reads any format) leaves the suffix's name in the file: the same
    assert main([*base, "--printer", "generic-4k", "-o", str(tmp_path / "e.pm5s")]) == 2
    assert "a .pm5s file is for the Anycubic Photon Mono M5s" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["torus.stl"]
    assert main([*base, "--resolution", "11520x5120", "--pixel", "0.019", "--pixel-y", "0.024", "-q",
                 "-o", str(tmp_path / "d.pm5s")]) == 0  # the M5s's display, given by hand


def test_errors_leave_no_file(tmp_path, torus):
    with pytest.raises(ParameterError, match=r"x\.pwx: not a Photon Workshop suffix"):
        write_target(iter_tiles(torus, SPEC, backend="numpy"), target(tmp_path / "x.pwx", torus))
    wide = RasterSpec(resolution=(70000, 30), pixel=0.05)
    with pytest.raises(ParameterError, match="65535"):
        write_target(iter([]), target(tmp_path / "w.pm5s", torus, wide))

    def broken():
        yield from iter_tiles(torus, SPEC, backend="numpy", layers=[0, 1])
        raise ParameterError("stop")

    with pytest.raises(ParameterError, match="stop"):
        write_target(broken(), target(tmp_path / "b.pwmx", torus))
    short = iter_tiles(torus, SPEC, backend="numpy", layers=[0, 1])
    with pytest.raises(ParameterError, match="expected 20 layers, got 2"):
        write_target(short, target(tmp_path / "c.pwmx", torus))
    assert list(tmp_path.iterdir()) == []


def test_real_file_layout_facts():
    """What the writer's fixed values rest on, as read from Photon Workshop's own files by hand (sample_data of
    futurelink/msla-imaging: Example_Photon_Mono_X.pwmx, _Mono_4K.pwma, _M3.pm3 at 516, _Mono.pwmo at 515): their
    tables sit at the addresses the writer computes for 426 layers."""
    from gpuslice.raster.photon import _sizes

    for version, first in ((516, (52, 152, 75444, 75472, 89124, 89196, 89352)), (515, (48, 144, 75436, 75464, 89116))):
        s = _sizes(version, 426)
        at = np.cumsum(list(s.values()))
        assert tuple(at) == first, version
    assert struct.calcsize("<10f3I2f5I") == 80


FOREIGN = os.environ.get("GPUSLICE_FOREIGN_ARCHIVES")


@pytest.mark.skipif(not FOREIGN, reason="set GPUSLICE_FOREIGN_ARCHIVES to a folder of Photon Workshop files written "
                    "by Anycubic's software (futurelink/msla-imaging's sample_data: public, but with no licence to "
                    "copy them here)")
def test_files_photon_workshop_wrote_read_back():
    """The test decoder reads files Anycubic's Photon Workshop wrote, and what it reads makes sense: the display and
    pitch of the machine the suffix names (:data:`MACHINES`: what the writer and its display check use), positive
    settings, every layer's run records covering the display exactly, and its lit pixels equal to the count the
    file's own LAYERDEF gives (layers 0, the middle and the last)."""
    files = sorted(p for p in Path(FOREIGN).iterdir() if p.suffix.lstrip(".") in MACHINES)
    assert files, f"no Photon Workshop file in {FOREIGN}"
    for path in files:
        f = read_photon(path)
        m, h = MACHINES[path.suffix.lstrip(".")], f.header
        assert f.version in (1, 515, 516, 517, 518) and len(f.layers) > 0, path.name
        assert (h["res_x"], h["res_y"]) == m.resolution, path.name
        assert h["pixel_um"] == pytest.approx(1000 * max(m.display[0] / m.resolution[0],
                                                         m.display[1] / m.resolution[1]), abs=0.5), path.name
        assert h["layer_height"] > 0 and h["exposure"] > 0 and h["bottom_exposure"] > 0 and h["bottom_layers"] >= 1
        for i in (0, len(f.layers) // 2, len(f.layers) - 1):
            start, length, grey = f.layer_runs(i)
            assert int(length.sum()) == int(f.layers[i]["nonzero"]), (path.name, i)
            assert f.layers[i]["exposure"] > 0 and f.layers[i]["thickness"] > 0


def test_name_fields_are_cut_at_a_character_boundary():
    from gpuslice.raster.photon import _name

    b = _name("ü" * 40, 32)
    assert len(b) == 32 and b.endswith(b"\0")
    text = b.rstrip(b"\0").decode("utf-8")  # decodes: no half character left
    assert text == "ü" * 15


# ---- the encoding kernels (kernels/photon.cl) against their numpy twin ----------------------------------------------
def _same(got, want) -> None:
    assert got[0] == want[0]
    for g, w in zip(got[1:], want[1:], strict=True):
        assert np.array_equal(g, w)


def test_kernels_equal_the_twin_on_random_groups(device):
    """Groups of layers with faint greys (below 16: blank after quantisation), neighbours equal after it, whole
    rows, blank layers first, inside and last, lone pixels at both ends, and layers lit only faintly (no box): the
    kernels' bytes, lit pixels, middle-grey flags and boxes equal the twin's, with no group left to it."""
    import sys

    from gpuslice.raster.photon import PhotonEncoder, encode_pw0_runs

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from run_images import runs_of

    enc = PhotonEncoder.of(device)
    rng = np.random.default_rng(22)
    h, w = 12, 35
    imgs = []
    for k in range(30):
        img = rng.choice(np.array([0, 0, 255, 255, 1, 15, 16, 17, 31, 128, 230, 250], np.uint8), size=(h, w))
        img[rng.random((h, w)) < 0.2 * (k % 5)] = 0
        imgs.append(img)
    for k in (0, 9, 29):
        imgs[k][:] = 0
    imgs[4][:] = 0
    imgs[4][0, 0] = imgs[4][-1, -1] = 255
    imgs[5][:] = 255
    imgs[6] = np.where(imgs[6] > 0, 7, 0).astype(np.uint8)  # faint only: blank after quantisation
    imgs[7] = np.where(imgs[7] > 0, 255, 0).astype(np.uint8)
    imgs[7][3, 3] = 230  # its one middle grey: the highest middle code, 14
    runs = runs_of(imgs)
    before = enc.fallbacks
    for a, b in ((0, 30), (0, 1), (3, 17), (4, 8), (9, 11), (29, 30), (5, 29)):
        got = encode_pw0_runs(runs, a, b, w, h * w, device=device)
        _same(got, encode_pw0_runs(runs, a, b, w, h * w))
    assert enc.fallbacks == before
    start, length, grey = decode_pw0(np.frombuffer(encode_pw0_runs(runs, 5, 6, w, h * w, device=device)[0][0],
                                                   np.uint8), h * w)
    assert start.tolist() == [0] and length.tolist() == [h * w] and q(grey).tolist() == [255]


def test_kernels_long_records_and_long_merges(device):
    """Segments longer than a record (0xF for middle greys, 0xFFF for 0 and 15) split into full records then the
    rest; a blank stretch of more faint runs than a work-item looks ahead over: left to the twin (counted)."""
    from gpuslice.raster.photon import PhotonEncoder, encode_pw0_runs
    from gpuslice.raster.runs import Runs

    enc = PhotonEncoder.of(device)
    lengths = np.array([1, 15, 16, 31, 0xFFF, 0x1000, 3 * 0xFFF + 5, 2])
    greys = np.array([128, 128, 255, 100, 255, 255, 255, 40], np.uint8)
    gaps = np.array([0, 1, 0xFFF, 0x1000, 1, 2 * 0xFFF, 3, 0x2001])
    start = np.cumsum(gaps + np.concatenate(([0], lengths[:-1])))
    cols = int(start[-1] + lengths[-1]) + 0x1003
    runs = Runs(np.arange(1), np.array([0, lengths.size]), np.zeros(lengths.size, np.int32), start.astype(np.int32),
                lengths.astype(np.int32), greys, (1, cols))
    before = enc.fallbacks
    got = encode_pw0_runs(runs, 0, 1, cols, cols, device=device)
    _same(got, encode_pw0_runs(runs, 0, 1, cols, cols))
    assert enc.fallbacks == before
    n = 5000  # faint one-pixel runs with one-pixel gaps: one blank segment of ~10,000 pieces
    runs = Runs(np.arange(1), np.array([0, n]), np.zeros(n, np.int32), np.arange(0, 2 * n, 2, dtype=np.int32),
                np.ones(n, np.int32), np.full(n, 9, np.uint8), (1, 2 * n + 4))
    assert enc.encode(runs, 0, 1, 2 * n + 4, 2 * n + 4) is None and enc.fallbacks == before + 1
    _same(encode_pw0_runs(runs, 0, 1, 2 * n + 4, 2 * n + 4, device=device),
          encode_pw0_runs(runs, 0, 1, 2 * n + 4, 2 * n + 4))


def test_writer_with_the_kernels_writes_the_twins_file(tmp_path, torus, device):
    from dataclasses import replace

    for gamma in (1.0, 0.0):
        spec = RasterSpec(resolution=(1200, 900), pixel=0.05, gamma=gamma)
        files = []
        for dev in (device, None):
            out = tmp_path / f"t{gamma:g}{dev is None}.pwmx"
            write_target(iter_run_layers(torus, spec, device=device), replace(target(out, torus, spec), device=dev))
            files.append(out.read_bytes())
        assert files[0] == files[1]
