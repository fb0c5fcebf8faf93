"""The GPU session's measuring scripts (docs/GPU.md) run here too, on whatever device there is, so that they do not
rot between the sessions that have a GPU: ``scripts/gpu_compare.py`` (one device against itself: every check must
say "same", and a file the loader refuses is counted as refused) and ``scripts/profile_stages.py``."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from gpuslice.cli import main

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def test_gpu_compare_one_device_against_itself(device, tmp_path):
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    assert main(["shape", "torus", "-o", str(meshes / "torus.stl")]) == 0
    (meshes / "empty.stl").write_bytes(bytes(80) + (0).to_bytes(4, "little"))
    (meshes / "catalog.csv").write_text("name,file\ntorus,torus.stl\nempty,empty.stl\n")
    spec = f"{device.platform_index}:{device.device_index}"
    out = tmp_path / "compare.json"
    proc = subprocess.run([sys.executable, str(SCRIPTS / "gpu_compare.py"), "--a", spec, "--b", spec, "--meshes",
                           str(meshes), "--fit", "40", "--thickness", "0.5,0.25", "--json", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    got = json.loads(out.read_text())
    assert got["summary"]["meshes"] == 2 and got["summary"]["refused"] == 1 and got["summary"]["differ"] == 0
    torus = next(r for r in got["rows"] if r["mesh"] == "torus")
    assert torus["weld"] and torus["runs_g1"] and torus["runs_g0"] and torus["n_runs_g1"] > 100
    assert torus["slice_0.5"]["differ"] == [] and torus["points_0.25"] > torus["points_0.5"] > 0


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_profile_stages_counts_the_calls_of_a_command(tmp_path):
    stl = tmp_path / "torus.stl"
    assert main(["shape", "torus", "-o", str(stl)]) == 0
    proc = subprocess.run([sys.executable, str(SCRIPTS / "profile_stages.py"), "--modules", "gpuslice.slicing",
                           "--top", "50", "--", "slice", str(stl), "-t", "0.5", "-o", str(tmp_path / "t.npz")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "warm-up: exit 0" in proc.stdout and "timed: exit 0" in proc.stdout
    lines = [ln.split() for ln in proc.stdout.splitlines() if ln.strip().endswith("slicer.slice_mesh")]
    assert lines and lines[0][0] == "1"  # one slice_mesh call in the timed run, counted once


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_profile_stages_cold_times_the_first_run(tmp_path):
    stl = tmp_path / "torus.stl"
    assert main(["shape", "torus", "-o", str(stl)]) == 0
    proc = subprocess.run([sys.executable, str(SCRIPTS / "profile_stages.py"), "--cold", "--modules",
                           "gpuslice.slicing", "--", "slice", str(stl), "-t", "0.5", "-o", str(tmp_path / "t.npz")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "warm-up" not in proc.stdout and "timed: exit 0" in proc.stdout
    lines = [ln.split() for ln in proc.stdout.splitlines() if ln.strip().endswith("slicer.slice_mesh")]
    assert lines and lines[0][0] == "1"
