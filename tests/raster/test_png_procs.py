"""PNG layers encoded in worker processes (gpuslice.raster.png_procs): the same files as the threads make, only where
enabled, and never a worker process where it is not allowed."""

from __future__ import annotations

import multiprocessing
import zipfile

import pytest

from gpuslice.cli import main
from gpuslice.mesh import shapes
from gpuslice.raster import png_procs

pytestmark = pytest.mark.skipif("forkserver" not in multiprocessing.get_all_start_methods(),
                                reason="no forkserver start method on this platform: the threads encode")


@pytest.fixture
def torus_stl(tmp_path):
    p = tmp_path / "torus.stl"
    shapes.write_stl(shapes.torus(15.0, 5.0, 48, 24), p)
    return p


def _raster(stl, out, *extra) -> None:
    assert main(["raster", str(stl), "-o", str(out), "-t", "0.5", "--resolution", "1200x800", "--pixel", "0.05",
                 "--gamma", "1", "--no-progress", "-q", *extra]) == 0


@pytest.mark.parametrize("suffix", [".sl1", ".nanodlp", "/"])
def test_processes_write_the_threads_bytes(tmp_path, torus_stl, device, monkeypatch, suffix):
    """With GPUSLICE_PNG_PROCESSES=1 the command line encodes PNG layers by numpy in worker processes (two
    workers); `--workers 1` on one thread: the same archive bytes (SL1, NanoDLP) or files (PNG stack) under
    SOURCE_DATE_EPOCH. The pool was made and let go. By default the PNGs are made on the device (kernels/png.cl,
    no pool): the same bytes again."""
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    monkeypatch.setenv("GPUSLICE_PNG_PROCESSES", "1")
    made = []
    real = png_procs.process_pool

    def spy(workers):
        pool = real(workers)
        made.append(pool)
        return pool

    monkeypatch.setattr(png_procs, "process_pool", spy)  # (the writers import it when they run)
    a, b = tmp_path / f"procs{suffix}", tmp_path / f"thread{suffix}"
    if suffix == "/":
        a, b = tmp_path / "procs", tmp_path / "thread"
    _raster(torus_stl, f"{a}/" if suffix == "/" else a, "--workers", "2")
    assert any(p is not None for p in made)
    assert png_procs._POOLS == {}  # shut down when the command ended
    made.clear()
    _raster(torus_stl, f"{b}/" if suffix == "/" else b, "--workers", "1")
    assert made and all(p is None for p in made)
    monkeypatch.delenv("GPUSLICE_PNG_PROCESSES")
    made.clear()
    c = tmp_path / ("device" if suffix == "/" else f"device{suffix}")
    _raster(torus_stl, f"{c}/" if suffix == "/" else c, "--workers", "2")
    assert not made  # no pool asked for
    if suffix == "/":
        names = sorted(p.name for p in a.iterdir())
        assert names and names == sorted(p.name for p in b.iterdir()) == sorted(p.name for p in c.iterdir())
        for name in names:
            assert (a / name).read_bytes() == (b / name).read_bytes() == (c / name).read_bytes(), name
    else:
        assert a.read_bytes() == b.read_bytes() == c.read_bytes()
        with zipfile.ZipFile(a) as z:
            assert z.testzip() is None and sum(n.endswith(".png") for n in z.namelist()) >= 20


def test_no_pool_unless_enabled_here_and_allowed(monkeypatch):
    """A library caller gets threads unless inside enabled(); a fork of an enabling process does not inherit it;
    one worker never needs processes; the block's end shuts the pool down and disables them again."""
    assert png_procs.process_pool(2) is None  # (the command line's enabled() of other tests has ended)
    monkeypatch.setattr(png_procs, "_ENABLED_IN", -1)  # enabled in another process (the parent of a fork)
    assert png_procs.process_pool(2) is None
    with png_procs.enabled():
        assert png_procs.process_pool(1) is None and png_procs.process_pool(None) is None
        pool = png_procs.process_pool(2)
        assert pool is not None and png_procs.process_pool(2) is pool  # made once, shared
        assert pool.submit(png_procs._ready).result() is None
    assert png_procs._POOLS == {} and png_procs.process_pool(2) is None


def test_main_module_must_be_safe_to_import(tmp_path):
    """A script without a main guard would run again in each worker: no processes for it; a guarded one, `python
    -m` and `python -c` are safe."""
    import subprocess
    import sys

    probe = "from gpuslice.raster.png_procs import main_is_import_safe\n"
    unguarded = tmp_path / "unguarded.py"
    unguarded.write_text(probe + "print(main_is_import_safe())\n")
    guarded = tmp_path / "guarded.py"
    guarded.write_text(probe + "if __name__ == '__main__':\n    print(main_is_import_safe())\n")
    busy = tmp_path / "busy.py"  # a guard, but work at the top level too
    busy.write_text(probe + "X = sum(range(3))\nif __name__ == '__main__':\n    print(main_is_import_safe())\n")
    run = lambda *a: subprocess.run([sys.executable, *a], capture_output=True, text=True, check=True).stdout  # noqa: E731
    assert run(str(unguarded)).strip() == "False"
    assert run(str(guarded)).strip() == "True"
    assert run(str(busy)).strip() == "False"
    assert run("-c", probe + "print(main_is_import_safe())").strip() == "True"


def test_overlapping_blocks_and_a_broken_pool(device):
    """Blocks may overlap (jobs on several threads): the pool lives until the last one ends. A worker that dies
    breaks its pool: the group is made in the calling thread instead (the same PNGs) and the pool is let go."""
    import os

    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.raster import RasterSpec
    from gpuslice.raster.deflate_runs import encode_png_from_runs
    from gpuslice.raster.layers import iter_run_layers

    res = slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 48, 24)), thickness=1.0, device=device)
    spec = RasterSpec(resolution=(900, 700), pixel=0.05)
    items = list(iter_run_layers(res, spec, device=device, clip=True))[:5]
    group = [it for it in items if it.runs is items[0].runs]
    want = [encode_png_from_runs(it.runs, it.j, *spec.png_size) for it in group]
    with png_procs.enabled():
        with png_procs.enabled():
            pool = png_procs.process_pool(2)
            assert [png for png, _ in png_procs.encode_group(pool, group, *spec.png_size)] == want
        assert png_procs.process_pool(2) is pool  # the outer block still holds it
        with pytest.raises(Exception):  # noqa: B017 - the pool is broken by the worker's exit
            pool.submit(os._exit, 3).result()
        assert [png for png, _ in png_procs.encode_group(pool, group, *spec.png_size)] == want
        assert png_procs.process_pool(2) is not pool  # a new one for the next group
    assert png_procs._POOLS == {} and png_procs.process_pool(2) is None


def test_the_command_line_leaves_no_multiprocessing_folder(tmp_path, torus_stl, device):
    """The encoder processes' forkserver keeps its socket in a ``pymp-*`` folder of ``$TMPDIR``; the command line
    ends with ``os._exit`` (no interpreter teardown), which skipped multiprocessing's own removal of it: every such
    command left the folder behind, with its dead socket."""
    import os
    import subprocess
    import sys

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(tmp), "GPUSLICE_PNG_PROCESSES": "1"}
    env.pop("GPUSLICE_SLOW_EXIT", None)
    proc = subprocess.run([sys.executable, "-m", "gpuslice.cli", "raster", str(torus_stl), "-o",
                           str(tmp_path / "x.sl1"), "-t", "0.5", "--resolution", "1200x800", "--pixel", "0.05",
                           "--workers", "2", "--no-progress", "-q"], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "x.sl1").exists()
    assert not list(tmp.iterdir())
