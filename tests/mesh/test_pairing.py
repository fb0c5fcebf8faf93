"""The mesh check's inputs made once, by the edge numbering (issue 14): the pairing of the facet sides along each
edge (``Mesh.edge_sides``), the shells' connected components (the device's union-find, scipy, numpy), and the
mesh check on a device-welded mesh against the host one, count for count and facet for facet.

Every reference here is computed independently of the code under test: per-edge side lists built by a plain
dictionary over the facets, components from scipy's ``connected_components``.
"""

from __future__ import annotations

import pickle
from dataclasses import astuple

import numpy as np
import pytest

import gpuslice
from gpuslice.mesh import shapes as S
from gpuslice.mesh.defects import outward_facets
from gpuslice.mesh.graph import components, connected_labels
from gpuslice.mesh.weld import EdgeSides, WeldKernel, edge_table_numpy, weld_device, weld_numpy


def _reference_sides(faces: np.ndarray, face_edges: np.ndarray) -> EdgeSides:
    """Side lists per edge id with a dictionary (slow, obviously right)."""
    n_e = int(face_edges.max()) + 1 if face_edges.size else 0
    lists: dict[int, list[int]] = {}
    fwd = np.zeros(n_e, np.int32)
    for s, e in enumerate(face_edges.reshape(-1).tolist()):
        lists.setdefault(e, []).append(s)
        f, k = divmod(s, 3)
        fwd[e] += int(faces[f, k] < faces[f, (k + 1) % 3])
    count = np.array([len(lists[e]) for e in range(n_e)], np.int32)
    first = np.array([min(lists[e]) for e in range(n_e)], np.int32)
    last = np.array([max(lists[e]) for e in range(n_e)], np.int32)
    return EdgeSides(count, first, last, fwd)


def _same_sides(a: EdgeSides, b: EdgeSides) -> None:
    for x, y in zip(astuple(a), astuple(b), strict=True):
        assert x.dtype == np.int32 and y.dtype == np.int32 and np.array_equal(x, y)


def _scipy_labels(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Each node's smallest node of its component, from scipy."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, comp = connected_components(coo_matrix((np.ones(a.size), (a, b)), shape=(n, n)), directed=False)
    smallest = np.full(comp.max() + 1, n)
    np.minimum.at(smallest, comp, np.arange(n))
    return smallest[comp]


def _meshes() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(4)
    flipped = S.torus().copy()
    flipped[::7] = flipped[::7, ::-1]  # every 7th facet wound backwards
    two = np.concatenate([S.box((0, 0, 0), (6, 6, 6)), S.box((6, 6, 0), (12, 12, 6))])  # a non-manifold edge
    return {
        "box": S.box(hi=(2, 3, 4)),
        "flipped torus": flipped,
        "open box": S.box(hi=(5, 5, 5))[2:],
        "two cubes": two,
        "mobius-ish soup": rng.integers(0, 6, (300, 3, 3)).astype(np.float32),
    }


@pytest.mark.parametrize("name", list(_meshes()))
def test_pairing_numpy_and_device_match_a_dictionary(name, device):
    tri = _meshes()[name]
    host = gpuslice.mesh_from_triangles(tri)
    want = _reference_sides(host.faces, host.face_edges)
    _same_sides(host.edge_sides(), want)  # kept from edge_table_numpy
    fe, ev, sides = WeldKernel.of(device).edge_table(host.faces, host.vertices.shape[0])
    assert np.array_equal(fe, host.face_edges) and np.array_equal(ev, host.edge_vertices)
    _same_sides(sides, want)
    bare = gpuslice.Mesh(host.vertices, host.faces, host.face_edges, host.edge_vertices)  # built elsewhere
    _same_sides(bare.edge_sides(), want)  # computed from face_edges
    assert bare.edge_face_counts().tolist() == want.count.tolist()


def test_pairing_of_random_faces(device):
    rng = np.random.default_rng(9)
    for n_v, n_f in [(4, 7), (50, 2000), (3000, 20_000)]:
        faces = rng.integers(0, n_v, (n_f, 3)).astype(np.int32)
        fe, _, sides = edge_table_numpy(faces, n_v)
        want = _reference_sides(faces, fe)
        _same_sides(sides, want)
        _same_sides(WeldKernel.of(device).edge_table(faces, n_v)[2], want)
        if n_f <= 2000:  # long probe chains (quadratic: small inputs only), same result
            crippled = WeldKernel(device, table_factor=1.0, hash_bits=3)
            _same_sides(crippled.edge_table(faces, n_v)[2], want)


@pytest.mark.parametrize("where", ["numpy", "scipy", "device"])
def test_components_label_each_node_with_its_smallest(where, device, monkeypatch):
    import gpuslice.mesh.graph as G

    monkeypatch.setattr(G, "SCIPY_NODES", 10**9 if where == "numpy" else 0)
    rng = np.random.default_rng(2)
    for n, m in ((1, 0), (7, 0), (50, 30), (5000, 2500), (5000, 9000)):
        a, b = rng.integers(0, n, m), rng.integers(0, n, m)
        if m > 5000:  # plus a long path numbered backwards: deep trees for the union-find
            a, b = np.concatenate([a, np.arange(n - 1)]), np.concatenate([b, np.arange(1, n)[::-1]])
        got = components(n, a, b, device if where == "device" else None)
        assert np.array_equal(got, _scipy_labels(n, a, b)), (where, n, m)
    if where == "numpy":  # the numpy pointer jumping agrees too (it is what "numpy" runs)
        assert np.array_equal(connected_labels(50, np.array([3, 9]), np.array([9, 40]))[[3, 9, 40]], [3, 3, 3])


def test_device_components_do_not_wait_for_a_slicer_holding_the_device(device):
    """The mesh check's union-find has a queue, buffers and a lock of its own: it runs beside a thread that holds the
    device's turn (a slicer), as ``pipeline._slice`` counts the defects while the layers are sliced."""
    import threading

    from gpuslice.prefetch import beside

    held, done = threading.Event(), threading.Event()

    def slicer():
        with device.exclusive():
            held.set()
            done.wait(30)

    holder = beside(slicer)
    try:
        assert held.wait(10)
        rng = np.random.default_rng(3)
        a, b = rng.integers(0, 3000, 2000), rng.integers(0, 3000, 2000)
        got = beside(components, 3000, a, b, device).result(timeout=20)  # (would wait 30 s for the device's turn)
        assert np.array_equal(got, _scipy_labels(3000, a, b))
    finally:
        done.set()
        holder.result(30)


def test_weld_reads_negative_zero_as_zero(device):
    rng = np.random.default_rng(6)
    pts = rng.integers(-2, 3, (4000, 3)).astype(np.float32)  # many zeros
    raw = pts * np.where(rng.random(pts.shape) < 0.5, np.float32(-1), np.float32(1))  # -0.0 in about half
    want = weld_numpy(raw + np.float32(0.0))  # normalised first, as before
    for got in (weld_numpy(raw, signed_zero=False), weld_device(raw, device, signed_zero=False)):
        assert all(np.array_equal(g, w) and g.dtype == w.dtype for g, w in zip(got, want, strict=True))
    assert not np.array_equal(weld_numpy(raw)[0], want[0])  # signed zeros kept apart by default


@pytest.mark.parametrize("name", list(_meshes()))
def test_mesh_check_on_the_device_matches_the_host(name, device):
    tri = _meshes()[name]
    host = gpuslice.mesh_from_triangles(tri)
    dev = gpuslice.mesh_from_triangles(tri, device=device)
    dev_mesh = gpuslice.mesh_from_triangles(tri)
    dev_mesh._cache["device"] = device  # small meshes weld on the host; the check may still use the device
    for m in (dev, dev_mesh):
        assert np.array_equal(m.faces, host.faces) and np.array_equal(m.face_edges, host.face_edges)
        f_host, c_host = outward_facets(host)
        f_dev, c_dev = outward_facets(m)
        assert c_host == c_dev and np.array_equal(f_host, f_dev)
    if name == "flipped torus":
        assert c_host["flipped_facets"] == len(tri[::7])


def test_device_welded_large_mesh_keeps_its_device_and_pickles(device):
    tri = S.icosphere(20, 5)  # 20,480 facets: above DEVICE_WELD_MIN_FACETS
    m = gpuslice.mesh_from_triangles(tri, device=device)
    assert m.device is device and gpuslice.mesh_from_triangles(tri).device is None
    host = gpuslice.mesh_from_triangles(tri)
    assert np.array_equal(m.face_edges, host.face_edges)
    _same_sides(m.edge_sides(), host.edge_sides())
    assert gpuslice.mesh_repairs(m) == gpuslice.mesh_repairs(host)
    back = pickle.loads(pickle.dumps(m))  # the device stays behind
    assert back.device is None and np.array_equal(back.faces, m.faces)
    assert gpuslice.mesh_repairs(back) == gpuslice.mesh_repairs(host)
