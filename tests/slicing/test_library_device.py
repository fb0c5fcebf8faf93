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
    """A build keeps the program's binary (whole, checksummed) and the next build loads it; a truncated or refused
    binary and an unwritable cache fall back to the source build; PYOPENCL_NO_CACHE=1 neither reads nor writes.
    (Every kernel-twin test runs the cached binary.)"""
    from gpuslice import device as devmod

    build = devmod._build.__wrapped__
    monkeypatch.setenv("GPUSLICE_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("PYOPENCL_NO_CACHE", raising=False)
    loaded = []
    real = devmod._cached_binary
    monkeypatch.setattr(devmod, "_cached_binary", lambda path: loaded.append(real(path)) or loaded[-1])
    first = build(device, device.local_size)
    (entry,) = (tmp_path / "cache").glob("*.bin")
    assert loaded == [None] and entry.stat().st_size > 1000
    second = build(device, device.local_size)
    assert loaded[-1] is not None and len(loaded[-1]) == entry.stat().st_size - 32
    names = sorted(k.function_name for k in first.all_kernels())
    assert names == sorted(k.function_name for k in second.all_kernels()) and "emit_segments" in names
    entry.write_bytes(entry.read_bytes()[:1000])  # a process killed mid-write (cannot happen: temp + rename)
    third = build(device, device.local_size)
    assert loaded[-1] is None and sorted(k.function_name for k in third.all_kernels()) == names
    assert real(entry) is not None  # written whole again
    monkeypatch.setenv("PYOPENCL_NO_CACHE", "1")
    n = len(loaded)
    build(device, device.local_size)
    assert len(loaded) == n
    monkeypatch.setenv("PYOPENCL_NO_CACHE", "0")  # as PyOpenCL reads it: the cache is on
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("GPUSLICE_CACHE_DIR", str(blocker / "sub"))  # cannot be made
    assert sorted(k.function_name for k in build(device, device.local_size).all_kernels()) == names
    assert len(loaded) == n + 1 and loaded[-1] is None


def test_asynchronous_transfers_give_the_same_slices_and_runs(device, monkeypatch):
    """On a CPU device the drivers transfer synchronously (``Device.sync_transfers``: PoCL holds the GIL in a
    non-blocking transfer behind a kernel); a GPU keeps them asynchronous. Both orders give the same contours, mesh
    topology and runs: the asynchronous path, a GPU's, is run here on the CPU device too."""
    from gpuslice.mesh.mesh import load_mesh
    from gpuslice.raster import RasterSpec
    from gpuslice.raster.runs import iter_runs

    tris = np.concatenate([shapes.torus(9.0, 3.0, 48, 24), shapes.hollow_box(12.0, 5.0) + [25.0, 0.0, 0.0]])

    def run():
        mesh = load_mesh(mesh_from_triangles(tris), device=device)  # welded on the device
        res = slice_mesh(mesh, thickness=0.25, device=device)
        spec = RasterSpec(resolution=(900, 500), pixel=0.05)
        runs = [(r.layers, r.row, r.x, r.length, r.grey) for r in iter_runs(res, spec, device=device,
                                                                            max_batch_pieces=5_000)]
        return res, runs

    assert device.sync_transfers == (not device.is_gpu)
    monkeypatch.setitem(device.__dict__, "sync_transfers", True)
    a, runs_a = run()
    monkeypatch.setitem(device.__dict__, "sync_transfers", False)
    b, runs_b = run()
    assert a.n_layers > 40 and len(runs_a) > 2  # several batches of runs
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.loop_offsets, b.loop_offsets)
    assert len(runs_a) == len(runs_b)
    for x, y in zip(runs_a, runs_b, strict=True):
        for u, v in zip(x, y, strict=True):
            np.testing.assert_array_equal(u, v)
