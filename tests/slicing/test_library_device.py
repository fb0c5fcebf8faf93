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
