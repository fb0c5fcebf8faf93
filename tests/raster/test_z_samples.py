"""Anti-aliasing in Z (``--z-samples K``): each layer's grey is that of its mean coverage over K sub-planes of its
slab; the sub-layers' runs are summed per row (gpuslice.raster.runs, z_samples=K)."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.cli import main
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec, coverage_numpy, layer_edges
from gpuslice.raster.coverage import choose_backend
from gpuslice.raster.edges import z_sample_planes
from gpuslice.raster.runs import layer_runs

SPEC = RasterSpec(resolution=(500, 500), pixel=0.1)


def _masks(res, spec, k, backend, device=None):
    return layer_runs(res, spec, backend=backend, device=device, z_samples=k).to_masks()


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_vertical_walls_give_the_same_greys(device, gamma):
    """A prism's K sub-planes cut the same polygon: K samples give the single plane's greys, but where the covered
    fraction c of a pixel lies within one 16.16 unit of a grey's edge (256·c within 1/256 of a whole number): each
    sub-plane's polygon has other float32 points along the walls' diagonal edges, so its pieces are rounded at other
    places (exact equality held here only by chance while each cell's share was rounded apart)."""
    import shapely
    from shapely import affinity

    from gpuslice.raster.edges import result_bounds

    spec = RasterSpec(resolution=SPEC.resolution, pixel=SPEC.pixel, gamma=gamma)
    poly = np.array([[0, 0], [30.3, 1.7], [24.1, 22.9], [3.3, 17.2]])
    res = slice_mesh(mesh_from_triangles(shapes.prism(poly, 0.0, 2.0)), thickness=0.5, backend="numpy")
    z, th = z_sample_planes(res, 4)
    sub = slice_mesh(mesh_from_triangles(shapes.prism(poly, 0.0, 2.0)), z=z, layer_thickness=th, backend="numpy")
    one = _masks(res, spec, 1, "opencl", device)
    a = spec.affine(result_bounds(res))
    pixels = [affinity.affine_transform(g, [a[0, 0], a[0, 1], a[1, 0], a[1, 1], a[0, 2], a[1, 2]])
              for g in res.to_shapely()]
    for backend in ("numpy", "opencl"):
        four = _masks(sub, spec, 4, backend, device)
        diff = np.argwhere(four != one)
        assert len(diff) <= 8, (backend, len(diff))
        for lay, r, c in diff.tolist():
            assert abs(int(four[lay, r, c]) - int(one[lay, r, c])) <= (1 if gamma else 255)
            k = 256 * shapely.area(shapely.intersection(shapely.box(c, r, c + 1, r + 1), pixels[lay]))
            assert abs(k - round(k)) < 1 / 256 and (gamma or round(k) == 128), (backend, lay, r, c, k)
    assert one.max() == 255 and 0 < (one[0] == 255).sum()


def test_sloped_walls_average_the_sub_planes(device):
    """A cone: OpenCL equals the numpy twin, and each grey is the mean of the K sub-planes' coverage (within the
    floor of each sub-plane's independent float64 coverage, `coverage_numpy`, and the twins' float32 rounding)."""
    mesh = mesh_from_triangles(shapes.cone(radius=20.0, height=10.0, n=64))
    res = slice_mesh(mesh, thickness=1.0, backend="numpy")
    k = 4
    z, th = z_sample_planes(res, k)
    np.testing.assert_allclose(z[:4], [0.125, 0.375, 0.625, 0.875])
    sub = slice_mesh(mesh, z=z, layer_thickness=th, backend="numpy")
    got = _masks(sub, SPEC, k, "opencl", device)
    assert np.array_equal(got, _masks(sub, SPEC, k, "numpy"))
    bounds = (-20.0, -20.0, 20.0, 20.0)
    le = layer_edges(sub, SPEC, bounds)
    ident = np.arange(256, dtype=np.uint8)  # the floor of 256 x coverage of each sub-plane
    want = np.zeros((res.n_layers, *SPEC.shape))
    for i in range(sub.n_layers):
        r0, c0, h, w = (int(v) for v in le.tiles[i])
        e = le.edges[le.edge_offsets[i] : le.edge_offsets[i + 1]]
        want[i // k, r0 : r0 + h, c0 : c0 + w] += coverage_numpy(e, h, w, ident) / k
    got = layer_runs(sub, SPEC, backend="opencl", device=device, z_samples=k, bounds=bounds).to_masks()
    assert np.abs(got.astype(float) - want).max() <= 2.0
    single = layer_runs(res, SPEC, backend="opencl", device=device, bounds=bounds).to_masks()
    assert (got != single).sum() > 100  # the slope shows: greys differ from the middle plane's at the edges


def test_cli_z_samples(tmp_path, device, capsys):
    stl = tmp_path / "cone.stl"
    shapes.write_stl(shapes.cone(radius=20.0, height=10.0, n=64), stl)
    args = ["raster", str(stl), "-t", "1", "--resolution", "500x500", "--pixel", "0.1", "-q", "--no-progress"]
    assert main([*args, "-o", f"{tmp_path / 'one'}/"]) == 0
    assert main([*args, "-o", f"{tmp_path / 'four'}/", "--z-samples", "4"]) == 0
    from PIL import Image

    one = np.stack([np.asarray(Image.open(p)) for p in sorted((tmp_path / "one").glob("*.png"))])
    four = np.stack([np.asarray(Image.open(p)) for p in sorted((tmp_path / "four").glob("*.png"))])
    assert one.shape == four.shape == (10, 500, 500) and not np.array_equal(one, four)
    capsys.readouterr()
    assert main([*args, "-o", f"{tmp_path / 'gl'}/", "--z-samples", "4", "--raster-backend", "numpy"]) == 2
    err = capsys.readouterr().err
    assert "--z-samples needs the OpenCL rasteriser" in err and len(err.strip().splitlines()) == 1


def test_auto_backend_is_the_runs_without_probing_gl(tmp_path, device, monkeypatch):
    """`auto` means the runs (OpenCL) and never probes EGL (0.1 s of start-up); z samples work with it."""
    import gpuslice.raster.gl as gl

    def probe(*a, **k):
        raise AssertionError("auto probed GL")

    monkeypatch.setattr(gl, "gl_info", probe)
    assert choose_backend("auto") == "opencl"
    stl = tmp_path / "cone.stl"
    shapes.write_stl(shapes.cone(radius=20.0, height=10.0, n=64), stl)
    args = ["raster", str(stl), "-t", "1", "--resolution", "500x500", "--pixel", "0.1", "-q", "--no-progress"]
    assert main([*args, "-o", f"{tmp_path / 'four'}/", "--z-samples", "4"]) == 0
    assert len(list((tmp_path / "four").glob("*.png"))) == 10


def test_z_samples_stream_in_chunks_of_layers(tmp_path, device, monkeypatch):
    """The sub-planes are sliced a chunk of layers at a time (memory set by the chunk): any chunk size gives the
    same archive."""
    import gpuslice.raster.z_sampled as z_sampled

    stl = tmp_path / "cone.stl"
    shapes.write_stl(shapes.cone(radius=20.0, height=10.0, n=64), stl)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    args = ["raster", str(stl), "-t", "0.5", "--resolution", "500x500", "--pixel", "0.1", "-q", "--no-progress",
            "--z-samples", "3"]
    outs = []
    for chunk in (1000, 3):
        monkeypatch.setattr(z_sampled, "Z_SAMPLE_CHUNK", chunk)
        out = tmp_path / f"c{chunk}.sl1"
        assert main([*args, "-o", str(out)]) == 0
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]
