"""The command line: outputs, the report, one-line errors with exit status 2 and no partial files."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from gpuslice import SliceResult
from gpuslice.cli import main
from gpuslice.formats.commonlayer import read_cli

REPORT_KEYS = {"z", "thickness", "area_mm2", "points", "loops", "open_chains", "repairs", "timings_s", "device"}


@pytest.fixture(scope="module")
def torus(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "torus.stl"
    assert main(["shape", "torus", "-o", str(path)]) == 0
    return path


def test_slice_writes_npz_svg_cli_and_report(torus, tmp_path, capsys):
    out, rep = tmp_path / "t.npz", tmp_path / "run.json"
    assert main(["slice", str(torus), "-t", "0.25", "-o", str(out), "--report", str(rep)]) == 0
    summary = capsys.readouterr().out
    assert "40 layers" in summary and "0 open chains" in summary and "device:" in summary
    res = SliceResult.load(out)
    report = json.loads(rep.read_text())
    assert REPORT_KEYS <= set(report)
    stages = {"load", "topology", "mesh_check", "crossings", "chaining", "nesting", "write", "cusp"}
    assert stages <= set(report["timings_s"])
    assert len(report["z"]) == len(report["thickness"]) == len(report["area_mm2"]) == len(report["points"]) == 40
    np.testing.assert_allclose(report["area_mm2"], res.area)
    assert report["points"] == res.points_per_layer.tolist()
    assert report["open_chains"] == 0 and report["loops"] == res.n_loops == 80
    for suffix in (".svg", ".cli"):
        assert main(["slice", str(torus), "-t", "0.25", "-o", str(tmp_path / f"t{suffix}"), "-q"]) == 0
    layers = read_cli(tmp_path / "t.cli")
    assert len(layers) == 40 and all(len(loops) == 2 for _, loops in layers)
    assert (tmp_path / "t.svg").read_text().count("<g ") >= 40


def test_adaptive_options_with_their_mode_are_taken(torus, tmp_path):
    out = tmp_path / "c.npz"
    assert main(["slice", str(torus), "--adaptive", "cusp", "--min-height", "0.1", "--max-cusp", "0.08",
                 "-o", str(out), "-q"]) == 0
    params = SliceResult.load(out).meta["params"]
    assert params["min_height"] == 0.1 and params["max_cusp"] == 0.08


def test_numpy_backend_and_options(torus, tmp_path):
    out = tmp_path / "p.npz"
    args = ["slice", str(torus), "-t", "0.5", "--z-mode", "paper", "--backend", "numpy", "--fill-rule", "evenodd"]
    assert main([*args, "-o", str(out), "-q"]) == 0
    res = SliceResult.load(out)
    np.testing.assert_allclose(res.z, 0.5 * np.arange(1, 20))
    assert res.meta["backend"] == "numpy"


def test_info_and_devices(torus, capsys):
    assert main(["info", str(torus), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["facets"] == 2304 and info["watertight"] and info["bodies"] == 1
    assert info["volume"] > 7000
    assert main(["devices"]) == 0
    assert "*" in capsys.readouterr().out


@pytest.mark.parametrize(
    "make, args, message",
    [
        (None, ["slice", "{missing}"], "no such file"),
        ("dir", ["slice", "{dir}"], "is a directory"),
        ("text", ["slice", "{text}"], "not an STL file"),
        ("torus", ["slice", "{torus}", "-t", "-1"], "thickness"),
        ("torus", ["slice", "{torus}", "--fit", "0"], "--fit"),
        ("torus", ["slice", "{torus}", "-o", "{out_png}"], "unknown output format"),
        ("torus", ["slice", "{torus}", "--device", "no-such-device"], "device"),
        # an adaptive schedule's option without its mode was ignored, silently: uniform layers came out
        ("torus", ["slice", "{torus}", "--max-cusp", "0.1"], "--max-cusp shapes --adaptive cusp layers; add"),
        ("torus", ["slice", "{torus}", "--adaptive", "roi", "--min-height", "0.1"],
         "--min-height shapes --adaptive cusp or area layers, not roi ones"),
        ("torus", ["slice", "{torus}", "--adaptive", "roi", "-t", "0.2"],
         "--thickness shapes uniform layers, not roi ones"),
        ("torus", ["raster", "{torus}", "--adaptive", "cusp", "--roi-windows", "2", "-o", "{dir}/layers/"],
         "--roi-windows shapes"),
    ],
)
def test_user_errors_are_one_line_exit_2_and_write_nothing(torus, tmp_path, capsys, make, args, message):
    paths = {"missing": tmp_path / "missing.stl", "dir": tmp_path, "text": tmp_path / "notes.stl",
             "torus": torus, "out_png": tmp_path / "x.png"}
    (tmp_path / "notes.stl").write_text("these are my notes, not a mesh\n")
    out = tmp_path / "out.npz"
    argv = [a.format(**paths) for a in args] + ["-o", str(out)] * ("-o" not in args)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("gpuslice: error: ") and message in err
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary files left behind


def test_console_script_prints_no_traceback(tmp_path):
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"\x00" * 84 + b"\x01\x02")
    proc = subprocess.run([sys.executable, "-m", "gpuslice.cli", "slice", str(bad)], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1 and str(bad) in proc.stderr


@pytest.mark.parametrize("slow_exit", ["", "1"])
def test_console_script_exit_keeps_output_and_status(torus, tmp_path, slow_exit):
    """The command ends without the interpreter's teardown (``exit_now``) unless GPUSLICE_SLOW_EXIT is set: either
    way everything printed reaches the pipe, the file is complete and the status is the command's."""
    out = tmp_path / "t.npz"
    env = {**__import__("os").environ, "GPUSLICE_SLOW_EXIT": slow_exit}
    proc = subprocess.run([sys.executable, "-m", "gpuslice.cli", "slice", str(torus), "-t", "0.5", "--fit", "20", "-o",
                           str(out), "--report", str(tmp_path / "r.json")], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.rstrip().endswith(f"wrote {out}") and "times (ms)" in proc.stdout
    ref = tmp_path / "ref.npz"
    assert main(["slice", str(torus), "-t", "0.5", "--fit", "20", "-o", str(ref), "-q"]) == 0
    got, want = SliceResult.load(out), SliceResult.load(ref)
    assert got.n_layers == want.n_layers > 5
    np.testing.assert_array_equal(got.points, want.points)
    assert json.loads((tmp_path / "r.json").read_text())["timings_s"]
    proc = subprocess.run([sys.executable, "-m", "gpuslice.cli", "slice", str(tmp_path / "none.stl")],
                          capture_output=True, text=True, env=env)
    assert proc.returncode == 2 and "none.stl" in proc.stderr


def test_exit_now_waits_for_threads_and_hooks(monkeypatch):
    import threading

    cli_main = sys.modules["gpuslice.cli.main"]  # the module (the package's ``main`` is the function)
    monkeypatch.delenv("GPUSLICE_SLOW_EXIT", raising=False)
    monkeypatch.setattr(sys, "modules", {k: v for k, v in sys.modules.items() if k not in ("coverage", "distributed",
                                                                                          "dask.distributed")})
    monkeypatch.setattr(sys, "gettrace", lambda: None)
    monkeypatch.setattr(sys, "getprofile", lambda: None)
    assert cli_main._nothing_pending()
    stop = threading.Event()
    worker = threading.Thread(target=stop.wait)  # not a daemon: the interpreter would wait for it
    worker.start()
    try:
        assert not cli_main._nothing_pending()
    finally:
        stop.set()
        worker.join()
    assert cli_main._nothing_pending()
    monkeypatch.setenv("GPUSLICE_SLOW_EXIT", "1")
    assert not cli_main._nothing_pending()
    monkeypatch.delenv("GPUSLICE_SLOW_EXIT")
    monkeypatch.setitem(sys.modules, "distributed", object())
    assert not cli_main._nothing_pending()


def test_unraisable_reports_are_kept_unless_interrupted(monkeypatch):
    """After Ctrl-C the command line swallows finalisers' "Exception ignored" reports (a library object half made
    when the interrupt landed); before it, Python's own report is kept."""
    cli_main = sys.modules["gpuslice.cli.main"]
    seen = []
    monkeypatch.setattr(sys, "__unraisablehook__", seen.append)
    monkeypatch.setattr(cli_main, "_INTERRUPTED", __import__("threading").Event())
    cli_main._unraisable("first")
    cli_main._INTERRUPTED.set()
    cli_main._unraisable("second")
    assert seen == ["first"]


def test_a_model_drawn_in_metres_gets_a_hint_at_the_units(tmp_path, capsys):
    from gpuslice.mesh import shapes as S

    small, big = tmp_path / "part_in_metres.stl", tmp_path / "part_in_mm.stl"
    S.write_stl(S.box((0, 0, 0), (0.02, 0.01, 0.02)), small)  # a 20 mm part saved in metres
    S.write_stl(S.box((0, 0, 0), (20, 10, 0.02)), big)  # a 0.02 mm film, drawn in mm
    for path, hint in ((small, True), (big, False)):
        out = tmp_path / "x.svg"
        assert main(["slice", str(path), "-t", "0.1", "-o", str(out)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "0.02 mm tall: no cutting plane lies below its top" in err
        assert ("if they are metres, give --scale 1000" in err) is hint
        assert not out.exists()
    assert main(["slice", str(small), "-t", "0.1", "--scale", "1000", "-o", str(tmp_path / "ok.svg")]) == 0


def test_special_files_as_outputs_are_refused_not_replaced(torus, tmp_path, capsys):
    # an atomic write renames a regular file over the path: over /dev/null (a helper's probe did so) or a FIFO that
    # would replace the device or the pipe for every program. Refused, and the special file is left as it was.
    import stat

    fifo = tmp_path / "pipe.svg"
    os.mkfifo(fifo)
    for argv in (["slice", str(torus), "-t", "1", "-o", str(fifo)],
                 ["slice", str(torus), "-t", "1", "-o", str(tmp_path / "ok.svg"), "--report", str(fifo)],
                 ["shape", "cube", "-o", str(fifo)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "not a regular file" in err and str(fifo) in err
        assert stat.S_ISFIFO(os.stat(fifo).st_mode)
    from gpuslice.errors import ParameterError
    from gpuslice.io.atomic import atomic_write_bytes

    with pytest.raises(ParameterError, match="not a regular file"):
        atomic_write_bytes(fifo, b"x")
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)


def test_report_through_a_linked_folder_is_the_output_itself(torus, tmp_path, capsys):
    (tmp_path / "d").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "d")
    argv = ["slice", str(torus), "-t", "1", "-o", str(tmp_path / "d" / "x.svg"),
            "--report", str(tmp_path / "link" / "x.svg")]
    assert main(argv) == 2
    assert "--report names the output itself" in capsys.readouterr().err
    assert not (tmp_path / "d" / "x.svg").exists()


def test_write_errors_name_the_output_not_its_temporary(torus, tmp_path, capsys):
    # a long valid name failed ("File name too long") on its longer hidden temporary, and the messages named the
    # temporary (a helper's probe)
    long = tmp_path / ("a" * 240 + ".svg")
    assert main(["slice", str(torus), "-t", "1", "-o", str(long), "-q"]) == 0 and long.is_file()
    from gpuslice.io.atomic import atomic_path

    with pytest.raises(OSError) as info, atomic_path(tmp_path / "x.bin") as tmp:
        raise OSError(28, "No space left on device")  # (a writer's error without a file name)
    assert info.value.filename == str(tmp_path / "x.bin") and not tmp.exists()
    with pytest.raises(OSError) as info, atomic_path(tmp_path / "y.bin") as tmp:
        open(tmp / "sub", "wb")  # noqa: SIM115 - fails: no such folder (the error names the temporary)
    assert info.value.filename == str(tmp_path / "y.bin")


@pytest.mark.parametrize("command", ["slice", "raster"])
def test_a_failing_report_leaves_the_previous_output(torus, tmp_path, capsys, monkeypatch, command):
    # the output used to be renamed into place before the report was written: a full disk at the report left a new
    # output beside no report and exit 2. Both are now renamed together at the end, or neither.
    import gpuslice.io.report as report_mod

    out = tmp_path / ("t.svg" if command == "slice" else "t.goo")
    out.write_bytes(b"the previous run's output")
    real = report_mod.atomic_write_text

    def full_disk(path, text, **kw):
        with real.__globals__["atomic_path"](path) as tmp:  # the report's temporary exists, then the disk fills
            tmp.write_text(text[:10])
            raise OSError(28, "No space left on device")

    monkeypatch.setattr(report_mod, "atomic_write_text", full_disk)
    argv = [command, str(torus), "-t", "1", "-o", str(out), "--report", str(tmp_path / "r.json"), "-q"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "r.json" in err and "No space left" in err
    assert out.read_bytes() == b"the previous run's output"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]  # no report, no temporaries
    monkeypatch.setattr(report_mod, "atomic_write_text", real)
    assert main(argv) == 0  # and a run that succeeds writes both
    assert out.read_bytes() != b"the previous run's output" and json.loads((tmp_path / "r.json").read_text())


def test_committed_together_renames_all_or_none(tmp_path):
    from gpuslice.io.atomic import atomic_write_bytes, committed_together

    with committed_together():
        atomic_write_bytes(tmp_path / "a", b"1")
        atomic_write_bytes(tmp_path / "b", b"2")
        assert not (tmp_path / "a").exists()  # complete, but not yet in place
    assert (tmp_path / "a").read_bytes() == b"1" and (tmp_path / "b").read_bytes() == b"2"
    with pytest.raises(KeyboardInterrupt), committed_together():
        atomic_write_bytes(tmp_path / "a", b"new")
        with committed_together():  # a nested block joins the outer one
            atomic_write_bytes(tmp_path / "c", b"3")
        raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"] and (tmp_path / "a").read_bytes() == b"1"
