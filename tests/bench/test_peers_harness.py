"""Checks of the peer-reference harness (scripts/peers.py) itself, on generated meshes with known sections.

A 20 mm cube (and a 20 mm cube with a 10 mm square through-hole) is written as a binary STL in tmp_path; every
section at 0 < z < 20 is exactly 400 mm^2 (300 mm^2 with the hole).  Peers that are not installed are skipped.
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

import numpy as np  # noqa: E402
import peers  # noqa: E402
import pytest  # noqa: E402

SIDE = 20.0
# Deliberately off-origin so that the z drop of write_scaled_stl and Slic3r's XY shift are exercised.
CUBE_MIN = np.array([5.0, -7.0, 3.0])

# 12 outward-facing triangles of the unit cube [0, 1]^3.
_UNIT_CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64
)
_UNIT_CUBE_F = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # bottom (-z)
        [4, 5, 6], [4, 6, 7],  # top (+z)
        [0, 1, 5], [0, 5, 4],  # -y
        [2, 3, 7], [2, 7, 6],  # +y
        [1, 2, 6], [1, 6, 5],  # +x
        [3, 0, 4], [3, 4, 7],  # -x
    ]
)  # fmt: skip


def _skip_hint(name: str) -> str:
    return f"{name} not installed: run ../shared/peers/setup-peers.sh"


def write_binary_stl(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rec = np.zeros(len(tri), dtype=peers.STL_DTYPE)
    rec["normal"] = normals
    rec["vertices"] = tri
    path.write_bytes(b"\0" * 80 + np.uint32(len(rec)).astype("<u4").tobytes() + rec.tobytes())


@pytest.fixture
def cube_stl(tmp_path: Path) -> Path:
    """20 mm cube at CUBE_MIN, as written; then the harness's scaled copy (scale 1, min z = 0)."""
    raw = tmp_path / "cube_raw.stl"
    write_binary_stl(raw, _UNIT_CUBE_V * SIDE + CUBE_MIN, _UNIT_CUBE_F)
    out = tmp_path / "cube.stl"
    s, offset = peers.write_scaled_stl(raw, out, scale=1.0)
    assert s == 1.0
    np.testing.assert_array_equal(offset, [0.0, 0.0, -CUBE_MIN[2]])
    return out


@pytest.fixture
def holed_cube_stl(tmp_path: Path) -> Path:
    """20 mm cube with a 10 mm square vertical through-hole (net section 300 mm^2), min at (0, 0, 0)."""
    manifold3d = pytest.importorskip("manifold3d")
    outer = manifold3d.Manifold.cube([SIDE, SIDE, SIDE])
    hole = manifold3d.Manifold.cube([10.0, 10.0, SIDE + 2.0]).translate([5.0, 5.0, -1.0])
    mesh = (outer - hole).to_mesh()
    path = tmp_path / "holed_cube.stl"
    write_binary_stl(path, np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts))
    return path


def _cube_arrays(stl: Path) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces = peers.load_stl(stl)
    assert len(vertices) == 8 and len(faces) == 12  # bit-identical corners weld exactly
    return vertices, faces


# ----------------------------------------------------------------------------------------------------------
# STL writing and plane helpers
# ----------------------------------------------------------------------------------------------------------


def test_write_scaled_stl_fit_and_scale(tmp_path: Path, cube_stl: Path) -> None:
    tri = peers.read_stl_triangles(cube_stl).reshape(-1, 3)
    np.testing.assert_array_equal(tri.min(axis=0), [CUBE_MIN[0], CUBE_MIN[1], 0.0])
    np.testing.assert_array_equal(tri.max(axis=0), [CUBE_MIN[0] + SIDE, CUBE_MIN[1] + SIDE, SIDE])

    fitted = tmp_path / "fit.stl"
    s, offset = peers.write_scaled_stl(cube_stl, fitted, fit=50.0)
    assert s == pytest.approx(2.5)
    np.testing.assert_array_equal(offset, [0.0, 0.0, 0.0])  # already at min z = 0
    tri = peers.read_stl_triangles(fitted).reshape(-1, 3)
    np.testing.assert_allclose(tri.min(axis=0), [CUBE_MIN[0] * 2.5, CUBE_MIN[1] * 2.5, 0.0])
    np.testing.assert_allclose(tri.max(axis=0) - tri.min(axis=0), [50.0, 50.0, 50.0])
    # Normals stay unit length and outward.
    normals = np.frombuffer(fitted.read_bytes(), dtype=peers.STL_DTYPE, offset=84)["normal"]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-6)

    with pytest.raises(ValueError):
        peers.write_scaled_stl(cube_stl, fitted)
    with pytest.raises(ValueError):
        peers.write_scaled_stl(cube_stl, fitted, fit=10.0, scale=2.0)
    with pytest.raises(ValueError):
        peers.write_scaled_stl(cube_stl, fitted, scale=-1.0)


def test_read_rejects_ascii_stl(tmp_path: Path) -> None:
    ascii_stl = tmp_path / "a.stl"
    ascii_stl.write_text("solid a\n" + " " * 200 + "\nendsolid a\n")
    with pytest.raises(ValueError, match="not a binary STL"):
        peers.read_stl_triangles(ascii_stl)


def test_mid_layer_planes() -> None:
    np.testing.assert_allclose(peers.mid_layer_planes(20.0, 0.5), (np.arange(40) + 0.5) * 0.5)
    assert len(peers.mid_layer_planes(20.0, 0.3)) == 67  # round(66.67)
    assert len(peers.mid_layer_planes(20.0, 0.15)) == 133  # round(133.33)


def test_find_peer_unknown() -> None:
    assert peers.find_peer("no-such-slicer-gpuslice") is None


def test_cura_definitions_lookup(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("GPUSLICE_PEERS_DIR", str(tmp_path / "peers"))
    defs = tmp_path / "peers" / "cura-defs"
    defs.mkdir(parents=True)
    (defs / "fdmprinter.def.json").write_text("{}")
    assert peers.cura_definitions() is None  # fdmextruder.def.json is required too
    (defs / "fdmextruder.def.json").write_text("{}")
    assert peers.cura_definitions() == defs


# ----------------------------------------------------------------------------------------------------------
# Slic3r
# ----------------------------------------------------------------------------------------------------------


def _need(name: str) -> None:
    if peers.find_peer(name) is None:
        pytest.skip(_skip_hint(name))


def test_slic3r_cube(cube_stl: Path) -> None:
    _need("slic3r")
    h = 0.5
    layers = peers.slic3r_layers(cube_stl, h)
    # Slic3r keeps a layer while its middle plane is below the top: round(20 / 0.5) = 40 layers, cut (and
    # reported via slic3r:z * 1e6) at the mid-layer planes (i + 0.5) * h.
    assert len(layers) == 40
    np.testing.assert_allclose([L.z for L in layers], (np.arange(40) + 0.5) * h, atol=1e-9)
    for layer in layers:
        assert layer.area == pytest.approx(SIDE * SIDE, rel=1e-9)
        assert [kind for kind, _ in layer.polygons] == ["contour"]
        pts = layer.polygons[0][1]
        # SVG frame: the mesh's bbox minimum is moved to (0, 0); xy_origin undoes it.
        np.testing.assert_allclose(pts.min(axis=0), [0.0, 0.0], atol=1e-6)
        np.testing.assert_allclose(pts.max(axis=0), [SIDE, SIDE], atol=1e-6)
    np.testing.assert_allclose(layers.xy_origin, CUBE_MIN[:2])
    assert layers.wall_s > 0


def test_slic3r_layer_count_rule_and_thick_layers(cube_stl: Path) -> None:
    _need("slic3r")
    assert len(peers.slic3r_layers(cube_stl, 0.3)) == 67  # 20 / 0.3 = 66.67 -> 67 (last plane at 19.95)
    # h above Slic3r's default nozzle (0.5 mm) needs --nozzle-diameter, which slic3r_layers passes.
    thick = peers.slic3r_layers(cube_stl, 1.0)
    np.testing.assert_allclose([L.z for L in thick], np.arange(20) + 0.5, atol=1e-9)


def test_slic3r_hole_markup(holed_cube_stl: Path) -> None:
    _need("slic3r")
    layers = peers.slic3r_layers(holed_cube_stl, 0.5)
    assert len(layers) == 40
    for layer in layers:
        assert sorted(kind for kind, _ in layer.polygons) == ["contour", "hole"]
        assert layer.area == pytest.approx(SIDE * SIDE - 100.0, rel=1e-9)


# ----------------------------------------------------------------------------------------------------------
# CuraEngine
# ----------------------------------------------------------------------------------------------------------


def test_cura_cube(cube_stl: Path) -> None:
    _need("CuraEngine")
    if peers.cura_definitions() is None:
        pytest.skip("Cura definitions (fdmprinter.def.json) missing: run ../shared/peers/setup-peers.sh")
    h = 0.5
    res = peers.cura_slice(cube_stl, h)
    assert res["layers"] == 40 == res["layer_count_header"]
    # gcode Z is the layer top; Cura cuts at the middle.
    np.testing.assert_allclose(res["z_top"], (np.arange(40) + 1) * h, atol=1e-6)
    assert res["polygons_per_layer"] == [1] * 40
    assert res["open_paths"] == 0
    np.testing.assert_allclose(res["area_per_layer"], SIDE * SIDE, rtol=1e-6)
    # With machine_center_is_zero=true Cura keeps the STL's x, y.
    pts = res["loops"][0][0].points
    np.testing.assert_allclose(pts.min(axis=0), CUBE_MIN[:2], atol=1e-3)
    assert res["unexpected_warnings"] == []
    assert res["wall_s"] > 0


# ----------------------------------------------------------------------------------------------------------
# manifold3d and trimesh
# ----------------------------------------------------------------------------------------------------------


def test_manifold_cube(cube_stl: Path) -> None:
    pytest.importorskip("manifold3d")
    vertices, faces = _cube_arrays(cube_stl)
    zs = np.concatenate([peers.mid_layer_planes(SIDE, 0.5), [SIDE + 1.0]])
    res = peers.manifold_slices(vertices, faces, zs)
    for area, n_points in res[:-1]:
        assert area == pytest.approx(SIDE * SIDE, rel=1e-9)
        # manifold3d keeps every edge crossing, collinear ones included: 4 vertical edges + the 4 side-face
        # diagonals of this triangulation.
        assert n_points == 8
    assert res[-1] == (0.0, 0)  # plane above the top
    m = peers.manifold_from_arrays(vertices, faces)
    assert m.volume() == pytest.approx(SIDE**3, rel=1e-9)


def test_manifold_hole(holed_cube_stl: Path) -> None:
    vertices, faces = peers.load_stl(holed_cube_stl)
    res = peers.manifold_slices(vertices, faces, [0.25, 10.0, 19.75])
    for area, n_points in res:
        assert area == pytest.approx(300.0, rel=1e-9)
        assert n_points >= 8  # 4 + 4 corners, plus the crossings of side-face diagonals


def test_trimesh_cube(cube_stl: Path) -> None:
    pytest.importorskip("trimesh")
    vertices, faces = _cube_arrays(cube_stl)
    zs = np.concatenate([peers.mid_layer_planes(SIDE, 0.5), [SIDE + 1.0]])
    areas = peers.trimesh_sections(vertices, faces, zs)
    np.testing.assert_allclose(areas[:-1], SIDE * SIDE, rtol=1e-9)
    assert areas[-1] == 0.0


def test_trimesh_hole(holed_cube_stl: Path) -> None:
    pytest.importorskip("trimesh")
    vertices, faces = peers.load_stl(holed_cube_stl)
    for loop_holes in (False, True):
        areas = peers.trimesh_sections(vertices, faces, [0.25, 10.0, 19.75], loop_holes=loop_holes)
        np.testing.assert_allclose(areas, 300.0, rtol=1e-9)
