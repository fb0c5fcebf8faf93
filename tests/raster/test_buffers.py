"""Kernel outputs read back by a copy (``gpuslice.buffers.OutputBuffers``, a GPU's way) give what the outputs
written in the host's arrays give (a CPU device's way): runs and layer images, forced here on any device."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.buffers import OutputBuffers
from gpuslice.cli import main
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec
from gpuslice.raster.runs import layer_runs


@pytest.fixture
def ways(monkeypatch):
    """Which way each OutputBuffers fetch took (True: in the arrays), and a switch to force the copies."""
    seen: list[bool] = []
    fetch = OutputBuffers.fetch

    def spy(self, q):
        seen.append(self._in_place)
        return fetch(self, q)

    monkeypatch.setattr(OutputBuffers, "fetch", spy)
    return seen, lambda: monkeypatch.setattr(OutputBuffers, "IN_PLACE", False)


def test_runs_read_back_by_copies_equal_the_runs_made_in_place(device, ways):
    seen, force_copies = ways
    res = slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 40, 20)), thickness=0.5)
    spec = RasterSpec(resolution=(480, 400), pixel=0.1, gamma=1.0)
    a = layer_runs(res, spec, device=device)
    force_copies()
    b = layer_runs(res, spec, device=device)
    assert set(seen) == {device.is_cpu, False}  # (both ways ran: on a GPU, the copies both times)
    assert a.n_runs > 1000
    for f in ("layers", "layer_offsets", "row", "x", "length", "grey"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f


@pytest.mark.parametrize("suffix", [".goo", ".ctb", ".pm3n"])
def test_archives_read_back_by_copies_are_byte_identical(device, ways, tmp_path, monkeypatch, suffix):
    seen, force_copies = ways
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    stl = tmp_path / "torus.stl"
    assert main(["shape", "torus", "-o", str(stl)]) == 0
    display = ["--printer", "anycubic-photon-mono-2"] if suffix == ".pm3n" else \
        ["--resolution", "1000x960", "--pixel", "0.05"]  # (a Photon file names its machine: its preset)
    args = ["raster", str(stl), "-t", "0.2", *display, "--gamma", "1"]
    outs = []
    for k, switch in enumerate((None, force_copies)):
        if switch:
            switch()
        out = tmp_path / f"a{k}{suffix}"
        assert main([*args, "-o", str(out)]) == 0
        outs.append(out.read_bytes())
    assert False in seen and len(outs[0]) > 10_000
    assert outs[0] == outs[1]
