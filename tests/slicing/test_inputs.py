"""Every mesh source ``slice_mesh``/``load_mesh`` take (a Trimesh, a Scene, arrays, a path, bytes, a binary file
object) gives the same result as the STL of the same mesh; 3MF inputs are inflated under a limit."""

from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

import gpuslice
from gpuslice.errors import MeshFileError, ParameterError
from gpuslice.io import meshfile
from gpuslice.slicing.result import SliceResult

ARRAYS = ("points", "loop_offsets", "layer_offsets", "loop_is_hole", "loop_parent", "loop_closed", "z", "thickness",
          "area")


def assert_same(a: SliceResult, b: SliceResult) -> None:
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def _stl_bytes(mesh: trimesh.Trimesh) -> bytes:
    return mesh.export(file_type="stl")  # binary STL


@pytest.mark.parametrize("name", ["fandisk", "prusa_extruder_idler"])
def test_trimesh_slices_as_its_binary_stl(shared_meshes, tmp_path, name):
    tm = trimesh.load(shared_meshes / f"{name}.stl")  # processed (vertices merged): its own triangles
    stl = tmp_path / f"{name}.stl"
    stl.write_bytes(_stl_bytes(tm))
    ref = gpuslice.slice_mesh(stl, thickness=0.1, fit=60)
    assert ref.n_layers > 100
    assert_same(gpuslice.slice_mesh(tm, thickness=0.1, fit=60), ref)
    assert_same(gpuslice.slice_mesh(gpuslice.load_mesh(tm, fit=60), thickness=0.1), ref)
    assert_same(gpuslice.slice_mesh((tm.vertices, tm.faces), thickness=0.1, fit=60), ref)
    assert_same(gpuslice.slice_mesh(stl.read_bytes(), thickness=0.1, fit=60), ref)
    with open(stl, "rb") as fh:
        assert_same(gpuslice.slice_mesh(fh, thickness=0.1, fit=60), ref)


@pytest.mark.parametrize("offset", [1e5, 1e6, 1e7])
def test_float64_source_far_above_the_bed_is_placed_before_rounding(offset):
    # float64 vertices finer than float32: moved to the bed (and scaled) in float64, rounded once after; rounding
    # them in their own far-away frame first cost 7 % of a layer's area at 1e6 mm, 75 % at 1e7 (a helper's probe)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=10.0)
    v = sphere.vertices + (0.1234567, -0.7654321, 0.0)  # (values off the float32 grid)
    near = gpuslice.slice_mesh((v, sphere.faces), thickness=0.5)
    far = gpuslice.slice_mesh((v + (0.0, 0.0, offset), sphere.faces), thickness=0.5)
    assert near.n_layers == 40
    for name in ("loop_offsets", "layer_offsets", "z"):
        np.testing.assert_array_equal(getattr(far, name), getattr(near, name))
    # (only the float64 sum v + offset - offset rounds: an ulp of 1e7 is 2e-9 mm, a float32 ulp at 10 mm 1e-6 mm)
    np.testing.assert_allclose(far.points, near.points, rtol=0, atol=2e-6)
    np.testing.assert_allclose(far.area, near.area, rtol=1e-6)
    fitted = gpuslice.slice_mesh((v * 1e3 + (0.0, 0.0, offset * 1e3), sphere.faces), thickness=0.5, fit=20.0)
    np.testing.assert_allclose(fitted.area, near.area, rtol=1e-5)


def test_obj_far_above_the_bed_from_a_path_or_bytes_is_placed_before_rounding(tmp_path):
    # OBJ, PLY, 3MF are read in float64 (trimesh) and placed before their one rounding, like the same file loaded by
    # trimesh and handed over: a path, bytes and the Trimesh give one result (a review found the files rounded first)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    near = gpuslice.slice_mesh((sphere.vertices + (0.1234567, 0.0, 0.0), sphere.faces), thickness=0.5)
    far = trimesh.Trimesh(sphere.vertices + (0.1234567, 0.0, 1e6), sphere.faces, process=False)
    path = tmp_path / "far.obj"
    path.write_text(far.export(file_type="obj"))
    results = [gpuslice.slice_mesh(path, thickness=0.5), gpuslice.slice_mesh(path.read_bytes(), thickness=0.5,
               name="far.obj"), gpuslice.slice_mesh(trimesh.load(path, process=False), thickness=0.5)]
    for res in results:
        assert_same(res, results[0])
    np.testing.assert_allclose(results[0].area, near.area, rtol=1e-5)  # (rounded in its own frame: 7e-3)


@pytest.mark.parametrize("kw", [{}, {"scale": 1e-30}, {"fit": 10.0}])
def test_float64_values_beyond_float32_keep_their_error(kw):
    v = np.array([[0, 0, 0], [1e39, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    with pytest.raises(gpuslice.errors.InvalidGeometryError, match="NaN or infinite vertex coordinates"):
        gpuslice.load_mesh((v, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]), **kw)


def test_scene_is_concatenated_with_its_transforms(tmp_path):
    a = trimesh.creation.box((10, 10, 10))
    b = trimesh.creation.icosphere(subdivisions=2, radius=4)
    scene = trimesh.Scene()
    scene.add_geometry(a)
    scene.add_geometry(b, transform=trimesh.transformations.translation_matrix([20, 0, 3]))
    merged = scene.to_mesh()
    res = gpuslice.slice_mesh(scene, thickness=0.5)
    assert_same(res, gpuslice.slice_mesh((merged.vertices, merged.faces), thickness=0.5))
    # the transforms make float64 coordinates off the float32 grid: placed before rounding, within a float32
    # rounding of the STL export's layers (which round first)
    stl = gpuslice.slice_mesh(_stl_bytes(merged), thickness=0.5)
    for name in ("loop_offsets", "layer_offsets", "z"):
        np.testing.assert_array_equal(getattr(res, name), getattr(stl, name))
    np.testing.assert_allclose(res.points, stl.points, rtol=0, atol=4e-6)
    assert res.layer(len(res) // 2).to_shapely().geoms.__len__() == 2  # both bodies, placed apart


def test_formats_from_memory_without_a_file(tmp_path):
    box = trimesh.creation.box((10, 20, 30))
    ref = gpuslice.slice_mesh(box, thickness=1.0)
    for ext in ("obj", "ply", "off", "3mf"):
        data = box.export(file_type=ext)
        data = data.encode() if isinstance(data, str) else data
        mesh = gpuslice.load_mesh(data, name=f"box.{ext}")
        assert mesh.name == f"box.{ext}" and mesh.source_format == ext
        np.testing.assert_allclose(gpuslice.slice_mesh(mesh, thickness=1.0).area, ref.area, rtol=1e-6)
        assert gpuslice.slice_mesh(io.BytesIO(data), name=f"box.{ext}", thickness=1.0).n_layers == ref.n_layers
    unnamed = gpuslice.load_mesh(box.export(file_type="3mf"))  # a zip without a name: read as 3MF
    assert unnamed.source_format == "3mf"
    path = tmp_path / "box.3mf"
    path.write_bytes(box.export(file_type="3mf"))
    assert_same(gpuslice.slice_mesh(path, thickness=1.0), gpuslice.slice_mesh(path.read_bytes(), thickness=1.0))


def test_bad_sources_are_one_line_errors(tmp_path):
    with pytest.raises(ParameterError, match="cannot load a mesh from a int"):
        gpuslice.load_mesh(42)
    with pytest.raises(ParameterError, match="binary mode"):
        gpuslice.load_mesh(io.StringIO("solid x\nendsolid x\n"))
    with pytest.raises(ParameterError, match=r"<arrays>: face indices out of range"):
        gpuslice.slice_mesh((np.zeros((3, 3)), [[0, 1, 3]]))
    with pytest.raises(MeshFileError, match=r"part\.stl: "):
        gpuslice.load_mesh(b"garbage that is no mesh", name="part.stl")
    mesh = gpuslice.load_mesh(trimesh.creation.box((1, 1, 1)))
    assert gpuslice.load_mesh(mesh) is mesh and gpuslice.load_mesh(mesh, scale=2).height == pytest.approx(2)


# ---------------------------------------------------------------------------------------------------------
# zipped inputs: the inflation limit
# ---------------------------------------------------------------------------------------------------------
def _zip_bomb(path: Path, inflated: int) -> None:
    """A small zip (3MF-named) whose one member is ``inflated`` bytes of zeros (deflates about 1000:1)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        with zf.open("3D/3dmodel.model", "w") as fh:
            block = bytes(1 << 20)
            for _ in range(inflated >> 20):
                fh.write(block)


def _forge_sizes(path: Path, declared: int) -> None:
    """Make the member declare ``declared`` inflated bytes, in its local header and in the central directory."""
    data = bytearray(path.read_bytes())
    local = data.find(b"PK\x03\x04")
    central = data.find(b"PK\x01\x02")
    struct.pack_into("<I", data, local + 22, declared)
    struct.pack_into("<I", data, central + 24, declared)
    path.write_bytes(bytes(data))


def test_3mf_declaring_a_huge_inflated_size_is_refused(tmp_path, monkeypatch):
    bomb = tmp_path / "bomb.3mf"
    _zip_bomb(bomb, 24 << 20)
    assert bomb.stat().st_size < 200_000
    monkeypatch.setattr(meshfile, "ZIP_MAX_INFLATED", 4 << 20)
    for source in (bomb, bomb.read_bytes()):
        with pytest.raises(MeshFileError, match=r"bomb\.3mf: 3MF members declare 25165824 bytes inflated, over the "
                                                r"limit of 4194304 bytes") as info:
            gpuslice.load_mesh(source, name=None if isinstance(source, Path) else "bomb.3mf")
        assert "\n" not in str(info.value)
    # the ratio limit alone: 24 MiB from a ~25 kB file is far beyond 200x once the 64 MiB floor is lowered
    monkeypatch.setattr(meshfile, "ZIP_MAX_INFLATED", 1 << 30)
    monkeypatch.setattr(meshfile, "ZIP_RATIO_FLOOR", 0)
    with pytest.raises(MeshFileError, match=r"bomb\.3mf: 3MF members declare"):
        gpuslice.load_mesh(bomb)


def test_3mf_whose_sizes_lie_is_stopped_while_inflating(tmp_path, monkeypatch):
    bomb = tmp_path / "liar.3mf"
    _zip_bomb(bomb, 24 << 20)
    _forge_sizes(bomb, 1000)  # declares 1000 bytes, inflates to 24 MiB
    monkeypatch.setattr(meshfile, "ZIP_MAX_INFLATED", 4 << 20)
    with pytest.raises(MeshFileError, match=r"liar\.3mf: ") as info:
        gpuslice.load_mesh(bomb)
    assert "\n" not in str(info.value)
