"""What trimesh lets through from a broken OBJ, PLY, OFF or 3MF file, refused with one line naming the file (a
helper's fuzzing of the non-STL readers): a vertex short of a coordinate (a crash, or a flat nonsense mesh), a face
naming a vertex that is not there (numpy took another: one facet too many), an ASCII PLY or OFF file cut short
(fewer facets, exit 0), and trimesh's own log lines on stderr beside the error line."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest

from gpuslice import load_mesh
from gpuslice.cli import main
from gpuslice.errors import MeshFileError

CUBE_V = [(0, 0, 0), (10, 0, 0), (10, 10, 0), (0, 10, 0), (0, 0, 10), (10, 0, 10), (10, 10, 10), (0, 10, 10)]
CUBE_Q = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]


def _obj(vertex_lines: list[str]) -> bytes:
    faces = [f"f {' '.join(str(i + 1) for i in q)}" for q in CUBE_Q]
    return "\n".join(vertex_lines + faces).encode() + b"\n"


def _ply(faces=CUBE_Q, cut: float = 1.0) -> bytes:
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(CUBE_V)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    body = "".join(f"{x} {y} {z}\n" for x, y, z in CUBE_V) + "".join(f"{len(q)} {' '.join(map(str, q))}\n"
                                                                   for q in faces)
    return head.encode() + body.encode()[: int(len(body) * cut)]


def _off(cut: float = 1.0) -> bytes:
    body = "".join(f"{x} {y} {z}\n" for x, y, z in CUBE_V) + "".join(f"4 {' '.join(map(str, q))}\n" for q in CUBE_Q)
    return f"OFF\n# a cube\n{len(CUBE_V)} {len(CUBE_Q)} 12\n".encode() + body.encode()[: int(len(body) * cut)]


def _3mf(triangles: str, build: str = '<item objectid="1"/>') -> bytes:
    verts = "".join(f'<vertex x="{x}" y="{y}" z="{z}"/>' for x, y, z in CUBE_V)
    model = ('<?xml version="1.0" encoding="UTF-8"?><model unit="millimeter" xmlns='
             '"http://schemas.microsoft.com/3dmanufacturing/core/2015/02"><resources><object id="1" type="model">'
             f"<mesh><vertices>{verts}</vertices><triangles>{triangles}</triangles></mesh></object></resources>"
             f"<build>{build}</build></model>")
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        z.writestr("[Content_Types].xml", '<?xml version="1.0"?><Types xmlns="http://schemas.openxmlformats.org/'
                   'package/2006/content-types"><Default Extension="model" ContentType="application/vnd.ms-package.'
                   '3dmanufacturing-3dmodel+xml"/></Types>')
        z.writestr("_rels/.rels", '<?xml version="1.0"?><Relationships xmlns="http://schemas.openxmlformats.org/'
                   'package/2006/relationships"><Relationship Target="/3D/3dmodel.model" Id="rel0" Type="http://'
                   'schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/></Relationships>')
        z.writestr("3D/3dmodel.model", model)
    return out.getvalue()


TRIS = "".join(f'<triangle v1="{a}" v2="{b}" v3="{c}"/>' for q in CUBE_Q for a, b, c in ((q[0], q[1], q[2]),
                                                                                         (q[0], q[2], q[3])))


def test_the_well_formed_files_read_as_twelve_facets():
    vlines = [f"v {x} {y} {z}" for x, y, z in CUBE_V]
    for data, name in ((_obj(vlines), "c.obj"), (_ply(), "c.ply"), (_off(), "c.off"), (_3mf(TRIS), "c.3mf"),
                       (_ply().replace(b"\n", b"\r\n"), "crlf.ply")):
        mesh = load_mesh(data, name=name)
        assert mesh.n_faces == 12 and np.allclose(np.ptp(mesh.vertices, axis=0), 10.0), name


def test_files_on_disk_are_counted_whole_and_without_a_last_newline(tmp_path):
    """The cut-short check counts a file's lines in pieces from disk; a last line without its newline counts."""
    for data, name in ((_ply(), "c.ply"), (_off(), "c.off")):
        path = tmp_path / name
        path.write_bytes(data.rstrip(b"\n"))
        assert load_mesh(path).n_faces == 12
        path.write_bytes(data[: data.rindex(b"\n", 0, len(data) - 1) + 1])  # the last face line gone
        with pytest.raises(MeshFileError, match="cut short"):
            load_mesh(path)


@pytest.mark.parametrize("drop", [1, 3])  # sizes that do not divide by 3 (a crash) and that do (a nonsense mesh)
def test_an_obj_vertex_short_of_a_coordinate(drop):
    vlines = [f"v {x} {y} {z}" for x, y, z in CUBE_V]
    for k in range(drop):
        vlines[k] = vlines[k].rsplit(" ", 1)[0]
    # (gpuslice's own OBJ reader since: it names the line)
    with pytest.raises(MeshFileError, match=r"^c\.obj: line 1: a vertex line that does not hold x y z \('v 0 0'\)$"):
        load_mesh(_obj(vlines), name="c.obj")


@pytest.mark.parametrize("data, name", [
    (_ply([*CUBE_Q[:5], (3, 0, 4, -1)]), "neg.ply"),
    (_3mf(TRIS.replace('v3="4"/>', 'v3="-1"/>', 1)), "neg.3mf"),
], ids=["ply", "3mf"])
def test_a_face_naming_no_vertex(data, name):
    with pytest.raises(MeshFileError, match=rf"{name}: a (PLY|3MF) face names vertex -1, but the file has 8 vertices"):
        load_mesh(data, name=name)


@pytest.mark.parametrize("data, name", [(_ply(cut=0.8), "cut.ply"), (_off(cut=0.8), "cut.off")], ids=["ply", "off"])
def test_an_ascii_file_cut_short(data, name):
    # (gpuslice's own PLY and OFF readers since: each counts what its header declares)
    with pytest.raises(MeshFileError, match=rf"{name}: (cannot read PLY file: the header declares 14 records \(8 "
                                            r"vertex, 6 face\)|the OFF header declares 8 vertices and 6 faces).*"
                                            r"\(cut short\?\)$"):
        load_mesh(data, name=name)


def test_trimesh_log_lines_stay_off_stderr(tmp_path, capsys):
    """A build item naming no object: trimesh logs "id 2 included but not defined!", which Python's last-resort
    handler printed on stderr above the one error line."""
    path = tmp_path / "missing.3mf"
    path.write_bytes(_3mf(TRIS, '<item objectid="2"/>'))
    assert main(["slice", str(path), "-t", "1", "-o", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"gpuslice: error: {path}"), err
