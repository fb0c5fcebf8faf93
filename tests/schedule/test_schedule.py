"""Layer schedules: where layers are cut and how they tile the object."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import ParameterError, from_z, uniform


def test_uniform_mid_layer_planes_below_the_top():
    s = uniform(20.0, 0.3)
    # Slic3r and CuraEngine: z_i = (i + 0.5) h, kept while below the top: 67 layers for 20 mm at 0.3 mm
    assert len(s) == 67
    np.testing.assert_allclose(s.z, (np.arange(67) + 0.5) * 0.3)
    assert s.z[-1] < 20.0 < s.z[-1] + 0.3
    np.testing.assert_allclose(s.bottom, np.arange(67) * 0.3, atol=1e-12)
    np.testing.assert_allclose(s.top - s.bottom, s.thickness)


def test_first_layer_and_tiling():
    s = uniform(2.0, 0.2, first_layer=0.3)
    assert s.thickness[0] == 0.3 and np.all(s.thickness[1:] == 0.2)
    assert s.z[0] == pytest.approx(0.15) and s.z[1] == pytest.approx(0.4)
    np.testing.assert_allclose(s.bottom[1:], 0.3 + 0.2 * np.arange(len(s) - 1))
    # every plane lies inside its own slab
    assert np.all((s.z > s.bottom) & (s.z < s.top))
    # a whole-number thickness (a Python int) keeps its first layer: it was cut to the int (1.5 mm became 1)
    s = uniform(5.0, 1, first_layer=1.5)
    np.testing.assert_array_equal(s.thickness, [1.5, 1.0, 1.0, 1.0])  # (the plane at 5.0 is the top: none)
    assert s.thickness.dtype == np.float64 and s.z[0] == 0.75 and s.z[1] == 2.0
    assert np.array_equal(uniform(3.0, 1, first_layer=0.3).thickness, [0.3, 1.0, 1.0, 1.0])  # (was an error)


def test_paper_planes():
    s = uniform(1.0, 0.25, z_mode="paper")
    np.testing.assert_allclose(s.z, [0.25, 0.5, 0.75])
    np.testing.assert_allclose(s.top, s.z)  # cut at the top of each layer


def test_custom_z_thicknesses():
    s = from_z([0.1, 0.3, 0.4])
    np.testing.assert_allclose(s.thickness, [0.2, 0.15, 0.1])
    s = from_z([0.05, 0.15], 0.1)
    np.testing.assert_allclose(s.thickness, [0.1, 0.1])


def test_planes_from_the_bed_up_keep_from_z_slabs():
    """``from_z`` gives a plane at the bed the slab around it ([-0.25, 0.25] for planes 0.5 mm apart); the exports'
    slabs (``bottom``) tiled such planes from the bed instead, each plane on its slab's bottom edge, where a section
    (the limit from below) belongs to the layer under it: layer 0 came out empty and every slab shifted."""
    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.mesh.shapes import box

    s = from_z(np.arange(0.0, 6.0, 0.5))
    np.testing.assert_allclose(s.bottom, np.arange(0.0, 6.0, 0.5) - 0.25)
    r = slice_mesh(mesh_from_triangles(box((0, 0, 0), (10, 10, 6))), schedule=s, backend="numpy")
    np.testing.assert_allclose(r.bottom, s.bottom)
    # planes inside their slabs from the bed up still tile from it (paper planes on their slabs' tops)
    np.testing.assert_allclose(from_z([0.5, 1.0, 1.5], 0.5).bottom, [0.0, 0.5, 1.0])


def test_schedule_and_z_together_are_refused():
    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.mesh.shapes import box

    with pytest.raises(ParameterError, match="z= gives planes"):
        slice_mesh(mesh_from_triangles(box()), schedule=uniform(20.0, 0.1), z=np.array([1.0]), backend="numpy")


@pytest.mark.parametrize("z, t", [([0.2, 0.1], None), ([0.1, 0.1], None), ([0.1, np.nan], None), ([0.1], [-1.0])])
def test_bad_schedules_raise(z, t):
    with pytest.raises(ParameterError):
        from_z(z, t)


@pytest.mark.parametrize("kw", [dict(thickness=0), dict(thickness=-0.1), dict(thickness=0.1, z_mode="x"),
                                dict(thickness=0.1, first_layer=0)])
def test_bad_uniform_raise(kw):
    with pytest.raises(ParameterError):
        uniform(10.0, **kw)


def test_a_plane_on_the_float32_top_is_dropped_whatever_the_rounding():
    # the planes are cut in float32 and a mesh's top is float32: "below the top" compared there. In float64 a plane
    # i·h that rounds onto the top was kept or dropped by the rounding (paper mode: a 0.4 and a 0.5 mm box both gave
    # 4 layers, 14 of 30 such heights kept the plane; a helper's probe)
    for k in range(1, 31):
        top = float(np.float32(k * 0.1))  # a box k·0.1 mm tall, as Mesh.height holds it
        assert len(uniform(top, 0.1, z_mode="paper")) == k - 1, k
        top = float(np.float32((2 * k + 1) * 0.05))  # mid mode: the plane (k + 0.5)·0.1 lands on the top
        assert len(uniform(top, 0.1)) == k, k


@pytest.mark.parametrize("kw", [{"thickness": 1e300}, {"thickness": 0.1, "first_layer": 1e300},
                                {"thickness": 1e300, "z_mode": "paper"}])
def test_a_layer_thicker_than_float32_holds_makes_no_plane_and_no_warning(kw):
    """-t 1e300 (or --first-layer 1e300) printed numpy's "overflow encountered in cast" before the clean "no layers"
    error: its plane is beyond float32, so above any model's top."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sched = uniform(5.0, **kw)
    assert len(sched.z) == 0  # (every plane lies above the 5 mm top: the command says there are no layers)
