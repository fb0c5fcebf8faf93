"""Start-up: what ``gpuslice`` and its command line import before any work (issue 14, part 3).

Every module imported at start-up costs every command its import time, so heavy libraries are imported where a
function needs them: PyOpenCL when a device is chosen, shapely when layers are nested, matplotlib for plots,
trimesh and scipy for the formats and checks that use them, and the benchmark helpers (``gpuslice.bench``) for
cusp heights in reports and ``gpuslice bench``.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("pyopencl", "shapely", "matplotlib", "scipy", "trimesh", "moderngl", "PIL", "rich", "dask")
LAZY_PACKAGES = ("gpuslice.bench", "gpuslice.batch", "gpuslice.raster", "gpuslice.view", "gpuslice.pipeline")


def _imported_by(statement: str) -> list[str]:
    """Modules a fresh interpreter has imported after ``statement``."""
    code = f"import json, sys\n{statement}\nprint(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout.splitlines()[-1])


@pytest.mark.parametrize("statement", ["import gpuslice", "import gpuslice.cli.main"])
def test_start_up_imports_nothing_heavy(statement):
    mods = _imported_by(statement)
    heavy = sorted(m for m in mods if m.split(".")[0] in HEAVY)
    lazy = sorted(m for m in mods if m.startswith(LAZY_PACKAGES))
    assert not heavy, f"{statement} imports {heavy}"
    assert not lazy, f"{statement} imports {lazy}"


def test_lazy_names_still_importable():
    mods = _imported_by("from gpuslice import cusp_summary, schedule_quality, volume_deviation, BatchOptions")
    assert "gpuslice.bench.quality" in mods and "gpuslice.batch.options" in mods


@pytest.mark.parametrize("statement", ["import gpuslice", "import gpuslice.cli.main"])
def test_package_and_command_line_import_no_numpy(statement):
    """The command line sets the process up (OPENBLAS_NUM_THREADS) before numpy loads, so neither imports it."""
    assert "numpy" not in _imported_by(statement)


def test_console_entry_keeps_openblas_to_one_thread_unless_set(tmp_path):
    code = ("import sys; sys.argv = ['gpuslice', '--version']\nfrom gpuslice.cli import entry\ntry:\n    entry()\n"
            "except SystemExit:\n    pass\n")
    probe = ("import atexit, os; atexit.register(lambda: print('OPENBLAS', os.environ.get('OPENBLAS_NUM_THREADS')))\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "OPENBLAS_NUM_THREADS"}
    env["GPUSLICE_SLOW_EXIT"] = "1"  # keep atexit: the probe prints at exit
    out = subprocess.run([sys.executable, "-c", probe + code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0 and "OPENBLAS 1" in out.stdout, out.stdout + out.stderr
    env["OPENBLAS_NUM_THREADS"] = "2"
    out = subprocess.run([sys.executable, "-c", probe + code], capture_output=True, text=True, env=env, timeout=120)
    assert "OPENBLAS 2" in out.stdout


def test_lazy_public_names_resolve():
    code = ("import gpuslice\nmissing = [n for n in gpuslice.__all__ if not hasattr(gpuslice, n)]\n"
            "print(missing, set(gpuslice.__all__) <= set(dir(gpuslice)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[] True"


def test_modules_reachable_as_attributes():
    """``gpuslice.device.get_device()`` and ``gpuslice.checks.run_checks`` (the README's spellings) work right after
    ``import gpuslice``."""
    code = ("import gpuslice\nprint(callable(gpuslice.device.get_device), callable(gpuslice.checks.run_checks), "
            "gpuslice.slicing.slicer.__name__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["True", "True", "gpuslice.slicing.slicer"]
