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



def test_no_driver_drops_a_non_blocking_transfer_event():
    """``gpuslice.device.TRANSFERS``: PyOpenCL's event of a non-blocking ``enqueue_copy`` waits for its transfer
    when dropped, holding the GIL (every other thread of the process stops). Every such call in the package keeps
    its event (an assignment) to wait on it later; the others are blocking (they wait with the GIL released)."""
    import ast
    from pathlib import Path

    import gpuslice

    dropped, kept = [], 0
    for path in Path(gpuslice.__file__).parent.rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "enqueue_copy"):
                continue
            blocking = next((k.value for k in node.keywords if k.arg == "is_blocking"), None)
            if blocking is None or (isinstance(blocking, ast.Constant) and blocking.value is True):
                continue  # (PyOpenCL's default is blocking)
            parent = next((p for p in ast.walk(tree) if node in ast.iter_child_nodes(p)), None)
            if isinstance(parent, ast.Assign):
                kept += 1
            else:
                dropped.append(f"{path.name}:{node.lineno}")
    assert not dropped, f"non-blocking enqueue_copy whose event is dropped: {dropped}"
    assert kept >= 2  # the chaining's reads that overlap its next kernels (the rule is exercised, not vacuous)


def test_input_buffer_shares_a_cpu_devices_memory_and_copies_for_a_gpu(device):
    """``input_buffer``: the array's own memory on a CPU device (no copy into fresh pages), a copy on others; the
    device reads the array's values either way (an odd, unaligned slice too, as the encoders pass)."""
    import pyopencl as cl

    from gpuslice.buffers import input_buffer

    data = np.arange(1_000_003, dtype=np.int32)[3:]
    buf = input_buffer(device, data)
    shared = bool(buf.flags & cl.mem_flags.USE_HOST_PTR)
    assert shared == device.is_cpu and bool(buf.flags & cl.mem_flags.COPY_HOST_PTR) == (not device.is_cpu)
    assert buf.flags & cl.mem_flags.READ_ONLY
    got = np.empty_like(data)
    cl.enqueue_copy(device.queue, got, buf, is_blocking=True)
    assert np.array_equal(got, data)
