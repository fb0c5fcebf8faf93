"""One malloc arena for the processes that slice and then write resin layers (``gpuslice.allocator``): the layers'
threads then reuse what the slicer freed, and ``release_scratch`` leaves that memory in the process; for ``slice``,
also every block from the heap and kept there (``keep_freed_memory``). Process-wide
settings are changed only in child processes here."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

import gpuslice.allocator as allocator
import gpuslice.device as device_mod

needs_glibc = pytest.mark.skipif(not allocator.on_glibc(), reason="malloc arenas are glibc's")

# a thread mallocs blocks below the mmap threshold (so from an arena), then glibc's malloc_info lists the heaps
HEAPS = textwrap.dedent("""
    import ctypes, re, sys, threading
    import gpuslice.allocator as a
    if sys.argv[1] == "one":
        assert a.one_malloc_arena() is True and a.one_arena()
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.fopen.restype = ctypes.c_void_p
    kept = []
    def work():
        kept.extend(libc.malloc(4096) for _ in range(64))
    t = threading.Thread(target=work)
    t.start()
    t.join()
    f = libc.fopen(sys.argv[2].encode(), b"w")
    libc.malloc_info(0, ctypes.c_void_p(f))
    libc.fclose(ctypes.c_void_p(f))
    print(len(re.findall(r'<heap nr="[0-9]+"', open(sys.argv[2]).read())))
""")


def _child_env() -> dict[str, str]:
    """This environment without malloc settings: the user's own (an arena limit would make the default case one
    arena too), or those another test left in this process (Dask's LocalCluster sets ``MALLOC_TRIM_THRESHOLD_`` in
    its parent's environment, which the command line then keeps as the user's)."""
    drop = {"GLIBC_TUNABLES", "GPUSLICE_PLAIN_MALLOC", *allocator._MALLOC_VARIABLES}
    return {k: v for k, v in os.environ.items() if k not in drop}


def _heaps(mode: str, tmp_path) -> int:
    out = subprocess.run([sys.executable, "-c", HEAPS, mode, str(tmp_path / f"{mode}.xml")], capture_output=True,
                         text=True, timeout=120, env=_child_env())
    assert out.returncode == 0, out.stderr
    return int(out.stdout.split()[-1])


@needs_glibc
def test_one_arena_keeps_a_threads_allocations_in_the_main_heap(tmp_path):
    assert _heaps("default", tmp_path) >= 2  # (a thread's own arena: the test can tell the two apart)
    assert _heaps("one", tmp_path) == 1


def test_off_glibc_nothing_is_done_and_nothing_raises(monkeypatch):
    def refused(name):
        raise ValueError("unrecognized configuration name")  # (macOS; musl raises OSError)

    monkeypatch.setattr(os, "confstr", refused, raising=False)
    assert allocator.on_glibc() is False
    assert allocator.one_malloc_arena() is False
    allocator.trim_heap()
    monkeypatch.delattr(os, "confstr")  # (Windows)
    assert allocator.on_glibc() is False


def test_release_scratch_trims_the_heap_unless_one_arena(monkeypatch):
    import ctypes

    calls = []

    class FakeLibc:
        def malloc_trim(self, pad):
            calls.append(pad)

    monkeypatch.setattr(allocator, "on_glibc", lambda: True)
    monkeypatch.setattr(ctypes, "CDLL", lambda *a, **k: FakeLibc())
    monkeypatch.setattr(device_mod.KernelDriver, "_instances", {})
    monkeypatch.setattr(allocator, "_ONE_ARENA", False)
    device_mod.release_scratch()
    assert calls == [0]
    monkeypatch.setattr(allocator, "_ONE_ARENA", True)
    device_mod.release_scratch()
    assert calls == [0]  # (left in the process: the next stage's threads reuse it)


@pytest.mark.parametrize("args, asks", [(["raster", "m.stl", "-o", "x.goo"], "resin"), (["--debug", "raster"], "resin"),
                                        (["slice", "m.stl"], "slice"), (["view", "m.stl"], "slice"),
                                        (["check", "raster.stl"], None), ([], None)])
def test_the_command_line_asks_for_its_malloc_settings(monkeypatch, args, asks):
    """One arena for raster; for slice and view also the freed memory kept (``keep_freed_memory``); else nothing."""
    import gpuslice.cli.main  # noqa: F401  (the package exports a function of the same name)

    cli_main = sys.modules["gpuslice.cli.main"]
    asked = []
    monkeypatch.setattr(allocator, "one_malloc_arena", lambda: asked.append("resin") or True)
    monkeypatch.setattr(allocator, "keep_freed_memory", lambda: asked.append("slice") or True)
    monkeypatch.setattr(cli_main, "main", lambda: 0)
    monkeypatch.setattr(cli_main, "exit_now", lambda code: None)
    monkeypatch.setattr(sys, "argv", ["gpuslice", *args])
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # (entry sets its own)
    for name in ("GPUSLICE_PLAIN_MALLOC", "GLIBC_TUNABLES", *allocator._MALLOC_VARIABLES):
        monkeypatch.delenv(name, raising=False)
    cli_main.entry()
    assert asked == ([asks] if asks else [])


# a 100 MB array, made and freed twice: where its memory came from ([heap] or a mapping of its own) and what stays
BIG = textwrap.dedent("""
    import sys
    import numpy as np
    import gpuslice.allocator as a
    if sys.argv[1] == "keep":
        assert a.keep_freed_memory() is True and a.one_arena()
    def heap():  # (numpy's madvise of its big arrays splits the heap's mapping: every piece counts)
        size = 0
        for line in open("/proc/self/maps"):
            if line.rstrip().endswith("[heap]"):
                lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
                size += hi - lo
        return size
    before = heap()
    for _ in range(2):
        x = np.ones(100 << 20, np.uint8)
        del x
    print(heap() - before)
""")


@needs_glibc
def test_keep_freed_memory_serves_big_arrays_from_the_heap_and_keeps_it(tmp_path):
    grown = {}
    for mode in ("default", "keep"):
        out = subprocess.run([sys.executable, "-c", BIG, mode], capture_output=True, text=True, timeout=120,
                             env=_child_env())
        assert out.returncode == 0, out.stderr
        grown[mode] = int(out.stdout.split()[-1])
    assert grown["default"] < 50 << 20  # (mapped on its own and handed back: the heap never held it)
    assert grown["keep"] >= 90 << 20  # from the heap (less what it had free already), still there after it was freed


@pytest.mark.parametrize("env", [("GPUSLICE_PLAIN_MALLOC", "1"), ("MALLOC_ARENA_MAX", "4"),
                                 ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=0")])
def test_the_users_own_malloc_settings_are_kept(monkeypatch, env):
    import gpuslice.cli.main  # noqa: F401

    cli_main = sys.modules["gpuslice.cli.main"]
    asked = []
    monkeypatch.setattr(allocator, "one_malloc_arena", lambda: asked.append(True) or True)
    monkeypatch.setattr(cli_main, "main", lambda: 0)
    monkeypatch.setattr(cli_main, "exit_now", lambda code: None)
    monkeypatch.setattr(sys, "argv", ["gpuslice", "raster", "m.stl", "-o", "x.goo"])
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
    monkeypatch.setenv(*env)
    cli_main.entry()
    assert asked == []


@needs_glibc
@pytest.mark.parametrize("one", [True, False])
def test_a_batch_worker_for_resin_outputs_uses_one_arena(one):
    code = ("import gpuslice.allocator as a; from gpuslice.batch.task import init_worker; "
            f"init_worker(None, None, 'numpy', {one}); print(a.one_arena())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=_child_env())
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == str(one)


@pytest.mark.parametrize("raster", [None, "goo"])
def test_the_batch_runner_asks_its_workers_for_one_arena_with_resin_outputs(monkeypatch, tmp_path, raster):
    from gpuslice.batch import runner as runner_mod
    from gpuslice.batch.options import BatchOptions

    seen = []

    class Stop(Exception):
        pass

    def executor(*args, initializer=None, initargs=(), **kw):
        seen.append((initializer, initargs))
        raise Stop

    monkeypatch.setattr(runner_mod, "ProcessPoolExecutor", executor)
    opts = BatchOptions(raster=raster, raster_options=(("printer", "elegoo-saturn-3-ultra"),) if raster else ())
    run = runner_mod.BatchRunner([], opts, tmp_path)
    with pytest.raises(Stop):
        run._run_local([], 1, 1)
    (init, args), = seen
    assert init is runner_mod.init_worker
    assert args[3] is (raster is not None)
