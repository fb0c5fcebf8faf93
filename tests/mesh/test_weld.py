"""The weld and the edge ids on the device (``gpuslice.mesh.weld``) against their numpy twins, bit for bit.

The numpy twins are the code of ``gpuslice.mesh`` (checked here against ``mesh_from_triangles``); the device path
must give identical arrays (ids numbered by first occurrence) whatever order its work-items ran in, also when a
tiny table or a crippled hash forces long collision chains.
"""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles
from gpuslice.mesh import shapes as S
from gpuslice.mesh.weld import WeldKernel, edge_ids_device, edge_ids_numpy, weld_device, weld_numpy


def _corners(triangles) -> np.ndarray:
    """(3F, 3) float32 corners, -0.0 turned into 0.0, as ``mesh_from_triangles`` prepares them."""
    return np.ascontiguousarray(np.asarray(triangles).reshape(-1, 3), dtype=np.float32) + np.float32(0.0)


def _drop_degenerate(vid: np.ndarray) -> np.ndarray:
    faces = vid.reshape(-1, 3)
    good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    return faces[good]


def _assert_same(got, want) -> None:
    for g, w in zip(got, want, strict=True):
        assert g.dtype == w.dtype and g.shape == w.shape
        assert np.array_equal(g, w)


def _check_weld_and_edges(corners: np.ndarray, kernel=None, device=None) -> tuple[np.ndarray, np.ndarray]:
    """Device == numpy for the weld and for the edge ids of the kept facets; returns the numpy weld."""
    want = weld_numpy(corners)
    got = kernel.weld(corners) if kernel is not None else weld_device(corners, device)
    _assert_same(got, want)
    faces = _drop_degenerate(want[0])
    n_v = want[1].shape[0]
    want_e = edge_ids_numpy(faces, n_v)
    got_e = kernel.edge_ids(faces, n_v) if kernel is not None else edge_ids_device(faces, n_v, device)
    _assert_same(got_e, want_e)
    return want


def _soup(rng: np.random.Generator, n_points: int = 1000, n_corners: int = 10_002) -> np.ndarray:
    """Corners drawn from a few distinct points: zeros of both signs (normalised) and 1-ulp neighbours included."""
    pts = rng.uniform(-50, 50, (n_points, 3)).astype(np.float32)
    pts[:40, 1] = 0.0
    pts[40:80, 0] = -0.0
    pts[80:120] = np.nextafter(pts[120:160], np.float32(np.inf))  # 1 ulp away from other points: no weld
    pts[160:200, 2] = np.nextafter(pts[200:240, 2], np.float32(-np.inf))
    corners = pts[rng.integers(0, n_points, n_corners)]
    corners[rng.random(n_corners) < 0.2, 1] *= np.float32(-1.0)  # -0.0 where y was 0.0
    return corners + np.float32(0.0)


# ---- the numpy twins are mesh.py's numbering ----


@pytest.mark.parametrize("name", ["box", "torus", "soup"])
def test_numpy_twins_match_mesh_from_triangles(name):
    if name == "soup":
        tri = _soup(np.random.default_rng(1), 500, 3000).reshape(-1, 3, 3)
        tri[:, :, 2] += np.float32(100.0)  # above the bed: the mesh is moved, its ids are not
    else:
        tri = S.box(hi=(2, 3, 4)) if name == "box" else S.torus()
    m = mesh_from_triangles(tri)
    vid, first = weld_numpy(_corners(tri))
    faces = _drop_degenerate(vid)
    face_edges, edge_vertices = edge_ids_numpy(faces, first.shape[0])
    assert m.vertices.shape[0] == first.shape[0]
    if m.offset == (0.0, 0.0, 0.0):
        assert np.array_equal(m.vertices, _corners(tri)[first])
    assert np.array_equal(m.faces, faces)
    assert np.array_equal(m.face_edges, face_edges) and np.array_equal(m.edge_vertices, edge_vertices)
    assert first.dtype == np.int64 and vid.dtype == np.int32
    assert face_edges.dtype == np.int32 and edge_vertices.dtype == np.int32


def test_numpy_weld_is_bitwise():
    a = np.array([[1.0, 2.0, 3.0]], np.float32)
    b = np.nextafter(a, np.float32(np.inf))
    corners = np.concatenate([a, b, a, np.zeros((1, 3), np.float32), -np.zeros((1, 3), np.float32) + 0.0, b])
    vid, first = weld_numpy(corners)
    assert vid.tolist() == [0, 1, 0, 2, 2, 1] and first.tolist() == [0, 1, 3]


# ---- the device against the twins ----


def test_device_cube(device):
    want = _check_weld_and_edges(_corners(S.box(hi=(2, 3, 4))), device=device)
    assert want[1].shape == (8,)


def test_device_torus(device):
    _check_weld_and_edges(_corners(S.torus()), device=device)
    _check_weld_and_edges(_corners(S.icosphere(20, 3)), device=device)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_device_random_soup(device, seed):
    rng = np.random.default_rng(seed)
    corners = _soup(rng)
    vid, first = _check_weld_and_edges(corners, device=device)
    distinct = np.unique(corners.view(np.uint32), axis=0).shape[0]
    assert first.shape[0] == distinct  # 1-ulp neighbours stay apart, 0.0 and (normalised) -0.0 weld
    assert not np.any(corners.view(np.uint32) == np.float32(-0.0).view(np.uint32))


def test_device_ulp_neighbours_and_signed_zero(device):
    a = np.array([[1.0, 2.0, 3.0], [0.0, 5.0, 0.0]], np.float32)
    up, down = np.nextafter(a, np.float32(np.inf)), np.nextafter(a, np.float32(-np.inf))
    negative_zero = np.array([[-0.0, 5.0, -0.0]], np.float32)
    raw = np.concatenate([a, up, down, a, negative_zero])
    corners = raw + np.float32(0.0)  # normalised: -0.0 welds with 0.0
    vid, first = weld_device(corners, device)
    assert vid.tolist() == [0, 1, 2, 3, 4, 5, 0, 1, 1] and first.tolist() == [0, 1, 2, 3, 4, 5]
    _assert_same((vid, first), weld_numpy(corners))
    # not normalised, -0.0 is another bit pattern: a vertex of its own on both paths
    vid, first = weld_device(raw, device)
    assert vid.tolist() == [0, 1, 2, 3, 4, 5, 0, 1, 6]
    _assert_same((vid, first), weld_numpy(raw))


def test_device_edge_ids_of_arbitrary_faces(device):
    # non-manifold, repeated and reversed sides, even degenerate ones: the numbering is still the numpy one
    rng = np.random.default_rng(7)
    for n_v, n_f in [(3, 5), (30, 1000), (400, 20_000)]:
        faces = rng.integers(0, n_v, (n_f, 3)).astype(np.int32)
        _assert_same(edge_ids_device(faces, n_v, device), edge_ids_numpy(faces, n_v))


def test_device_empty_and_single(device):
    vid, first = weld_device(np.zeros((0, 3), np.float32), device)
    assert vid.shape == (0,) and first.shape == (0,) and vid.dtype == np.int32 and first.dtype == np.int64
    fe, ev = edge_ids_device(np.zeros((0, 3), np.int32), 0, device)
    assert fe.shape == (0, 3) and ev.shape == (0, 2)
    one = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    _check_weld_and_edges(one, device=device)


def test_device_buffers_reused_across_sizes(device):
    kernel = WeldKernel(device)
    rng = np.random.default_rng(3)
    for n_points, n_corners in [(50, 300), (2000, 30_000), (10, 60), (2000, 30_000)]:
        _check_weld_and_edges(_soup(rng, n_points, n_corners), kernel=kernel)


@pytest.mark.parametrize(("factor", "bits"), [(1.0, 32), (1.05, 32), (1.0, 4), (2.0, 0)])
def test_device_hash_collision_stress(device, factor, bits):
    """A table barely larger than the items, or a hash cut to a few bits: long probe chains, same result."""
    kernel = WeldKernel(device, table_factor=factor, hash_bits=bits)
    rng = np.random.default_rng(11)
    n = 1023 if bits else 255  # all-distinct corners: 1023 keys in 1024 slots at factor 1
    distinct = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
    _check_weld_and_edges(distinct, kernel=kernel)
    _check_weld_and_edges(_soup(rng, 300 if bits else 60, 2400 if bits else 600), kernel=kernel)
    faces = rng.integers(0, 40, (n // 3 if bits else 80, 3)).astype(np.int32)
    _assert_same(kernel.edge_ids(faces, 40), edge_ids_numpy(faces, 40))


def test_kernel_parameters_checked(device):
    with pytest.raises(ValueError):
        WeldKernel(device, table_factor=0.5)
    with pytest.raises(ValueError):
        WeldKernel(device, hash_bits=33)
    with pytest.raises(ValueError):
        edge_ids_device(np.array([[0, 1, 5]], np.int32), 3, device)


@pytest.mark.parametrize("name", ["benchy.stl", "nefertiti.stl"])
def test_device_real_meshes(device, shared_meshes, name):
    from gpuslice.io.meshfile import read_mesh_file

    path = shared_meshes / name
    if not path.is_file():
        pytest.skip(f"{path} not found")
    raw = read_mesh_file(path)
    _check_weld_and_edges(_corners(raw.triangles), device=device)
