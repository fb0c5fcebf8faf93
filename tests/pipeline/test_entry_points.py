"""One job through every entry point: ``slice``, ``raster``, ``view``, ``batch`` (in this process, on local workers
and on a Dask cluster) and ``bench`` all run :func:`gpuslice.pipeline.run_job`'s stages, so they must agree on the
layers: the same cutting planes, areas and points per layer, and the same masks."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from gpuslice import Placement, SliceParams
from gpuslice.batch import BatchOptions, run_batch
from gpuslice.cli import main
from gpuslice.pipeline import Job, ResinOutput, ViewOutput, run_job
from gpuslice.raster import RasterSpec, ResinOptions, masks
from gpuslice.slicing.result import SliceResult
from gpuslice.view.page import read_view_data

ARGS = ["-t", "0.25", "--fit", "30"]


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    folder = tmp_path_factory.mktemp("entry")
    (folder / "models").mkdir()
    stl = folder / "models" / "torus.stl"
    assert main(["shape", "torus", "-o", str(stl)]) == 0
    return stl


@pytest.fixture(scope="module")
def reference(model, tmp_path_factory):
    """``gpuslice slice`` of the model: the layers every other entry point must reproduce."""
    out = tmp_path_factory.mktemp("ref") / "ref.npz"
    assert main(["slice", str(model), *ARGS, "-o", str(out), "-q"]) == 0
    res = SliceResult.load(out)
    assert res.n_layers > 20 and res.points.shape[0] > 1000  # a real job, not an empty one
    return res


def _same_layers(a: SliceResult, b: SliceResult) -> None:
    np.testing.assert_array_equal(a.z, b.z)
    np.testing.assert_array_equal(a.thickness, b.thickness)
    np.testing.assert_array_equal(a.area, b.area)
    np.testing.assert_array_equal(a.points_per_layer, b.points_per_layer)
    np.testing.assert_array_equal(a.points, b.points)


def test_library_job_equals_slice_command(model, reference, device):
    done = run_job(Job(source=str(model), placement=Placement(fit=30.0), params=SliceParams(thickness=0.25)))
    _same_layers(done.result, reference)
    assert {"device", "load", "topology", "schedule", "crossings", "chaining", "nesting", "mesh_check"} <= set(
        done.timings)


def test_mesh_check_beside_the_slicing_gives_its_counts_and_errors(model, device, monkeypatch):
    """The mesh check counts on a thread while the layers are sliced: its counts land in the report as before, its
    error is the job's error, and a slice that fails waits for it (no thread left reading the mesh)."""
    import gpuslice.mesh.defects as defects
    import gpuslice.slicing.slicer as slicer

    job = Job(source=str(model), placement=Placement(fit=30.0), params=SliceParams(thickness=0.25))
    done = run_job(job, device=device)
    assert set(defects.MESH_REPAIR_KINDS) <= set(done.result.meta["repairs"])

    def broken(mesh):
        raise ValueError("mesh check failed")

    monkeypatch.setattr(defects, "mesh_repairs", broken)
    with pytest.raises(ValueError, match="mesh check failed"):
        run_job(job, device=device)

    finished = []

    def slow(mesh):
        import time

        time.sleep(0.2)
        finished.append(True)
        return {}

    def no_slice(*args, **kwargs):
        raise RuntimeError("slicing failed")

    monkeypatch.setattr(defects, "mesh_repairs", slow)
    monkeypatch.setattr(slicer, "slice_mesh", no_slice)
    with pytest.raises(RuntimeError, match="slicing failed"):
        run_job(job, device=device)
    assert finished  # (the job waited for the mesh check before its error went up)


def test_the_file_is_read_beside_the_device_set_up(model, reference, monkeypatch, tmp_path):
    """A job that makes its own device reads the mesh file on a thread while PyOpenCL starts: the layers are the
    same; a file that cannot be read is still the job's one-line error, and a device that cannot be made is the
    error reported first, after the read has finished (no thread left reading)."""
    import threading
    import time

    import gpuslice.io.meshfile as meshfile
    import gpuslice.pipeline as pipeline
    from gpuslice.errors import MeshFileError, ParameterError

    read_on = []
    real = meshfile.read_mesh_source

    def spy(*args):
        read_on.append(threading.current_thread() is threading.main_thread())
        return real(*args)

    monkeypatch.setattr(meshfile, "read_mesh_source", spy)
    job = Job(source=str(model), placement=Placement(fit=30.0), params=SliceParams(thickness=0.25))
    _same_layers(run_job(job).result, reference)
    assert read_on == [False]
    missing = Job(source=str(tmp_path / "none.stl"), params=SliceParams(thickness=0.25))
    with pytest.raises(MeshFileError, match="none.stl: no such file"):
        run_job(missing)
    finished = []

    def slow(*args):
        time.sleep(0.2)
        finished.append(True)
        raise MeshFileError("late.stl: no such file")

    def no_device(*args, **kwargs):
        raise ParameterError("no OpenCL device matches 'nothing'")

    monkeypatch.setattr(meshfile, "read_mesh_source", slow)
    monkeypatch.setattr(pipeline, "prepare_device", no_device)
    with pytest.raises(ParameterError, match="no OpenCL device"):
        run_job(job)
    assert finished


def test_view_agrees(model, reference, tmp_path):
    page = tmp_path / "v.html"
    assert main(["view", str(model), *ARGS, "-o", str(page), "-q"]) == 0
    arrays = read_view_data(page)["arrays"]
    np.testing.assert_array_equal(arrays["z"], reference.z)
    np.testing.assert_array_equal(arrays["area"], reference.area)
    np.testing.assert_array_equal(arrays["layer_points"], reference.points_per_layer)
    np.testing.assert_array_equal(arrays["points"].reshape(-1, 2), reference.points)


def test_raster_agrees(model, reference, tmp_path):
    """The PNG stack of ``gpuslice raster`` equals the masks of the reference layers on the same display."""
    stack = tmp_path / "stack"
    disp = ["--resolution", "200x160", "--pixel", "0.25", "--raster-backend", "opencl"]
    assert main(["raster", str(model), *ARGS, *disp, "-o", f"{stack}/", "-q", "--no-progress"]) == 0
    files = sorted(stack.glob("*.png"))
    assert len(files) == reference.n_layers
    spec = RasterSpec(resolution=(200, 160), pixel=0.25)
    done = run_job(Job(source=str(model), placement=Placement(fit=30.0), params=SliceParams(thickness=0.25),
                       resin=ResinOutput(str(tmp_path / "b.sl1"), "sl1", spec, ResinOptions(raster_backend="opencl"))))
    mesh_bounds = done.mesh.bounds
    bounds = (mesh_bounds[0, 0], mesh_bounds[0, 1], mesh_bounds[1, 0], mesh_bounds[1, 1])
    want = masks(reference, spec, backend="opencl", bounds=bounds)
    got = np.stack([np.asarray(Image.open(f)) for f in files])
    np.testing.assert_array_equal(got, want)
    assert want.max() == 255 and (want > 0).sum() > 1000


def test_batch_local_and_dask_agree(model, reference, tmp_path):
    """batch in this process, on local workers and on a Dask cluster: npz outputs with the reference's layers."""
    opts = BatchOptions(SliceParams(thickness=0.25), Placement(fit=30.0))
    outs = {}
    for workers in (0, 2):
        out = tmp_path / f"local{workers}"
        report = run_batch([model.parent], out, opts, workers=workers)
        assert report["summary"]["done"] == 1, report["models"]
        outs[workers] = (out / "torus.npz").read_bytes()
        _same_layers(SliceResult.load(out / "torus.npz"), reference)
    assert outs[0] == outs[2]
    distributed = pytest.importorskip("distributed", reason="dask.distributed not installed (gpuslice[batch])")
    cluster = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0",
                                       host="127.0.0.1")
    try:
        with distributed.Client(cluster) as client:
            out = tmp_path / "dask"
            report = run_batch([model.parent], out, opts, client=client)
            assert report["summary"]["done"] == 1 and report["summary"]["mode"] == "dask", report["models"]
            assert (out / "torus.npz").read_bytes() == outs[0]
    finally:
        cluster.close()


def test_bench_agrees(model, reference, capsys):
    assert main(["bench", str(model), *ARGS, "--repeat", "1", "--no-quality", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert len(rows) == 1
    assert rows[0]["layers"] == reference.n_layers
    assert rows[0]["points"] == int(reference.points.shape[0])


def test_view_job_with_masks(model, reference, tmp_path):
    """The view stage with resin masks, from the library: the page's layers are the reference's."""
    spec = RasterSpec(resolution=(200, 160), pixel=0.25)
    done = run_job(Job(source=str(model), placement=Placement(fit=30.0), params=SliceParams(thickness=0.25),
                       mesh_check=False, view=ViewOutput(str(tmp_path / "m.html"), masks=spec, mask_every=5)))
    data = read_view_data(tmp_path / "m.html")
    np.testing.assert_array_equal(data["arrays"]["area"], reference.area)
    assert sorted(data["masks"]["png"]) == list(range(0, reference.n_layers, 5))
    assert done.stats["view_bytes"] == (tmp_path / "m.html").stat().st_size


def test_release_scratch_drops_the_drivers_buffers_and_slicing_still_agrees(model, reference, device):
    """The pipeline gives the slicer's scratch memory back before resin layers (``device.release_scratch``): the
    drivers' buffers are gone afterwards, and the next slice (buffers made again) gives the same layers."""
    from gpuslice import load_mesh, slice_mesh
    from gpuslice.device import KernelDriver, release_scratch

    mesh = load_mesh(model, fit=30)
    first = slice_mesh(mesh, thickness=0.25, device=device)
    held = [d for (_, i), d in KernelDriver._instances.items() if i == id(device) and d._buffers]
    assert held  # slicing on the device left reusable buffers behind
    release_scratch(device)
    assert not any(d._buffers for (_, i), d in KernelDriver._instances.items() if i == id(device))
    again = slice_mesh(mesh, thickness=0.25, device=device)
    assert np.array_equal(first.points, again.points) and np.array_equal(first.loop_offsets, again.loop_offsets)
    assert np.allclose(again.area, reference.area)


def test_a_cpu_devices_large_buffers_live_in_host_memory_and_slicing_agrees(model, device, monkeypatch):
    """On a CPU device a driver's buffers from ``HOST_BACKED_BYTES`` up use numpy's memory (``USE_HOST_PTR``: huge
    pages); with every buffer made that way (the threshold lowered) the slice is the same as with none."""
    import pyopencl as cl

    from gpuslice import device as devmod
    from gpuslice import load_mesh, slice_mesh
    from gpuslice.device import KernelDriver, release_scratch

    if not device.is_cpu:
        pytest.skip("buffers are host-backed on CPU devices only")

    class Probe(KernelDriver):
        pass

    drv = Probe(device)
    big, small = drv._buffer("big", devmod.HOST_BACKED_BYTES), drv._buffer("small", 1024)
    assert big.flags & cl.mem_flags.USE_HOST_PTR and big.hostbuf is not None
    assert not small.flags & cl.mem_flags.USE_HOST_PTR
    data = np.arange(devmod.HOST_BACKED_BYTES // 4, dtype=np.int32)
    got = np.empty_like(data)
    drv._put("big", data)
    drv._read((got, drv.buffer("big")))
    assert np.array_equal(got, data)

    mesh = load_mesh(model, fit=30)
    results = []
    for threshold in (1 << 62, 64):
        monkeypatch.setattr(devmod, "HOST_BACKED_BYTES", threshold)
        release_scratch(device)
        results.append(slice_mesh(mesh, thickness=0.25, device=device))
        flags = [b.flags for (_, i), d in KernelDriver._instances.items() if i == id(device)
                 for b, _ in d._buffers.values()]
        assert any(f & cl.mem_flags.USE_HOST_PTR for f in flags) == (threshold == 64)
    release_scratch(device)
    a, b = results
    for name in ("points", "loop_offsets", "layer_offsets", "area"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


RELEASE_WHILE_RUNNING = """
import numpy as np
from gpuslice.device import get_device, release_scratch
from gpuslice.slicing.walk import chain_kernels
dev = get_device()
ck = chain_kernels(dev)
pts = np.random.default_rng(0).random((4_000_000, 2)).astype(np.float32)
offs = np.arange(0, 4_000_001, 200, dtype=np.int64)
ref = ck.simple_loops(pts, offs, wait=True)
for _ in range(3):
    pending = ck.simple_loops(pts, offs, wait=False)  # left running, as nesting leaves the loops' screen
    release_scratch(dev)
    assert np.array_equal(pending(), ref)
print("ok")
"""


def test_release_scratch_waits_for_a_kernel_left_running(device):
    """``release_scratch`` while a kernel still runs (the loops' screen, left running while the host nests): the
    queue is finished before the buffers go, whose memory on a CPU device is numpy's and freed with them (the
    process crashed with a segmentation fault before). In a child process, so that a crash fails only this test."""
    import subprocess
    import sys

    from gpuslice.slicing.walk import chain_kernels

    if chain_kernels(device)._simple is None:
        pytest.skip("the device has no doubles: no loops' screen")
    p = subprocess.run([sys.executable, "-c", RELEASE_WHILE_RUNNING], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and p.stdout.strip() == "ok", (p.returncode, p.stderr[-2000:])


def test_drained_waits_for_the_queue_only_on_an_exception():
    """``buffers.drained``: the queue is finished before an exception leaves the block (the host arrays its
    commands use in place are freed as it unwinds), and not on the normal path (the block waits itself)."""
    from gpuslice.buffers import drained

    class Queue:
        finished = 0

        def finish(self) -> None:
            self.finished += 1

    q = Queue()
    with drained(q):
        pass
    assert q.finished == 0
    with pytest.raises(KeyError, match="boom"), drained(q):
        raise KeyError("boom")
    assert q.finished == 1


def test_a_kernel_driver_is_made_once_when_threads_ask_at_once(device):
    """The archive writers' encoder threads ask for their encoding driver at the same moment: one driver comes back
    to all of them (made once: PyOpenCL warns on stderr when a kernel is looked up twice)."""
    import threading
    import warnings

    from gpuslice.device import KernelDriver

    class Probe(KernelDriver):
        made = 0

        def __init__(self, dev) -> None:
            super().__init__(dev)
            type(self).made += 1
            gate.wait(0.2)  # hold the first maker so that the other threads come while it works

    gate = threading.Event()
    got: list = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        threads = [threading.Thread(target=lambda: got.append(Probe.of(device))) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    KernelDriver._instances.pop((Probe, id(device)), None)
    assert len(got) == 8 and all(d is got[0] for d in got) and Probe.made == 1
