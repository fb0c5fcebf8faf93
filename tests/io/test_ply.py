"""gpuslice's own PLY reader (:mod:`gpuslice.io.ply`): the same vertices and faces as trimesh where trimesh reads the
file right, in all three encodings; polygons (not triangulated) counted and listed exactly as written; other
properties and elements (lists among them, of mixed lengths in binary) skipped; broken files refused with one line
naming the file and the problem."""

from __future__ import annotations

import io
import struct

import numpy as np
import pytest

from gpuslice.errors import MeshFileError
from gpuslice.io.ply import read_ply

trimesh = pytest.importorskip("trimesh")

ENCODINGS = ["ascii", "binary_little_endian", "binary_big_endian"]
CODES = {"char": "b", "int8": "b", "uchar": "B", "uint8": "B", "short": "h", "int16": "h", "ushort": "H",
         "uint16": "H", "int": "i", "int32": "i", "uint": "I", "uint32": "I", "float": "f", "float32": "f",
         "double": "d", "float64": "d"}
CUBE_V = [(0, 0, 0), (10, 0, 0), (10, 10, 0), (0, 10, 0), (0, 0, 10), (10, 0, 10), (10, 10, 10), (0, 10, 10),
          (5, 0, 10)]  # (the last: on the front top edge, a fifth corner of the top and front faces)
# a closed cube of triangles (the bottom), quads and pentagons, every face outwards
CUBE_F = [(0, 3, 2), (0, 2, 1), (4, 8, 5, 6, 7), (0, 1, 5, 8, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
XYZ = ["float x", "float y", "float z"]
FACE = ["list uchar int vertex_indices"]


def ply(fmt: str, elements: list[tuple[str, list[str], list[tuple]]], head: str = "comment made by hand\n") -> bytes:
    """A PLY file of ``elements`` (name, property lines after ``property``, records: one value per property, a
    sequence for a list) in format ``fmt``."""
    lines = ["ply", f"format {fmt} 1.0", head.rstrip("\n")] if head else ["ply", f"format {fmt} 1.0"]
    body = []
    order = "<" if fmt == "binary_little_endian" else ">"
    for name, props, rows in elements:
        lines += [f"element {name} {len(rows)}", *(f"property {p}" for p in props)]
        for row in rows:
            fields = []
            for prop, value in zip(props, row, strict=True):
                t = prop.split()
                fields += [(t[1], len(value)), *((t[2], v) for v in value)] if t[0] == "list" else [(t[0], value)]
            if fmt == "ascii":
                body.append(" ".join(str(v) for _, v in fields).encode() + b"\n")
            else:
                body.append(b"".join(struct.pack(order + CODES[t], v) for t, v in fields))
    return ("\n".join(lines) + "\nend_header\n").encode() + b"".join(body)


def cube(fmt: str, faces=CUBE_F, vprops=XYZ, fprops=FACE, before=(), between=(), after=()) -> bytes:
    """The cube of :data:`CUBE_F` in format ``fmt``: vertex properties ``vprops``, face properties ``fprops`` (other
    properties than x y z and the face list filled with 3, a list with 1 2), other elements before, between and
    after the vertex and face elements."""
    def row(props, named):
        return tuple(named.get(p.split()[-1], [1, 2] if p.startswith("list") else 3) for p in props)

    vrows = [row(vprops, dict(zip("xyz", v, strict=True))) for v in CUBE_V]
    frows = [row(fprops, {"vertex_indices": f, "vertex_index": f}) for f in faces]
    return ply(fmt, [*before, ("vertex", vprops, vrows), *between, ("face", fprops, frows), *after])


def flat(faces) -> tuple[np.ndarray, np.ndarray]:
    return np.array([len(f) for f in faces]), np.array([i for f in faces for i in f])


def check_cube(data: bytes, faces=CUBE_F) -> None:
    vertices, counts, indices = read_ply(data, "c.ply")
    assert vertices.dtype == np.float64 and counts.dtype == indices.dtype == np.int64
    assert np.array_equal(vertices, np.array(CUBE_V, np.float64))
    want_counts, want_indices = flat(faces)
    assert np.array_equal(counts, want_counts) and np.array_equal(indices, want_indices)


def trimesh_read(data: bytes):
    mesh = trimesh.load(io.BytesIO(data), file_type="ply", process=False, force="mesh")
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def triangle_mesh():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=12.3456789)  # (coordinates not exact in float32)
    mesh.vertices += (1.5, -2.25, 3.125)
    return mesh


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_triangles_as_trimesh_reads_them(encoding):
    mesh = triangle_mesh()
    if encoding == "binary_big_endian":  # (trimesh writes little-endian only; it reads big-endian)
        data = ply(encoding, [("vertex", XYZ, [tuple(map(float, np.float32(v))) for v in mesh.vertices]),
                              ("face", FACE, [(tuple(map(int, f)),) for f in mesh.faces])])
    else:
        data = mesh.export(file_type="ply", encoding="binary" if encoding != "ascii" else "ascii")
        assert f"format {encoding} 1.0".encode() in data
    vertices, counts, indices = read_ply(data, "t.ply")
    want_v, want_f = trimesh_read(data)
    assert len(want_f) == len(mesh.faces) > 100
    assert np.array_equal(vertices, want_v)  # (ASCII: rounded to float32 as declared, as trimesh does)
    assert np.array_equal(counts, np.full(len(want_f), 3)) and np.array_equal(indices.reshape(-1, 3), want_f)
    assert np.allclose(vertices, mesh.vertices, atol=1e-5)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_extra_vertex_properties_between_x_y_z(encoding):
    vprops = ["float nx", "float x", "uchar red", "uchar green", "double y", "float ny", "short z", "uchar alpha"]
    data = cube(encoding, faces=[(0, 3, 2), (0, 2, 1)], vprops=vprops)
    check_cube(data, faces=[(0, 3, 2), (0, 2, 1)])
    want_v, want_f = trimesh_read(data)
    vertices, _, indices = read_ply(data, "c.ply")
    assert np.array_equal(vertices, want_v) and np.array_equal(indices.reshape(-1, 3), want_f)


OTHER = [("edge", ["int vertex1", "int vertex2", "uchar red"], [(0, 1, 255), (1, 2, 0), (2, 3, 9)]),
         ("material", ["list ushort float weights", "uchar id", "list char int8 tags"],
          [((0.5, 0.25, 2.0), 1, (1, -2)), ((), 2, ()), ((1.0,), 3, (4, 5, 6, 7))])]


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("where", ["before", "between", "after", "everywhere"])
def test_other_elements_are_skipped(encoding, where):
    places = {w: OTHER for w in ("before", "between", "after") if where in (w, "everywhere")}
    check_cube(cube(encoding, **places))
    check_cube(cube(encoding, faces=[f for f in CUBE_F if len(f) == 4] * 3, **places),
               faces=[f for f in CUBE_F if len(f) == 4] * 3)


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("fprops", [
    FACE,
    ["list uchar int vertex_index"],
    ["list char uint vertex_indices"],
    ["list int8 uint16 vertex_indices"],
    ["list ushort int8 vertex_indices"],
    ["list uint uint32 vertex_indices"],
    ["list int int vertex_indices", "uchar red"],  # (trimesh writes a ushort after the list)
    ["uchar flags", "list uchar int vertex_indices", "uchar red", "float quality"],
    ["list uchar float texcoord", "list uchar uint vertex_indices", "list int short extra"],
], ids=["uchar-int", "vertex_index", "char-uint", "int8-uint16", "ushort-int8", "uint-uint32", "red-after",
        "around", "three-lists"])
def test_face_list_types_and_extra_face_properties(encoding, fprops):
    check_cube(cube(encoding, fprops=fprops))
    quads = [f for f in CUBE_F if len(f) == 4]
    check_cube(cube(encoding, faces=quads, fprops=fprops), faces=quads)  # (the fixed-length path in binary)


@pytest.mark.parametrize("encoding", ENCODINGS)
@pytest.mark.parametrize("fprops", [FACE, ["uchar a", "list ushort int vertex_indices", "double b"],
                                    ["list uchar int vertex_indices", "list uchar float texcoord"]])
@pytest.mark.parametrize("pattern", ["runs", "alternating", "random", "first-longer"])
def test_many_faces_of_mixed_lengths(encoding, fprops, pattern):
    """Runs of equal lengths (read a run at a time in binary), lengths alternating (walked a record at a time), and
    both; a first face longer than the rest (the fixed-length guess of the whole element past the file's end)."""
    rng = np.random.default_rng(7)
    n = 3000
    sizes = {"runs": np.repeat([3, 4, 3, 5, 6, 3], [1000, 700, 1, 200, 99, 1000]),
             "alternating": np.tile([3, 4], n // 2),
             "random": np.where(rng.random(n) < 0.9, 3, rng.integers(3, 9, n)),
             "first-longer": np.r_[7, np.full(n - 1, 3)]}[pattern]
    faces = [tuple(int(i) for i in rng.integers(0, len(CUBE_V), k)) for k in sizes]
    check_cube(cube(encoding, faces=faces, fprops=fprops, before=OTHER, after=OTHER[::-1]), faces=faces)


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_a_vertex_element_with_lists_of_mixed_lengths(encoding):
    """x y z gathered from vertex records of different sizes; elements without properties (binary: no bytes)."""
    vprops = ["list uchar float weights", "float x", "list ushort int8 bones", "float y", "float z", "uchar red"]
    rows = [((0.5,) * (k % 3), x, (1, 2, 3)[: k % 4], y, z, k) for k, (x, y, z) in enumerate(CUBE_V)]
    empty = [("empty", [], [] if encoding == "ascii" else [(), ()])]
    data = ply(encoding, [*empty, ("vertex", vprops, rows), *empty, ("face", FACE, [(f,) for f in CUBE_F])])
    check_cube(data)


def test_no_faces_and_crlf_bom_headers():
    data = cube("ascii", faces=[])
    vertices, counts, indices = read_ply(data, "c.ply")
    assert vertices.shape == (9, 3) and counts.shape == indices.shape == (0,)
    for encoding in ENCODINGS:
        data = cube(encoding, before=OTHER)
        head, body = data.split(b"end_header\n")
        check_cube(head.replace(b"\n", b"\r\n") + b"end_header\r\n" + body)
        check_cube(b"\xef\xbb\xbf" + data)
        check_cube(head.replace(b"\n", b"\n\nobj_info a b c\n") + b"end_header  \n" + body)
    check_cube(cube("ascii").replace(b"\n", b"\r\n"))  # (the ASCII body too)
    check_cube(cube("ascii").replace(b"\n", b"\n\n"))  # (blank lines skipped)
    check_cube(cube("ascii").replace(b" ", b" \t ")[:-1])  # (blanks of any kind; no line end after the last)


def test_ascii_numbers_are_rounded_to_their_declared_type():
    data = ply("ascii", [("vertex", ["float x", "double y", "float z"], [(0.1, 0.1, 1e-3), (1, 2, 3), (4, 5, 6)]),
                         ("face", FACE, [((0, 1, 2),)])])
    vertices = read_ply(data, "c.ply")[0]
    assert vertices[0].tolist() == [float(np.float32(0.1)), 0.1, float(np.float32(1e-3))]


def _id(value) -> str:
    """A case's id: its message (the data's is left out)."""
    return value[:60] if isinstance(value, str) else "ply"


def edit(old: bytes, new: bytes) -> bytes:
    """The ASCII cube with ``old`` (once) replaced by ``new``."""
    data = cube("ascii")
    assert data.count(old) == 1
    return data.replace(old, new)


@pytest.mark.parametrize("data, message", [
    (b"solid cube\nendsolid\n", r"not a PLY file \(no 'ply' line at its start\)"),
    (b"ply\nformat ascii 1.0\nelement vertex 0\n", r"no end_header line \(not a PLY file, or its header is cut "
                                                   r"short\)"),
    (edit(b"format ascii", b"format binary_middle_endian"),
     r"header line 2 \('format binary_middle_endian 1.0'\) is not 'format ascii\|binary_little_endian\|"
     r"binary_big_endian 1.0'"),
    (edit(b"ascii 1.0", b"ascii 2.0"), r"header line 2 \('format ascii 2.0'\) is not 'format "),
    (edit(b"format ascii 1.0", b"comment no format"), r"no format line in the header"),
    (edit(b"comment made", b"format ascii 1.0\ncomment made"), r"header line 3 \('format ascii 1.0'\): a second "
                                                               r"format line"),
    (edit(b"comment made by hand", b"texture t.png"), r"header line 3 \('texture t.png'\): unknown keyword "
                                                      r"'texture'"),
    (edit(b"comment made by hand", b"property float w"), r"header line 3 \('property float w'\): a property before "
                                                         r"any element"),
    (edit(b"vertex 9", b"vertex nine"), r"header line 4 \('element vertex nine'\) is not 'element NAME COUNT'"),
    (edit(b"vertex 9", b"vertex -9"), r"header line 4 \('element vertex -9'\) is not 'element NAME COUNT'"),
    (edit(b"float z", b"float y"), r"header line 7 \('property float y'\): a second property y in element vertex"),
    (edit(b"float z", b"quad z"), r"header line 7 \('property quad z'\) is not 'property TYPE NAME' or 'property "
                                  r"list COUNT_TYPE ITEM_TYPE NAME' \(an integer COUNT_TYPE\) with PLY's types"),
    (edit(b"list uchar", b"list float"), r"header line 9 \('property list float int vertex_indices'\) is not "
                                         r"'property TYPE NAME' or 'property list "),
    (cube("ascii", after=[("vertex", XYZ, [])]), r"header line 10 \('element vertex 0'\): a second vertex element"),
    (edit(b"float z", b"float w"), r"the vertex element has no z property"),
    (edit(b"float y", b"list uchar float y"), r"the vertex property y is a list, not a coordinate"),
    (cube("binary_little_endian").replace(b"element face", b"element tri"), r"no face element \(its elements: "
                                                                            r"vertex, tri; gpuslice reads faces, not "
                                                                            r"tri\)"),
    (ply("ascii", [("vertex", XYZ, CUBE_V)]), r"no faces \(a point cloud\?\)"),
    (edit(b"element vertex", b"element point"), r"no vertex element in the header"),
    (edit(b"vertex_indices", b"corners"), r"the face element has no vertex_indices list"),
    (edit(b"list uchar int vertex_indices", b"int vertex_indices"),
     r"the face property vertex_indices is not a list \(property list COUNT_TYPE ITEM_TYPE vertex_indices\)"),
    (edit(b"list uchar int", b"list uchar float"),
     r"the face list vertex_indices holds floating-point numbers, not vertex indices"),
], ids=_id)
def test_broken_headers_are_one_line_errors(data, message):
    with pytest.raises(MeshFileError, match=r"^b\.ply: cannot read PLY file: " + message) as caught:
        read_ply(data, "b.ply")
    assert "\n" not in str(caught.value)


QUADS = [f for f in CUBE_F if len(f) == 4]


def _material_cut(encoding: str) -> bytes:
    """The cube after the other elements, cut 5 bytes into the first material record (after 3 edges, 9 bytes each)."""
    data = cube(encoding, before=OTHER)
    return data[: data.index(b"end_header\n") + 11 + 27 + 5]


def _negative(encoding: str) -> bytes:
    """Two triangles, the second one's count (a char) -1."""
    data = cube(encoding, fprops=["list char int vertex_indices"], faces=[(0, 1, 2), (1, 2, 3)])
    return data[:-13] + b"\xff" + data[-12:]


@pytest.mark.parametrize("encoding", ["binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("data, message", [
    (lambda e: cube(e)[:-1], r"the header declares 7 face records, the file holds 6 \(cut short\?\)"),
    (lambda e: cube(e, faces=QUADS)[:-17], r"the header declares 3 face records, the file holds 2 \(cut short\?\)"),
    (lambda e: cube(e, faces=[])[:-30], r"the header declares 9 vertex records, the file holds 6 \(cut short\?\)"),
    (lambda e: cube(e, after=OTHER)[:-1], r"the header declares 3 material records, the file holds 2 \(cut short\?\)"),
    (_material_cut, r"the header declares 3 material records, the file holds 0 \(cut short\?\)"),
    (lambda e: cube(e) + b"\n", r"1 bytes after the last record the header declares \(a wrong count\?\)"),
    (_negative, r"face record 2 holds a negative list count -1"),
    (lambda e: cube(e, faces=[(0, 1, 2), (1, 2)]), r"face 2 \(of 2\) has 2 vertices \(a face needs 3\)"),
    (lambda e: cube(e, faces=[(0, 1, 2), ()] * 40), r"face 2 \(of 80\) has 0 vertices \(a face needs 3\)"),
], ids=_id)
def test_broken_binary_files_are_one_line_errors(encoding, data, message):
    with pytest.raises(MeshFileError, match=r"^b\.ply: cannot read PLY file: " + message + "$") as caught:
        read_ply(data(encoding), "b.ply")
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("data, message", [
    (cube("ascii")[:-10], r"the header declares 16 records \(9 vertex, 7 face\), the file holds 15 lines after it "
                          r"\(cut short\?\)"),
    (cube("ascii") + b"3 0 1 2\n", r"the header declares 16 records \(9 vertex, 7 face\), the file holds 17 lines "
                                   r"after it \(a wrong count\?\)"),
    (edit(b"\n10 0 10\n", b"\n10 0\n"), r"vertex line 6 \('10 0'\) is short of numbers for its properties "
                                        r"\(x y z\)"),
    (edit(b"\n10 0 10\n", b"\n10 0 10 1\n"), r"vertex line 6 \('10 0 10 1'\) holds more numbers than its "
                                             r"properties \(x y z\)"),
    (edit(b"\n10 0 10\n", b"\n10 zero 10\n"), r"vertex line 6 \('10 zero 10'\): 'zero' is not a number"),
    (edit(b"\n3 0 3 2\n", b"\n3 0 3\n"), r"face line 1 \('3 0 3'\) is short of numbers for its properties "
                                         r"\(vertex_indices\)"),
    (cube("ascii", fprops=["uchar flags", *FACE]).replace(b"\n3 4 3 0 4 7\n", b"\n3\n"),
     r"face line 7 \('3'\) is short of numbers for its properties \(flags vertex_indices\)"),
    (edit(b"\n3 0 3 2\n", b"\n3 0 3 2 2\n"), r"face line 1 \('3 0 3 2 2'\) holds more numbers than its "
                                             r"properties \(vertex_indices\)"),
    (edit(b"\n3 0 3 2\n", b"\n3 0 3 2.0\n"), r"face line 1 \('3 0 3 2.0'\): vertex_indices holds other than "
                                             r"integers"),
    (edit(b"\n4 3 0 4 7\n", b"\n4 3 0 4 -\n"), r"face line 7 \('4 3 0 4 -'\): vertex_indices holds other than "
                                               r"integers"),  # (numpy's parser took the last "-" as a 0)
    (edit(b"\n3 0 3 2\n", b"\n3.0 0 3 2\n"), r"face line 1 \('3.0 0 3 2'\): '3.0' is not a count of "
                                             r"vertex_indices"),
    (edit(b"\n3 0 3 2\n", b"\n-1 0 3 2\n"), r"face line 1 \('-1 0 3 2'\): '-1' is not a count of vertex_indices"),
    (edit(b"\n3 0 3 2\n", b"\n3 0 3 99999999999999999999\n"), r"a face list holds a number out of range "
                                                              r"\(over 64 bits\)"),
    (edit(b"\n3 0 3 2\n", b"\n3 0 3 -99999999999999999999\n"), r"a face list holds a number out of range "
                                                               r"\(over 64 bits\)"),
    (cube("ascii", faces=[(0, 1, 2), (0, 1)]), r"face 2 \(of 2\) has 2 vertices \(a face needs 3\)"),
    (cube("ascii", faces=[(0, 1)] * 3), r"face 1 \(of 3\) has 2 vertices \(a face needs 3\)"),
], ids=_id)
def test_broken_ascii_files_are_one_line_errors(data, message):
    with pytest.raises(MeshFileError, match=r"^b\.ply: cannot read PLY file: " + message + "$") as caught:
        read_ply(data, "b.ply")
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
@pytest.mark.parametrize("mesh_name", ["cow.stl", "prusa_A.stl", "spot.stl", "nefertiti.stl"])
def test_a_shared_mesh_as_trimesh_reads_it(shared_meshes, mesh_name, encoding):
    path = shared_meshes / mesh_name
    if not path.is_file():
        pytest.skip(f"{path} not found in the shared mesh folder")
    data = trimesh.load(path, force="mesh").export(file_type="ply", encoding=encoding)
    vertices, counts, indices = read_ply(data, mesh_name)
    want_v, want_f = trimesh_read(data)
    assert len(want_f) > 0 and (counts == 3).all()
    assert np.array_equal(vertices, want_v) and np.array_equal(indices.reshape(-1, 3), want_f)
