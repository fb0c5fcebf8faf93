"""Mesh loading, welding and `info` against the shared catalog (figures computed by others)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from gpuslice import load_mesh, mesh_from_triangles
from gpuslice.mesh import shapes as S


def test_weld_and_edges_on_a_cube():
    m = mesh_from_triangles(S.box(hi=(2, 3, 4)))
    assert m.vertices.shape == (8, 3) and m.faces.shape == (12, 3)
    assert m.edge_vertices.shape == (18, 2)  # 12 box edges + 6 face diagonals
    assert np.all(m.edge_face_counts() == 2)
    info = m.info()
    assert info["watertight"] and info["winding_consistent"] and info["volume"] == pytest.approx(24.0)
    # each facet side's edge joins the right two vertices
    f, e = m.faces, m.face_edges
    for k in range(3):
        pair = np.sort(np.stack([f[:, k], f[:, (k + 1) % 3]], axis=1), axis=1)
        np.testing.assert_array_equal(m.edge_vertices[e[:, k]], pair)


def test_scale_fit_and_bed_placement():
    tri = S.box((-5, -5, -7), (5, 15, 3))
    m = mesh_from_triangles(tri, fit=40)
    b = m.bounds
    assert b[0, 2] == 0 and (b[1] - b[0]).max() == pytest.approx(40)
    assert b[0, 0] == pytest.approx(-10) and b[0, 1] == pytest.approx(-10)  # X and Y kept (scaled)
    m2 = mesh_from_triangles(tri, scale=2)
    np.testing.assert_allclose(m2.bounds, [[-10, -10, 0], [10, 30, 20]])


def test_degenerate_facets_dropped_and_ids_deterministic():
    tri = np.concatenate([S.box(), [[[0, 0, 0], [0, 0, 0], [1, 1, 1]]]])
    m = mesh_from_triangles(tri)
    assert m.dropped_degenerate == 1 and m.n_faces == 12
    m2 = mesh_from_triangles(tri)
    np.testing.assert_array_equal(m.faces, m2.faces)
    np.testing.assert_array_equal(m.face_edges, m2.face_edges)


def catalog(shared):
    with open(shared / "catalog.csv") as fh:
        return [r for r in csv.DictReader(fh) if int(r["facets"]) > 0 and r["name"] != "p_flt_max_coords"]


def test_info_matches_catalog(shared_meshes):
    mismatches = []
    for row in catalog(shared_meshes):
        info = load_mesh(shared_meshes / row["file"]).info()
        got = {
            "facets": info["facets"] + info["degenerate_dropped"],
            "watertight": str(info["watertight"]),
            "bodies": info["bodies"],
            "boundary_edges": info["boundary_edges"],
            "nonmanifold_edges": info["nonmanifold_edges"],
            "winding_consistent": str(info["winding_consistent"]),
        }
        want = {k: (int(row[k] or 0) if k not in ("watertight", "winding_consistent") else row[k]) for k in got}
        got["vertices"], want["vertices"] = info["vertices"], int(row["vertices"])
        if row["name"] == "p_capsule_degenerate":
            # gpuslice welds -0.0 with +0.0 (the same point); the catalog kept them apart: see the next test
            for key in ("vertices", "watertight", "boundary_edges"):
                got.pop(key), want.pop(key)
        if row["watertight"] == "True" and row["winding_consistent"] == "True":
            vol = float(row["volume"])
            got["volume_ok"], want["volume_ok"] = abs(info["volume"] - vol) <= 1e-5 * abs(vol), True
        # a volume only where the mesh (as gpuslice welds it) is closed and consistently wound: the signed sum of
        # an open or inconsistently wound mesh means nothing
        closed = info["watertight"] and info["winding_consistent"]
        got["volume_defined"], want["volume_defined"] = info["volume"] is not None, closed
        if got != want:
            mismatches.append((row["name"], {k: (got[k], want[k]) for k in got if got[k] != want[k]}))
    assert not mismatches


def test_signed_zero_welds(shared_meshes):
    # the capsule's seam has -0.0 and +0.0 coordinates: welded, the capsule (less its 200 degenerate facets) is closed
    info = load_mesh(shared_meshes / "p_capsule_degenerate.stl").info()
    assert info["degenerate_dropped"] == 200 and info["vertices"] == 5002 and info["watertight"]


@pytest.mark.parametrize("ext", ["obj", "ply", "off", "3mf"])
def test_other_formats_through_trimesh(tmp_path, ext):
    trimesh = pytest.importorskip("trimesh")
    path = tmp_path / f"box.{ext}"
    trimesh.creation.box(extents=(10, 20, 30)).export(path)
    m = load_mesh(path)
    assert m.source_format == ext and m.n_faces == 12
    info = m.info()
    assert info["watertight"] and info["volume"] == pytest.approx(6000.0)


def test_kernels_are_package_data():
    from importlib import resources

    names = {p.name for p in resources.files("gpuslice.kernels").iterdir()}
    assert {"crossings.cl", "walk.cl"} <= names


def test_device_weld_gives_the_same_mesh(device):
    tri = S.icosphere(radius=20, subdivisions=5)  # 20,480 facets: above DEVICE_WELD_MIN_FACETS
    a = mesh_from_triangles(tri, fit=50)
    b = mesh_from_triangles(tri, fit=50, device=device)
    for name in ("vertices", "faces", "face_edges", "edge_vertices"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_a_replaced_mesh_keeps_nothing_of_the_original():
    """``dataclasses.replace(mesh, vertices=...)`` makes another mesh: its normals and mesh check are its own, and the
    original's stay right (the kept values' dict was shared by both before)."""
    from dataclasses import replace

    from gpuslice import mesh_repairs

    m = mesh_from_triangles(S.box())
    normals = m.face_normals().copy()
    assert mesh_repairs(m)["inverted_shells"] == 0
    v = m.vertices.copy()
    v[:, 0] = -v[:, 0]  # mirrored in x: the same faces now wind inwards
    mirrored = replace(m, vertices=v)
    assert mesh_repairs(mirrored)["inverted_shells"] == 1
    np.testing.assert_allclose(mirrored.face_normals(), normals * [1, -1, -1], atol=1e-6)  # det -1: turned
    np.testing.assert_array_equal(m.face_normals(), normals)
    assert mesh_repairs(m)["inverted_shells"] == 0


def test_an_inside_out_mesh_has_a_positive_volume_and_says_so():
    # every facet turned round: the signed sum is negative, the solid it bounds is not (info printed -1000 mm^3)
    tri = S.box((0, 0, 0), (10, 10, 10))
    m = mesh_from_triangles(tri[:, ::-1])
    info = m.info()
    assert info["watertight"] and info["winding_consistent"]
    assert info["volume"] == pytest.approx(1000.0) and info["signed_volume"] == pytest.approx(-1000.0)
    assert info["inside_out"] and not mesh_from_triangles(tri).info()["inside_out"]
    flipped_one = tri.copy()
    flipped_one[0] = flipped_one[0, ::-1]
    assert mesh_from_triangles(flipped_one).info()["volume"] is None


def test_a_signalling_nan_normal_is_a_mismatch_without_a_warning():
    """An STL's stored normal may hold any bits: a signalling NaN (0x7fa00000) raised numpy's "invalid value
    encountered in cast" when widened, which `gpuslice info` printed (an internal error under -W error)."""
    import warnings

    from gpuslice.mesh.mesh import stored_normal_mismatch

    tri = np.asarray(S.box(), np.float32)
    computed = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    computed /= np.linalg.norm(computed, axis=1, keepdims=True)
    stored = computed.copy()
    stored.view(np.uint32)[0, 0] = 0x7FA00000  # a signalling NaN
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bad = stored_normal_mismatch(stored, computed)
        info = mesh_from_triangles(tri, stored).info()
    assert bad[0] and not bad[1:].any()
    assert info["stored_normal_mismatch"] == 1
