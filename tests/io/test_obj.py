"""gpuslice's own OBJ reader (:mod:`gpuslice.io.obj`) and the triangles of polygon faces (:mod:`gpuslice.io.polygons`):
every layout of a cube reads as the whole cube, trimesh's triangles on the shared meshes, a concave face cut inside
its outline (trimesh's fan folded over itself: every layer through it was repaired as overlapping loops), and each
broken file refused with one line naming the file and the line."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

import gpuslice
from gpuslice import load_mesh, slice_mesh
from gpuslice.cli import main
from gpuslice.errors import MeshFileError
from gpuslice.io.obj import read_obj
from gpuslice.io.polygons import fan, triangulate

MESHES = Path(__file__).resolve().parents[3] / "shared" / "meshes"
CUBE_V = [(0, 0, 0), (10, 0, 0), (10, 10, 0), (0, 10, 0), (0, 0, 10), (10, 0, 10), (10, 10, 10), (0, 10, 10)]
CUBE_Q = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
CUBE_T = [t for q in CUBE_Q for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]


def obj(faces=CUBE_Q, vertex: str = "v {} {} {}", ref: str = "{}", head: str = "", key: str = "f",
        between: str = "") -> bytes:
    v = [vertex.format(*p) for p in CUBE_V]
    f = [f"{key} " + " ".join(ref.format(i + 1, i - len(CUBE_V)) for i in q) for q in faces]
    return (head + "\n".join(v) + "\n" + between + "\n".join(f) + "\n").encode()


def volume(mesh) -> float:
    tri = mesh.triangles.astype(np.float64)
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


@pytest.mark.parametrize("data", [
    obj(CUBE_T),
    obj(),
    obj(ref="{}/1/1", head="vt 0 0\nvn 0 0 1\n"),
    obj(ref="{}//1", head="vn 0 0 1\n"),
    obj(ref="{}/1"),
    obj(ref="{1}"),  # counted back from the last vertex: -8 .. -1
    obj(key="fo"),
    obj(vertex="v {} {} {} 1.0"),  # a weight
    obj(vertex="v {} {} {} 0.5 0.25 1"),  # a colour
    obj(vertex="v\t{}\t{}\t{}"),
    obj(head="# made by hand\nmtllib cube.mtl\no cube\ng side\ns off\nusemtl red\n",
        between="l 1 2\np 3\n# faces\n"),
    obj().replace(b"\n", b"\r\n"),
    obj().replace(b"\n", b"\r"),
    b"\xef\xbb\xbf" + obj(),
    obj().replace(b"f 1 4", b"   f 1 4"),  # leading blanks
    obj().replace(b"f 1 4 3 2", b"f 1 4 \\\n 3 2"),  # a statement continued on the next line
    obj().replace(b"f 1 4 3 2\n", b"f 1 4 3 2  # the bottom\n"),
    obj().replace(b"f 1 4 3 2\n", b"").replace(b"f 4 1 5 8\n", b"f 4 1 5 8\nf 1 4 \\\n 3 2\\"),  # to the end
    obj().replace(b"f 1 4", b"f 1\x0b4\x0c"),  # (a vertical tab and a form feed: blanks to OBJ readers)
], ids=["triangles", "quads", "v/vt/vn", "v//vn", "v/vt", "negative", "fo", "weight", "rgb", "tabs", "statements",
        "crlf", "cr", "bom", "indent", "continued", "comment", "continued-to-the-end", "vertical-tab"])
def test_a_cube_in_every_layout_is_the_whole_cube(data):
    mesh = load_mesh(data, name="c.obj")
    assert mesh.n_faces == 12 and np.allclose(np.ptp(mesh.vertices, axis=0), 10.0)
    assert volume(mesh) == pytest.approx(1000.0)  # every face there, outwards


def test_negative_references_count_back_from_the_face_line():
    """-1 is the last vertex above the face line, not the file's last: two cubes, each face counting back."""
    one = "\n".join(f"v {x} {y} {z}" for x, y, z in CUBE_V)
    two = "\n".join(f"v {x + 20} {y} {z}" for x, y, z in CUBE_V)
    faces = "\n".join("f " + " ".join(str(i - 8) for i in q) for q in CUBE_Q)
    mesh = load_mesh(f"{one}\n{faces}\n{two}\n{faces}\n".encode(), name="two.obj")
    assert mesh.n_faces == 24 and volume(mesh) == pytest.approx(2000.0)
    assert np.ptp(mesh.vertices[:, 0]) == pytest.approx(30.0)


@pytest.mark.parametrize("data, message", [
    (obj(vertex="v {} {}"), r"line 1: a vertex line that does not hold x y z \('v 0 0'\)"),
    (obj(vertex="v {} {} x{}"), r"line 1: a vertex line that does not hold x y z \('v 0 0 x0'\)"),
    (obj([*CUBE_Q[:5], (0, 1)]), r"line 14: a face of 2 vertices \('f 1 2'; a face needs 3\)"),
    (obj().replace(b"f 1 4 3 2", b"f 1 4 3 x"), r"line 9: a face reference that is not a vertex number "
                                               r"\('f 1 4 3 x'\)"),
    (obj().replace(b"f 1 4 3 2", b"f 1 4 3 1_0"), r"line 9: a face reference that is not a vertex number"),
    (obj().replace(b"f 1 4 3 2", b"f 1 4 3 2.0"), r"line 9: a face reference that is not a vertex number"),
    (obj().replace(b"f 1 4 3 2", b"f 1 4 3 -"), r"line 9: a face reference that is not a vertex number"),
    (obj().replace(b"f 1 4 3 2", b"f 1 4 3 +"), r"line 9: a face reference that is not a vertex number"),
    (obj().replace(b"f 1 4 3 2", b"f 1 4 3 99999999999999999999"), r"line 9: a face names a vertex index out of "
                                                                    r"range"),
    (obj().replace(b"f 1 4 3 2", b"f 1 4 3 9"), r"line 9: a face names vertex 9, but the file has 8 vertices "
                                               r"\('f 1 4 3 9'; OBJ counts them from 1\)"),
    (obj().replace(b"f 1 4 3 2", b"f -9 -1 -2"), r"line 9: a face counts back past the first vertex \('f -9 -1 -2': "
                                                r"8 vertices above it\)"),
    (b"v 0 0 0\nf -1 -2 -3\nv 1 0 0\nv 0 1 0\n", r"line 2: a face counts back past the first vertex"),
    (obj(head="cstype bspline\nsurf 0 1 0 1 1 2 3 4\n"), r"line 2: a free-form surface \(surf\): gpuslice reads "
                                                          r"polygons"),
], ids=["short-vertex", "vertex-word", "two-vertex-face", "word", "underscore", "decimal", "minus", "plus", "huge",
        "past-the-end", "back-too-far", "back-before-defined", "surf"])
def test_broken_files_are_refused_naming_the_line(data, message, tmp_path, capsys):
    with pytest.raises(MeshFileError, match=rf"^b\.obj: {message}"):
        load_mesh(data, name="b.obj")
    path = tmp_path / "b.obj"
    path.write_bytes(data)
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"gpuslice: error: {path}: line ") and "\n" not in err


def test_a_file_of_vertices_only_has_no_facets():
    with pytest.raises(MeshFileError, match=r"^v\.obj: no facets \(OBJ file\)$"):
        load_mesh(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nl 1 2\n", name="v.obj")


def _trimesh_obj_corners(data: bytes) -> np.ndarray:
    import trimesh

    t = trimesh.load(io.BytesIO(data), file_type="obj", force="mesh", process=False)
    return np.asarray(t.vertices)[np.asarray(t.faces)]


@pytest.mark.skipif(not MESHES.is_dir(), reason=f"the shared meshes are not at {MESHES}")
@pytest.mark.parametrize("name", ["nefertiti", "cow", "p_block_hole", "prusa_mk4_gantry"])
def test_the_shared_meshes_as_obj_read_as_trimesh_reads_them(name):
    """Triangle files: the same corners, face by face, as trimesh's reader (which gpuslice used before)."""
    import trimesh

    m = trimesh.load(MESHES / f"{name}.stl", force="mesh", process=False)
    data = trimesh.exchange.obj.export_obj(m, include_normals=True, include_texture=False).encode()
    v, counts, idx = read_obj(data, name)
    assert (counts == 3).all()
    np.testing.assert_array_equal(v[triangulate(v, counts, idx)[0]], _trimesh_obj_corners(data))


# an L-shaped prism: the L (area 500 mm²) in the x-z plane, 10 mm deep in y; its two L faces are concave
L_SHAPE = [(0, 0), (30, 0), (30, 10), (10, 10), (10, 30), (0, 30)]


def l_prism(start: int, suffix: str = "obj") -> bytes:
    n = len(L_SHAPE)
    pts = L_SHAPE[start:] + L_SHAPE[:start]
    v = [(x, 0.0, z) for x, z in pts] + [(x, 10.0, z) for x, z in pts]
    faces = [list(range(n)), [n + i for i in reversed(range(n))]]  # y = 0 (normal -y), y = 10 (normal +y)
    faces += [[i, n + i, n + (i + 1) % n, (i + 1) % n] for i in range(n)]  # outwards
    if suffix == "ply":
        return (f"ply\nformat ascii 1.0\nelement vertex {2 * n}\nproperty double x\nproperty double y\n"
                f"property double z\nelement face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
                + "".join(f"{x} {y} {z}\n" for x, y, z in v)
                + "".join(f"{len(f)} {' '.join(map(str, f))}\n" for f in faces)).encode()
    if suffix == "off":
        return (f"OFF\n{2 * n} {len(faces)} 0\n" + "".join(f"{x} {y} {z}\n" for x, y, z in v)
                + "".join(f"{len(f)} {' '.join(map(str, f))}\n" for f in faces)).encode()
    return ("".join(f"v {x} {y} {z}\n" for x, y, z in v)
            + "".join("f " + " ".join(str(i + 1) for i in f) + "\n" for f in faces)).encode()


@pytest.mark.parametrize("suffix", ["obj", "off", "ply"])
@pytest.mark.parametrize("start", range(6))
def test_a_concave_face_is_cut_inside_its_outline(start, suffix):
    """From some of its corners the L's fan folds over itself: the slices came out right only after every layer's
    loops were rebuilt as overlapping ones (20-40 repairs on 40 layers). Cut inside the outline: no repair."""
    mesh = load_mesh(l_prism(start, suffix), name=f"l.{suffix}")
    assert mesh.n_faces == 2 * 4 + 6 * 2
    tri = mesh.triangles.astype(np.float64)
    assert np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum() / 2 == pytest.approx(
        2 * 500 + 10 * (30 + 10 + 20 + 20 + 10 + 30))  # no triangle overlaps another: their areas add up
    assert volume(mesh) == pytest.approx(5000.0)
    res = slice_mesh(mesh, thickness=0.5)
    assert res.meta["repairs"]["overlaps_resolved"] == 0
    expect = np.where(res.z < 10, 300.0, 100.0)
    np.testing.assert_allclose(res.area, expect, rtol=1e-6)


def _random_polygon(rng, n: int) -> np.ndarray:
    """A simple polygon of n vertices, often concave: star-shaped around the origin (angles in order, no two more
    than half a turn apart, radii random)."""
    ang = (np.arange(n) + rng.uniform(0, 0.8, n)) * 2 * np.pi / n
    r = rng.uniform(0.2, 1.0, n)
    return np.column_stack([r * np.cos(ang), r * np.sin(ang)])


def test_random_concave_faces_in_random_planes():
    """Each face's triangles: n - 2 of them, its own vertices, none turned against the face, areas adding up to the
    face's (so none overlaps another); convex faces and triangles keep their fans exactly."""
    rng = np.random.default_rng(7)
    verts, counts, idx, areas = [], [], [], []
    base = 0
    for k in range(300):
        n = 3 + k % 12
        p2 = _random_polygon(rng, n)
        if k % 5 == 0:  # a convex one: its hull's order
            p2 = np.column_stack([np.cos(np.linspace(0, 2 * np.pi, n, endpoint=False)),
                                  np.sin(np.linspace(0, 2 * np.pi, n, endpoint=False))])
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))  # a random plane, anywhere
        p3 = np.column_stack([p2, np.zeros(n)]) @ q.T * 10 + rng.normal(size=3) * 50
        shift = int(rng.integers(n))  # the fan's first vertex anywhere on the outline
        order = np.roll(np.arange(n), shift)
        if k % 2:
            order = order[::-1]
        x, y = p2[:, 0], p2[:, 1]
        areas.append(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2 * 100)
        verts.append(p3)
        counts.append(n)
        idx.append(base + order)
        base += n
    v = np.concatenate(verts)
    counts = np.array(counts)
    flat = np.concatenate(idx)
    tri, cut = triangulate(v, counts, flat)
    assert cut > 50  # many of the random faces were concave
    per = counts - 2
    assert tri.shape == (per.sum(), 3)
    face = np.repeat(np.arange(counts.size), per)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    a = v[tri]
    own = np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0])
    for f in range(counts.size):
        mine = tri[face == f]
        ring = flat[start[f] : start[f] + counts[f]]
        assert np.isin(mine, ring).all()
        p = v[ring]
        normal = np.cross(p, np.roll(p, -1, axis=0)).sum(axis=0)
        assert (own[face == f] @ normal >= -1e-9 * np.linalg.norm(normal)).all(), f
        assert np.linalg.norm(own[face == f], axis=1).sum() / 2 == pytest.approx(areas[f], rel=1e-9), f
    convex = (np.arange(counts.size) % 5 == 0) | (counts == 3)
    fan_tri, fan_face = fan(counts, flat)
    np.testing.assert_array_equal(tri[np.isin(face, np.flatnonzero(convex))],
                                  fan_tri[np.isin(fan_face, np.flatnonzero(convex))])


def test_faces_without_an_inside_keep_their_fan():
    """A bow-tie (its outline crosses itself) and a face naming a point twice have no outline to cut inside: the
    fan, as before; collinear points on a convex face (a point in the middle of an edge) are a fan too."""
    v = np.array([(0, 0, 0), (1, 1, 0), (1, 0, 0), (0, 1, 0),  # bow-tie
                  (0, 0, 1), (2, 0, 1), (2, 2, 1), (1, 1, 1), (0, 2, 1), (1, 1, 1),  # (1, 1, 1) twice
                  (0, 0, 2), (1, 0, 2), (2, 0, 2), (2, 1, 2), (0, 1, 2)], float)  # a rectangle, a point mid-edge
    counts = np.array([4, 6, 5])
    flat = np.arange(15)
    tri, cut = triangulate(v, counts, flat)
    assert cut == 0
    np.testing.assert_array_equal(tri, fan(counts, flat)[0])


def test_a_concave_face_after_one_left_to_its_fan_is_turned_as_its_own():
    """The turn of each face's triangles was read from the concave faces' list at the position GEOS's output had
    (a review): after a face left to its fan (its outline repeats a point, as exporters write), the next concave
    face took the wrong face's turn and came out inside-out (4 flipped facets, no volume)."""
    data = b"".join(f"v {x} {y} {z}\n".encode() for z in (0, 1) for x, y in L_SHAPE_3) + (
        b"f 9 10 10 11 12 7 8\n"  # the top L, its point 10 twice: a fan
        b"f 6 5 4 3 2 1\n"  # the bottom L: concave, cut inside its outline
        + b"".join(f"f {i + 1} {(i + 1) % 6 + 1} {(i + 1) % 6 + 7} {i + 7}\n".encode() for i in range(6)))
    mesh = load_mesh(data, name="l.obj")
    assert volume(mesh) == pytest.approx(5.0)
    assert gpuslice.mesh_repairs(mesh)["flipped_facets"] == 0
    assert slice_mesh(mesh, thickness=0.25).meta["repairs"]["overlaps_resolved"] == 0


L_SHAPE_3 = [(0, 0), (3, 0), (3, 1), (1, 1), (1, 3), (0, 3)]


@pytest.mark.parametrize("size", [1e-100, 1e-3, 1e100])
def test_a_concave_face_of_any_size_is_cut_inside(size):
    """At 1e-100 the turn test's products underflowed to 0, and the folded fan passed for convex (a fuzzing helper):
    each face is now tested moved to its first corner and scaled by a power of two."""
    v = np.array([(0, 0, 0), (2, 0, 0), (1, 0.2, 0), (1, 2, 0)]) * size  # a dart: concave at (1, 0.2)
    for shift in range(4):
        order = np.roll(np.arange(4), shift)
        tri, cut = triangulate(v, np.array([4]), order)
        a = v[tri]
        turn = np.cross(a[:, 1] - a[:, 0], a[:, 2] - a[:, 0])[:, 2]
        assert (turn > 0).all(), (shift, turn)  # counter-clockwise, as the dart


def test_a_concave_face_past_the_limit_keeps_its_fan(monkeypatch):
    """GEOS's time grows with the cube of a face's vertex count (a spiral of 16,000: 91 s): past MAX_INSIDE the fan,
    as before (the slices stay right, through the overlap repair)."""
    from gpuslice.io import polygons

    v = np.array([(0, 0, 0), (2, 0, 0), (1, 0.2, 0), (1, 2, 0)], float)
    order = np.array([1, 2, 3, 0])  # the fan from (2, 0) folds
    assert triangulate(v, np.array([4]), order)[1] == 1
    monkeypatch.setattr(polygons, "MAX_INSIDE", 3)
    tri, cut = triangulate(v, np.array([4]), order)
    assert cut == 0
    np.testing.assert_array_equal(tri, fan(np.array([4]), order)[0])


def test_concave_faces_past_the_budget_keep_their_fans(monkeypatch):
    """Each face is capped, and so are all of a file's together (20 spirals of 2,048 vertices took 13 s): the first
    faces in file order within the budget are cut inside, the rest keep their fans."""
    from gpuslice.io import polygons

    v = np.array([(0, 0, 0), (2, 0, 0), (1, 0.2, 0), (1, 2, 0)] * 3, float) + np.repeat(np.arange(3) * 10.0, 4)[:, None]
    order = np.array([1, 2, 3, 0, 5, 6, 7, 4, 9, 10, 11, 8])  # three darts whose fans fold
    counts = np.array([4, 4, 4])
    assert triangulate(v, counts, order)[1] == 3
    monkeypatch.setattr(polygons, "INSIDE_BUDGET", 2 * 16.0)  # room for two faces of 4 vertices
    tri, cut = triangulate(v, counts, order)
    assert cut == 2
    np.testing.assert_array_equal(tri[4:], fan(counts, order)[0][4:])
