"""Shared fixtures: the backend (numpy reference and OpenCL), the shared mesh folder, the device header."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO.parent / "shared" / "meshes"


def read_catalog() -> dict[str, dict[str, str]]:
    """``../shared/meshes/catalog.csv`` as {name: row}; empty where the shared folder is absent."""
    import csv

    path = SHARED_MESHES / "catalog.csv"
    if not path.is_file():
        return {}
    with open(path, newline="") as f:
        return {row["name"]: row for row in csv.DictReader(f)}


def _opencl_device():
    try:
        from gpuslice.device import get_device

        return get_device()
    except Exception as exc:  # no pyopencl, no platform
        return exc


def pytest_assertrepr_compare(config, op, left, right):
    """Unequal long byte strings (archives, PNGs) explained by their lengths and first differing byte: pytest's own
    explanation runs difflib over them, which takes minutes for a few MB."""
    if op == "==" and isinstance(left, bytes | bytearray) and isinstance(right, bytes | bytearray):
        if max(len(left), len(right)) > 4096:
            import numpy as np

            n = min(len(left), len(right))
            a, b = np.frombuffer(left, np.uint8, n), np.frombuffer(right, np.uint8, n)
            diff = np.flatnonzero(a != b)
            at = int(diff[0]) if diff.size else n
            return [f"{len(left)} bytes == {len(right)} bytes", f"first difference at byte {at} "
                    f"({int(diff.size)} of the first {n} bytes differ)"]
    return None


def pytest_report_header(config):
    dev = _opencl_device()
    name = dev.name if not isinstance(dev, Exception) else f"none ({dev})"
    shared = SHARED_MESHES if SHARED_MESHES.is_dir() else "absent"
    return [f"gpuslice OpenCL device: {name}", f"shared meshes: {shared}"]


@pytest.fixture(scope="session")
def device():
    dev = _opencl_device()
    if isinstance(dev, Exception):
        pytest.skip(f"no OpenCL device: {dev}")
    return dev


@pytest.fixture(params=["numpy", "opencl"])
def backend(request):
    """Both implementations of every stage: the numpy reference and the OpenCL kernels."""
    if request.param == "opencl":
        request.getfixturevalue("device")
    return request.param


@pytest.fixture(scope="session")
def shared_meshes() -> Path:
    if not SHARED_MESHES.is_dir():
        pytest.skip("../shared/meshes not found: real-mesh tests need the shared data folder beside the repo")
    return SHARED_MESHES


@pytest.fixture(scope="session")
def shared_results(shared_meshes):
    """``get(name, fit)`` -> (SliceResult at 0.05 mm on OpenCL, the mesh's XY bounds): each shared mesh sliced once
    per session for every archive format's 12K test."""
    import trimesh

    from gpuslice import mesh_from_triangles, slice_mesh

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
