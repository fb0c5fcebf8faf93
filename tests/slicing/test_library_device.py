"""The library takes an OpenCL device as a name or as the Device object itself."""

from __future__ import annotations

import numpy as np

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.device import get_device
from gpuslice.mesh import shapes


def test_slice_mesh_takes_a_device_object(device):
    """``slice_mesh(mesh, device=get_device())`` slices on that device, as the default device name does."""
    mesh = mesh_from_triangles(shapes.cone(radius=5.0, height=10.0, n=32))
    assert get_device(device) is device
    a = slice_mesh(mesh, thickness=1.0, device=device)
    b = slice_mesh(mesh, thickness=1.0)
    np.testing.assert_array_equal(a.area, b.area)
    assert a.n_layers == 10 and np.all(a.area > 0)


def test_slice_mesh_of_a_path_welds_on_the_slicing_device(device, tmp_path, monkeypatch):
    """``slice_mesh(path)`` loads the mesh with the device it slices on (issue 14: the library no longer welds on
    the host when the caller slices with a device), and the result equals slicing a host-welded mesh."""
    import gpuslice.mesh.mesh as mesh_module
    from gpuslice import load_mesh
    from gpuslice.cli import main

    stl = tmp_path / "sphere.stl"
    assert main(["shape", "sphere", "-o", str(stl)]) == 0
    seen = []
    real = mesh_module.load_mesh

    def spy(source, **kw):
        seen.append(kw.get("device"))
        return real(source, **kw)

    monkeypatch.setattr(mesh_module, "load_mesh", spy)
    res = slice_mesh(stl, thickness=0.5, device=device)
    assert seen == [device]
    ref = slice_mesh(load_mesh(stl), thickness=0.5, device=device)  # welded on the host
    np.testing.assert_array_equal(res.points, ref.points)
    seen.clear()
    slice_mesh(stl, thickness=0.5, backend="numpy")
    assert seen == [None]  # the numpy backend has no device


def test_kernels_load_from_the_binary_cache_as_built_from_source(device, tmp_path, monkeypatch):
    """The program comes from PyOpenCL's binary cache (once built anywhere, later builds are cache hits); a source
    build (``PYOPENCL_NO_CACHE=1``) holds the same kernels. (Every kernel-twin test runs the cached binary.)"""
    import pyopencl.cache as pcache

    from gpuslice import device as devmod

    hits = []
    real = pcache.create_built_program_from_source_cached

    def spy(*args, **kwargs):
        prg, cached = real(*args, **kwargs)
        hits.append(cached)
        return prg, cached

    monkeypatch.setattr(pcache, "create_built_program_from_source_cached", spy)
    build = devmod._build.__wrapped__
    build(device, device.local_size)  # a miss only on a machine that never built these kernels
    cached = build(device, device.local_size)
    assert len(hits) == 2 and hits[1] is True
    monkeypatch.setenv("PYOPENCL_NO_CACHE", "1")
    source = build(device, device.local_size)
    assert len(hits) == 2  # not asked this time
    names = sorted(k.function_name for k in cached.all_kernels())
    assert names == sorted(k.function_name for k in source.all_kernels()) and "emit_segments" in names
