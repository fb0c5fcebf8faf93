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
