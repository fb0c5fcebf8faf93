"""Tests of gpuslice.io.meshfile: binary / ASCII STL parsing, trimesh formats, and every user-facing error."""

from __future__ import annotations

import csv
import os
import struct
import subprocess
import sys
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gpuslice.errors import EmptyMeshError, GpusliceError, InvalidGeometryError, MeshFileError
from gpuslice.io import meshfile as stl_module
from gpuslice.io.meshfile import RawMesh, read_mesh_file, read_stl_bytes

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "meshes"
SHARED_MISSING = f"../shared/meshes not found: {SHARED} (the shared mesh corpus beside the repository)"

# --------------------------------------------------------------------------------------------------------
# helpers that write STL files


def random_triangles(n: int, seed: int = 0, scale: float = 100.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((n, 3, 3)) * scale).astype(np.float32)


def make_binary_stl(tri: np.ndarray, normals: np.ndarray | None = None, header: bytes = b"gpuslice test",
                    count: int | None = None, extra: bytes = b"") -> bytes:
    """A binary STL of ``tri`` ((F, 3, 3)); ``count`` overrides the declared facet count."""
    tri = np.asarray(tri, dtype="<f4").reshape(-1, 3, 3)
    if normals is None:
        normals = np.zeros((len(tri), 3), dtype="<f4")
    rec = np.zeros(len(tri), dtype=stl_module.BINARY_STL_RECORD)
    rec["normal"] = normals
    rec["v"] = tri
    head = header[:80].ljust(80, b"\0")
    return head + struct.pack("<I", len(tri) if count is None else count) + rec.tobytes() + extra


def fmt(x: float) -> str:
    """Shortest text that reads back as the same float32."""
    return np.format_float_scientific(np.float32(x), unique=True)


def make_ascii_stl(tri: np.ndarray, normals: np.ndarray | None = None, name: str = "test", eol: str = "\n",
                   upper: bool = False, end_junk: bool = False) -> bytes:
    """An ASCII STL of ``tri`` as one solid."""
    tri = np.asarray(tri, dtype=np.float32).reshape(-1, 3, 3)
    if normals is None:
        normals = np.zeros((len(tri), 3), dtype=np.float32)
    lines = [f"solid {name}"]
    for t, n in zip(tri, normals, strict=True):
        lines.append(f"  facet normal {fmt(n[0])} {fmt(n[1])} {fmt(n[2])}")
        lines.append("    outer loop")
        for v in t:
            lines.append(f"      vertex {fmt(v[0])} {fmt(v[1])} {fmt(v[2])}")
        lines.append("    endloop" + (" trailing words" if end_junk else ""))
        lines.append("  endfacet" + (" bar" if end_junk else ""))
    lines.append(f"endsolid {name}" + (" some blah blah" if end_junk else ""))
    text = eol.join(lines) + eol
    if upper:
        text = text.upper()
    return text.encode("ascii")


def write(tmp_path: Path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


def check_message(exc: BaseException, path: Path | str) -> str:
    """Every user error is one line naming the file."""
    msg = str(exc)
    assert "\n" not in msg and "\r" not in msg, msg
    assert str(path) in msg, msg
    return msg


def raises_for(tmp_path: Path, name: str, data: bytes, cls: type[Exception], match: str) -> str:
    p = write(tmp_path, name, data)
    with pytest.raises(cls, match=match) as info:
        read_mesh_file(p)
    return check_message(info.value, p)


CUBE_TRI = random_triangles(12, seed=1)

# --------------------------------------------------------------------------------------------------------
# binary STL


def test_binary_round_trip(tmp_path: Path) -> None:
    tri = random_triangles(37, seed=2)
    normals = random_triangles(37, seed=3)[:, 0]
    p = write(tmp_path, "model.stl", make_binary_stl(tri, normals, header=b"my header"))
    mesh = read_mesh_file(p)
    assert isinstance(mesh, RawMesh)
    assert mesh.source_format == "binary STL"
    assert mesh.triangles.dtype == np.float32 and mesh.triangles.shape == (37, 3, 3)
    assert mesh.triangles.flags.c_contiguous and mesh.triangles.flags.writeable
    np.testing.assert_array_equal(mesh.triangles, tri)
    assert mesh.normals is not None and mesh.normals.dtype == np.float32
    np.testing.assert_array_equal(mesh.normals, normals)
    assert mesh.header == b"my header".ljust(80, b"\0")
    assert mesh.solids == 1
    assert mesh.path == str(p)


def test_binary_path_like_and_str(tmp_path: Path) -> None:
    p = write(tmp_path, "a.stl", make_binary_stl(CUBE_TRI))
    np.testing.assert_array_equal(read_mesh_file(str(p)).triangles, read_mesh_file(p).triangles)


def test_binary_with_solid_header_is_binary(tmp_path: Path) -> None:
    """Size decides: a binary file whose header starts with 'solid' is still binary."""
    data = make_binary_stl(CUBE_TRI, header=b"solid REAR_CASE exported by CAD")
    mesh = read_mesh_file(write(tmp_path, "solidheader.stl", data))
    assert mesh.source_format == "binary STL"
    np.testing.assert_array_equal(mesh.triangles, CUBE_TRI)


def test_binary_junk_normals_kept(tmp_path: Path) -> None:
    normals = np.array([[np.nan, np.inf, -np.inf]] + [[0, 0, 0]] * 11, dtype=np.float32)
    mesh = read_mesh_file(write(tmp_path, "n.stl", make_binary_stl(CUBE_TRI, normals)))
    np.testing.assert_array_equal(mesh.normals, normals)


def test_read_stl_bytes_default_name() -> None:
    mesh = read_stl_bytes(make_binary_stl(CUBE_TRI))
    assert mesh.path == "<bytes>"
    np.testing.assert_array_equal(mesh.triangles, CUBE_TRI)
    mesh = read_stl_bytes(bytearray(make_binary_stl(CUBE_TRI)), "buf.stl")
    assert mesh.path == "buf.stl"


@pytest.mark.parametrize("extra", [1, 2, 49])
def test_binary_small_trailing_padding_accepted(tmp_path: Path, extra: int) -> None:
    mesh = read_mesh_file(write(tmp_path, "pad.stl", make_binary_stl(CUBE_TRI, extra=b"\0" * extra)))
    np.testing.assert_array_equal(mesh.triangles, CUBE_TRI)


@pytest.mark.parametrize("extra", [50, 51, 120, 5000])
def test_binary_large_trailing_data_rejected(tmp_path: Path, extra: int) -> None:
    data = make_binary_stl(CUBE_TRI, extra=b"\x01" * extra)
    raises_for(tmp_path, "trail.stl", data, MeshFileError,
               rf"trail\.stl: binary STL has {extra} unexpected bytes after the 12 facets its header "
               r"declares")


def test_binary_truncated(tmp_path: Path) -> None:
    data = make_binary_stl(random_triangles(5))[:200]
    msg = raises_for(tmp_path, "model.stl", data, MeshFileError,
                     r"model\.stl: truncated binary STL: header declares 5 facets \(334 bytes\) "
                     r"but the file has 200 bytes")
    assert "MeshFileError" not in msg


def test_binary_huge_count_does_not_allocate(tmp_path: Path) -> None:
    """A header claiming 2**32-1 facets (214 GB) on a 200-byte file must fail fast without allocating."""
    data = make_binary_stl(random_triangles(2), count=2**32 - 1)
    data = data + b"\x07" * (200 - len(data))
    assert len(data) == 200
    p = write(tmp_path, "liar.stl", data)
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(MeshFileError, match=r"truncated binary STL: header declares 4294967295 facets"):
            read_mesh_file(p)
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert elapsed < 1.0
    assert peak < 1_000_000, peak


def test_binary_too_short(tmp_path: Path) -> None:
    raises_for(tmp_path, "short.stl", b"\x00\x01\x02" * 10, MeshFileError,
               r"short\.stl: .*too short to be a binary STL \(30 bytes\)")


def test_binary_empty_is_empty_mesh_error(tmp_path: Path) -> None:
    data = make_binary_stl(np.zeros((0, 3, 3)))
    assert len(data) == 84
    raises_for(tmp_path, "empty.stl", data, EmptyMeshError, r"empty\.stl: no facets")


def test_binary_nan_and_inf_coordinates(tmp_path: Path) -> None:
    tri = CUBE_TRI.copy()
    tri[3, 1, 2] = np.nan
    tri[7, 0, 0] = np.inf
    tri[7, 2, 1] = -np.inf
    raises_for(tmp_path, "nan.stl", make_binary_stl(tri), InvalidGeometryError,
               r"nan\.stl: 2 facets have NaN or infinite vertex coordinates \(first: facet 4 of 12\)")


def test_binary_flt_max_coordinates(tmp_path: Path) -> None:
    tri = CUBE_TRI.copy()
    tri[0, 0, 0] = np.finfo(np.float32).max
    raises_for(tmp_path, "big.stl", make_binary_stl(tri), InvalidGeometryError,
               r"big\.stl: coordinates up to 3\.4e\+38 overflow float32 arithmetic")


def test_coordinate_limit_is_inclusive(tmp_path: Path) -> None:
    tri = CUBE_TRI.copy()
    tri[0, 0, 0] = 1e17
    mesh = read_mesh_file(write(tmp_path, "ok.stl", make_binary_stl(tri)))
    assert mesh.triangles[0, 0, 0] == np.float32(1e17)
    tri[0, 0, 0] = -2e18
    raises_for(tmp_path, "far.stl", make_binary_stl(tri), InvalidGeometryError, r"coordinates up to 2e\+18")


# --------------------------------------------------------------------------------------------------------
# not STL at all, file system errors


@pytest.mark.parametrize(
    ("data", "what"),
    [
        (b"\x89PNG\r\n\x1a\n" + b"\x00" * 200, "PNG image"),
        (b"PK\x03\x04" + b"\x00" * 300, "ZIP archive"),
        (b"This is a README, not a mesh.\nIt has several lines of text, but no solid keyword.\n" * 3, "text"),
        (b"hello", "too short"),
        (b"", "empty"),
    ],
)
def test_not_an_stl_file(tmp_path: Path, data: bytes, what: str) -> None:
    msg = raises_for(tmp_path, "fake.stl", data, MeshFileError, r"fake\.stl: not an STL file")
    assert what in msg


def test_missing_file(tmp_path: Path) -> None:
    p = tmp_path / "nope.stl"
    with pytest.raises(MeshFileError, match=r"nope\.stl: no such file") as info:
        read_mesh_file(p)
    check_message(info.value, p)
    with pytest.raises(MeshFileError, match=r"nope\.obj: no such file"):
        read_mesh_file(tmp_path / "nope.obj")


def test_directory(tmp_path: Path) -> None:
    d = tmp_path / "folder.stl"
    d.mkdir()
    with pytest.raises(MeshFileError, match=r"folder\.stl: is a directory") as info:
        read_mesh_file(d)
    check_message(info.value, d)


def test_unreadable_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = write(tmp_path, "locked.stl", make_binary_stl(CUBE_TRI))

    def denied(*args: object, **kwargs: object) -> None:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(stl_module, "open", denied, raising=False)
    with pytest.raises(MeshFileError, match=r"locked\.stl: cannot read: permission denied") as info:
        read_mesh_file(p)
    check_message(info.value, p)


def test_errors_are_gpuslice_errors() -> None:
    assert issubclass(EmptyMeshError, MeshFileError) and issubclass(InvalidGeometryError, MeshFileError)
    assert issubclass(MeshFileError, GpusliceError)


# --------------------------------------------------------------------------------------------------------
# ASCII STL


@pytest.mark.parametrize("eol", ["\n", "\r\n", "\r"], ids=["LF", "CRLF", "CR"])
def test_ascii_round_trip_line_ends(tmp_path: Path, eol: str) -> None:
    tri = random_triangles(25, seed=4)
    normals = random_triangles(25, seed=5)[:, 0]
    mesh = read_mesh_file(write(tmp_path, "a.stl", make_ascii_stl(tri, normals, name="Part 7", eol=eol)))
    assert mesh.source_format == "ASCII STL"
    assert mesh.triangles.dtype == np.float32 and mesh.triangles.shape == (25, 3, 3)
    np.testing.assert_array_equal(mesh.triangles, tri)
    np.testing.assert_array_equal(mesh.normals, normals)
    assert mesh.header == b"solid Part 7"
    assert mesh.solids == 1


def test_ascii_upper_case_keywords_and_end_junk(tmp_path: Path) -> None:
    tri = random_triangles(6, seed=6)
    mesh = read_mesh_file(write(tmp_path, "u.stl", make_ascii_stl(tri, upper=True, end_junk=True)))
    np.testing.assert_array_equal(mesh.triangles, tri)
    assert mesh.header == b"SOLID TEST"


def test_ascii_any_layout(tmp_path: Path) -> None:
    """Tokens may be laid out on lines in any way; tabs and leading blank lines are fine."""
    text = (b"\n\n  solid odd\n\tfacet normal 0 0 1 outer loop vertex 0 0 0\tvertex 1 0 0 vertex 0 1 0 "
            b"endloop endfacet\nfacet normal 0 0 1\nouter loop\nvertex 1 1 1\nvertex 2 1 1\nvertex 1 2 1\n"
            b"endloop\nendfacet\nendsolid\n")
    mesh = read_mesh_file(write(tmp_path, "layout.stl", text))
    np.testing.assert_array_equal(mesh.triangles[1], [[1, 1, 1], [2, 1, 1], [1, 2, 1]])


def test_ascii_two_solids(tmp_path: Path) -> None:
    a, b = random_triangles(3, seed=7), random_triangles(4, seed=8)
    data = make_ascii_stl(a, name="first") + make_ascii_stl(b, name="second", eol="\r\n")
    mesh = read_mesh_file(write(tmp_path, "two.stl", data))
    assert mesh.solids == 2
    assert mesh.header == b"solid first"
    np.testing.assert_array_equal(mesh.triangles, np.concatenate([a, b]))


def test_ascii_junk_normals(tmp_path: Path) -> None:
    lines = _facets_text(2)
    assert lines[1].startswith("  facet normal")
    lines[1] = "  facet normal +inf  -inf  weirdvalue"
    data = "\n".join(lines).encode()
    mesh = read_mesh_file(write(tmp_path, "junk.stl", data))
    assert mesh.normals is not None
    assert mesh.normals[0, 0] == np.inf and mesh.normals[0, 1] == -np.inf and np.isnan(mesh.normals[0, 2])
    np.testing.assert_array_equal(mesh.normals[1], [0, 0, 0])
    np.testing.assert_array_equal(mesh.triangles, CUBE_TRI[:2])


def test_ascii_trailing_nul_and_ctrl_z(tmp_path: Path) -> None:
    mesh = read_mesh_file(write(tmp_path, "dos.stl", make_ascii_stl(CUBE_TRI) + b"\x1a\x00\x00"))
    np.testing.assert_array_equal(mesh.triangles, CUBE_TRI)


def test_ascii_empty(tmp_path: Path) -> None:
    raises_for(tmp_path, "e.stl", b"solid nothing\nendsolid nothing\n", EmptyMeshError, r"e\.stl: no facets")


def _facets_text(n: int) -> list[str]:
    return make_ascii_stl(CUBE_TRI[:n]).decode().splitlines()


def test_ascii_four_vertices(tmp_path: Path) -> None:
    lines = _facets_text(3)
    # facet 2 spans lines 9..15; add a fourth vertex after its third (line 13)
    lines.insert(13, "      vertex 1 2 3")
    raises_for(tmp_path, "quad.stl", "\n".join(lines).encode(), MeshFileError,
               r"quad\.stl: malformed ASCII STL: facet 2 \(line 9\): "
               r"the outer loop has 4 vertices, expected 3")


def test_ascii_two_vertices(tmp_path: Path) -> None:
    lines = _facets_text(3)
    del lines[18]  # facet 3's second vertex
    raises_for(tmp_path, "two.stl", "\n".join(lines).encode(), MeshFileError,
               r"two\.stl: malformed ASCII STL: facet 3 \(line 16\): "
               r"the outer loop has 2 vertices, expected 3")


def test_ascii_unparsable_coordinate(tmp_path: Path) -> None:
    lines = _facets_text(3)
    lines[11] = "      vertex 1.0 abc 2.0"
    raises_for(tmp_path, "bad.stl", "\n".join(lines).encode(), MeshFileError,
               r"bad\.stl: malformed ASCII STL: facet 2 \(line 12\): cannot parse vertex coordinate 'abc'")


def test_ascii_vertex_with_two_coordinates(tmp_path: Path) -> None:
    lines = _facets_text(2)
    lines[3] = "      vertex 1.0 2.0"
    raises_for(tmp_path, "v2.stl", "\n".join(lines).encode(), MeshFileError,
               r"v2\.stl: malformed ASCII STL: facet 1 \(line 4\): a vertex has 2 coordinates, expected 3")


def test_ascii_missing_endsolid(tmp_path: Path) -> None:
    data = make_ascii_stl(CUBE_TRI[:2]).rsplit(b"endsolid", 1)[0]
    raises_for(tmp_path, "cut.stl", data, MeshFileError, r"cut\.stl: truncated ASCII STL: .*no 'endsolid'")


def test_ascii_cut_inside_facet(tmp_path: Path) -> None:
    data = make_ascii_stl(CUBE_TRI[:3])
    data = data[: data.index(b"endloop", 400)] + b"endsolid test\n"
    raises_for(tmp_path, "cut2.stl", data, MeshFileError, r"cut2\.stl: malformed ASCII STL: facet \d")


@pytest.mark.parametrize(
    "data",
    [
        b"solid words\nhello world this is not a mesh\nendsolid words\n",
        b"solid words\nhello world this is not a mesh at all, just words words words words words\n",
        b"solid x\n" + bytes(range(256)) * 3,
        b"solid \x00\x01\x02\x03",
    ],
    ids=["words", "words-no-end", "binary-junk", "short-binary"],
)
def test_ascii_garbage(tmp_path: Path, data: bytes) -> None:
    raises_for(tmp_path, "garbage.stl", data, MeshFileError, r"garbage\.stl: not an STL file")


def test_ascii_text_outside_solid(tmp_path: Path) -> None:
    data = make_ascii_stl(CUBE_TRI[:1]) + b"and then some words\n"
    raises_for(tmp_path, "after.stl", data, MeshFileError,
               r"after\.stl: malformed ASCII STL: line 10: unexpected text")


@pytest.mark.parametrize(("value", "match"), [
    ("nan", r"1 facet has NaN or infinite vertex coordinates \(first: facet 2 of 3\)"),
    ("-inf", r"1 facet has NaN or infinite vertex coordinates"),
    ("1e400", r"1 facet has NaN or infinite vertex coordinates"),
    ("3.4e38", r"coordinates up to 3\.4e\+38 overflow float32 arithmetic"),
    ("-1e30", r"coordinates up to 1e\+30 overflow float32 arithmetic \(limit 1e\+18 as given, before any scaling; "
              r"1 facet affected\)"),
])
def test_ascii_bad_coordinates(tmp_path: Path, value: str, match: str) -> None:
    lines = _facets_text(3)
    lines[11] = f"      vertex 1.0 {value} 2.0"
    data = "\n".join(lines).encode()
    raises_for(tmp_path, "coord.stl", data, InvalidGeometryError, r"coord\.stl: " + match)


# --------------------------------------------------------------------------------------------------------
# trimesh formats

OBJ = b"""# two triangles
v 0 0 0
v 1 0 0
v 0 1 0
v 0 0 1
f 1 2 3
f 1 2 4
"""
OFF = b"OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 1 3\n"
PLY = (b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
       b"element face 2\nproperty list uchar int vertex_indices\nend_header\n"
       b"0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 1 3\n")
EXPECTED_TWO = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 0, 0], [1, 0, 0], [0, 0, 1]]], np.float32)


@pytest.mark.parametrize(("suffix", "data", "fmt_name"), [(".obj", OBJ, "obj"), (".OFF", OFF, "off"),
                                                         (".ply", PLY, "ply")])
def test_trimesh_formats(tmp_path: Path, suffix: str, data: bytes, fmt_name: str) -> None:
    mesh = read_mesh_file(write(tmp_path, "m" + suffix, data))
    assert mesh.source_format == fmt_name
    assert mesh.triangles.dtype == np.float64 and mesh.triangles.flags.c_contiguous  # (placed before rounding)
    np.testing.assert_array_equal(mesh.triangles, EXPECTED_TWO)
    assert mesh.normals is None and mesh.header == b"" and mesh.solids == 1


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
@pytest.mark.parametrize(("suffix", "data"), [(".obj", OBJ), (".stl", None)])
def test_a_fifo_is_read_like_a_file(tmp_path: Path, suffix: str, data: bytes | None) -> None:
    """A mesh piped in through a FIFO is read from its bytes (trimesh refused an OBJ by name: "not a file")."""
    import threading

    data = make_binary_stl(random_triangles(4, seed=9, scale=10.0)) if data is None else data
    fifo = tmp_path / ("pipe" + suffix)
    os.mkfifo(fifo)
    writer = threading.Thread(target=fifo.write_bytes, args=(data,), daemon=True)
    writer.start()
    try:
        mesh = read_mesh_file(fifo)
    finally:
        if writer.is_alive():  # the FIFO was not read (a failure): open it once so that the writer returns
            os.close(os.open(fifo, os.O_RDONLY | os.O_NONBLOCK))
        writer.join(timeout=10)
    np.testing.assert_array_equal(mesh.triangles, read_mesh_file(write(tmp_path, "m" + suffix, data)).triangles)


def test_trimesh_errors(tmp_path: Path) -> None:
    raises_for(tmp_path, "bad.ply", b"\x00\x01garbage", MeshFileError, r"bad\.ply: cannot read PLY file: ")
    raises_for(tmp_path, "bad.off", b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1\n3 0 1 2\n", MeshFileError,
               r"bad\.off: cannot read OFF file: vertex line 3")
    raises_for(tmp_path, "bad.3mf", b"PK\x03\x04junk", MeshFileError, r"bad\.3mf: cannot read 3MF file: ")
    raises_for(tmp_path, "empty.obj", b"# nothing\n", EmptyMeshError, r"empty\.obj: no facets")
    raises_for(tmp_path, "nan.obj", OBJ.replace(b"v 0 0 1", b"v 0 nan 1"), InvalidGeometryError,
               r"nan\.obj: 1 facet has NaN")


def test_import_does_not_import_trimesh() -> None:
    code = (
        "import sys, gpuslice.errors\n"
        "before = set(sys.modules)\n"
        "import gpuslice.io.meshfile\n"
        "new = sorted(m for m in set(sys.modules) - before if m.split('.')[0] in ('trimesh', 'scipy'))\n"
        "assert not new, new\n"
    )
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]))
    subprocess.run([sys.executable, "-c", code], check=True, cwd=root, env=env)


# --------------------------------------------------------------------------------------------------------
# the shared mesh corpus


def _catalog() -> list[dict[str, str]]:
    path = SHARED / "catalog.csv"
    if not path.is_file():
        return []
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


CATALOG = _catalog()
CATALOG_FILES = [row["file"] for row in CATALOG] or ["<missing>"]
RAW_FILES = [row["raw_file"] for row in CATALOG if row["raw_file"]] or ["<missing>"]


def _row(file: str) -> dict[str, str]:
    if not CATALOG:
        pytest.skip(SHARED_MISSING)
    return next(r for r in CATALOG if r["file"] == file or r["raw_file"] == file)


@pytest.mark.parametrize("file", CATALOG_FILES)
def test_shared_binary_files(file: str) -> None:
    row = _row(file)
    path = SHARED / file
    if file in ("p_empty_binary.stl", "p_empty_ascii.stl"):
        with pytest.raises(EmptyMeshError, match="no facets") as info:
            read_mesh_file(path)
        check_message(info.value, path)
        return
    if file == "p_flt_max_coords.stl":
        overflow = r"coordinates up to 3\.4e\+38 overflow float32 arithmetic"
        with pytest.raises(InvalidGeometryError, match=overflow) as info:
            read_mesh_file(path)
        check_message(info.value, path)
        return
    mesh = read_mesh_file(path)
    assert mesh.source_format == "binary STL"  # including the files whose header starts with "solid"
    assert len(mesh.triangles) == int(row["facets"])
    assert mesh.header[:5].lower() == b"solid" if row["header_starts_with_solid"] == "True" else True
    assert np.isfinite(mesh.triangles).all()


@pytest.mark.parametrize("raw", RAW_FILES)
def test_shared_ascii_matches_binary(raw: str) -> None:
    """The binary files were converted from the ASCII originals: the triangles must agree.

    Measured: they agree bit for bit (decimal -> float64 -> float32 here gives the same float32 as the
    converter), so this asserts exact equality rather than the 1e-6 relative tolerance one might expect.
    """
    row = _row(raw)
    ascii_path, binary_path = SHARED / raw, SHARED / row["file"]
    if int(row["facets"]) == 0:
        with pytest.raises(EmptyMeshError, match="no facets") as info:
            read_mesh_file(ascii_path)
        check_message(info.value, ascii_path)
        return
    a = read_mesh_file(ascii_path)
    b = read_mesh_file(binary_path)
    assert a.source_format == "ASCII STL" and b.source_format == "binary STL"
    assert len(a.triangles) == int(row["facets"])
    np.testing.assert_array_equal(a.triangles, b.triangles)
    assert a.header.lower().startswith(b"solid")


def test_shared_ascii_details() -> None:
    if not SHARED.is_dir():
        pytest.skip(SHARED_MISSING)
    assert read_mesh_file(SHARED / "raw" / "p_ascii_two_solids.stl").solids == 2
    assert read_mesh_file(SHARED / "raw" / "p_ascii_multibody.stl").solids == 2
    cr = SHARED / "raw" / "p_ascii_cr.stl"
    assert b"\r" in cr.read_bytes() and b"\n" not in cr.read_bytes()
    assert len(read_mesh_file(cr).triangles) == 12
    normals = read_mesh_file(SHARED / "raw" / "p_ascii_nonstandard.stl").normals
    assert normals is not None
    odd = normals[~np.isfinite(normals).all(axis=1)]
    assert len(odd) == 1
    assert odd[0, 0] == np.inf and odd[0, 1] == -np.inf and np.isnan(odd[0, 2])


# --------------------------------------------------------------------------------------------------------
# property tests: nothing but MeshFileError (or success) for damaged files

VALID_BINARY = make_binary_stl(random_triangles(4, seed=9, scale=10.0))
VALID_ASCII = make_ascii_stl(random_triangles(3, seed=10, scale=10.0))


def _only_mesh_errors(data: bytes) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            mesh = read_stl_bytes(data, "fuzz.stl")
        except MeshFileError as exc:
            msg = str(exc)
            assert msg.startswith("fuzz.stl: ") and "\n" not in msg, msg
            return
    assert mesh.triangles.dtype == np.float32 and mesh.triangles.ndim == 3 and len(mesh.triangles) >= 1
    assert np.isfinite(mesh.triangles).all()


def _damage(valid: bytes) -> st.SearchStrategy[bytes]:
    n = len(valid)
    truncated = st.integers(0, n + 60).map(lambda k: valid[:k] if k <= n else valid + b"\0" * (k - n))
    spliced = st.tuples(st.integers(0, n), st.integers(0, 60), st.binary(max_size=60)).map(
        lambda t: valid[: t[0]] + t[2] + valid[t[0] + t[1]:])
    flipped = st.tuples(st.integers(0, n - 1), st.integers(1, 255)).map(
        lambda t: valid[: t[0]] + bytes([valid[t[0]] ^ t[1]]) + valid[t[0] + 1:])
    return st.one_of(truncated, spliced, flipped, st.binary(max_size=400))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_damage(VALID_BINARY))
def test_property_damaged_binary_raises_only_mesh_errors(data: bytes) -> None:
    _only_mesh_errors(data)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_damage(VALID_ASCII))
def test_property_damaged_ascii_raises_only_mesh_errors(data: bytes) -> None:
    _only_mesh_errors(data)


def test_a_3mf_slice_stack_is_not_read_as_a_model(tmp_path: Path) -> None:
    """gpuslice's own 3MF output (a slice stack whose mesh is its bounding box, marked lowres) was read back as that
    box: sliced as a 20 mm cube by the next batch that found it. Refused, naming the file; a plain 3MF still reads."""
    import trimesh

    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.formats import export
    from gpuslice.mesh import shapes

    res = slice_mesh(mesh_from_triangles(shapes.hollow_box(20.0, 10.0)), thickness=2.0, backend="numpy")
    stack = tmp_path / "stack.3mf"
    export(res, stack)
    with pytest.raises(MeshFileError, match=r"stack\.3mf: a 3MF slice stack \(its mesh is a low-resolution"):
        read_mesh_file(stack)
    plain = tmp_path / "plain.3mf"
    trimesh.creation.box([10, 10, 10]).export(plain)
    assert read_mesh_file(plain).triangles.shape == (12, 3, 3)


def _3mf_in(path: Path, unit: str | None) -> Path:
    """A 10 mm box as a 3MF whose model declares ``unit`` (None: no unit attribute, the spec's millimetres)."""
    import io
    import re
    import zipfile

    import trimesh

    data = trimesh.creation.box([10, 10, 10]).export(file_type="3mf")
    src = zipfile.ZipFile(io.BytesIO(data))
    model = src.read("3D/3dmodel.model").decode()
    assert 'unit="millimeter"' in model
    model = re.sub(r' unit="millimeter"', "" if unit is None else f' unit="{unit}"', model, count=1)
    with zipfile.ZipFile(path, "w") as out:
        for name in src.namelist():
            out.writestr(name, model if name == "3D/3dmodel.model" else src.read(name))
    return path


@pytest.mark.parametrize(("unit", "mm"), [("inch", 254.0), ("centimeter", 100.0), ("micron", 0.01),
                                          ("meter", 10000.0), ("foot", 3048.0), ("millimeter", 10.0), (None, 10.0)])
def test_a_3mf_is_read_in_the_unit_its_model_declares(tmp_path: Path, unit, mm) -> None:
    """A 3MF in inches was read as millimetres (a 10 inch box sliced as 10 mm: silently 25.4 times too small)."""
    tri = read_mesh_file(_3mf_in(tmp_path / "box.3mf", unit)).triangles
    assert np.ptp(tri.reshape(-1, 3), axis=0) == pytest.approx([mm] * 3)


def test_a_3mf_of_an_unknown_unit_is_refused(tmp_path: Path) -> None:
    with pytest.raises(MeshFileError, match=r"box\.3mf: unknown 3MF unit 'parsec' \(the 3MF units are micron, "):
        read_mesh_file(_3mf_in(tmp_path / "box.3mf", "parsec"))
