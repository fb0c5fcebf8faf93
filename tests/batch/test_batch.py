"""``gpuslice batch``: discovery, byte-identical outputs on local workers and on a Dask LocalCluster, the broken
file reported while the others finish, re-runs skipping finished models, a worker killed mid-batch, Ctrl-C."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from gpuslice import Placement, SliceParams
from gpuslice.batch import (
    JOURNAL_NAME,
    MANIFEST_NAME,
    BatchError,
    BatchOptions,
    BatchRunner,
    default_workers,
    discover,
    run_batch,
)
from gpuslice.mesh import shapes
from gpuslice.slicing.result import SliceResult

# small public meshes (a few thousand facets at most), scaled with --fit
PUBLIC = ["prusa_cube_with_hole", "prusa_u_overhang", "prusa_bridge", "xyz_cube_20mm", "prusa_A", "cow", "spot",
          "prusa_two_hollow_squares", "prusa_sloping_hole", "prusa_overhang", "p_ascii_cr", "p_block_hole",
          "thingi_472042", "p_ascii_two_solids"]
GENERATED = {
    "cube": lambda: shapes.box(),
    "cylinder": lambda: shapes.cylinder(n=48),
    "torus": lambda: shapes.torus(n_major=32, n_minor=16),
    "sphere": lambda: shapes.uv_sphere(),
    "hollow": lambda: shapes.hollow_box(),
    "stair": lambda: shapes.stair(),
    "cone": lambda: shapes.cone(n=24),
    "ico": lambda: shapes.icosphere(subdivisions=2),
}
SHARED_MESHES = Path(__file__).resolve().parents[3] / "shared" / "meshes"
OPTS = BatchOptions(SliceParams(thickness=0.5), Placement(fit=25.0))
BROKEN = "broken/garbage.stl"


@pytest.fixture(scope="module")
def tree(tmp_path_factory, device) -> Path:
    """At least 20 models in a tree: public meshes (where the shared folder is there), generated solids (in
    subfolders, some with upper-case suffixes), and one broken file."""
    root = tmp_path_factory.mktemp("models")
    (root / "public").mkdir()
    (root / "gen" / "deep").mkdir(parents=True)
    (root / "broken").mkdir()
    n = 0
    if SHARED_MESHES.is_dir():
        for name in PUBLIC:
            src = SHARED_MESHES / f"{name}.stl"
            if src.is_file():
                shutil.copy(src, root / "public" / src.name)
                n += 1
    for k, (name, make) in enumerate(GENERATED.items()):
        folder = root / "gen" / ("deep" if k % 2 else "")
        shapes.write_stl(make(), folder / (f"{name}.STL" if k == 3 else f"{name}.stl"))
    # without the shared meshes, scaled variants of the generated solids keep the batch at 20+ models
    for k in range(max(0, 12 - n)):
        shapes.write_stl(shapes.cylinder(radius=5 + k, height=10 + k, n=16 + 4 * k), root / "gen" / f"cyl{k}.stl")
    (root / BROKEN).write_bytes(b"solid nothing\n  facet normal 0 0 1\n   outer loop\n    vertex 1 2\n")
    (root / "notes.txt.bak").write_text("not a model")
    return root


def _outputs(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name not in (MANIFEST_NAME, JOURNAL_NAME)}


@pytest.fixture(scope="module")
def serial(tree, tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    report = run_batch([tree], out, OPTS, workers=0)
    return report, _outputs(out)


def _by_model(report) -> dict[str, dict]:
    names = [r["model"] for r in report["models"]]
    assert len(names) == len(set(names)), "a model is listed twice"
    return {r["model"]: r for r in report["models"]}


def _check_complete(report, tree):
    recs = _by_model(report)
    assert len(recs) >= 20
    assert recs[BROKEN]["status"] == "failed"
    assert "garbage.stl" in recs[BROKEN]["error"] and "\n" not in recs[BROKEN]["error"]
    assert recs[BROKEN]["attempts"] == 1  # a broken file fails on any worker: not retried
    others = {k: r for k, r in recs.items() if k != BROKEN}
    assert all(r["status"] == "done" for r in others.values()), [r for r in others.values() if r["status"] != "done"]
    assert all(r["layers"] > 0 and r["facets"] > 0 for r in others.values())


# ---- discovery ------------------------------------------------------------------------------------------
def test_discover_mirrors_the_tree(tree):
    models = discover([tree])
    rels = [m.rel for m in models]
    assert rels == sorted(rels) and "gen/deep/cylinder.stl" in rels and "gen/deep/sphere.STL" in rels
    assert "notes.txt.bak" not in rels and BROKEN in rels
    assert {m.out for m in models} >= {"gen/deep/cylinder.npz", "gen/deep/sphere.npz", "broken/garbage.npz"}
    # a glob, matched case-insensitively at any depth
    assert [m.rel for m in discover([tree], "**/deep/*.stl")] == [r for r in rels if r.startswith("gen/deep/")]
    assert {m.rel for m in discover([tree], "*.stl")} == set(rels)
    # several paths: relative to the deepest folder holding them all; the same file twice counts once
    two = discover([tree / "gen" / "cube.stl", tree / "gen" / "deep", tree / "gen" / "cube.stl"], suffix=".svg")
    assert two[0].rel == "cube.stl" and two[0].out == "cube.svg" and all(m.rel.startswith(("cube", "deep/"))
                                                                          for m in two)


def test_discover_list_file_and_errors(tree, tmp_path):
    lst = tmp_path / "models.txt"
    lst.write_text(f"# two models\n{tree / 'gen' / 'cube.stl'}\n\n{tree / 'gen' / 'deep' / 'cylinder.stl'}\n")
    assert [m.rel for m in discover([lst])] == ["cube.stl", "deep/cylinder.stl"]
    lst.write_text("missing.stl\n")
    with pytest.raises(BatchError, match=r"models.txt:1: missing.stl: no such model file"):
        discover([lst])
    with pytest.raises(BatchError, match="no such file or folder"):
        discover([tmp_path / "nope"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(BatchError, match="no model files"):
        discover([tmp_path / "empty"])
    clash = tmp_path / "clash"
    clash.mkdir()
    for name in ("a.stl", "a.obj"):
        shapes.write_stl(shapes.box(), clash / name)
    with pytest.raises(BatchError, match="clashes"):
        discover([clash])


def test_npz_is_deterministic_and_loads(tree, tmp_path, serial):
    report, outputs = serial
    data = outputs["gen/cube.npz"]
    (tmp_path / "a.npz").write_bytes(data)
    res = SliceResult.load(tmp_path / "a.npz")
    assert res.n_layers == _by_model(report)["gen/cube.stl"]["layers"]
    assert "timings_s" not in res.meta and "device" not in res.meta and res.meta["file"] == "gen/cube.stl"
    with zipfile.ZipFile(tmp_path / "a.npz") as zf:
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    res.save(tmp_path / "b.npz")  # the one .npz writer: equal results give equal bytes
    assert (tmp_path / "b.npz").read_bytes() == data
    np.testing.assert_array_equal(SliceResult.load(tmp_path / "b.npz").points, res.points)


def test_default_workers_shares_out_the_cores(device):
    cores = len(os.sched_getaffinity(0))
    if device.is_gpu:
        assert default_workers(100) == (min(4, cores), max(1, cores // min(4, cores)))
    else:  # PoCL: one worker per core, one PoCL thread each; fewer models than cores: more threads each
        assert default_workers(100) == (cores, 1)
        assert default_workers(1) == (1, cores)
    assert default_workers(0)[0] == 1


# ---- local workers --------------------------------------------------------------------------------------
def test_local_workers_match_serial_and_rerun_skips(tree, serial, tmp_path):
    ref_report, ref = serial
    _check_complete(ref_report, tree)
    out = tmp_path / "local"
    report = run_batch([tree], out, OPTS, workers=2)
    _check_complete(report, tree)
    assert _outputs(out) == ref  # byte-identical to the serial run
    assert report["summary"]["workers"] == 2 and report["summary"]["retries"] == 0
    # a second run skips the finished models (the broken one is tried again: it has no output)
    again = _by_model(run_batch([tree], out, OPTS, workers=2))
    assert {k for k, r in again.items() if r["status"] == "skipped"} == set(again) - {BROKEN}
    # other options into the same folder are refused, unless forced
    other = BatchOptions(SliceParams(thickness=0.4), Placement(fit=25.0))
    with pytest.raises(BatchError, match=r"other options \(thickness 0.5 -> 0.4\)"):
        run_batch([tree], out, other, workers=0)
    forced = _by_model(run_batch([tree / "gen" / "deep"], out, other, workers=0, force=True))
    assert all(r["status"] == "done" for r in forced.values())


def test_outputs_not_written_by_a_batch_are_not_skipped(tree, serial, tmp_path):
    """An output path that already holds a file in a folder no batch has written to (no manifest) was skipped as if
    finished; it is refused by name, before any model, unless forced."""
    out = tmp_path / "foreign"
    report = run_batch([tree / "gen" / "deep"], out, OPTS, workers=0)
    first = next(r["output"] for r in report["models"] if r["status"] == "done")
    (out / ".gpuslice-batch.json").unlink()
    (out / first).write_bytes(b"someone else's file")
    with pytest.raises(BatchError, match=r"exists, and .* has no batch manifest .* not written by gpuslice batch"):
        run_batch([tree / "gen" / "deep"], out, OPTS, workers=0)
    assert (out / first).read_bytes() == b"someone else's file" and not (out / ".gpuslice-batch.json").exists()
    forced = _by_model(run_batch([tree / "gen" / "deep"], out, OPTS, workers=0, force=True))
    assert all(r["status"] == "done" for r in forced.values()) and (out / first).read_bytes() != b"someone else's file"
    again = _by_model(run_batch([tree / "gen" / "deep"], out, OPTS, workers=0))  # the manifest is there now
    assert all(r["status"] == "skipped" for r in again.values())


def test_a_file_put_into_a_batch_folder_later_is_not_skipped(tmp_path, device):
    """In a folder a batch wrote (its manifest there), a file in the place of a model that failed, or an output changed
    since, was skipped as that model's finished output; it is refused by name unless forced (the batch's journal
    lists the files it left). The batch's own outputs are still skipped, and a folder of a batch from before the
    journal keeps the older rule (its outputs recorded as they are)."""
    models = tmp_path / "models"
    models.mkdir()
    for name, make in (("cube", shapes.box), ("cone", lambda: shapes.cone(n=24))):
        shapes.write_stl(make(), models / f"{name}.stl")
    (models / "bad.stl").write_bytes(b"solid nothing\n  facet normal 0 0 1\n")
    out = tmp_path / "out"
    recs = _by_model(run_batch([models], out, OPTS, workers=0))
    assert recs["bad.stl"]["status"] == "failed" and (out / JOURNAL_NAME).is_file()
    bad, cube = out / recs["bad.stl"]["output"], out / recs["cube.stl"]["output"]
    skipped = lambda rep: {k for k, r in _by_model(rep).items() if r["status"] == "skipped"}  # noqa: E731
    assert skipped(run_batch([models], out, OPTS, workers=0)) == {"cube.stl", "cone.stl"}
    bad.write_bytes(b"put here later")  # the failed model's place filled by someone else
    with pytest.raises(BatchError, match=rf"{bad.name}: exists, but .* journal .* does not list it as it is"):
        run_batch([models], out, OPTS, workers=0)
    assert bad.read_bytes() == b"put here later"
    bad.unlink()
    made = cube.read_bytes()
    cube.write_bytes(made + b"changed")  # an output changed since the batch wrote it
    with pytest.raises(BatchError, match=rf"{cube.name}: exists, but"):
        run_batch([models], out, OPTS, workers=0)
    forced = _by_model(run_batch([models], out, OPTS, workers=0, force=True))
    assert forced["cube.stl"]["status"] == "done" and cube.read_bytes() == made
    assert skipped(run_batch([models], out, OPTS, workers=0)) == {"cube.stl", "cone.stl"}
    (out / JOURNAL_NAME).unlink()  # a folder of a batch from before the journal: the older rule, then recorded
    assert skipped(run_batch([models], out, OPTS, workers=0)) == {"cube.stl", "cone.stl"}
    bad.write_bytes(b"put here later")
    with pytest.raises(BatchError, match="does not list it as it is"):
        run_batch([models], out, OPTS, workers=0)


def test_outputs_of_old_options_are_never_skipped_after_a_partial_forced_run(tmp_path):
    """`--force` with new options over part of the models (a glob, or a run stopped early) left the others' outputs
    of the old options listed in the journal, and the next run skipped them under the new manifest: the journal is
    forgotten when the options change, so they are refused by name (a reviewer's audit)."""
    models = tmp_path / "models"
    (models / "sub").mkdir(parents=True)
    shapes.write_stl(shapes.box(), models / "cube.stl")
    shapes.write_stl(shapes.cone(n=24), models / "sub" / "cone.stl")
    out = tmp_path / "out"
    run_batch([models], out, OPTS, workers=0)
    other = BatchOptions(SliceParams(thickness=0.4), Placement(fit=25.0))
    forced = _by_model(run_batch([models], out, other, glob="sub/*", workers=0, force=True))
    assert set(forced) == {"sub/cone.stl"} and forced["sub/cone.stl"]["status"] == "done"
    with pytest.raises(BatchError, match="cube.npz: exists, but .* journal .* does not list it"):
        run_batch([models], out, other, workers=0)  # cube.npz is still the 0.5 mm one: not skipped
    again = _by_model(run_batch([models], out, other, workers=0, force=True))
    assert again["cube.stl"]["status"] == "done"
    assert SliceResult.load(out / "cube.npz").thickness[0] == pytest.approx(0.4)


def test_a_changed_preset_file_is_a_change_of_options(tmp_path):
    """`--raster-opt printer=FILE` recorded the file's name only: a preset edited since (another exposure) had its
    models skipped with the old archives. Its contents are part of the options now."""
    models = tmp_path / "models"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    preset = tmp_path / "resin.toml"
    preset.write_text('inherits = "elegoo-saturn-3-ultra"\n[settings]\nexposure = 2.2\n')
    opts = BatchOptions(SliceParams(thickness=1.0), Placement(fit=20.0), raster="goo",
                        raster_options=(("printer", str(preset)), ("raster_backend", "numpy")))
    out = tmp_path / "out"
    run_batch([models], out, opts, workers=0)
    assert {r["status"] for r in run_batch([models], out, opts, workers=0)["models"]} == {"skipped"}
    preset.write_text('inherits = "elegoo-saturn-3-ultra"\n[settings]\nexposure = 3.5\n')
    with pytest.raises(BatchError, match="holds outputs made with other options .*printer_file_sha256"):
        run_batch([models], out, opts, workers=0)


def test_a_preset_file_travels_with_the_options_and_counts_by_its_contents(tmp_path, monkeypatch, device):
    """`--raster-opt printer=FILE` was read by each Dask worker from its own working folder (every model failed
    naming a path the user never typed), and the same file given by another path was other options (an audit):
    the options carry the preset as read where they are made, and a folder made with it by one path resumes by
    another."""
    import dataclasses
    import pickle

    from gpuslice.batch.task import run_model

    models = tmp_path / "models"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    (tmp_path / "resin.toml").write_text('inherits = "elegoo-saturn-3-ultra"\n[settings]\nexposure = 2.2\n')
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    opts = BatchOptions(SliceParams(thickness=1.0), Placement(fit=20.0), raster="goo",
                        raster_options=(("printer", "resin.toml"), ("raster_backend", "numpy")))
    out = tmp_path / "out"
    assert [r["status"] for r in run_batch([models], out, opts, workers=0)["models"]] == ["done"]
    absolute = dataclasses.replace(opts, preset_files=(), raster_options=(("printer", str(tmp_path / "resin.toml")),
                                                                          ("raster_backend", "numpy")))
    assert [r["status"] for r in run_batch([models], out, absolute, workers=0)["models"]] == ["skipped"]
    # a worker elsewhere, without the file: the options it is sent still hold the preset
    sent = pickle.loads(pickle.dumps(opts))
    elsewhere = tmp_path / "worker"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    (tmp_path / "resin.toml").unlink()
    model = discover([models])[0]
    rec = run_model(model, sent, None)
    assert rec["status"] == "done", rec["error"]
    assert rec["payload"] == (out / "cube.goo").read_bytes()  # (the same preset, the same date: the same file)


def test_a_model_that_fails_half_way_leaves_none_of_its_files(tmp_path):
    """With --check the check report is written before the archive: a model whose archive then failed kept its
    report alone beside nothing (a reviewer's audit: a PNG-stack folder holding other files)."""
    models = tmp_path / "models"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    out = tmp_path / "out"
    (out / "cube").mkdir(parents=True)
    (out / "cube" / "notes.txt").write_text("mine")
    opts = BatchOptions(SliceParams(thickness=1.0), Placement(fit=20.0), raster="png", check=True,
                        raster_options=(("resolution", (640, 480)), ("raster_backend", "numpy")))
    rec = _by_model(run_batch([models], out, opts, workers=0, force=True))["cube.stl"]
    assert rec["status"] == "failed" and "holds other files" in rec["error"]
    assert not list(out.glob("cube*.json")) and (out / "cube" / "notes.txt").read_text() == "mine"


def test_journal_records_files_put_in_place_during_the_run(tmp_path):
    """After Ctrl-C, a model whose worker renamed its files into place during the run (its result never back) is
    journaled, so a re-run skips it instead of refusing it; files older than the run are not."""
    from gpuslice.batch.journal import read_journal, record_written_since

    (tmp_path / "a.npz").write_bytes(b"old")
    since = time.time_ns() + 1
    time.sleep(0.01)
    (tmp_path / "b.npz").write_bytes(b"new")
    (tmp_path / "b.check.json").write_bytes(b"{}")
    record_written_since(tmp_path, ["a.npz"], since)
    record_written_since(tmp_path, ["b.npz", "b.check.json"], since)
    record_written_since(tmp_path, ["c.npz"], since)  # not there
    assert set(read_journal(tmp_path)) == {"b.npz", "b.check.json"}


def test_only_a_failure_another_attempt_may_not_repeat_is_retried(tmp_path, device, monkeypatch):
    """A model that fails for a reason outside its file and options (here a RuntimeError on its first attempt) is
    retried once, and its record keeps the first error; a broken file (``MeshFileError``) or a refused option
    (``ParameterError``) would fail the same way again: one attempt, no retry."""
    import gpuslice.pipeline
    from gpuslice.errors import ParameterError

    models = tmp_path / "models"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    shapes.write_stl(shapes.cone(n=12), models / "cone.stl")
    shapes.write_stl(shapes.box(), models / "full.stl")
    (models / "garbage.stl").write_bytes(b"solid nothing\n  facet normal 0 0 1\n")
    real, calls = gpuslice.pipeline.run_job, []

    def flaky(job, **kw):
        name = Path(job.model_name).name
        calls.append(name)
        if name == "cube.stl" and calls.count(name) == 1:
            raise RuntimeError("clEnqueueNDRangeKernel failed: OUT_OF_RESOURCES")
        if name == "cone.stl":
            raise ParameterError(f"{job.model_name}: refused")
        if name == "full.stl":  # (a full disk: every worker's, so not retried; said as the command line says it)
            raise OSError(errno.ENOSPC, "No space left on device", job.contours)
        return real(job, **kw)

    monkeypatch.setattr(gpuslice.pipeline, "run_job", flaky)
    report = run_batch([models], tmp_path / "out", OPTS, workers=0)
    recs = _by_model(report)
    assert recs["cube.stl"]["status"] == "done" and recs["cube.stl"]["attempts"] == 2
    assert "OUT_OF_RESOURCES" in recs["cube.stl"]["earlier_errors"][0]
    for name in ("garbage.stl", "cone.stl", "full.stl"):
        assert recs[name]["status"] == "failed" and recs[name]["attempts"] == 1
    assert calls.count("garbage.stl") <= 1 and calls.count("cone.stl") == 1 and calls.count("full.stl") == 1
    assert recs["full.stl"]["error"].endswith("full.npz: No space left on device"), recs["full.stl"]["error"]
    assert "OSError" not in recs["full.stl"]["error"]
    assert report["summary"]["retries"] == 1
    assert not any("deterministic" in r for r in report["models"])


def test_a_failed_models_output_through_a_link(tmp_path, device, monkeypatch):
    """An output path that is a symbolic link is written through it; when the model then fails, the file written is
    removed, not the user's link (a review: the link went and the new file stayed)."""
    import gpuslice.pipeline

    models = tmp_path / "models"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    out, target = tmp_path / "out", tmp_path / "elsewhere" / "t.npz"
    out.mkdir()
    target.parent.mkdir()
    (out / "cube.npz").symlink_to(target)
    real = gpuslice.pipeline.run_job

    def written_then_failed(job, **kw):
        real(job, **kw)
        assert target.is_file()  # (written through the link)
        raise RuntimeError("failed after writing")

    monkeypatch.setattr(gpuslice.pipeline, "run_job", written_then_failed)
    report = run_batch([models], out, OPTS, workers=0, force=True)
    assert _by_model(report)["cube.stl"]["status"] == "failed"
    assert (out / "cube.npz").is_symlink() and not target.exists()


def test_a_file_a_worker_cannot_read_is_tried_on_another(tmp_path, device):
    """A model the worker could not read (here a link to nowhere; on a cluster, a mount one worker lacks) is where
    it is read, not what it holds: tried once more, on the other worker (a review: every MeshFileError was taken
    for the file's fault), while a broken file's content is not retried."""
    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    (models / "gone.stl").symlink_to(tmp_path / "nowhere.stl")
    (models / "bad.stl").write_bytes(b"solid nothing\n")
    recs = _by_model(run_batch([models], tmp_path / "out", OPTS, workers=2))
    gone = recs["gone.stl"]
    assert gone["status"] == "failed" and "no such file" in gone["error"] and gone["attempts"] == 2
    assert len(gone["workers"]) == 2 and gone["workers"][0] != gone["workers"][1]
    assert recs["bad.stl"]["attempts"] == 1 and recs["cube.stl"]["status"] == "done"


def test_killed_worker_mid_batch(tree, serial, tmp_path):
    """SIGKILL one worker after the third finished model: the pool replaces it, its unfinished models re-run, and
    every model is done exactly once with the serial run's bytes; no temporary file is left."""
    _, ref = serial
    out = tmp_path / "killed"
    killed = []

    def progress(rec):
        if len(killed) == 0 and rec.get("pid") and rec["status"] == "done":
            seen.append(rec)
            if len(seen) == 3:
                pids = runner.worker_pids()
                assert rec["pid"] in pids
                os.kill(rec["pid"], signal.SIGKILL)
                killed.append(rec["pid"])

    seen: list[dict] = []
    (out / "gen").mkdir(parents=True)
    (out / "gen" / ".cube.npz.tmp-999999-dead.npz").write_bytes(b"half")  # left by a worker killed before
    (out / "gen" / ".notours.tmp-1").write_bytes(b"someone else's")
    runner = BatchRunner(discover([tree]), OPTS, out, progress=progress)
    report = runner.run(2)
    assert killed and report["summary"]["workers_lost"] == 1
    _check_complete(report, tree)
    assert _outputs(out).pop("gen/.notours.tmp-1") == b"someone else's"
    assert not [p for p in out.rglob(".*tmp-*") if p.name != ".notours.tmp-1"]
    assert {k: v for k, v in _outputs(out).items() if "notours" not in k} == ref


# ---- Dask -----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def dask_client():
    distributed = pytest.importorskip("distributed", reason="dask.distributed not installed (gpuslice[batch])")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                       host="127.0.0.1")
    client = distributed.Client(cluster)
    try:
        yield client
    finally:
        client.close()
        cluster.close()


@pytest.mark.parametrize("transfer", ["bytes", "shared"])
def test_dask_local_cluster_matches_serial(tree, serial, tmp_path, dask_client, transfer):
    _, ref = serial
    out = tmp_path / f"dask-{transfer}"
    report = run_batch([tree], out, OPTS, client=dask_client, transfer=transfer)
    _check_complete(report, tree)
    assert _outputs(out) == ref
    recs = _by_model(report)
    assert report["summary"]["mode"] == "dask" and report["summary"]["workers"] == 2
    assert len({r["worker"] for r in recs.values()}) == 2  # both workers took part
    assert report["summary"]["retries"] == 0  # the broken file is not tried twice
    again = _by_model(run_batch([tree], out, OPTS, client=dask_client, transfer=transfer))
    assert {k for k, r in again.items() if r["status"] == "skipped"} == set(again) - {BROKEN}
    assert again[BROKEN]["status"] == "failed"


def test_dask_worker_killed_mid_batch(tree, serial, tmp_path, dask_client):
    """Kill one Dask worker process: its nanny restarts it and the scheduler re-runs its tasks."""
    _, ref = serial
    out = tmp_path / "dask-killed"
    killed: list[int] = []

    def progress(rec):
        if not killed and rec["status"] == "done" and rec.get("pid") and rec["pid"] != os.getpid():
            os.kill(rec["pid"], signal.SIGKILL)
            killed.append(rec["pid"])

    report = run_batch([tree], out, OPTS, client=dask_client, transfer="shared", progress=progress)
    assert killed
    _check_complete(report, tree)
    assert _outputs(out) == ref
    dask_client.wait_for_workers(2, timeout=60)


# ---- the command line -----------------------------------------------------------------------------------
def test_cli_batch(tree, serial, tmp_path, capsys):
    from gpuslice.cli import main

    _, ref = serial
    out, rep = tmp_path / "cli", tmp_path / "batch.json"
    rc = main(["batch", str(tree), "-o", str(out), "-t", "0.5", "--fit", "25", "-j", "2", "--report", str(rep)])
    cap = capsys.readouterr()
    assert rc == 1  # some model failed; the others are done
    assert "garbage.stl" in cap.out and "failed" in cap.out
    assert _outputs(out) == ref
    report = json.loads(rep.read_text())
    assert report["summary"]["done"] == len(report["models"]) - 1 and report["options"]["thickness"] == 0.5
    rc = main(["batch", str(tree), "-o", str(out), "-t", "0.3", "--fit", "25"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "other options" in err
    rc = main(["batch", str(tree / "gen"), "-o", str(tmp_path / "svg"), "-t", "0.5", "--fit", "25", "-j", "0",
               "--format", "svg", "-q"])
    assert rc == 0 and (tmp_path / "svg" / "deep" / "cylinder.svg").read_bytes().startswith(b"<?xml")


def test_cli_adaptive_layers(tree, tmp_path):
    """The slice command's adaptive options reach every model, and shape the outputs (another fingerprint)."""
    from gpuslice.cli import main

    out, rep = tmp_path / "adaptive", tmp_path / "a.json"
    rc = main(["batch", str(tree / "gen" / "deep"), "-o", str(out), "--fit", "25", "--adaptive", "cusp",
               "--max-cusp", "0.05", "--min-height", "0.1", "--max-height", "0.5", "-j", "0", "-q",
               "--report", str(rep)])
    assert rc == 0
    report = json.loads(rep.read_text())
    assert report["options"]["schedule"]["adaptive"] == "cusp"
    varied = 0
    for r in report["models"]:
        res = SliceResult.load(out / r["output"])
        assert res.meta["params"]["adaptive"] == "cusp" and res.n_layers == r["layers"]
        inner = res.thickness[:-1]  # the last layer may be thinner: adaptive layers tile [0, height] exactly
        assert inner.min() >= 0.1 - 1e-9 and res.thickness.max() <= 0.5 + 1e-9
        varied += inner.max() - inner.min() > 1e-6
    assert varied  # curved solids get thinner layers where the surface is flat-ish
    assert main(["batch", str(tree / "gen" / "deep"), "-o", str(out), "--fit", "25", "-q"]) == 2  # uniform: other


@pytest.mark.parametrize(("sig", "code", "said"), [(signal.SIGINT, 130, b"interrupted"),
                                                   (signal.SIGTERM, 143, b"terminated (SIGTERM)"),
                                                   (signal.SIGHUP, 129, b"terminated (SIGHUP)")],
                         ids=["ctrl-c", "sigterm", "sighup"])
def test_cli_ctrl_c_stops_cleanly(tmp_path, device, sig, code, said):
    """SIGINT to the process group (what Ctrl-C does) mid-batch: exit 130, workers gone, only complete outputs. The
    same for SIGTERM to the group (a service manager's stop: the workers took it for a model's result and ran for
    ever, holding the caller's pipes) and SIGHUP (a closed terminal: the resource tracker died with it, and a new
    one printed a traceback a semaphore)."""
    models = tmp_path / "many"
    models.mkdir()
    tri = shapes.torus(n_major=96, n_minor=48)
    for k in range(40):
        shapes.write_stl(tri, models / f"t{k:02d}.stl")
    out, rep = tmp_path / "out", tmp_path / "rep.json"
    cmd = [sys.executable, "-m", "gpuslice.cli", "batch", str(models), "-o", str(out), "-t", "0.02", "-j", "2",
           "--backend", "numpy", "--report", str(rep)]
    # (SIGHUP at its default action, as under a terminal: a test run under nohup passes it on ignored)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    def finished():  # (not the hidden temporaries ".t00.npz.tmp-...npz", which the glob also matches)
        return sorted(p for p in out.glob("*.npz") if not p.name.startswith("."))

    # (3: a model whose output is in place but whose worker has not yet returned is undone, as not finished: at
    # most one a worker)
    while time.monotonic() < deadline and len(finished()) < 3:
        time.sleep(0.05)
    os.killpg(proc.pid, sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err.decode()
    assert err.count(said) == 1 and b"Traceback" not in err and b"Warning" not in err  # said once, with the counts
    assert b"done" in err and b"not run" in err
    done = finished()
    assert 1 <= len(done) < 40
    assert not list(out.glob(".*tmp-*"))
    for p in done:
        SliceResult.load(p)  # every output there is complete
    report = json.loads(rep.read_text())
    assert report["summary"]["interrupted"] and report["summary"]["not_run"] > 0
    if not _group_ends(proc.pid, 10):  # the whole group, workers and forkserver included, goes away
        pytest.fail("processes of the interrupted batch are still running")


def _group_ends(pgid: int, seconds: float) -> bool:
    """Whether every process of the group ``pgid`` is gone within ``seconds`` (those left are killed)."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.1)
    os.killpg(pgid, signal.SIGKILL)
    return False


def test_workers_of_a_killed_driver_end(tmp_path, device):
    """The driver killed outright (SIGKILL, the OOM killer): its workers, idle on their queues, and the forkserver
    they kept alive ran on for ever (a review), holding the caller's pipes. Each worker watches the driver."""
    models = tmp_path / "many"
    models.mkdir()
    tri = shapes.torus(n_major=96, n_minor=48)
    for k in range(40):
        shapes.write_stl(tri, models / f"t{k:02d}.stl")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "gpuslice.cli", "batch", str(models), "-o", str(out), "-t", "0.02", "-j", "2",
           "--backend", "numpy", "-q"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not [p for p in out.glob("*.npz") if not p.name.startswith(".")]:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    if not _group_ends(proc.pid, 15):
        pytest.fail("processes of the killed batch's group are still running")
    assert not list(out.glob(".*tmp-*"))  # (the workers removed their temporaries on the way out)


@pytest.mark.parametrize("kind", ["sl1", "png"])
def test_raster_batch(tree, tmp_path, monkeypatch, kind):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    opts = BatchOptions(SliceParams(thickness=0.5), Placement(fit=25.0), raster=kind,
                        raster_options=(("resolution", "400x300"), ("pixel", 0.1), ("raster_backend", "numpy")))
    outs = []
    for workers in (0, 2):
        out = tmp_path / f"{kind}{workers}"
        report = run_batch([tree / "gen" / "deep"], out, opts, workers=workers)
        assert all(r["status"] == "done" for r in report["models"]), report["models"]
        for r in report["models"]:
            target = out / r["output"]
            assert target.is_file() if kind == "sl1" else len(list(target.glob("*.png"))) == r["layers"]
        outs.append({k: _zip_members(v) if k.endswith(".sl1") else v for k, v in _outputs(out).items()})
    # the same archives (member by member: sl1.py stamps its .ini and thumbnail entries with the current time)
    assert outs[0] == outs[1]


def _zip_members(data: bytes) -> dict[str, bytes]:
    import io

    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return {name: zf.read(name) for name in zf.namelist()}


def test_outputs_are_never_inputs(tmp_path):
    """A batch whose output folder lies in its input tree does not read its own outputs back as models, and an
    output that would replace its model (3MF slice stacks into the models' own folder) is refused before any work."""
    models = tmp_path / "models"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    opts = BatchOptions(SliceParams(thickness=2.0), Placement(fit=20.0), fmt="3mf")
    out = models / "out"
    for _ in range(2):  # the second run sees out/cube.3mf in the input tree
        report = run_batch([models], out, opts, workers=0, force=True)
        assert [r["model"] for r in report["models"]] == ["cube.stl"]
    (models / "part.3mf").write_bytes((out / "cube.3mf").read_bytes())  # a 3MF model beside the STL
    before = (models / "part.3mf").read_bytes()
    with pytest.raises(BatchError, match="would replace it"):
        run_batch([models], models, opts, workers=0)
    assert (models / "part.3mf").read_bytes() == before


def test_manifest_records_raster_options_as_given(tmp_path):
    """The output folder's manifest records --raster-opt values as 8c0d960 did (the text read as an int, a float, a
    bool or the text), so folders it made stay valid; the values are typed by their option fields only when used."""
    opts = BatchOptions(SliceParams(thickness=0.5), Placement(fit=25.0), raster="sl1",
                        raster_options=(("resolution", "400x300"), ("gamma", "1"), ("pixel", "0.1"),
                                        ("mirror_x", "true")))
    assert opts.shaping()["raster_options"] == [["resolution", "400x300"], ["gamma", 1], ["pixel", 0.1],
                                                ["mirror_x", True]]
    spec, _, _ = opts.resin()
    assert spec.resolution == (400, 300) and spec.gamma == 1.0 and spec.mirror_x is True
    # what 8c0d960 computed for these options (its BatchOptions.shaping, json with sorted keys, sha256[:16])
    import hashlib

    old = {"thickness": 0.5, "first_layer": None, "z_mode": "mid", "fill_rule": "nonzero", "max_gap": 2.0,
           "scale": None, "fit": 25.0, "fmt": "npz", "raster": "sl1",
           "raster_options": [["resolution", "400x300"], ["gamma", 1], ["pixel", 0.1], ["mirror_x", True]],
           "schedule": {}}
    assert opts.fingerprint() == hashlib.sha256(json.dumps(old, sort_keys=True).encode()).hexdigest()[:16]


def test_cli_raster_option_errors_name_raster_opt(tmp_path, capsys):
    from gpuslice.cli import main

    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    for opt, want in (("png_level=12", "--raster-opt png_level"), ("resolution=abc", "--raster-opt resolution"),
                      ("nope=1", "unknown raster option nope")):
        args = ["batch", str(models), "-o", str(tmp_path / "o"), "--raster", "sl1", "--raster-opt", opt, "-q"]
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert want in err and len(err.splitlines()) == 1, err
    args = ["batch", str(models), "-o", str(tmp_path / "o"), "--raster", "goo", "--format", "svg", "-q"]
    assert main(args) == 2  # --format was ignored without a word
    assert "--format and --raster" in capsys.readouterr().err
    # a display that is not the one of the printer the archive names: refused before any model
    for raster, opt in (("pm5s", "resolution=3840x2400"), ("goo", "printer=elegoo-saturn-3-ultra")):
        extra = ["--raster-opt", "resolution=3840x2400"] if raster == "goo" else []
        args = ["batch", str(models), "-o", str(tmp_path / "o"), "--raster", raster, "--raster-opt", opt, *extra, "-q"]
        assert main(args) == 2
        err = capsys.readouterr().err.strip()
        assert "display is 11520x5120 px" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "o").exists()



@pytest.mark.parametrize(("args", "flag"), [
    (["-t", "0"], "--thickness"), (["-t", "-1"], "--thickness"), (["--first-layer", "-1"], "--first-layer"),
    (["--z-mode", "paper", "--first-layer", "0.2"], "--first-layer"),
    (["--adaptive", "cusp", "--min-height", "0"], "--min-height"),
    (["--adaptive", "area", "--max-area", "0"], "--max-area"),
    (["--adaptive", "roi", "--roi-ladder", "0.1,0.5"], "--roi-ladder")])
def test_cli_bad_layer_settings_are_refused_before_any_model(tmp_path, capsys, args, flag):
    # each used to fail every model on its own line (exit 1, the folder's journal left behind); `slice` refuses them
    from gpuslice.cli import main

    shapes.write_stl(shapes.box(), tmp_path / "cube.stl")
    assert main(["batch", str(tmp_path / "cube.stl"), "-o", str(tmp_path / "o"), "-j", "0", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("gpuslice: error: ") and flag in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_batch_options_refuse_bad_layer_settings():
    from gpuslice.errors import ParameterError

    for params in (SliceParams(thickness=0), SliceParams(adaptive="cusp", max_cusp=-1.0),
                   SliceParams(adaptive="roi", roi_quantile=2.0)):
        with pytest.raises(ParameterError):
            BatchOptions(params)
    BatchOptions(SliceParams(adaptive="cusp", thickness=-1.0))  # (adaptive layers have no uniform thickness)

def test_cli_raster_batch_writes_what_raster_writes(tmp_path, monkeypatch):
    """`batch --raster goo --raster-opt printer=…` without -t gives each model the file `gpuslice raster --printer …
    -o part.goo` writes: the same layer height (raster's 0.05 mm, not slice's 0.1), the same bytes; -t still wins."""
    from gpuslice.cli import main

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    fast = ["--backend", "numpy", "--fit", "4"]
    printer = "elegoo-saturn-3-ultra"
    assert main(["raster", str(models / "cube.stl"), *fast, "--printer", printer, "--raster-backend", "numpy",
                 "--no-progress", "-q", "-o", str(tmp_path / "cube.goo")]) == 0
    opts = ["--raster-opt", f"printer={printer}", "--raster-opt", "raster_backend=numpy", "-j", "0", "-q"]
    assert main(["batch", str(models), *fast, "--raster", "goo", *opts, "-o", str(tmp_path / "a")]) == 0
    assert (tmp_path / "a" / "cube.goo").read_bytes() == (tmp_path / "cube.goo").read_bytes()
    assert main(["batch", str(models), *fast, "-t", "0.1", "--raster", "goo", *opts, "-o", str(tmp_path / "b")]) == 0
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "raster"))
    from goo_reader import read_goo

    layers = [read_goo(tmp_path / d / "cube.goo").header["total_layers"] for d in "ab"]
    assert layers == [80, 40]  # a 4 mm cube at 0.05 and at 0.1 mm


def test_batch_report_never_names_an_input_or_an_output(tmp_path, capsys):
    # the report is written at the end: naming a model, a list file or a model's output, it replaced that file (a
    # helper's probe); refused before any model, the files left as they were
    from gpuslice.cli import main

    models = tmp_path / "models"
    models.mkdir()
    for name in ("a", "b"):
        shapes.write_stl(shapes.box(), models / f"{name}.stl")
    lst = tmp_path / "list.txt"
    lst.write_text(f"{models / 'a.stl'}\n")
    out = tmp_path / "out"
    before = {p: p.read_bytes() for p in (models / "a.stl", models / "b.stl", lst)}
    for inputs, report, words in (([models], models / "b.stl", "an input"), ([lst], lst, "an input"),
                                  ([models / "a.stl"], models / "a.stl", "an input"),
                                  ([models], out / "a.npz", "the output of")):
        rc = main(["batch", *map(str, inputs), "-o", str(out), "-t", "5", "-j", "0", "-q", "--report", str(report)])
        err = capsys.readouterr().err
        assert rc == 2 and err.count("\n") == 1 and words in err, err
    assert {p: p.read_bytes() for p in before} == before
    assert not out.exists() or not any(out.iterdir())


def test_discovery_follows_links_once_and_keeps_linked_models(tmp_path):
    # two folder links looping back (d/up -> .., d/up2 -> ..) made the walk endless; a link to a model outside the
    # inputs that shared a model's name was taken for the same file and silently dropped (a helper's probe)
    tree = tmp_path / "m"
    (tree / "d").mkdir(parents=True)
    shapes.write_stl(shapes.box(), tree / "a.stl")
    (tree / "d" / "up").symlink_to("..")
    (tree / "d" / "up2").symlink_to("..")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shapes.write_stl(shapes.torus(n_major=16, n_minor=8), elsewhere / "a.stl")
    (tree / "d" / "link.stl").symlink_to(elsewhere / "a.stl")
    (tree / "zz.stl").symlink_to(elsewhere / "a.stl")  # the same outside file twice: sliced once
    models = discover([tree])
    assert sorted(m.rel for m in models) == ["a.stl", "zz.stl"]  # (the first link found names it)
    assert {Path(m.path).resolve() for m in models} == {(tree / "a.stl").resolve(), (elsewhere / "a.stl").resolve()}


def test_folder_outputs_inside_one_another_and_a_report_on_the_output_folder_are_refused(tmp_path, capsys):
    # with PNG stacks a.stl's out/a/ held a/b.stl's out/a/b/ (a re-run with --force then failed); --report naming
    # the output folder failed only after every model (a helper's probe)
    from gpuslice.cli import main

    tree = tmp_path / "m"
    (tree / "a").mkdir(parents=True)
    shapes.write_stl(shapes.box(), tree / "a.stl")
    shapes.write_stl(shapes.box(), tree / "a" / "b.stl")
    with pytest.raises(BatchError, match=r"its output a/b would lie inside that of .*a\.stl \(a/\)"):
        discover([tree], suffix="")
    assert len(discover([tree], suffix=".npz")) == 2  # (files: a.npz beside a/b.npz)
    out = tmp_path / "out"
    assert main(["batch", str(tree), "-o", str(out), "-t", "5", "-j", "0", "-q", "--report", str(out)]) == 2
    assert "--report names the output folder" in capsys.readouterr().err and not out.exists()


def test_an_output_folder_whose_parent_is_missing_is_refused(tmp_path, capsys):
    """`batch -o new/a/b` made the whole tree (a typo's too), where every other command refuses a missing parent."""
    from gpuslice.cli import main

    tree = tmp_path / "m"
    tree.mkdir()
    shapes.write_stl(shapes.box(), tree / "a.stl")
    assert main(["batch", str(tree), "-o", str(tmp_path / "new" / "a" / "b"), "-t", "5", "-j", "0", "-q"]) == 2
    assert "does not exist" in capsys.readouterr().err and not (tmp_path / "new").exists()
    assert main(["batch", str(tree), "-o", str(tmp_path / "one"), "-t", "5", "-j", "0", "-q"]) == 0  # (one level)


@pytest.mark.parametrize("name", [".gpuslice-batch.done", ".gpuslice-batch.json", "a.npz.check.json"])
def test_a_report_on_the_batchs_own_records_is_refused(tmp_path, capsys, name):
    """`--report out/.gpuslice-batch.done` replaced the journal (the next run refused the folder), and
    `--check --report out/a.npz.check.json` a model's check report, with exit 0 (an audit of the outputs)."""
    from gpuslice.cli import main

    tree = tmp_path / "m"
    tree.mkdir()
    shapes.write_stl(shapes.box(), tree / "a.stl")
    out = tmp_path / "out"
    assert main(["batch", str(tree), "-o", str(out), "-t", "5", "-j", "0", "-q", "--check", "--report",
                 str(out / name)]) == 2
    err = capsys.readouterr().err
    assert ("batch's own record" in err or "names the output of" in err) and not out.exists(), err


def test_raster_options_in_another_order_are_the_same_options(tmp_path):
    """A folder made with --raster-opt exposure=2.5 --raster-opt printer=... was refused ("holds outputs made with
    other options") when the same batch gave them the other way round; its manifest stays valid for both orders."""
    from gpuslice.batch import run_batch

    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    out = tmp_path / "out"
    a = (("exposure", "2.5"), ("resolution", "200x200"), ("pixel", "0.1"))

    def opts(pairs):
        return BatchOptions(SliceParams(thickness=1.0), Placement(), raster="goo", raster_options=pairs)

    assert opts(a).fingerprint() != opts(a[::-1]).fingerprint()  # (recorded as given: older folders stay valid)
    first = run_batch([models], out, opts(a), workers=0)
    assert first["summary"]["done"] == 1
    again = run_batch([models], out, opts(a[::-1]), workers=0)
    assert again["summary"]["skipped"] == 1 and again["summary"]["failed"] == 0
    with pytest.raises(BatchError, match=r"holds outputs made with other options \(raster_options"):
        run_batch([models], out, opts((("exposure", "3.0"), *a[1:])), workers=0)


def test_workers_write_the_date_of_the_batchs_environment(tmp_path, monkeypatch, device):
    """A Dask worker started without the client's SOURCE_DATE_EPOCH wrote its own date into dated archives (an
    audit: CTB headers and SL1 zip dates differed from `raster`'s): the options take the date where the batch runs,
    and a worker whose environment says another writes the same bytes."""
    import dataclasses
    import datetime as dt

    from gpuslice.batch.discover import discover as find
    from gpuslice.batch.task import run_model

    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box((0, 0, 0), (10, 10, 4)), models / "cube.stl")
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    opts = BatchOptions(SliceParams(thickness=0.5), Placement(), raster="sl1")
    assert opts.date == dt.datetime(2023, 11, 14, 22, 13, 20)
    model = find([models])[0]
    want = run_model(model, opts, None)["payload"]
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1600000000")  # the worker's own environment
    assert run_model(model, opts, None)["payload"] == want
    undated = dataclasses.replace(opts, date=None)  # (made here, where the environment says 1600000000)
    assert undated.date == dt.datetime(2020, 9, 13, 12, 26, 40) and run_model(model, undated, None)["payload"] != want


def test_cli_batch_says_what_raster_warns_and_failures_under_q(tmp_path, capsys):
    """`batch --raster` dropped `raster`'s warnings (no printer named; a preset without exposures), and -q hid the
    failed models' lines too, so a failing batch printed nothing (an audit): both are said, once, on stderr."""
    from gpuslice.cli import main

    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box((0, 0, 0), (10, 10, 2)), models / "cube.stl")
    (models / "bad.stl").write_bytes(b"solid x\n")
    args = ["batch", str(models), "--raster", "ctb", "-t", "0.5", "-q"]
    assert main([*args, "-o", str(tmp_path / "a"), "--raster-opt", "printer=elegoo-saturn-3-ultra"]) == 1
    err = capsys.readouterr().err.splitlines()
    assert any(line.startswith("gpuslice: failed:") and "bad.stl" in line for line in err)
    assert [line for line in err if "warning" in line] == [
        line for line in err if line.startswith("gpuslice: warning: each ctb file in") and "holds no exposures" in line]
    assert len([line for line in err if "warning" in line]) == 1
    assert main([*args, "-o", str(tmp_path / "b")]) == 1
    assert sum("names no printer" in line for line in capsys.readouterr().err.splitlines()) == 1


def test_a_forced_redo_that_fails_leaves_no_stale_output(tmp_path, device):
    """A model whose forced redo failed kept its old output, which the next run then skipped as done (an audit):
    the failed redo removes it, so the next run tries the model again and says it fails."""
    models = tmp_path / "m"
    models.mkdir()
    cube = models / "cube.stl"
    shapes.write_stl(shapes.box(), cube)
    out = tmp_path / "out"
    assert _by_model(run_batch([models], out, OPTS, workers=0))["cube.stl"]["status"] == "done"
    assert (out / "cube.npz").is_file()
    cube.write_bytes(b"solid broken\n")  # the model changed, and is now broken
    forced = _by_model(run_batch([models], out, OPTS, workers=0, force=True))["cube.stl"]
    assert forced["status"] == "failed" and not (out / "cube.npz").exists()
    again = _by_model(run_batch([models], out, OPTS, workers=0))["cube.stl"]
    assert again["status"] == "failed"  # tried again, not skipped


def test_outputs_written_into_the_input_folder_are_not_read_back(tmp_path, device):
    """`-o` the input folder itself with 3MF slice stacks: the second run took the first run's `.3mf` outputs for
    models (an audit: exit 2, "its output would replace it"); the batch's own files, as its journal lists them, are
    left out, and a model put there by the user is still taken."""
    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "cube.stl")
    opts = BatchOptions(SliceParams(thickness=1.0), Placement(), fmt="3mf")
    first = run_batch([models], models, opts, workers=0)
    assert [r["status"] for r in first["models"]] == ["done"] and (models / "cube.3mf").is_file()
    shapes.write_stl(shapes.cone(n=12), models / "cone.stl")
    again = _by_model(run_batch([models], models, opts, workers=0))
    assert {k: r["status"] for k, r in again.items()} == {"cube.stl": "skipped", "cone.stl": "done"}


def test_discovery_takes_a_users_model_put_where_a_journaled_output_was(tmp_path, device):
    """With the output folder the input folder, a batch's own outputs are left out by its journal; a file of the same
    name that is not the journaled one (size, date) is the user's model and is taken (a review)."""
    import trimesh

    models = tmp_path / "m"
    models.mkdir()
    shapes.write_stl(shapes.box(), models / "old.stl")
    opts = BatchOptions(SliceParams(thickness=1.0), Placement(), fmt="3mf")
    run_batch([models], models, opts, workers=0)
    (models / "old.stl").unlink()
    trimesh.creation.box((5, 5, 5)).export(models / "old.3mf")  # the user's model, where the output was
    assert [m.rel for m in discover([models], None, ".npz", models)] == ["old.3mf"]
