"""The command line against bad input and bad settings, as a new user meets them: one error line naming the file or
the option and the problem, exit status 2, no traceback, no output file (nor a hidden temporary) left behind, and no
work started before a refusal that could be made up front. Signals other than Ctrl-C (SIGTERM from ``kill`` or
``timeout``, SIGHUP from a closed terminal) leave no partial output either."""

from __future__ import annotations

import os
import signal
import socket
import struct
import subprocess
import sys
import textwrap
import time
import zipfile

import pytest

from gpuslice.cli import main


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    path = tmp_path_factory.mktemp("sweep") / "cube.stl"
    assert main(["shape", "cube", "-o", str(path)]) == 0  # 20 mm
    return path


def _one_line_error(capsys, *words: str) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("gpuslice: error: "), err
    assert "Traceback" not in err and all(w in lines[0] for w in words), err
    return lines[0]


@pytest.fixture
def no_work(monkeypatch):
    """Any pipeline job or batch started fails the test (main() reports it as an internal error, exit 1)."""
    import gpuslice.batch
    import gpuslice.pipeline

    def started(*args, **kwargs):
        raise AssertionError("work started before the refusal")

    monkeypatch.setattr(gpuslice.pipeline, "run_job", started)
    monkeypatch.setattr(gpuslice.batch, "BatchRunner", started)


# ---- inputs --------------------------------------------------------------------------------------------------------
@pytest.mark.skipif(not hasattr(socket, "AF_UNIX"), reason="Unix sockets")
def test_device_or_socket_as_the_model_is_refused(tmp_path, capsys):
    """A character device (/dev/zero would be read until memory runs out) or a socket is no mesh file."""
    sock_path = tmp_path / "s.stl"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(sock_path))
        for model in [str(sock_path)] + (["/dev/null"] if os.path.exists("/dev/null") else []):
            assert main(["slice", model, "--backend", "numpy", "-o", str(tmp_path / "o.npz")]) == 2
            _one_line_error(capsys, f"{model}: not a regular file")
    finally:
        sock.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.stl"]


def test_3mf_without_a_model_part_says_so(tmp_path, capsys):
    path = tmp_path / "empty.3mf"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("[Content_Types].xml", "<Types/>")
    assert main(["slice", str(path), "--backend", "numpy", "-o", str(tmp_path / "o.npz")]) == 2
    _one_line_error(capsys, f"{path}: not a 3MF file", "no 3D model part")
    assert not (tmp_path / "o.npz").exists()


_THREE = "0 0 0\n1 0 0\n0 1 1\n"
_MODEL = ('<?xml version="1.0"?><model unit="millimeter" xmlns="http://schemas.microsoft.com/3dmanufacturing/core/'
          '2015/02"><resources><object id="1" type="model"><mesh><vertices><vertex x="0" y="0" z="0"/><vertex x="1" '
          'y="0" z="0"/><vertex x="0" y="1" z="1"/></vertices><triangles><triangle v1="0" v2="1" v3="7"/></triangles>'
          '</mesh></object></resources><build><item objectid="1"/></build></model>')


@pytest.mark.parametrize("name, data", [
    ("idx.obj", "v 0 0 0\nv 1 0 0\nv 0 1 1\nf 1 2 9\n"),
    ("idx.ply", "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                "element face 1\nproperty list uchar int vertex_indices\nend_header\n" + _THREE + "3 0 1 99\n"),
    ("idx.off", "OFF\n3 1 0\n" + _THREE + "3 0 1 50\n"),
    ("idx.3mf", None),
    ("bytes.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 \xff\xfe\nf 1 2 3\n"),
], ids=["obj-index", "ply-index", "off-index", "3mf-index", "obj-not-text"])
def test_malformed_trimesh_files_are_one_line_errors(tmp_path, capsys, name, data):
    """Faces naming vertices that do not exist, bytes that are no text: one line naming the file."""
    path = tmp_path / name
    if data is None:
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("3D/3dmodel.model", _MODEL)
    else:
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
    assert main(["slice", str(path), "--backend", "numpy", "-o", str(tmp_path / "o.npz")]) == 2
    line = _one_line_error(capsys, f"{path}: ")
    assert "cannot read" in line or "face names vertex" in line or "a vertex line that does not hold" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_binary_stl_declaring_billions_of_facets_is_refused(tmp_path, capsys):
    path = tmp_path / "huge.stl"
    path.write_bytes(bytes(80) + struct.pack("<I", 4_000_000_000) + bytes(150))
    assert main(["slice", str(path), "-o", str(tmp_path / "o.npz")]) == 2
    _one_line_error(capsys, f"{path}: truncated binary STL")


# ---- outputs: refused before any work -----------------------------------------------------------------------------
@pytest.mark.parametrize("args, words", [
    (["slice", "{cube}", "-o", "{tmp}/no/o.npz"], ["directory {tmp}/no does not exist"]),
    (["slice", "{cube}", "-o", "{tmp}/file.txt/o.npz"], ["file.txt is a file, not a directory"]),
    (["slice", "{cube}", "-o", "{tmp}/o.npz", "--report", "{tmp}"], ["{tmp}: is a folder"]),
    (["raster", "{cube}", "-o", "{tmp}/o.goo", "--report", "{tmp}/no/r.json"], ["{tmp}/no does not exist"]),
    (["check", "{cube}", "--json", "{tmp}/no/r.json"], ["{tmp}/no does not exist"]),
    (["view", "{cube}", "-o", "{tmp}/no/v.html"], ["{tmp}/no does not exist"]),
    (["batch", "{cube}", "-o", "{tmp}/out", "--report", "{tmp}"], ["{tmp}: is a folder"]),
])
def test_unwritable_outputs_are_refused_before_any_work(cube, tmp_path, capsys, no_work, args, words):
    (tmp_path / "file.txt").write_text("notes")
    fill = {"cube": cube, "tmp": tmp_path}
    assert main([a.format(**fill) for a in args]) == 2
    _one_line_error(capsys, *(w.format(**fill) for w in words))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]


@pytest.mark.parametrize("args", [
    ["slice", "{cube}", "-o", "{tmp}/o.npz", "--report", "{tmp}/o.npz"],
    ["raster", "{cube}", "-o", "{tmp}/o.goo", "--report", "{tmp}/../{name}/o.goo"],
])
def test_a_report_over_the_output_is_refused(cube, tmp_path, capsys, no_work, args):
    """--report naming -o's file would replace the archive just written by its JSON report."""
    assert main([a.format(cube=cube, tmp=tmp_path, name=tmp_path.name) for a in args]) == 2
    _one_line_error(capsys, "--report names the output itself")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args", [
    ["raster", "{cube}", "-o", "{tmp}/stack/", "--format", "png", "--job-name", "../evil"],
    ["raster", "{cube}", "-o", "{tmp}/o.sl1", "--job-name", "a\\b"],
    ["batch", "{cube}", "-o", "{tmp}/out", "--raster", "png", "--raster-opt", "job_name=../evil"],
])
def test_a_job_name_cannot_lead_out_of_the_output(cube, tmp_path, capsys, no_work, args):
    """A PNG stack's layers are <job name>NNNNN.png: '../evil' wrote them beside the stack's folder."""
    assert main([a.format(cube=cube, tmp=tmp_path) for a in args]) == 2
    _one_line_error(capsys, "job", "cannot hold '/'")
    assert list(tmp_path.iterdir()) == []


# ---- settings --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("args, flag", [
    (["raster", "{cube}", "-o", "{tmp}/o.goo", "-t", "5e-6"], "--thickness 5e-06 mm"),
    (["raster", "{cube}", "-o", "{tmp}/o.goo", "--first-layer", "1e-9"], "--first-layer 1e-09 mm"),
    (["raster", "{cube}", "-o", "{tmp}/o.goo", "--adaptive", "cusp", "--min-height", "1e-4"], "--min-height"),
    (["raster", "{cube}", "-o", "{tmp}/o.goo", "--adaptive", "roi", "--roi-ladder", "1,1e-5"], "--roi-ladder"),
    (["check", "{cube}", "-t", "1e-5"], "--thickness"),
    (["view", "{cube}", "--raster", "-t", "1e-5", "-o", "{tmp}/v.html"], "--thickness"),
    (["batch", "{cube}", "-o", "{tmp}/out", "--raster", "goo", "-t", "1e-5"], "--thickness"),
])
def test_absurdly_thin_resin_layers_are_refused_up_front(cube, tmp_path, capsys, no_work, args, flag):
    """-t 5e-6 on a 20 mm part: 4 million layers of a 4K display, hours of work, refused at once."""
    assert main([a.format(cube=cube, tmp=tmp_path) for a in args]) == 2
    _one_line_error(capsys, flag, "thinner than 0.001 mm")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, words", [
    (["--adaptive", "roi", "--roi-windows", "-1"], ["--roi-windows must be a whole number >= 0"]),
    (["--adaptive", "roi", "--roi-threshold", "nan"], ["--roi-threshold must be points per layer >= 0"]),
    (["--adaptive", "roi", "--roi-threshold", "-5"], ["--roi-threshold must be points per layer >= 0"]),
    (["--adaptive", "roi", "--roi-ladder", "1,1e-9"], ["--roi-ladder", "more than 5e7 layers"]),
    (["--adaptive", "cusp", "--min-height", "1e-9"], ["--min-height must be at least 5e-05 mm", "20 mm tall"]),
])
def test_adaptive_settings_out_of_range(cube, tmp_path, capsys, args, words):
    out = tmp_path / "o.npz"
    assert main(["slice", str(cube), "--backend", "numpy", *args, "-o", str(out)]) == 2
    _one_line_error(capsys, *words)
    assert not out.exists()


def test_bench_and_plot_refuse_settings_that_give_no_layers(cube, tmp_path, capsys):
    flat = tmp_path / "flat.stl"
    tri = [0, 0, 0, 10, 0, 0, 0, 10, 0]
    flat.write_bytes(bytes(80) + struct.pack("<I", 1) + struct.pack("<12fH", 0, 0, 1, *tri, 0))
    base = ["--backend", "numpy", "--repeat", "1"]
    assert main(["bench", str(cube), "-t", "0.5,100", *base]) == 2
    _one_line_error(capsys, f"{cube}: -t 100 mm gives no layers", "20 mm tall")
    assert main(["bench", str(cube), "-t", "0.5", "--ref-thickness", "100", *base]) == 2
    _one_line_error(capsys, f"{cube}: --ref-thickness 100 mm gives no layers")  # (it read as -t's)
    assert main(["bench", str(cube), "-t", "0.5", "--ref-thickness", "0", *base]) == 2  # 0 meant the default
    _one_line_error(capsys, "--ref-thickness must be a positive number of mm")
    assert main(["bench", str(flat), "--adaptive", "cusp", *base]) == 2
    _one_line_error(capsys, f"{flat}: the model is flat")
    assert main(["plot", str(cube), "-t", "100", "--backend", "numpy", "-o", str(tmp_path / "p")]) == 2
    _one_line_error(capsys, "-t 100 mm gives no layers")
    # a helper's sweep: named neither flag, or the wrong one; an item left out; a repeat that ran until killed
    for args, words in ((["-t", "5e-324"], "-t: layer thickness must be a positive number of mm (at least 1e-06)"),
                        (["-t", "1,,2"], "-t: an empty item in '1,,2'"),
                        (["-t", "0.5", "--ref-thickness", "inf"], "--ref-thickness must be a positive number of mm"),
                        (["-t", "0.5", "--repeat", "99999999999"], "--repeat must be from 1 to 1000")):
        assert main(["bench", str(cube), *args, "--backend", "numpy"]) == 2
        _one_line_error(capsys, words)
    assert not (tmp_path / "p").exists()  # not even an empty folder


def test_plot_layer_out_of_range_writes_no_plots(cube, tmp_path, capsys):
    assert main(["plot", str(cube), "-t", "1", "--backend", "numpy", "--layers", "99", "-o", str(tmp_path / "p")]) == 2
    _one_line_error(capsys, "--layers: [99] out of range (0..19)")
    assert not (tmp_path / "p").exists()


def test_view_mask_every_below_one_is_refused_without_raster(cube, tmp_path, capsys, no_work):
    assert main(["view", str(cube), "--mask-every", "-1", "-o", str(tmp_path / "v.html")]) == 2
    _one_line_error(capsys, "--mask-every must be >= 1")


# ---- interruptions ---------------------------------------------------------------------------------------------------
SLOW_WRITE = textwrap.dedent("""
    import sys, time
    import gpuslice.formats.svg as svg
    real = svg._svg_chunk
    def slow(*args, **kwargs):  # a long write: the signal lands while the temporary file is being written
        out = real(*args, **kwargs)
        time.sleep(0.3)
        return out
    svg._svg_chunk = slow
    from gpuslice.cli.main import exit_now, main
    exit_now(main(sys.argv[1:]))
""")


def _hangup_as_a_terminal_has_it() -> None:
    """(In the child, before its program starts) SIGHUP at its default action: a test run under ``nohup`` passes it
    on ignored, and gpuslice then keeps it ignored, as it should."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")
@pytest.mark.parametrize("signame", ["SIGTERM", "SIGHUP"])
def test_terminate_while_writing_leaves_nothing(tmp_path, signame):
    """``kill`` / ``timeout`` (SIGTERM) or a closed terminal (SIGHUP) while the output is written: the temporary file
    is removed, one line says so, and the exit status is 128 + the signal's number."""
    import gpuslice.formats.svg as svg

    assert hasattr(svg, "_svg_chunk"), "formats.svg._svg_chunk is gone: adapt the slow writer of this test"
    stl = tmp_path / "torus.stl"
    assert main(["shape", "torus", "-o", str(stl)]) == 0
    proc = subprocess.Popen([sys.executable, "-c", SLOW_WRITE, "slice", str(stl), "-t", "0.005", "--backend", "numpy",
                             "-o", str(tmp_path / "t.svg"), "-q"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_hangup_as_a_terminal_has_it)
    deadline = time.monotonic() + 120
    while not [p for p in os.listdir(tmp_path) if ".tmp-" in p]:
        assert proc.poll() is None, f"finished before writing started: {proc.communicate()}"
        assert time.monotonic() < deadline, "the temporary output never appeared"
        time.sleep(0.01)
    sig = getattr(signal, signame)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, (proc.returncode, err)
    assert err.strip() == f"gpuslice: terminated ({signame})" and "Traceback" not in err
    assert sorted(os.listdir(tmp_path)) == ["torus.stl"]


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")
def test_terminate_handling_keeps_nohup_and_restores_handlers():
    """SIGHUP ignored (``nohup``) stays ignored; the handlers before the command come back after it."""
    cli_main = sys.modules["gpuslice.cli.main"]
    old_hup = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    old_term = signal.getsignal(signal.SIGTERM)
    try:
        with cli_main._stop_on_terminate():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            if old_term == signal.SIG_DFL:
                assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, signal.SIG_IGN)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) == old_term
    finally:
        signal.signal(signal.SIGHUP, old_hup)


# ---- follow-ups of the sweep (outside the command-line modules) -----------------------------------------------------
@pytest.mark.parametrize("args", [
    ["slice", "{cube}", "-t", "100", "-o", "{tmp}/o.svg"],
    ["check", "{cube}", "-t", "100", "--json", "{tmp}/r.json"],
    ["view", "{cube}", "-t", "100", "-o", "{tmp}/v.html"],
    ["slice", "{cube}", "-t", "100", "--report", "{tmp}/r.json"],
    ["slice", "{cube}", "-t", "100"],
])
def test_a_model_thinner_than_one_layer_writes_nothing(cube, tmp_path, capsys, args):
    """`raster` already refused it; `slice`, `check` and `view` wrote an empty file (or report) with exit 0, and
    `slice` with only --report, or with no output (its summary: "0 layers"), still did."""
    assert main([a.format(cube=cube, tmp=tmp_path) for a in args]) == 2
    _one_line_error(capsys, str(cube), "no layers to write")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.skipif(sys.platform == "win32", reason="file names of arbitrary bytes")
@pytest.mark.parametrize("suffix", [".goo", ".sl1"])
def test_a_model_file_name_that_is_not_utf8(cube, tmp_path, suffix):
    """Its name's stray bytes (kept by Python as surrogates) broke the archives' UTF-8 name fields (internal error)."""
    model = os.path.join(os.fsdecode(bytes(tmp_path)), os.fsdecode(b"\xfe-part.stl"))
    with open(cube, "rb") as src, open(model, "wb") as dst:
        dst.write(src.read())
    out = tmp_path / f"o{suffix}"
    assert main(["raster", model, "-o", str(out), "-q", "--no-progress", "--resolution", "600x600"]) == 0
    assert out.stat().st_size > 0


def test_a_pixel_too_large_for_any_display_is_refused(cube, tmp_path, capsys, no_work):
    """--pixel 1e300 overflowed the formats' float32 header fields (internal error after the slicing)."""
    assert main(["raster", str(cube), "-o", str(tmp_path / "o.goo"), "--pixel", "1e300"]) == 2
    _one_line_error(capsys, "--pixel", "up to 1000")


@pytest.mark.parametrize("pixel", ["5e-324", "1e-9"])
def test_a_pixel_too_small_for_arithmetic_is_refused(cube, tmp_path, capsys, no_work, pixel):
    """--pixel 5e-324 (a denormal) made 1 / pixel infinite: numpy's 'invalid value' warning, and with a preset of
    that pitch the archive was written for a display of no width."""
    assert main(["raster", str(cube), "-o", str(tmp_path / "o.goo"), "--pixel", pixel]) == 2
    _one_line_error(capsys, "--pixel", "from 1e-06")


@pytest.mark.parametrize("name", ["../evil", "a\\b", "x/y", ""])
def test_the_library_refuses_a_job_name_that_leads_out_of_the_output(name):
    """The rule lives in ResinOptions, so library callers get it too (the command line maps it to --job-name)."""
    from gpuslice.errors import ParameterError
    from gpuslice.raster.spec import ResinOptions

    with pytest.raises(ParameterError, match="job name is a file name prefix"):
        ResinOptions(job_name=name)
    assert ResinOptions(job_name="part-1").job_name == "part-1"


def _under_the_command_s_handlers(body: str) -> subprocess.CompletedProcess:
    """``body`` (Python, indented as the block of a ``with``; ``os``, ``signal``, ``time`` and ``cli_main`` at hand)
    run in a child process inside the command line's signal handling (``_stop_on_terminate``)."""
    code = ("import importlib, os, signal, time\ncli_main = importlib.import_module('gpuslice.cli.main')\n"
            "with cli_main._stop_on_terminate():\n" + textwrap.indent(textwrap.dedent(body), "    "))
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")
def test_a_second_terminate_while_unwinding_ends_the_process():
    """The first SIGTERM unwinds the command (its clean-up runs); a second one does not wait for that clean-up (a
    thread stuck in a driver call would hold it forever): the process ends as the signal asks."""
    proc = _under_the_command_s_handlers("""
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
        except cli_main.Terminated:
            print("first", flush=True)
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
            print("survived", flush=True)
    """)
    assert proc.returncode == -signal.SIGTERM and proc.stdout.split() == ["first"], (proc.returncode, proc.stdout)


def test_a_second_ctrl_c_lets_the_clean_up_finish_and_a_third_ends_the_process():
    """Two SIGINTs a few ms apart (``timeout -s INT`` sends one to the process and one to its group; a user presses
    twice): the second interrupted the first's clean-up (a traceback from a thread's wait after "gpuslice:
    interrupted", 6 runs of 28; an empty temporary file left, 2 of 60). It is let go now; a third ends the process."""
    proc = _under_the_command_s_handlers("""
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            print("first", cli_main._INTERRUPTED.is_set(), flush=True)
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(50):
                time.sleep(0.002)
            print("cleaned", flush=True)
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
            print("survived", flush=True)
    """)
    assert proc.returncode == -signal.SIGINT, (proc.returncode, proc.stdout, proc.stderr)
    assert proc.stdout.split() == ["first", "True", "cleaned"], proc.stdout


def test_batch_terminated_exits_with_the_signal(cube, tmp_path, capsys, monkeypatch):
    """`batch` caught the Terminated interrupt as Ctrl-C's and exited 130 "interrupted"; now 143 / "terminated"."""
    import gpuslice.batch

    cli_main = sys.modules["gpuslice.cli.main"]

    def run(self, *args, **kwargs):
        raise cli_main.Terminated(signal.SIGTERM)

    monkeypatch.setattr(gpuslice.batch.BatchRunner, "run", run)
    assert main(["batch", str(cube), "-o", str(tmp_path / "out"), "-q", "-j", "0"]) == 128 + signal.SIGTERM
    err = capsys.readouterr().err.strip()
    assert err.startswith("gpuslice: terminated (SIGTERM): 0 done") and "Traceback" not in err


def test_a_report_inside_the_output_folder_the_command_makes(cube, tmp_path):
    """`batch -o out --report out/r.json`: the folder does not exist yet, but the command makes it before the report
    is written (the sweep's first check refused them)."""
    out = tmp_path / "out"
    assert main(["batch", str(cube), "-o", str(out), "-q", "-j", "0", "--report", str(out / "r.json")]) == 0
    assert (out / "r.json").stat().st_size > 0


def test_a_png_stack_folder_holding_other_files_is_refused_before_slicing(cube, tmp_path, capsys, monkeypatch):
    """The refusal came from the writer, after all the slicing (minutes on a big job): an audit of the outputs."""
    import gpuslice.pipeline

    out = tmp_path / "stack"
    out.mkdir()
    (out / "keep.txt").write_text("mine")

    def no_slicing(*args, **kwargs):
        raise AssertionError("sliced before the refusal")

    monkeypatch.setattr(gpuslice.pipeline, "_slice", no_slicing)
    assert main(["raster", str(cube), "-o", f"{out}/", "-q", "--no-progress", "--resolution", "600x600"]) == 2
    _one_line_error(capsys, "directory holds other files (keep.txt, ...)")
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]


@pytest.mark.parametrize("name", ["r.json", "cube00000.png"])
def test_a_report_inside_a_png_stack_is_refused(cube, tmp_path, capsys, name):
    """`raster -o stack/ --report stack/cube00000.png` replaced layer 0 with the JSON report, exit 0 (an audit of
    the outputs); `--report stack/r.json` made the next run refuse the folder, which held another file."""
    out = tmp_path / "stack"
    assert main(["raster", str(cube), "-o", f"{out}/", "-q", "--no-progress", "--resolution", "600x600",
                 "--report", str(out / name)]) == 2
    _one_line_error(capsys, str(out / name), "which holds only the PNG stack's layers")
    assert not out.exists()


@pytest.mark.skipif(sys.platform == "win32", reason="file names of arbitrary bytes")
def test_a_non_utf8_name_in_reports_views_and_job_names(cube, tmp_path):
    """The model's stray bytes (or a job name's) became encoding errors in the JSON report, the viewer page and the
    GOO/SL1 name fields: they are written as U+FFFD now."""
    import json

    model = os.path.join(os.fsdecode(bytes(tmp_path)), os.fsdecode(b"\xfe-part.stl"))
    with open(cube, "rb") as src, open(model, "wb") as dst:
        dst.write(src.read())
    assert main(["slice", model, "-o", str(tmp_path / "s.svg"), "--report", str(tmp_path / "r.json"), "-q"]) == 0
    report = json.loads((tmp_path / "r.json").read_text(encoding="utf-8"))
    assert os.path.basename(report["file"]) == "\ufffd-part.stl"
    assert main(["view", model, "-o", str(tmp_path / "v.html")]) == 0
    assert "\ufffd-part" in (tmp_path / "v.html").read_text(encoding="utf-8")
    for suffix in (".goo", ".sl1"):
        assert main(["raster", str(cube), "-o", str(tmp_path / f"j{suffix}"), "-q", "--no-progress",
                     "--resolution", "600x600", "--job-name", os.fsdecode(b"x\xffy")]) == 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's struct sigaction")
def test_ctrl_c_stays_python_s_after_the_opencl_driver_loaded():
    """PoCL's LLVM put its own SIGINT handler over Python's (SA_RESETHAND: the default action while it passes a signal
    on), so two SIGINTs a few ms apart killed the process by the signal, with no word and an output's temporary file
    left (a review: `timeout -s INT` on `raster`, 2 runs in 60; killpg twice, 4 in 16). The device module puts
    Python's handlers back: no handler with SA_RESETHAND for SIGINT, SIGTERM or SIGHUP once a device is made."""
    code = textwrap.dedent("""
        import ctypes, signal
        class Sigaction(ctypes.Structure):  # glibc's struct sigaction on Linux
            _fields_ = [("handler", ctypes.c_void_p), ("mask", ctypes.c_ulong * 16), ("flags", ctypes.c_int),
                        ("restorer", ctypes.c_void_p)]
        libc = ctypes.CDLL(None, use_errno=True)
        def flags(sig):
            old = Sigaction()
            assert libc.sigaction(sig, None, ctypes.byref(old)) == 0
            return old.flags & 0xFFFFFFFF
        signal.signal(signal.SIGINT, signal.default_int_handler)  # (as Python has it, whatever the test runner's)
        signal.signal(signal.SIGTERM, lambda *a: None)  # (a program's own: put back too)
        from gpuslice.device import get_device
        get_device()
        print(*(flags(s) & 0x80000000 for s in (signal.SIGINT, signal.SIGTERM)))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["0", "0"], proc.stdout
