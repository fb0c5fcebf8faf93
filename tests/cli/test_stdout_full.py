"""What the commands print on standard output (``info``'s table, ``slice``'s summary) when it is a full disk: one line
that says it was standard output that could not take it (the OSError names no file: the line said only "No space
left on device"), exit 2. And ``-`` as an output: refused (a file named ``-`` was written)."""

from __future__ import annotations

import errno
import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gpuslice.cli import main

BOX = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [0, 0, 10], [10, 0, 10], [10, 10, 10], [0, 10, 10]],
               float)
FACES = [(0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4), (1, 2, 6), (1, 6, 5), (2, 3, 7),
         (2, 7, 6), (3, 0, 4), (3, 4, 7)]


@pytest.fixture
def box(tmp_path: Path) -> Path:
    import trimesh

    path = tmp_path / "box.stl"
    trimesh.Trimesh(BOX, FACES, process=False).export(path)
    return path


class _Full(io.TextIOWrapper):
    """A text stream on a disk that is full."""

    def __init__(self) -> None:
        super().__init__(io.BytesIO(), encoding="utf-8")

    def write(self, data):  # noqa: D102
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("args", [
    ["slice", "{box}", "-t", "1", "-o", "{tmp}/x.npz"],
    ["info", "{box}"],
], ids=["slice-summary", "info"])
def test_in_process(args, box, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "stdout", _Full())
    code = main([a.format(box=box, tmp=tmp_path) for a in args])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err == f"gpuslice: error: standard output: {os.strerror(errno.ENOSPC)}"
    assert isinstance(sys.stdout, _Full)  # (left as it was found)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full on this system")
def test_a_command_writing_to_dev_full(box):
    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "gpuslice.cli", "info", str(box)], stdout=full,
                           stderr=subprocess.PIPE, text=True, timeout=120)
    assert p.returncode == 2
    assert p.stderr.strip() == f"gpuslice: error: standard output: {os.strerror(errno.ENOSPC)}"


@pytest.mark.parametrize("args", [
    ["slice", "{box}", "-t", "1", "-o", "-", "--format", "svg"],
    ["slice", "{box}", "-t", "1", "-o", "{tmp}/x.npz", "--report", "-"],
    ["raster", "{box}", "-t", "1", "-o", "-", "--format", "goo"],
    ["check", "{box}", "-t", "1", "--json", "-"],
    ["batch", "{box}", "-o", "-"],
], ids=["slice", "report", "raster", "check", "batch"])
def test_a_dash_is_not_standard_output(args, box, tmp_path, monkeypatch, capsys):
    """``-o -`` wrote a file named ``-`` in the current folder: refused before any work, saying so."""
    monkeypatch.chdir(tmp_path)
    assert main([a.format(box=box, tmp=tmp_path) for a in args]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "gpuslice: error: -: gpuslice writes files, not standard output; name the file to write (./- for a " \
                  "file named '-')"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["box.stl"]


def test_control_characters_of_a_file_are_escaped_in_its_error(tmp_path, capsys):
    """A PLY element named with an ESC sequence reached the terminal as it was (a fuzzing helper)."""
    path = tmp_path / "e.ply"
    path.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                     b"element \x1b[2Jevil 1\nproperty float a\nend_header\n0 0 0\n1 0 0\n0 1 0\n1\n")
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert "\x1b" not in err and "\\x1b[2Jevil" in err and err.count("\n") == 1


def test_a_batch_model_named_with_control_characters(tmp_path, capsys):
    """A batch's failure line and table printed the name raw (an ESC sequence reached the terminal), and twice: the
    model's escaped name in its message was not found, so the raw one was put before it (a review)."""
    models = tmp_path / "in"
    models.mkdir()
    (models / "bad\x1b[31mred.obj").write_bytes(b"v 1 2\n")
    code = main(["batch", str(models), "-o", str(tmp_path / "out"), "-j", "1", "--backend", "numpy"])
    out, err = capsys.readouterr()
    assert code != 0 and "\x1b" not in err + out
    failed = [line for line in err.splitlines() if line.startswith("gpuslice: failed: ")]
    assert len(failed) == 1 and failed[0].count("bad\\x1b[31mred.obj") == 1, failed
