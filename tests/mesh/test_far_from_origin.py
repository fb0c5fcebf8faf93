"""A model far from the origin in X/Y (a helper's audit: a float64 cylinder at x = 1e6 mm sliced 0.29 % off in area,
and its resin greys changed by up to 229 levels, with nothing said): ``center`` moves it to the origin in float64
before the one rounding to float32; a resin job, which centres the part on the display anyway, does so by itself
beyond :data:`gpuslice.mesh.mesh.FAR_XY_MM`; ``slice``, ``check`` and ``view`` say when they keep it far."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from PIL import Image

from gpuslice import load_mesh, slice_mesh
from gpuslice.cli import main
from gpuslice.mesh.mesh import FAR_XY_MM

SIDES = 64
EXACT = 0.5 * SIDES * 25.0 * np.sin(2 * np.pi / SIDES)  # the 64-gon of radius 5


def cylinder(x: float) -> trimesh.Trimesh:
    c = trimesh.creation.cylinder(radius=5, height=10, sections=SIDES)
    c.apply_translation([x, -0.5 * x, 5.0])
    return c


@pytest.mark.parametrize("x", [1e5, 1e6])
def test_center_keeps_a_far_float64_model_exact(x):
    far = cylinder(x)
    plain = slice_mesh(load_mesh(far), thickness=1.0, backend="numpy")
    assert abs(plain.area[0] / EXACT - 1) > 1e-5  # what float32 at 1e5-1e6 mm costs
    mesh = load_mesh(far, center=True)
    assert mesh.offset[0] == pytest.approx(-x) and mesh.offset[1] == pytest.approx(0.5 * x)
    assert np.abs(mesh.vertices[:, :2]).max() <= 5.0 + 1e-6
    res = slice_mesh(mesh, thickness=1.0, backend="numpy")
    np.testing.assert_allclose(res.area, EXACT, rtol=1e-7)
    assert load_mesh(far, center=None).offset == mesh.offset  # beyond FAR_XY_MM: centred when asked "if far"
    near = load_mesh(cylinder(FAR_XY_MM / 4), center=None)
    assert near.offset[:2] == (0.0, 0.0)


def test_slice_warns_of_a_far_model_and_center_quiets_it(tmp_path, capsys):
    path = tmp_path / "far.obj"
    cylinder(1e6).export(path)
    assert main(["slice", str(path), "-t", "1", "-q"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"gpuslice: warning: {path}: its X/Y reach 1e+06 mm from the origin, "
                                               "where float32 coordinates lie 0.062 mm apart")
    assert main(["slice", str(path), "-t", "1", "-q", "--center"]) == 0
    assert capsys.readouterr().err == ""
    near = tmp_path / "near.obj"
    cylinder(0.0).export(near)
    assert main(["slice", str(near), "-t", "1", "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_a_resin_job_centres_a_far_model_itself(tmp_path):
    """The same cylinder at the origin and at 1e6 mm: the same greys (before: up to 227 levels apart)."""
    stacks = []
    for x in (0.0, 1e6):
        path = tmp_path / f"c{int(x)}.obj"
        cylinder(x).export(path)
        out = tmp_path / f"p{int(x)}"
        assert main(["raster", str(path), "--resolution", "400x300", "--pixel", "0.05", "-t", "0.5", "-q",
                     "--no-progress", "-o", f"{out}/"]) == 0
        stacks.append([np.asarray(Image.open(p)) for p in sorted(out.glob("*.png"))])
    assert len(stacks[0]) == len(stacks[1]) == 20
    for a, b in zip(*stacks, strict=True):
        np.testing.assert_array_equal(a, b)


def test_center_and_keep_xy_are_refused_together(tmp_path, capsys):
    """--keep-xy places the model by its own X/Y, which --center moves (a review: accepted, and a later error called
    the centred coordinates the model's own)."""
    path = tmp_path / "c.obj"
    cylinder(0.0).export(path)
    assert main(["raster", str(path), "--center", "--keep-xy", "--resolution", "400x300", "--pixel", "0.05", "-q",
                 "--no-progress", "-o", str(tmp_path / "x.goo")]) == 2
    assert "--center moves the model's X/Y to the origin, and --keep-xy" in capsys.readouterr().err
    assert not (tmp_path / "x.goo").exists()
