"""One malloc arena for the processes that slice and then write resin layers (``gpuslice.device.one_malloc_arena``):
the layers' threads then reuse what the slicer freed, and ``release_scratch`` leaves that memory in the process.
Process-wide settings are changed only in child processes here."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

import gpuslice.device as device_mod

GLIBC = (os.confstr("CS_GNU_LIBC_VERSION") or "").startswith("glibc") if hasattr(os, "confstr") else False
needs_glibc = pytest.mark.skipif(not GLIBC, reason="malloc arenas are glibc's")

# a thread mallocs blocks below the mmap threshold (so from an arena), then glibc's malloc_info lists the heaps
HEAPS = textwrap.dedent("""
    import ctypes, re, sys, tempfile, threading
    import gpuslice.device as d
    if sys.argv[1] == "one":
        assert d.one_malloc_arena() is True and d._ONE_ARENA
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.fopen.restype = ctypes.c_void_p
    kept = []
    def work():
        kept.extend(libc.malloc(4096) for _ in range(64))
    t = threading.Thread(target=work)
    t.start()
    t.join()
    path = tempfile.mktemp()
    f = libc.fopen(path.encode(), b"w")
    libc.malloc_info(0, ctypes.c_void_p(f))
    libc.fclose(ctypes.c_void_p(f))
    print(len(re.findall(r'<heap nr="[0-9]+"', open(path).read())))
""")


def _heaps(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", HEAPS, mode], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return int(out.stdout.split()[-1])


@needs_glibc
def test_one_arena_keeps_a_threads_allocations_in_the_main_heap():
    assert _heaps("default") >= 2  # (a thread's own arena: the test can tell the two apart)
    assert _heaps("one") == 1


def test_release_scratch_trims_the_heap_unless_one_arena(monkeypatch):
    import ctypes

    calls = []

    class FakeLibc:
        def malloc_trim(self, pad):
            calls.append(pad)

    monkeypatch.setattr(ctypes, "CDLL", lambda *a, **k: FakeLibc())
    monkeypatch.setattr(device_mod.KernelDriver, "_instances", {})
    monkeypatch.setattr(device_mod, "_ONE_ARENA", False)
    device_mod.release_scratch()
    assert calls == [0]
    monkeypatch.setattr(device_mod, "_ONE_ARENA", True)
    device_mod.release_scratch()
    assert calls == [0]  # (left in the process: the next stage's threads reuse it)


@pytest.mark.parametrize("args, one", [(["raster", "m.stl", "-o", "x.goo"], True), (["--debug", "raster"], True),
                                       (["slice", "m.stl"], False), (["check", "raster.stl"], False), ([], False)])
def test_the_command_line_asks_for_one_arena_for_raster_only(monkeypatch, args, one):
    import gpuslice.cli.main  # noqa: F401  (the package exports a function of the same name)

    cli_main = sys.modules["gpuslice.cli.main"]
    asked = []
    monkeypatch.setattr(device_mod, "one_malloc_arena", lambda: asked.append(True) or True)
    monkeypatch.setattr(cli_main, "main", lambda: 0)
    monkeypatch.setattr(cli_main, "exit_now", lambda code: None)
    monkeypatch.setattr(sys, "argv", ["gpuslice", *args])
    monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # (entry sets its own)
    cli_main.entry()
    assert bool(asked) is one


@needs_glibc
@pytest.mark.parametrize("one", [True, False])
def test_a_batch_worker_for_resin_outputs_uses_one_arena(one):
    code = ("import gpuslice.device as d; from gpuslice.batch.task import init_worker; "
            f"init_worker(None, None, 'numpy', {one}); print(d._ONE_ARENA)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == str(one)
