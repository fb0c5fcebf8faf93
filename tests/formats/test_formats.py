"""Tests of the contour formats (gpuslice.formats: SVG, CLI, the suffix dispatch), atomic writes (gpuslice.io.atomic)
and JSON reports (gpuslice.io.report).

The results are built by hand (no slicer involved): small squares whose areas are known exactly.
"""

from __future__ import annotations

import json
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from gpuslice.errors import GpusliceError, MeshFileError, ParameterError
from gpuslice.formats import export, suffixes
from gpuslice.formats import numbers as ex
from gpuslice.formats.commonlayer import CLI_CLOCKWISE, CLI_COUNTER_CLOCKWISE, CLI_OPEN, read_cli, write_cli
from gpuslice.formats.svg import write_svg
from gpuslice.io.atomic import atomic_path, atomic_write_bytes, atomic_write_text
from gpuslice.io.report import write_report
from gpuslice.slicing.result import SliceResult

SVG = "{http://www.w3.org/2000/svg}"


# ---------------------------------------------------------------------------------------------------------
# hand-built results
# ---------------------------------------------------------------------------------------------------------
def square(x0: float, y0: float, side: float, ccw: bool = True) -> np.ndarray:
    p = np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]], dtype=np.float32)
    return p if ccw else p[::-1].copy()


def make_result(layers: list[list[tuple[np.ndarray, bool, int, bool]]], thickness: float = 0.2) -> SliceResult:
    """``layers``: per layer, loops as (points, is_hole, parent index within the layer or -1, closed)."""
    pts, loop_offsets, layer_offsets = [], [0], [0]
    loop_layer, is_hole, parent, closed, area = [], [], [], [], []
    for i, loops in enumerate(layers):
        first = len(loop_layer)
        a = 0.0
        for p, hole, par, cl in loops:
            pts.append(p)
            loop_offsets.append(loop_offsets[-1] + len(p))
            loop_layer.append(i)
            is_hole.append(hole)
            parent.append(first + par if par >= 0 else -1)
            closed.append(cl)
            if cl:
                x, y = p[:, 0].astype(np.float64), p[:, 1].astype(np.float64)
                a += 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
        layer_offsets.append(len(loop_layer))
        area.append(a)
    n = len(layers)
    return SliceResult(
        points=np.concatenate(pts).astype(np.float32) if pts else np.zeros((0, 2), np.float32),
        loop_offsets=np.array(loop_offsets, dtype=np.int64),
        layer_offsets=np.array(layer_offsets, dtype=np.int64),
        loop_layer=np.array(loop_layer, dtype=np.int32),
        loop_is_hole=np.array(is_hole, dtype=bool),
        loop_parent=np.array(parent, dtype=np.int32),
        loop_closed=np.array(closed, dtype=bool),
        z=(np.arange(n) + 0.5) * thickness,
        thickness=np.full(n, thickness),
        area=np.array(area),
        repairs={"reversed": np.arange(n, dtype=np.int32)},
        meta={"device": "test", "n": n},
    )


@pytest.fixture
def result() -> SliceResult:
    """Layer 0: 10x10 square with a 4x4 hole (area 84); layer 1: two squares (9 + 4); layer 2: a 5x5
    square and an open chain (25); layer 3: empty."""
    chain = np.array([[-2.5, -1.0], [0.0, 1.5], [2.25, -1.0]], dtype=np.float32)
    return make_result(
        [
            [(square(-5, -5, 10), False, -1, True), (square(-2, -2, 4, ccw=False), True, 0, True)],
            [(square(20, 0, 3), False, -1, True), (square(30.125, 0, 2), False, -1, True)],
            [(square(0, 0, 5), False, -1, True), (chain, False, -1, False)],
            [],
        ]
    )


@pytest.fixture
def random_result() -> SliceResult:
    """Irregular float32 coordinates (negative, fractional) to check the number formatting."""
    rng = np.random.default_rng(7)
    layers = []
    for _ in range(3):
        loops = []
        for k in range(3):
            t = np.sort(rng.random(7)) * 2 * np.pi
            r = 1 + rng.random(7)
            c = rng.normal(0, 50, 2)
            outer = np.stack([c[0] + 3 * r * np.cos(t), c[1] + 3 * r * np.sin(t)], 1).astype(np.float32)
            loops.append((outer, False, -1, True))
            if k == 0:
                hole = np.stack([c[0] + 0.5 * np.cos(-t), c[1] + 0.5 * np.sin(-t)], 1).astype(np.float32)
                loops.append((hole, True, len(loops) - 1, True))
        loops.append((rng.normal(0, 30, (4, 2)).astype(np.float32), False, -1, False))
        layers.append(loops)
    return make_result(layers, thickness=0.1)


# ---------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------
def parse_d(d: str) -> list[tuple[np.ndarray, bool]]:
    """SVG path data as written by write_svg -> [(points (n, 2) in SVG coordinates, closed), ...]."""
    out = []
    for sub in d.split("M")[1:]:
        closed = sub.rstrip().endswith("Z")
        nums = sub.replace("Z", " ").replace("L", " ").replace(",", " ").split()
        out.append((np.array(nums, dtype=np.float64).reshape(-1, 2), closed))
    return out


def shoelace(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def svg_layers(path: Path) -> tuple[ET.Element, list[ET.Element]]:
    root = ET.parse(path).getroot()
    return root, root.findall(f"{SVG}g")


# ---------------------------------------------------------------------------------------------------------
# SVG
# ---------------------------------------------------------------------------------------------------------
def test_svg_structure(result, tmp_path):
    out = tmp_path / "r.svg"
    write_svg(result, out)
    root, groups = svg_layers(out)
    assert root.tag == f"{SVG}svg"
    assert len(groups) == result.n_layers
    assert len(root.findall(f".//{SVG}g")) == result.n_layers  # no other groups
    for i, g in enumerate(groups):
        assert g.get("id") == f"layer-{i}"
        assert float(g.get("data-z")) == pytest.approx(result.z[i], abs=1e-6)
        assert float(g.get("data-thickness")) == pytest.approx(result.thickness[i], abs=1e-6)
        assert float(g.get("data-bottom")) == pytest.approx(result.bottom[i], abs=1e-6)
    assert [len(g.findall(f"{SVG}path")) for g in groups] == [1, 2, 2, 0]

    # layer 0: one polygon path, outer + hole as two closed subpaths, even-odd
    (poly,) = groups[0].findall(f"{SVG}path")
    assert poly.get("fill-rule") == "evenodd"
    assert poly.get("class") == "polygon"
    subs = parse_d(poly.get("d"))
    assert len(subs) == 2 and all(closed for _, closed in subs)
    assert len(subs[0][0]) == 4 and len(subs[1][0]) == 4


def test_svg_area_matches_result(result, random_result, tmp_path):
    for k, res in enumerate((result, random_result)):
        out = tmp_path / f"r{k}.svg"
        write_svg(res, out)
        _, groups = svg_layers(out)
        for i, g in enumerate(groups):
            area = 0.0
            for path in g.findall(f"{SVG}path[@class='polygon']"):
                for pts, closed in parse_d(path.get("d")):
                    assert closed
                    back = pts * [1.0, -1.0]  # documented: y_svg = -y
                    area += shoelace(back)  # outer CCW (+), holes CW (-): the even-odd area of nested loops
            assert area == pytest.approx(res.area[i], abs=1e-3), i
    # layer 0 of the squares: |outer| - |hole| = 100 - 16
    assert result.area[0] == pytest.approx(84.0)


def test_svg_y_axis_points_up(result, tmp_path):
    out = tmp_path / "r.svg"
    write_svg(result, out)
    root, groups = svg_layers(out)
    (poly,) = groups[0].findall(f"{SVG}path")
    outer, _ = parse_d(poly.get("d"))[0]
    src = result.layer(0).loop(0).astype(np.float64)
    np.testing.assert_allclose(outer[:, 0], src[:, 0], atol=1e-4)
    np.testing.assert_allclose(outer[:, 1], -src[:, 1], atol=1e-4)
    # a point with a larger y has a smaller SVG y, i.e. it is drawn higher on the picture
    pts = np.concatenate([p for p, _ in parse_d(poly.get("d"))])
    y = np.concatenate([result.layer(0).loop(0), result.layer(0).loop(1)])[:, 1]
    assert np.array_equal(np.sign(np.subtract.outer(y, y)), -np.sign(np.subtract.outer(pts[:, 1], pts[:, 1])))
    # outer loops, counter-clockwise in the result, are clockwise in SVG's y-down coordinates
    assert shoelace(outer) < 0
    # the viewBox contains every point with a margin, and width/height are its size in mm
    x0, y0, w, h = map(float, root.get("viewBox").split())
    pts = result.points.astype(np.float64)
    assert x0 < pts[:, 0].min() and x0 + w > pts[:, 0].max()
    assert y0 < -pts[:, 1].max() and y0 + h > -pts[:, 1].min()
    assert root.get("width") == f"{ex.fmt_scalar(w)}mm"
    assert float(root.get("height")[:-2]) == pytest.approx(h)


def test_svg_open_chain(result, tmp_path):
    out = tmp_path / "r.svg"
    write_svg(result, out)
    _, groups = svg_layers(out)
    (chain,) = groups[2].findall(f"{SVG}path[@class='open']")
    assert chain.get("fill") == "none" and chain.get("stroke")
    assert "Z" not in chain.get("d")
    ((pts, closed),) = parse_d(chain.get("d"))
    assert not closed
    np.testing.assert_allclose(pts * [1, -1], result.layer(2).loop(1), atol=1e-4)


def test_svg_coordinates_precision(random_result, tmp_path):
    out = tmp_path / "r.svg"
    write_svg(random_result, out)
    _, groups = svg_layers(out)
    got = [pts * [1, -1] for g in groups for path in g.findall(f"{SVG}path") for pts, _ in parse_d(path.get("d"))]
    want = [lay.loop(k) for lay in random_result for k in range(len(lay.loops))]
    assert len(got) == len(want)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=0.5e-4 + 1e-5)
    assert re.search(r"-?\d+\.\d{4},-?\d+\.\d{4} ", out.read_text())  # fixed 4 decimals


def test_svg_deterministic_and_chunking(random_result, tmp_path, monkeypatch):
    a, b, c = tmp_path / "a.svg", tmp_path / "b.svg", tmp_path / "c.svg"
    write_svg(random_result, a)
    random_result.meta["timing"] = 123.0  # meta is not written
    write_svg(random_result, b)
    assert a.read_bytes() == b.read_bytes()
    monkeypatch.setattr(ex, "CHUNK_POINTS", 3)  # many small chunks: same bytes
    write_svg(random_result, c)
    assert a.read_bytes() == c.read_bytes()


def test_svg_scale_and_errors(result, tmp_path):
    write_svg(result, tmp_path / "a.svg")
    write_svg(result, tmp_path / "b.svg", scale=2)
    ra, rb = ET.parse(tmp_path / "a.svg").getroot(), ET.parse(tmp_path / "b.svg").getroot()
    assert ra.get("viewBox") == rb.get("viewBox")
    assert float(rb.get("width")[:-2]) == pytest.approx(2 * float(ra.get("width")[:-2]))
    for bad in (0, -1.0, float("nan"), float("inf"), "2"):
        with pytest.raises(ParameterError):
            write_svg(result, tmp_path / "c.svg", scale=bad)
    with pytest.raises(ParameterError):
        write_svg(result, tmp_path / "c.svg", decimals=12)
    result.points[0, 0] = np.nan
    with pytest.raises(ParameterError, match="non-finite"):
        write_svg(result, tmp_path / "c.svg")
    assert sorted(os.listdir(tmp_path)) == ["a.svg", "b.svg"]


def test_svg_orphan_hole_never_fills(tmp_path):
    res = make_result([[(square(0, 0, 2, ccw=False), True, -1, True), (square(5, 5, 2), False, -1, True)]])
    write_svg(res, tmp_path / "o.svg")
    _, (g,) = svg_layers(tmp_path / "o.svg")
    assert [p.get("class") for p in g.findall(f"{SVG}path")] == ["orphan", "polygon"]
    assert g.find(f"{SVG}path[@class='orphan']").get("fill") == "none"


def test_svg_empty_result(tmp_path):
    res = make_result([[], []])
    write_svg(res, tmp_path / "e.svg")
    root, groups = svg_layers(tmp_path / "e.svg")
    assert len(groups) == 2 and not root.findall(f".//{SVG}path")


# ---------------------------------------------------------------------------------------------------------
# CLI
# ---------------------------------------------------------------------------------------------------------
def check_cli_roundtrip(res: SliceResult, path: Path, atol: float) -> None:
    layers = read_cli(path)
    assert len(layers) == res.n_layers
    top = res.bottom + res.thickness
    for i, (z, polylines) in enumerate(layers):
        assert z == pytest.approx(top[i], abs=atol)  # documented: the layer's top
        lay = res.layer(i)
        assert len(polylines) == len(lay.loops)
        for k, (direction, pts) in enumerate(polylines):
            r = lay.loops[k]
            src = lay.loop(k)
            if res.loop_closed[r]:
                want = CLI_CLOCKWISE if res.loop_is_hole[r] else CLI_COUNTER_CLOCKWISE
                assert direction == want
                assert len(pts) == len(src) + 1
                np.testing.assert_array_equal(pts[0], pts[-1])  # closed: first point repeated
                np.testing.assert_allclose(pts[:-1], src, rtol=0, atol=atol)
            else:
                assert direction == CLI_OPEN
                np.testing.assert_allclose(pts, src, rtol=0, atol=atol)


def test_cli_roundtrip(result, random_result, tmp_path):
    for k, res in enumerate((result, random_result)):
        out = tmp_path / f"r{k}.cli"
        write_cli(res, out)
        check_cli_roundtrip(res, out, atol=0.5e-4 + 1e-5)


def test_cli_layers_thinner_than_its_digits_keep_their_heights(tmp_path):
    """Layers of 0.00005 mm written to 4 decimals were $$LAYER/0.0000, 0.0001, 0.0002, 0.0002, ... (a helper's
    audit): the heights now get the digits that keep them apart; digits the caller chose are refused instead."""
    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.mesh import shapes

    res = slice_mesh(mesh_from_triangles(shapes.box(hi=(1.0, 1.0, 0.001))), thickness=0.00005, backend="numpy")
    assert res.n_layers == 20
    write_cli(res, tmp_path / "t.cli")
    tops = [z for z, _ in read_cli(tmp_path / "t.cli")]
    np.testing.assert_allclose(tops, res.bottom + res.thickness, rtol=0, atol=1e-9)
    assert "$$LAYER/0.00005\n" in (tmp_path / "t.cli").read_text()
    check_cli_roundtrip(res, tmp_path / "t.cli", atol=0.5e-4 + 1e-9)
    with pytest.raises(ParameterError, match=r"decimals=4 writes two layers at one height"):
        write_cli(res, tmp_path / "u.cli", decimals=4)
    assert not (tmp_path / "u.cli").exists()


def test_cli_text(result, tmp_path):
    out = tmp_path / "r.cli"
    write_cli(result, out)
    lines = out.read_text().splitlines()
    assert lines[:4] == ["$$HEADERSTART", "$$ASCII", "$$UNITS/00000001.000000", "$$VERSION/200"]
    assert "$$LAYERS/000004" in lines
    assert lines.index("$$HEADEREND") < lines.index("$$GEOMETRYSTART")
    assert lines[-1] == "$$GEOMETRYEND"
    layer_lines = [ln for ln in lines if ln.startswith("$$LAYER/")]
    assert layer_lines == ["$$LAYER/0.2000", "$$LAYER/0.4000", "$$LAYER/0.6000", "$$LAYER/0.8000"]
    # layer 0: outer CCW (dir 1) then the hole CW (dir 0), 4 corners + the repeated first point
    i = lines.index("$$LAYER/0.2000")
    assert lines[i + 1] == (
        "$$POLYLINE/1,1,5,-5.0000,-5.0000,5.0000,-5.0000,5.0000,5.0000,-5.0000,5.0000,-5.0000,-5.0000"
    )
    assert lines[i + 2].startswith("$$POLYLINE/1,0,5,-2.0000,2.0000,")
    assert "$$POLYLINE/1,2,3,-2.5000,-1.0000,0.0000,1.5000,2.2500,-1.0000" in lines
    assert lines[lines.index("$$LAYER/0.8000") + 1] == "$$GEOMETRYEND"  # the empty layer is kept
    assert "$$DIMENSION/-5.0000,-5.0000,0.0000,32.1250,5.0000,0.8000" in lines


def test_cli_units(random_result, tmp_path):
    out = tmp_path / "um.cli"
    write_cli(random_result, out, units_mm=0.001)
    text = out.read_text()
    assert "$$UNITS/00000000.001000" in text
    poly = next(ln for ln in text.splitlines() if ln.startswith("$$POLYLINE"))
    assert re.fullmatch(r"\$\$POLYLINE/1,[012],\d+(,-?\d+\.\d)+", poly)  # 1 decimal of µm
    check_cli_roundtrip(random_result, out, atol=0.5e-4 + 1e-5)
    write_cli(random_result, out, units_mm=0.001, decimals=0)
    assert re.fullmatch(r"\$\$POLYLINE/1,[012],\d+(,-?\d+)+", out.read_text().splitlines()[10])
    check_cli_roundtrip(random_result, out, atol=0.5e-3 + 1e-5)
    for bad in (0, -1, 1e-9, float("nan")):
        with pytest.raises(ParameterError):
            write_cli(random_result, out, units_mm=bad)
    with pytest.raises(ParameterError):
        write_cli(random_result, out, label="a,b")


def test_cli_deterministic_and_chunking(random_result, tmp_path, monkeypatch):
    a, b, c = tmp_path / "a.cli", tmp_path / "b.cli", tmp_path / "c.cli"
    write_cli(random_result, a)
    write_cli(random_result, b)
    assert a.read_bytes() == b.read_bytes()
    monkeypatch.setattr(ex, "CHUNK_POINTS", 2)
    write_cli(random_result, c)
    assert a.read_bytes() == c.read_bytes()


def test_read_cli_tolerant_and_errors(tmp_path):
    p = tmp_path / "x.cli"
    p.write_text(
        "$$HEADERSTART // a comment //\n$$ASCII\n$$UNITS/0.5\n$$HEADEREND\n$$GEOMETRYSTART\n"
        "$$LAYER/2\n$$POLYLINE/1,1,4,0,0,\n 2,0,2,2,\n0,0\n$$HATCHES/1,1,0,0,1,1\n$$GEOMETRYEND\n"
    )
    ((z, ((direction, pts),)),) = read_cli(p)
    assert z == 1.0 and direction == 1
    np.testing.assert_array_equal(pts, [[0, 0], [1, 0], [1, 1], [0, 0]])
    for bad in ("garbage", "$$LAYER/1\n$$POLYLINE/1,1,3,0,0", "$$BINARY\n", "$$POLYLINE/1,1,1,0,0"):
        p.write_text(bad)
        with pytest.raises(MeshFileError):
            read_cli(p)
    with pytest.raises(MeshFileError):
        read_cli(tmp_path / "missing.cli")


# ---------------------------------------------------------------------------------------------------------
# npz (SliceResult.save / load, which use atomic_path)
# ---------------------------------------------------------------------------------------------------------
def test_npz_roundtrip_and_bytes(result, tmp_path, monkeypatch):
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    result.save(a)
    monkeypatch.setattr("time.time", lambda: 2_000_000_000.0)  # a different clock must not matter
    result.save(b)
    assert a.read_bytes() == b.read_bytes()
    assert sorted(os.listdir(tmp_path)) == ["a.npz", "b.npz"]
    back = SliceResult.load(a)
    for name in ex_result_arrays():
        x, y = getattr(result, name), getattr(back, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert back.repairs.keys() == result.repairs.keys()
    np.testing.assert_array_equal(back.repairs["reversed"], result.repairs["reversed"])
    assert back.meta == result.meta


def ex_result_arrays() -> tuple[str, ...]:
    from gpuslice.slicing import result as result_module

    return result_module._ARRAYS


# ---------------------------------------------------------------------------------------------------------
# atomic_path
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("exc", [ValueError, KeyboardInterrupt, SystemExit])
def test_atomic_path_failure_leaves_nothing(tmp_path, exc):
    target = tmp_path / "out.svg"
    seen = []
    with pytest.raises(exc):
        with atomic_path(target) as tmp:
            seen.append(tmp)
            tmp.write_text("partial")
            raise exc()
    assert os.listdir(tmp_path) == []
    (tmp,) = seen
    assert tmp.parent == tmp_path and tmp.name.startswith(".out.svg.tmp-") and tmp.suffix == ".svg"
    assert f"-{os.getpid()}-" in tmp.name


def test_atomic_path_failure_keeps_old_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text("new but unfinished")
            raise KeyboardInterrupt
    assert target.read_text() == "old"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_atomic_path_success(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert not tmp.exists()
        tmp.write_text("new")
        assert target.read_text() == "old"  # nothing visible until the block completes
    assert target.read_text() == "new"
    assert os.listdir(tmp_path) == ["out.txt"]


def test_atomic_path_directories(tmp_path):
    target = tmp_path / "layers"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            (tmp / "sub").mkdir(parents=True)
            (tmp / "sub" / "a.png").write_bytes(b"x")
            raise RuntimeError("boom")
    assert os.listdir(tmp_path) == []
    for content in (b"first", b"second"):  # a new tree, then one replacing it
        with atomic_path(target) as tmp:
            tmp.mkdir()
            (tmp / "a.bin").write_bytes(content)
        assert (target / "a.bin").read_bytes() == content
        assert os.listdir(tmp_path) == ["layers"]


def test_atomic_path_errors(tmp_path):
    with pytest.raises(ParameterError, match="does not exist"):
        with atomic_path(tmp_path / "no" / "such.txt"):
            pass
    with pytest.raises(FileNotFoundError):
        with atomic_path(tmp_path / "x.txt"):
            pass  # nothing written
    (tmp_path / "d").mkdir()
    with pytest.raises(ParameterError, match="is a directory"):
        atomic_write_text(tmp_path / "d", "x")
    assert sorted(os.listdir(tmp_path)) == ["d"]


@pytest.mark.skipif(os.name == "nt", reason="POSIX links and modes")
def test_atomic_path_through_links_and_over_protected_files(tmp_path):
    """An audit of the outputs: a symbolic link was replaced by a file and its target left stale (exit 0); a folder
    reached through a link failed with "Not a directory"; a write-protected file was replaced without a word; a
    0600 output came back 0644."""
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "t.bin"
    target.write_bytes(b"old")
    link = tmp_path / "l.bin"
    link.symlink_to(target)
    atomic_write_bytes(link, b"new")
    assert link.is_symlink() and target.read_bytes() == b"new"
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "a").write_bytes(b"1")
    (tmp_path / "dl").symlink_to(tmp_path / "d")
    with atomic_path(tmp_path / "dl") as tmp:
        tmp.mkdir()
        (tmp / "b").write_bytes(b"2")
    assert (tmp_path / "dl").is_symlink() and sorted(p.name for p in (tmp_path / "d").iterdir()) == ["b"]
    private = tmp_path / "p.bin"
    private.write_bytes(b"x")
    private.chmod(0o600)
    atomic_write_bytes(private, b"y")
    assert private.read_bytes() == b"y" and private.stat().st_mode & 0o777 == 0o600
    private.chmod(0o444)
    with pytest.raises(ParameterError, match=r"p\.bin: is write-protected"):
        atomic_write_bytes(private, b"z")
    assert private.read_bytes() == b"y" and not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]


def test_atomic_write_helpers(tmp_path):
    atomic_write_bytes(tmp_path / "b.bin", b"\x00\x01")
    atomic_write_text(tmp_path / "t.txt", "é\r\nx")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    assert (tmp_path / "t.txt").read_bytes() == "é\r\nx".encode()
    assert sorted(os.listdir(tmp_path)) == ["b.bin", "t.txt"]


# ---------------------------------------------------------------------------------------------------------
# reports and dispatch
# ---------------------------------------------------------------------------------------------------------
def test_write_report(tmp_path):
    report = {
        "b": np.arange(3, dtype=np.int32),
        "a": {"x": np.float32(0.5), "n": np.int64(7), "flag": np.bool_(True), "p": tmp_path / "f"},
        "t": (1, np.float64(2.5)),
        "m": np.eye(2),
        np.int64(3): "key",
    }
    out = tmp_path / "r.json"
    write_report(report, out)
    text = out.read_text()
    assert text.startswith('{\n "3": "key",\n "a": {\n  "flag": true,')
    assert text.endswith("}\n")
    back = json.loads(text)
    assert back == {
        "3": "key",
        "a": {"flag": True, "n": 7, "p": str(tmp_path / "f"), "x": 0.5},
        "b": [0, 1, 2],
        "m": [[1.0, 0.0], [0.0, 1.0]],
        "t": [1, 2.5],
    }
    assert list(back) == sorted(back)
    with pytest.raises(TypeError):
        write_report({"x": object()}, tmp_path / "bad.json")
    assert sorted(os.listdir(tmp_path)) == ["r.json"]


def test_export_dispatch(result, tmp_path):
    export(result, tmp_path / "a.svg")
    write_svg(result, tmp_path / "b.svg")
    assert (tmp_path / "a.svg").read_bytes() == (tmp_path / "b.svg").read_bytes()
    export(result, tmp_path / "a.CLI", units_mm=0.01)
    assert "$$UNITS/00000000.010000" in (tmp_path / "a.CLI").read_text()
    export(result, tmp_path / "a.npz")
    np.testing.assert_array_equal(SliceResult.load(tmp_path / "a.npz").points, result.points)
    listed = suffixes()
    assert listed[:3] == [".npz", ".svg", ".cli"]
    usage = ", ".join(listed[:-1]) + " or " + listed[-1]  # every registered format is named
    with pytest.raises(ParameterError, match=re.escape(f"unknown output format '.stl' (use {usage})")):
        export(result, tmp_path / "a.stl")
    with pytest.raises(ParameterError, match=re.escape(f"noext: no suffix to say the output format (use {usage}")):
        export(result, tmp_path / "noext")
    with pytest.raises(ParameterError):
        export(result, tmp_path / "c.svg", bogus=1)
    with pytest.raises(GpusliceError):
        export(result, tmp_path / "no" / "dir.svg")
    assert sorted(os.listdir(tmp_path)) == ["a.CLI", "a.npz", "a.svg", "b.svg"]


# ---------------------------------------------------------------------------------------------------------
# the vectorised number formatter
# ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("decimals", [0, 1, 4, 9])
def test_format_fixed_matches_python(decimals):
    rng = np.random.default_rng(decimals)
    v = rng.normal(0, 1, 2000) * 10.0 ** rng.integers(-6, 9, 2000)
    v = np.concatenate([v[np.abs(v) <= 1e9], [0.0, -0.0, 1e-12, -1e-12, 9.99995, -9.99995, 1e9, -1e9]])
    tokens_before = [(np.array([0, 5]), b"<"), (np.array([5]), [b"[["])]
    buf, starts = ex.format_fixed(v, decimals, ord("|"), tokens_before, [(np.array([5, len(v) - 1]), b">")])
    text = buf.tobytes().decode()
    pieces = [text[starts[i] : starts[i + 1]] for i in range(len(v))]
    q = np.rint(v * 10.0**decimals).astype(np.int64)
    want = [f"{abs(x) / 10**decimals:.{decimals}f}" if abs(x) < 2**53 else None for x in q.tolist()]
    for i, (piece, w, x) in enumerate(zip(pieces, want, q.tolist(), strict=True)):
        core = piece.lstrip("<[").rstrip(">").rstrip("|")
        digits = str(abs(x)).rjust(decimals + 1, "0")
        exact = digits[:-decimals] + "." + digits[-decimals:] if decimals else digits
        assert core == ("-" if x < 0 else "") + exact, (i, piece)
        if w is not None and abs(x) < 1e15:
            assert core.lstrip("-") == w
    assert pieces[0] == "<" + pieces[0][1:] and pieces[5].startswith("<[[") and pieces[5].endswith("|>")
    assert pieces[-1].endswith("|>")


def test_formats_that_state_layers_by_their_tops_refuse_slabs_that_do_not_stack(tmp_path):
    """A 3MF slice stack and a CLI file give each layer its top alone, the one below ending where it starts: planes
    at 3, 5 and 7 mm with 0.1 mm slabs came out as 2 mm thick layers (an audit). Refused, naming the formats that
    state each slab; planes whose slabs stack from any height are written."""
    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.formats.threemf import read_3mf_slices
    from gpuslice.mesh import shapes

    cube = mesh_from_triangles(shapes.box((0, 0, 0), (10, 10, 10)))
    apart = slice_mesh(cube, z=np.array([3.0, 5.0, 7.0]), layer_thickness=0.1, backend="numpy")
    for suffix in (".3mf", ".cli"):
        out = tmp_path / f"apart{suffix}"
        with pytest.raises(ParameterError, match=r"layer 0 ends at 3\.05 mm and layer 1 starts at 4\.95 mm"):
            export(apart, out)
        assert not out.exists()
    band = slice_mesh(cube, z=np.array([3.05, 3.15, 3.25]), layer_thickness=0.1, backend="numpy")
    export(band, tmp_path / "band.3mf")
    z_bottom, slices = read_3mf_slices(tmp_path / "band.3mf")
    assert z_bottom == pytest.approx(3.0) and [s[0] for s in slices] == pytest.approx([3.1, 3.2, 3.3])
    export(band, tmp_path / "band.cli")
    assert [z for z, _ in read_cli(tmp_path / "band.cli")] == pytest.approx([3.1, 3.2, 3.3])
