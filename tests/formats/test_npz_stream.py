"""The ``.npz`` written while the layers are sliced (issue 14 parts 3 and 4): the same bytes as ``np.savez`` of the
finished result, atomic, and the points never held twice."""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.formats.npz import NpzStream, crc32_combine
from gpuslice.mesh import shapes as S
from gpuslice.pipeline import Job, run_job
from gpuslice.slicing.params import SliceParams
from gpuslice.slicing.result import SliceResult


def test_crc32_combine_equals_zlib_on_the_joined_bytes():
    rng = np.random.default_rng(5)
    for n1, n2 in [(0, 0), (0, 7), (7, 0), (1, 1), (100, 3), (3, 100), (4096, 65537)] + [
        (int(a), int(b)) for a, b in rng.integers(0, 5000, (40, 2))
    ]:
        a, b = rng.bytes(n1), rng.bytes(n2)
        assert crc32_combine(zlib.crc32(a), zlib.crc32(b), len(b)) == zlib.crc32(a + b), (n1, n2)


def _stream(result: SliceResult, path, pieces) -> SliceResult:
    s = NpzStream(path)
    for piece in pieces:
        s.append(piece)
    streamed = replace(result, points=s.array())
    s.commit(streamed)
    return streamed


@pytest.mark.parametrize("splits", [1, 2, 7])
def test_streamed_points_give_savez_bytes(tmp_path, splits):
    mesh = mesh_from_triangles(S.hollow_box(20, 10, core=6))
    r = slice_mesh(mesh, thickness=0.5, backend="numpy")
    r.save(tmp_path / "whole.npz")
    pieces = np.array_split(r.points, splits) + [np.zeros((0, 2), np.float32)]
    streamed = _stream(r, tmp_path / "streamed.npz", pieces)
    assert (tmp_path / "streamed.npz").read_bytes() == (tmp_path / "whole.npz").read_bytes()
    np.testing.assert_array_equal(streamed.points, r.points)
    back = SliceResult.load(tmp_path / "streamed.npz")  # (zipfile checks each member's CRC as it reads)
    np.testing.assert_array_equal(back.points, r.points)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["streamed.npz", "whole.npz"]  # no temporary left


def test_a_result_without_points_streams_too(tmp_path):
    r = slice_mesh(mesh_from_triangles(S.box((0, 0, 0), (10, 10, 10))), thickness=2.0, backend="numpy")
    empty = replace(r, points=np.zeros((0, 2), np.float32), loop_offsets=np.zeros(1, np.int64),
                    layer_offsets=np.zeros(r.n_layers + 1, np.int64), loop_layer=np.zeros(0, np.int32),
                    loop_is_hole=np.zeros(0, bool), loop_parent=np.zeros(0, np.int32), loop_closed=np.zeros(0, bool))
    empty.save(tmp_path / "whole.npz")
    _stream(empty, tmp_path / "streamed.npz", [])
    assert (tmp_path / "streamed.npz").read_bytes() == (tmp_path / "whole.npz").read_bytes()


def test_abort_and_foreign_points_leave_nothing(tmp_path):
    r = slice_mesh(mesh_from_triangles(S.box((0, 0, 0), (10, 10, 10))), thickness=2.0, backend="numpy")
    s = NpzStream(tmp_path / "a.npz")
    s.append(r.points)
    with pytest.raises(ValueError, match="not the ones streamed"):
        s.commit(r)  # its own points, not the file's
    s.abort()
    s.abort()
    assert list(tmp_path.iterdir()) == []


def test_a_job_in_batches_streams_the_bytes_save_writes(tmp_path, backend):
    # several batches of layers: each batch's points are written as it is nested; the file must be the one
    # SliceResult.save writes for the same result, and the result's points are the file's, not a copy in memory
    mesh = mesh_from_triangles(S.hollow_box(20, 10, core=6))
    src = tmp_path / "box.stl"
    _write_stl(mesh, src)
    out = tmp_path / "box.npz"
    job = Job(str(src), params=SliceParams(thickness=0.25, backend=backend, max_segments_per_batch=100),
              contours=str(out), portable=True)
    res = run_job(job).result
    assert res.meta["batches"] > 5
    assert isinstance(res.points, np.memmap)
    res.save(tmp_path / "again.npz")
    assert out.read_bytes() == (tmp_path / "again.npz").read_bytes()
    whole = run_job(replace(job, params=replace(job.params, max_segments_per_batch=10**9), contours=None)).result
    np.testing.assert_array_equal(SliceResult.load(out).points, whole.points)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.npz", "box.npz", "box.stl"]


def test_a_job_that_fails_while_slicing_leaves_no_file(tmp_path, monkeypatch):
    import gpuslice.slicing.slicer as slicer

    mesh = mesh_from_triangles(S.hollow_box(20, 10, core=6))
    src = tmp_path / "box.stl"
    _write_stl(mesh, src)
    calls = []

    def failing(*args, **kw):
        calls.append(1)
        if len(calls) == 3:  # the third batch: two batches' points are in the file already
            raise KeyboardInterrupt
        return nest(*args, **kw)

    nest = slicer.nest_loops
    monkeypatch.setattr(slicer, "nest_loops", failing)
    job = Job(str(src), params=SliceParams(thickness=0.25, backend="numpy", max_segments_per_batch=100),
              contours=str(tmp_path / "box.npz"))
    with pytest.raises(KeyboardInterrupt):
        run_job(job)
    assert len(calls) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["box.stl"]


def _write_stl(mesh, path) -> None:
    import trimesh

    trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
