"""Command-line refusals found by an audit of the commands (fifteenth session)."""

from __future__ import annotations

from gpuslice.cli import main
from gpuslice.mesh import shapes


def test_a_report_path_ending_in_a_slash_is_a_folder(tmp_path, capsys):
    """`--report newdir/` wrote a file named newdir: refused, as an existing folder is."""
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    report = str(tmp_path / "new") + "/"
    assert main(["slice", str(stl), "-t", "1", "-o", str(tmp_path / "x.npz"), "--report", report]) == 2
    assert "is a folder; name the file to write" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.stl"]
    # `slice -o newdir/` said "unknown output format ''" (an audit of the outputs, twenty-third session)
    assert main(["slice", str(stl), "-t", "1", "-o", report]) == 2
    assert "new/: is a folder; name the file to write" in capsys.readouterr().err


def test_shape_writes_stl_only(tmp_path, capsys):
    """`shape cube -o c.obj` wrote STL bytes under an OBJ name, which nothing could read back."""
    assert main(["shape", "cube", "-o", str(tmp_path / "c.obj")]) == 2
    assert "shape writes binary STL" in capsys.readouterr().err and not list(tmp_path.iterdir())
    assert main(["shape", "cube", "-o", str(tmp_path / "c.STL")]) == 0


def test_a_writers_refusal_names_the_file(tmp_path, capsys):
    """A contour writer's own refusal (coordinates beyond what it writes) names the output, as every error does."""
    import numpy as np

    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.errors import ParameterError
    from gpuslice.formats import export

    res = slice_mesh(mesh_from_triangles(shapes.box() * 1e8), thickness=4e8, backend="numpy")
    out = tmp_path / "big.svg"
    try:
        export(res, out)
    except ParameterError as exc:
        assert str(exc).startswith(f"{out}: ") and "too large" in str(exc)
    else:
        raise AssertionError("expected a refusal")
    assert np.isfinite(res.points).all()


def test_mean_cusp_of_slanted_facets_without_area_is_zero_not_nan():
    """A mesh whose only slanted facets have no area (a sliver) gave mean_cusp_mm NaN: invalid JSON in --report."""
    import json
    from types import SimpleNamespace

    import numpy as np

    from gpuslice.bench.quality import mean_cusp

    verts = np.array([[0, 0, 0], [1, 0, 1], [2, 0, 2]], np.float32)  # collinear: no area, but it rises
    mesh = SimpleNamespace(vertices=verts, faces=np.array([[0, 1, 2]]), height=2.0)
    schedule = SimpleNamespace(thickness=np.full(20, 0.1), z=(np.arange(20) + 0.5) * 0.1)
    slopes = (np.array([0.0]), np.array([2.0]), np.array([0.5]))
    value = mean_cusp(mesh, schedule, slopes=slopes)
    assert value == 0.0 and json.loads(json.dumps({"mean_cusp_mm": value})) == {"mean_cusp_mm": 0.0}


def test_an_unwritable_output_folder_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    """A read-only destination failed only when the writing started, after all the slicing (an audit of the
    outputs). The folder is made unwritable here by os.access's answer (the tests may run as root)."""
    import os

    import gpuslice.pipeline

    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if str(p) == str(ro) and mode & os.W_OK
                        else real(p, mode, **kw))
    monkeypatch.setattr(gpuslice.pipeline, "run_job", lambda *a, **k: (_ for _ in ()).throw(AssertionError("work")))
    for args in (["slice", str(stl), "-t", "1", "-o", str(ro / "x.svg")],
                 ["raster", str(stl), "-t", "1", "--resolution", "400x300", "-o", str(ro / "x.goo")],
                 ["slice", str(stl), "-t", "1", "-o", str(tmp_path / "x.svg"), "--report", str(ro / "r.json")],
                 ["batch", str(stl), "-t", "1", "-o", str(ro), "-j", "0"]):
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert f"directory {ro} is not writable" in err, err
    assert not list(ro.iterdir())


def test_review_wording_of_three_errors(tmp_path, capsys):
    """A review's wording (thirty-first session): a missing result named "not a gpuslice result ([Errno 2] ...)",
    a read-only model given as the output was told to be made writable, and `-o o` was "unknown output format ''"."""
    stl = tmp_path / "cube.stl"
    shapes.write_stl(shapes.box(), stl)
    assert main(["view", str(tmp_path / "missing.npz"), "-o", str(tmp_path / "v.html")]) == 2
    assert capsys.readouterr().err.strip() == f"gpuslice: error: {tmp_path / 'missing.npz'}: no such file"
    stl.chmod(0o444)
    try:
        assert main(["slice", str(stl), "--format", "svg", "-o", str(stl)]) == 2
        err = capsys.readouterr().err.strip()
        assert "is the model" in err and "itself" in err and "write-protected" not in err, err
    finally:
        stl.chmod(0o644)
    assert main(["slice", str(stl), "-t", "1", "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "no suffix to say the output format" in err and len(err.splitlines()) == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cube.stl"]
