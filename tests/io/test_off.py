"""The OFF reader (:mod:`gpuslice.io.off`) and the OBJ face index 0: files trimesh read wrongly without a word (a
comment line after the counts dropped a face, a face colour dropped every face, a face line short of an index
dropped that face, an OBJ vertex 0 was taken as vertex 1), now read as Geomview's OFF page says or refused with one
line naming the file and the line."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import load_mesh
from gpuslice.cli import main
from gpuslice.errors import MeshFileError

CUBE_V = [(0, 0, 0), (10, 0, 0), (10, 10, 0), (0, 10, 0), (0, 0, 10), (10, 0, 10), (10, 10, 10), (0, 10, 10)]
CUBE_Q = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
CUBE_T = [t for q in CUBE_Q for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]


def off(faces=CUBE_T, head: str = "OFF\n{nv} {nf} 0\n", vertex: str = "{} {} {}", face: str = "{n} {idx}") -> bytes:
    body = [vertex.format(*v) for v in CUBE_V] + [face.format(n=len(f), idx=" ".join(map(str, f))) for f in faces]
    return (head.format(nv=len(CUBE_V), nf=len(faces)) + "\n".join(body) + "\n").encode()


def volume(mesh) -> float:
    tri = mesh.triangles.astype(np.float64)
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("data", [
    off(),
    off(CUBE_Q),  # quads: fans of two triangles
    off(head="OFF\n# made by hand\n\n{nv} {nf} 0\n# the vertices\n"),  # trimesh: 11 facets
    off(face="{n} {idx} 255 0 0"),  # a colour after each face: trimesh read no face at all
    off(face="{n} {idx} 0.5 0.5 0.5 1.0  # red"),
    off(head="OFF {nv} {nf} 0\n"),  # the counts on the keyword's line
    off(head="{nv} {nf} 0\n"),  # no keyword (Geomview: optional)
    off(head="COFF\n{nv} {nf} 0\n", vertex="{} {} {} 1 0 0 1"),  # a colour after each vertex
    off(head="NOFF\n{nv} {nf}\n", vertex="{} {} {} 0 0 1"),  # normals; no edge count
    off(CUBE_Q).replace(b"\n", b"\r\n"),
    off(CUBE_Q).replace(b"\n", b"\r"),  # (old Mac line ends: "cut short?", a review found)
    b"\xef\xbb\xbf" + off(),  # (a UTF-8 byte-order mark)
], ids=["triangles", "quads", "comments", "rgb", "rgba-comment", "one-line", "no-keyword", "coff", "noff", "crlf",
        "cr", "bom"])
def test_a_cube_in_every_layout_is_the_whole_cube(data):
    mesh = load_mesh(data, name="c.off")
    assert mesh.n_faces == 12 and np.allclose(np.ptp(mesh.vertices, axis=0), 10.0)
    assert volume(mesh) == pytest.approx(1000.0)  # every face there, outwards


@pytest.mark.parametrize("data, message", [
    (off(CUBE_T[:3] + [(0, 1)] + CUBE_T[4:], face="3 {idx}"), r"face line 4 \('3 0 1'\) lists fewer vertex indices "
                                                               "than its count 3"),
    (off(CUBE_T[:5] + [(0, 1)]), r"face line 6 \('2 0 1'\) has 2 vertices \(a face needs 3\)"),
    (off(CUBE_T[:2] + [(0, 1, "x")]), r"face line 3 \('3 0 1 x'\) is not a count and vertex indices"),
    (off(CUBE_T[:2] + [(0, 1, 10**20)]), r"face line 3 \('3 0 1 100000000000000000000'\) names a vertex index "
                                          "out of range"),
    (off(vertex="{} {}"), r"vertex line 1 \('0 0'\) does not start with 3 numbers"),
    (off(head="OFF\n{nv} faces\n"), r"the counts line '8 faces' is not vertex, face \(and edge\) counts"),
    (off(head="4OFF\n{nv} {nf} 0\n"), r"a 4OFF file holds points of other than 3 dimensions"),
    (b"OFF BINARY\n\x00\x00\x00\x08", r"a binary OFF file \(save it as ASCII OFF\)"),
    (b"# only a comment\n\n", r"no OFF header"),
    (off(head="OFFX\n{nv} {nf} 0\n"), r"the counts line 'OFFX' is not"),
    (off(CUBE_Q, face="{n} {idx} 255 0 0").replace(b"\n4 0 3 2 1", b"\n4 0_0 3 2 1"), r"face line 1 \('4 0_0 3 2 1 "
                                                                                    r"255 0 0'\) is not a count"),
], ids=["short-face", "two-vertices", "not-a-number", "huge-index", "short-vertex", "counts", "4d", "binary", "empty",
        "keyword", "underscore"])
def test_broken_off_files_are_one_line_errors(data, message):
    with pytest.raises(MeshFileError, match=r"^b\.off: cannot read OFF file: " + message):
        load_mesh(data, name="b.off")


def test_an_off_face_naming_no_vertex_and_a_file_cut_short():
    with pytest.raises(MeshFileError, match=r"b\.off: a OFF face names vertex 8, but the file has 8 vertices"):
        load_mesh(off(CUBE_T[:11] + [(0, 1, 8)]), name="b.off")
    data = off()
    with pytest.raises(MeshFileError, match=r"b\.off: the OFF header declares 8 vertices and 12 faces, the file holds "
                                            r"19 lines after it \(cut short\?\)"):
        load_mesh(data[: data.rindex(b"\n", 0, len(data) - 1) + 1], name="b.off")
    # more faces than the count: the last one was dropped without a word, the cube left open (a fuzzing helper)
    with pytest.raises(MeshFileError, match=r"b\.off: the OFF header declares 8 vertices and 11 faces, the file holds "
                                            r"20 lines after it \(a wrong count\?\)"):
        load_mesh(off(head="OFF\n{nv} 11 0\n"), name="b.off")


def _obj(faces: list[str]) -> bytes:
    return ("".join(f"v {x} {y} {z}\n" for x, y, z in CUBE_V) + "".join(f + "\n" for f in faces)).encode()


OBJ_FACES = [f"f {' '.join(str(i + 1) for i in q)}" for q in CUBE_Q]


@pytest.mark.parametrize("face", ["f 0 4 3 2", "f 0/1 4/1 3/1 2/1", "  f 1 4 3 0", "fo 1\t0\t3 2"])
def test_an_obj_face_naming_vertex_0(face, tmp_path, capsys):
    data = _obj([face, *OBJ_FACES[1:]])
    with pytest.raises(MeshFileError, match=r"^z\.obj: line 9: an OBJ face names vertex 0 \(OBJ counts vertices "
                                            r"from 1\)$"):
        load_mesh(data, name="z.obj")
    path = tmp_path / "z.obj"
    path.write_bytes(data)
    assert main(["info", str(path)]) == 2
    assert capsys.readouterr().err.strip() == f"gpuslice: error: {path}: line 9: an OBJ face names vertex 0 (OBJ " \
                                              "counts vertices from 1)"


def test_zeros_elsewhere_in_an_obj_are_not_vertex_0():
    """Zero coordinates, a texture index 0 (not ours to judge), a 0 in a comment line."""
    faces = [OBJ_FACES[0].replace(" 3", " 3/0"), "# f 0 1 2", *OBJ_FACES[1:]]
    mesh = load_mesh(_obj(faces), name="c.obj")
    assert mesh.n_faces == 12 and volume(mesh) == pytest.approx(1000.0)
