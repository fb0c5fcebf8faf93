"""Fixtures of the raster tests: shared meshes sliced once per session for the archive formats' 12K checks."""

from __future__ import annotations

import pytest

from gpuslice import mesh_from_triangles, slice_mesh


@pytest.fixture(scope="session")
def shared_results(shared_meshes):
    """``get(name, fit)`` -> (SliceResult at 0.05 mm on OpenCL, the mesh's XY bounds): each shared mesh sliced once
    for every format's test."""
    import trimesh

    cache = {}

    def get(name: str, fit: float):
        if (name, fit) not in cache:
            m = trimesh.load(shared_meshes / f"{name}.stl", force="mesh")
            mesh = mesh_from_triangles(m.vertices[m.faces], fit=fit)
            b = mesh.bounds
            cache[name, fit] = (slice_mesh(mesh, thickness=0.05, backend="opencl"),
                                (b[0, 0], b[0, 1], b[1, 0], b[1, 1]))
        return cache[name, fit]

    return get
