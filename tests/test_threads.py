"""One device used by several threads or processes of one program (a Dask worker runs a task per thread; a library
user may fork): jobs take turns on the device's shared kernel drivers (``Device.exclusive``), and a forked child
that inherits the parent's OpenCL context gets a one-line error instead of waiting forever."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.errors import DeviceError
from gpuslice.mesh import shapes

FIELDS = ("points", "loop_offsets", "layer_offsets", "loop_is_hole", "loop_parent", "area")


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in FIELDS)


def test_threads_slicing_at_once_get_what_each_gets_alone(device):
    """Two threads slicing two meshes at once, as two batch tasks on a Dask worker's threads: each gets the result
    it gets alone (before, they overwrote each other's segment and chain buffers: wrong layers, exceptions, crashes)."""
    jobs = [(mesh_from_triangles(shapes.torus(15.0, 5.0, 40, 20)), 0.05),
            (mesh_from_triangles(shapes.hollow_box(20.0, 10.0, 4.0)), 0.04)]
    alone = [slice_mesh(m, thickness=t, device=device) for m, t in jobs]
    for _ in range(4):
        out: list = [None, None]

        def work(i: int, out: list = out) -> None:
            try:
                out[i] = slice_mesh(jobs[i][0], thickness=jobs[i][1], device=device)
            except Exception as exc:  # noqa: BLE001 - reported by the assertion below
                out[i] = exc

        threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for i in range(2):
            assert not isinstance(out[i], Exception), out[i]
            assert _same(out[i], alone[i])


def test_a_slice_waits_while_another_thread_holds_the_device(device):
    mesh = mesh_from_triangles(shapes.torus(15.0, 5.0, 40, 20))
    done = threading.Event()

    def work() -> None:
        slice_mesh(mesh, thickness=0.5, device=device)
        done.set()

    with device.exclusive():
        t = threading.Thread(target=work)
        t.start()
        assert not done.wait(0.5)  # the other thread's slice waits for the device
    t.join(60)
    assert done.is_set()
    with device.exclusive(), device.exclusive():  # re-entrant: the roi schedule slices inside a slice
        assert slice_mesh(mesh, thickness=0.5, device=device).n_layers > 0


_PARENT_DEVICE: list = []  # (the parent's device, inherited by a forked child)


def _child(conn, what: str) -> None:
    try:
        if what == "components":  # (the mesh check's union-find, on the parent's device object: a driver with a lock
            # and a queue of its own, not the device's turn, which checks the process)
            from gpuslice.mesh.graph import components

            components(10, np.arange(5), np.arange(1, 6), _PARENT_DEVICE[0])
        else:
            slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 40, 20)), thickness=0.5)
        conn.send("done")
    except DeviceError as exc:
        conn.send(f"DeviceError: {exc}")
    except BaseException as exc:  # noqa: BLE001 - anything else is a failure, shown by the parent's assertion
        conn.send(f"{type(exc).__name__}: {exc}")
    conn.close()
    os._exit(0)


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="the platform has no fork")
@pytest.mark.filterwarnings("ignore:This process .* is multi-threaded:DeprecationWarning")
@pytest.mark.parametrize("what", ["slice", "components"])
def test_a_forked_child_gets_an_error_not_a_hang(device, what):
    """The parent's context does not work in a forked child (PoCL's threads were not forked): before, the child's
    first kernel waited forever; now the child is told so at once."""
    slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 40, 20)), thickness=0.5)  # the default device in use
    from gpuslice.mesh.graph import components

    components(10, np.arange(5), np.arange(1, 6), device)  # (its lane's queue made in the parent too)
    _PARENT_DEVICE[:] = [device]
    ctx = multiprocessing.get_context("fork")
    parent, child = ctx.Pipe(duplex=False)
    p = ctx.Process(target=_child, args=(child, what))
    t0 = time.monotonic()
    p.start()
    child.close()
    got = parent.recv() if parent.poll(60) else "no answer within 60 s"
    p.join(10)
    if p.is_alive():
        p.kill()
        p.join()
    assert got.startswith("DeviceError:") and "fork" in got, got
    assert time.monotonic() - t0 < 30


def test_the_fork_error_asks_the_driver_nothing(device):
    """A forked child's error names the device without asking the driver: NVIDIA's driver answers a forked child's
    every call with INVALID_DEVICE (seen on an H200), which surfaced as a ``LogicError`` instead of this error."""
    import copy

    class Gone:  # what a forked child's driver objects are: any attribute read is a refused driver call
        def __getattr__(self, name):
            raise AssertionError(f"asked the driver for {name}")

    child = copy.copy(device)  # (a shallow copy: the real device is left as it is)
    child.device, child._pid = Gone(), os.getpid() + 1
    with pytest.raises(DeviceError, match="fork") as err:
        child.check_process()
    assert device.name in str(err.value)
