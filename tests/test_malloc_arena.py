"""One malloc arena for the processes that slice and then write resin layers (``gpuslice.allocator``): the layers'
threads then reuse what the slicer freed, and ``release_scratch`` leaves that memory in the process. Process-wide
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
    """This environment without the user's own arena limits (which would make the default case one arena too)."""
    return {k: v for k, v in os.environ.items() if k not in ("MALLOC_ARENA_MAX", "GLIBC_TUNABLES")}


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


@pytest.mark.parametrize("args, one, pre", [(["raster", "m.stl", "-o", "x.goo"], True, False),
                                            (["--debug", "raster"], True, False), (["slice", "m.stl"], False, True),
                                            (["check", "raster.stl"], False, True), (["info", "m.stl"], False, False),
                                            ([], False, False)])
def test_the_command_line_asks_for_one_arena_for_raster_and_a_prefault_for_slice_and_check(monkeypatch, args, one,
                                                                                           pre):
    import gpuslice.cli.main  # noqa: F401  (the package exports a function of the same name)

    cli_main = sys.modules["gpuslice.cli.main"]
    asked, prefaulted = [], []
    monkeypatch.setattr(allocator, "one_malloc_arena", lambda: asked.append(True) or True)
    monkeypatch.setattr(allocator, "prefault", lambda n: prefaulted.append(n) or True)
    monkeypatch.setattr(cli_main, "main", lambda: 0)
    monkeypatch.setattr(cli_main, "exit_now", lambda code: None)
    monkeypatch.setattr(sys, "argv", ["gpuslice", *args])
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # (entry sets its own)
    cli_main.entry()
    assert bool(asked) is one
    assert bool(prefaulted) is pre


@pytest.mark.parametrize("command", ["raster", "slice", "check"])
def test_plain_malloc_leaves_the_allocator_alone(monkeypatch, command):
    import gpuslice.cli.main  # noqa: F401

    cli_main = sys.modules["gpuslice.cli.main"]
    called = []
    monkeypatch.setattr(allocator, "one_malloc_arena", lambda: called.append("arena") or True)
    monkeypatch.setattr(allocator, "prefault", lambda n: called.append("prefault") or True)
    monkeypatch.setattr(cli_main, "main", lambda: 0)
    monkeypatch.setattr(cli_main, "exit_now", lambda code: None)
    monkeypatch.setattr(sys, "argv", ["gpuslice", command, "m.stl"])
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)
    monkeypatch.setenv("GPUSLICE_PLAIN_MALLOC", "1")
    cli_main.entry()
    assert called == []


def test_prefault_gives_up_quietly(monkeypatch):
    """The user's own malloc settings, or no memory (malloc returns NULL): False, nothing raised."""
    import ctypes

    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "1000")
    assert allocator.user_tuned_malloc() and allocator.prefault(64 << 20) is False
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_")
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=2")
    assert allocator.prefault(64 << 20) is False
    monkeypatch.delenv("GLIBC_TUNABLES")
    monkeypatch.setattr(allocator, "on_glibc", lambda: True)
    real = ctypes.CDLL

    class NoMemory:
        def __init__(self, *args, **kwargs):
            self._libc = real(None)

        def __getattr__(self, name):
            fn = getattr(self._libc, name)
            if name == "malloc":
                return ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_size_t)(lambda n: None)
            if name == "mallopt":
                return lambda *a: 1  # (the process's real thresholds stay as they are)
            return fn

    monkeypatch.setattr(ctypes, "CDLL", NoMemory)
    assert allocator.prefault(64 << 20) is False


NO_THREAD = textwrap.dedent("""
    import _thread
    import gpuslice.allocator as a
    def refuse(*args):
        raise RuntimeError("can't start new thread")
    _thread.start_new_thread = refuse
    print(a.prefault(64 << 20))
""")


@needs_glibc
def test_prefault_without_a_thread_is_false():
    out = subprocess.run([sys.executable, "-c", NO_THREAD], capture_output=True, text=True, timeout=120,
                         env=_child_env())
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == "False"


def test_the_prefault_is_sized_by_the_model_file(tmp_path):
    import gpuslice.cli.main  # noqa: F401

    cli_main = sys.modules["gpuslice.cli.main"]
    model, old_out = tmp_path / "m.stl", tmp_path / "old.npz"
    model.write_bytes(b"\0" * 3_000_000)
    old_out.write_bytes(b"\0" * 9_000_000)  # (an output being overwritten: not the model)
    args = ["slice", "-t", "0.05", str(model), "-o", str(old_out), "--report", str(old_out), str(tmp_path)]
    assert cli_main._prefault_bytes("slice", args) == cli_main.PREFAULT["slice"] * 3_000_000
    assert cli_main._prefault_bytes("check", ["check", str(tmp_path / "missing.stl")]) == 0
    assert cli_main._prefault_bytes("info", ["info", str(model)]) == 0
    ascii_stl = tmp_path / "a.stl"
    ascii_stl.write_bytes(b"solid part\n" + b" " * 4_999_989)  # (an ASCII STL holds ~5x fewer facets a byte)
    assert cli_main._prefault_bytes("slice", ["slice", str(ascii_stl)]) == cli_main.PREFAULT["slice"] * 1_000_000
    binary = tmp_path / "b.stl"
    binary.write_bytes(b"solid but binary".ljust(80) + (100_000).to_bytes(4, "little") + b"\0" * 5_000_000)
    assert cli_main._prefault_bytes("slice", ["slice", str(binary)]) == cli_main.PREFAULT["slice"] * 5_000_084
    big = tmp_path / "big.stl"
    with open(big, "wb") as f:
        f.truncate(cli_main.PREFAULT_MAX)  # (sparse)
    assert cli_main._prefault_bytes("slice", ["slice", str(big)]) == cli_main.PREFAULT_MAX


# after prefault (or not), numpy arrays of 8-24 MB: the page faults their first touch costs
REUSE = textwrap.dedent("""
    import resource, sys, time
    import os
    import numpy as np
    import gpuslice.allocator as a
    def rss():
        return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    n, r0 = int(sys.argv[1]) << 20, rss()
    started = a.prefault(n) if n else False
    t = time.monotonic()
    while started and rss() < r0 + 0.9 * n and time.monotonic() - t < 10:  # (the thread populating the heap's top)
        time.sleep(0.01)
    # (this thread's faults only: the populating thread's are charged to it)
    keep, f0 = [], resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
    for mb in (8, 16, 24):
        keep.append(np.ones(mb << 18, np.float32))
    print(started, resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - f0)
""")


@needs_glibc
def test_prefault_makes_the_first_touch_of_new_arrays_fault_free():
    def run(mb):
        out = subprocess.run([sys.executable, "-c", REUSE, str(mb)], capture_output=True, text=True, timeout=120,
                             env=_child_env())
        assert out.returncode == 0, out.stderr
        started, faults = out.stdout.split()
        return started == "True", int(faults)

    started, faults = run(96)
    if not started:
        pytest.skip("no MADV_POPULATE_WRITE on this kernel (Linux < 5.14): prefault() does nothing there")
    started0, faults0 = run(0)
    assert not started0
    assert faults0 >= 20  # (48 MB of arrays: ~12k pages, or ~24 huge pages)
    assert faults <= 2  # (a page or two of the arrays' headers at most)


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
