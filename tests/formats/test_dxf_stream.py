"""The DXF writer streams its polylines into the file a run of layers at a time (memory bounded by the run, not the
model) and writes, byte for byte, the file of the writer it replaced, which built every loop as an ezdxf entity and
saved the whole drawing at the end: that writer is kept below as :func:`_reference_write_dxf`."""

from __future__ import annotations

import os
import tracemalloc
from collections import OrderedDict
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import gpuslice
from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.errors import ParameterError
from gpuslice.formats import dxf
from gpuslice.formats.dxf import dxf_layer_name, read_dxf, write_dxf
from gpuslice.formats.numbers import MAX_ABS, result_arrays
from gpuslice.io.atomic import atomic_path
from gpuslice.mesh import shapes as S
from gpuslice.slicing.result import SliceResult

ezdxf = pytest.importorskip("ezdxf")

VERSIONS = ["R2000", "R2010"]


def _reference_write_dxf(result: SliceResult, path: str | os.PathLike, *, version: str = "R2010") -> None:
    """The writer before streaming, unchanged: every loop an ezdxf ``LWPOLYLINE`` entity, the drawing saved whole."""
    points, loop_offsets, layer_offsets = result_arrays(result)
    if points.size and np.abs(points).max() > MAX_ABS:
        raise ParameterError("result coordinates are too large to write (beyond 1e9 mm)")
    closed = np.asarray(result.loop_closed, dtype=bool).tolist()
    z = np.asarray(result.z, dtype=np.float64).tolist()
    thickness = np.asarray(result.thickness, dtype=np.float64).tolist()
    area = np.asarray(result.area, dtype=np.float64).tolist()
    saved = ezdxf.options.write_fixed_meta_data_for_testing
    try:
        ezdxf.options.write_fixed_meta_data_for_testing = True  # reproducible bytes: fixed dates and GUIDs
        doc = ezdxf.new(version, setup=False, units=ezdxf.units.MM)
        doc.header["$MEASUREMENT"] = 1
        msp = doc.modelspace()
        offsets = loop_offsets.tolist()
        for i in range(len(z)):
            name = dxf_layer_name(i)
            layer = doc.layers.add(name)
            layer.description = f"z={z[i]!r} thickness={thickness[i]!r} area={area[i]!r}"
            attribs = {"layer": name, "elevation": z[i]}
            for r in range(int(layer_offsets[i]), int(layer_offsets[i + 1])):
                a, b = offsets[r], offsets[r + 1]
                if b - a < 2:
                    continue
                msp.add_lwpolyline(points[a:b].astype(np.float64), format="xy", close=closed[r], dxfattribs=attribs)
        doc.classes.add_required_classes(doc.dxfversion)
        doc.classes.classes = OrderedDict(sorted(doc.classes.classes.items()))
        with atomic_path(path) as tmp:
            doc.saveas(tmp)
    finally:
        ezdxf.options.write_fixed_meta_data_for_testing = saved


def _assert_same_bytes(result: SliceResult, tmp_path: Path, version: str = "R2010", name: str = "r") -> bytes:
    ref, new = tmp_path / f"{name}_{version}_ref.dxf", tmp_path / f"{name}_{version}_new.dxf"
    _reference_write_dxf(result, ref, version=version)
    write_dxf(result, new, version=version)
    a, b = ref.read_bytes(), new.read_bytes()
    if a != b:  # the first difference, with a little context, not two files of megabytes
        k = next((i for i, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))
        pytest.fail(f"{name} {version}: {len(a)} bytes expected, {len(b)} written, first difference at byte {k}: "
                    f"{a[max(0, k - 120) : k + 60]!r} != {b[max(0, k - 120) : k + 60]!r}")
    return b


def _result(loops: list[tuple[np.ndarray, bool, int]], z: list[float]) -> SliceResult:
    """A hand-built result: ``loops`` (points (n, 2), closed, layer) in layer order."""
    counts = [len(p) for p, _, _ in loops]
    layer = np.array([lay for _, _, lay in loops], np.int32)
    return SliceResult(
        points=np.concatenate([np.asarray(p).reshape(-1, 2) for p, _, _ in loops]) if loops
        else np.zeros((0, 2), np.float32),
        loop_offsets=np.concatenate(([0], np.cumsum(counts))).astype(np.int64),
        layer_offsets=np.searchsorted(layer, np.arange(len(z) + 1)).astype(np.int64),
        loop_layer=layer, loop_is_hole=np.zeros(len(loops), bool), loop_parent=np.full(len(loops), -1, np.int32),
        loop_closed=np.array([c for _, c, _ in loops], bool),
        z=np.asarray(z, np.float64), thickness=np.full(len(z), 0.2), area=np.linspace(0.0, 99.123456789, len(z)),
    )


def _hand_result() -> SliceResult:
    """Layer 0: a square with a square hole and a square; layer 1: empty; layer 2: a square and an open chain."""
    sq = lambda x, y, s: np.array([[x, y], [x + s, y], [x + s, y + s], [x, y + s]], np.float32)  # noqa: E731
    chain = np.array([[0, 8], [2, 9], [4, 8]], np.float32)
    return _result([(sq(0, 0, 10), True, 0), (sq(3, 3, 4)[::-1], True, 0), (sq(20, 0, 3), True, 0),
                    (sq(0, 0, 5), True, 2), (chain, False, 2)], [0.1, 0.3, 0.5])


def _many_digits(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 2) float32 of every magnitude the writer accepts: mm-sized values with all their digits, tiny ones
    (exponent notation in the text), subnormals, ±0.0, and values up to 1e9."""
    mags = 10.0 ** rng.uniform(-12, 9, (n, 2))
    pts = (rng.choice([-1.0, 1.0], (n, 2)) * mags).astype(np.float32)
    special = np.array([0.0, -0.0, 1e-45, -1e-45, 1e-40, 1e-4, -1e-4, 9.9999e-5, 1e9, -1e9, 0.1, -0.3, 1 / 3, 2.0**-30,
                        123456.789, 16777216.0, 1e-5, 1e16 / 1e8], np.float32)
    pts.ravel()[: special.size] = special
    pts.ravel()[special.size : 2 * special.size] = -special
    return pts


# ---------------------------------------------------------------------------------------------------------
# the same bytes
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("version", [*VERSIONS, "R2004", "R2018"])
@pytest.mark.parametrize("chunk", [None, 1, 5])
def test_hand_result_same_bytes(tmp_path, monkeypatch, version, chunk):
    if chunk is not None:  # runs of one layer, and runs that end inside the layers
        monkeypatch.setattr(dxf, "CHUNK_POINTS", chunk)
    data = _assert_same_bytes(_hand_result(), tmp_path, version)
    assert data.count(b"\nLWPOLYLINE\n") == 5
    layers = read_dxf(tmp_path / f"r_{version}_new.dxf")
    assert sorted(layers) == ["SLICE_00000", "SLICE_00002"] and [c for _, c, _ in layers["SLICE_00002"]] == [1, 0]


@pytest.fixture(scope="module")
def built() -> dict[str, SliceResult]:
    """Sliced shapes: a torus, a box with a hole through it, a cylinder with a slit in its wall (open chains on every
    layer) and a torus cut by explicit planes (empty layers below, at and above it)."""
    cyl = S.cylinder(10, 20, 64)
    side = np.flatnonzero(np.ptp(cyl[:, :, 2], axis=1) > 0)
    out = {
        "torus": slice_mesh(mesh_from_triangles(S.torus()), thickness=0.37, backend="numpy"),
        "hollow_box": slice_mesh(mesh_from_triangles(S.hollow_box(20, 10, core=6)), thickness=0.5, backend="numpy"),
        "slit": slice_mesh(mesh_from_triangles(np.delete(cyl, side[:6], axis=0)), thickness=0.5, backend="numpy",
                           fill_holes=False),  # (filled, its slit would close)
        "planes": slice_mesh(mesh_from_triangles(S.torus()), z=np.array([-20.0, 0.0, 1.2345678, 3.3, 30.0]),
                             backend="numpy"),
    }
    assert (~out["slit"].loop_closed).sum() == out["slit"].n_layers > 0  # open chains
    assert (out["planes"].loops_per_layer == 0).sum() >= 2 and out["planes"].loops_per_layer.max() > 0  # empty layers
    return out


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("chunk", [None, 64])
def test_sliced_shapes_same_bytes(built, tmp_path, monkeypatch, version, chunk):
    if chunk is not None:
        monkeypatch.setattr(dxf, "CHUNK_POINTS", chunk)
    for name, res in built.items():
        data = _assert_same_bytes(res, tmp_path, version, name)
        assert data.count(b"\nLWPOLYLINE\n") == res.n_loops, name


@pytest.mark.parametrize("version", VERSIONS)
def test_shared_meshes_same_bytes(shared_meshes, tmp_path, version):
    """Real meshes at 0.1 mm after fitting to 60 mm: CAD, holes, hollow squares, open chains (a mesh with holes in
    its surface), an organic one."""
    for name in ("fandisk", "prusa_two_hollow_squares", "p_conveyor_holes", "cow"):
        open_ = name == "p_conveyor_holes"  # (its hole left open: open chains, as the docstring says)
        res = gpuslice.slice_mesh(shared_meshes / f"{name}.stl", thickness=0.1, fit=60, fill_holes=not open_)
        if open_:
            assert (~res.loop_closed).any()
        _assert_same_bytes(res, tmp_path, version, name)


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("chunk", [None, 3])
def test_short_loops_digits_negative_zeros_and_zero_elevation(tmp_path, monkeypatch, version, chunk):
    """Loops of 0 and 1 points (skipped: they take no handle) before, between and after written ones, a layer of
    short loops only; coordinates of every magnitude (exponent notation too) and -0.0; z = 0 and -0 (no elevation
    written: ezdxf leaves an optional attribute at its default out), negative and many-digit z."""
    if chunk is not None:
        monkeypatch.setattr(dxf, "CHUNK_POINTS", chunk)
    rng = np.random.default_rng(7)
    pts = _many_digits(rng, 400)
    one = pts[:1]
    empty = np.zeros((0, 2), np.float32)
    loops = [(empty, True, 0), (pts[0:40], True, 0), (one, False, 0), (pts[40:42], False, 0), (empty, True, 0),
             (one, True, 1), (empty, False, 1),
             (pts[42:100], True, 2), (one, True, 2),
             (pts[100:101], False, 4), (pts[101:103], True, 4), (pts[103:200], False, 4), (empty, True, 4),
             (pts[200:400], True, 5)]
    z = [0.0, -0.0, -1.5, 0.1 + 0.2, -0.0, 1e-7]
    res = _result(loops, z)
    data = _assert_same_bytes(res, tmp_path, version, "short")
    assert data.count(b"\nLWPOLYLINE\n") == 6 and b" 38\n" in data
    assert b"e-" in data and b"\n-0.0\n" in data and b"\n1000000000.0\n" in data  # the cases are there
    got = read_dxf(tmp_path / f"short_{version}_new.dxf")
    assert [len(p) for p, _, _ in got["SLICE_00000"]] == [40, 2] and "SLICE_00001" not in got
    np.testing.assert_array_equal(got["SLICE_00005"][0][0], pts[200:400].astype(np.float64))
    assert [e for _, _, e in got["SLICE_00000"]] == [0.0, 0.0] and got["SLICE_00004"][0][2] == -0.0


def test_float64_points_same_bytes(tmp_path):
    """A result whose points are float64 (not what the slicer makes, but the writer takes them): every digit."""
    rng = np.random.default_rng(3)
    pts = _many_digits(rng, 300).astype(np.float64) * (1 - rng.uniform(0, 1e-9, (300, 2)))  # within 1e9
    res = _result([(pts[:150], True, 0), (pts[150:], False, 1)], [np.pi, -np.e])
    for version in VERSIONS:
        _assert_same_bytes(res, tmp_path, version, "f64")


def test_no_layers_and_no_loops_same_bytes_r12_refused_with_loops(tmp_path):
    hand = _hand_result()
    no_loops = replace(hand, points=np.zeros((0, 2), np.float32), loop_offsets=np.zeros(1, np.int64),
                       layer_offsets=np.zeros(4, np.int64), loop_layer=np.zeros(0, np.int32),
                       loop_is_hole=np.zeros(0, bool), loop_parent=np.zeros(0, np.int32), loop_closed=np.zeros(0, bool))
    no_layers = replace(no_loops, layer_offsets=np.zeros(1, np.int64), z=np.zeros(0), thickness=np.zeros(0),
                        area=np.zeros(0))
    for version in [*VERSIONS, "R12"]:  # R12 has no LWPOLYLINE, but a drawing with no loops to write is written
        _assert_same_bytes(no_loops, tmp_path, version, "no_loops")
        _assert_same_bytes(no_layers, tmp_path, version, "no_layers")
    short_only = _result([(np.zeros((1, 2), np.float32), True, 0)], [0.5])
    _assert_same_bytes(short_only, tmp_path, "R12", "short_only")
    with pytest.raises(ezdxf.DXFVersionError, match="LWPOLYLINE requires DXF R2000"):
        write_dxf(hand, tmp_path / "r12.dxf", version="R12")
    with pytest.raises(ezdxf.DXFVersionError, match="LWPOLYLINE requires DXF R2000"):
        _reference_write_dxf(hand, tmp_path / "r12_ref.dxf", version="R12")
    assert not (tmp_path / "r12.dxf").exists() and not (tmp_path / "r12_ref.dxf").exists()


# ---------------------------------------------------------------------------------------------------------
# refusals and the atomic write
# ---------------------------------------------------------------------------------------------------------
def test_refusals_leave_the_file_alone(tmp_path):
    out = tmp_path / "x.dxf"
    out.write_bytes(b"before")
    hand = _hand_result()
    big = replace(hand, points=hand.points * np.float32(2e8))
    with pytest.raises(ParameterError, match="too large"):
        write_dxf(big, out)
    nan = replace(hand, points=np.where(np.arange(hand.points.shape[0])[:, None] == 2, np.nan, hand.points))
    with pytest.raises(ParameterError, match="non-finite"):
        write_dxf(nan, out)
    with pytest.raises(ParameterError, match="inconsistent"):
        write_dxf(replace(hand, layer_offsets=np.array([0, 3, 2, 5], np.int64)), out)
    assert out.read_bytes() == b"before" and sorted(p.name for p in tmp_path.iterdir()) == ["x.dxf"]


def test_failure_while_streaming_leaves_no_file(built, tmp_path, monkeypatch):
    """The file is written under a temporary name and renamed once complete: a failure between two runs of layers
    leaves the previous file, and no partial one."""
    monkeypatch.setattr(dxf, "CHUNK_POINTS", 64)
    calls = []
    real = dxf._polylines

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(dxf, "_polylines", failing)
    out = tmp_path / "t.dxf"
    out.write_bytes(b"before")
    with pytest.raises(KeyboardInterrupt):
        write_dxf(built["torus"], out)
    assert out.read_bytes() == b"before" and sorted(p.name for p in tmp_path.iterdir()) == ["t.dxf"]


# ---------------------------------------------------------------------------------------------------------
# memory
# ---------------------------------------------------------------------------------------------------------
def _stack(n_layers: int, n_points: int) -> SliceResult:
    """``n_layers`` layers, each one circle of ``n_points`` points (float32 values with all their digits)."""
    t = np.linspace(0, 2 * np.pi, n_points, endpoint=False)
    ring = np.stack([40 + 30 * np.cos(t), 40 + 30 * np.sin(t)], 1).astype(np.float32)
    return _result([(ring, True, i) for i in range(n_layers)], (0.1 + 0.2 * np.arange(n_layers)).tolist())


def _peak(write, result: SliceResult, path: Path) -> int:
    tracemalloc.start()
    try:
        write(result, path)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_is_bounded_by_a_run_of_layers(tmp_path, monkeypatch):
    """Four times the layers (the same content in each) hardly moves the streaming writer's peak (a run of layers
    plus each slice's small LAYER table entry), where the writer that held every loop as an entity took about 4x."""
    monkeypatch.setattr(dxf, "CHUNK_POINTS", 4096)  # a few layers a run, so both results stream several runs
    warm = _stack(2, 8)
    write_dxf(warm, tmp_path / "warm.dxf")  # imports and first-call caches out of the measurement
    _reference_write_dxf(warm, tmp_path / "warm.dxf")
    small, large = _stack(16, 1000), _stack(64, 1000)
    new = [_peak(write_dxf, r, tmp_path / "new.dxf") for r in (small, large)]
    ref = [_peak(_reference_write_dxf, r, tmp_path / "ref.dxf") for r in (small, large)]
    assert (tmp_path / "new.dxf").read_bytes() == (tmp_path / "ref.dxf").read_bytes()
    assert ref[1] > 2.5 * ref[0], ref  # the measure sees a writer whose memory grows with the model
    assert new[1] < 1.5 * new[0], new
    assert new[1] < 0.5 * ref[1], (new, ref)
