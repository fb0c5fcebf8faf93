"""The device's screen for simple loops (``simple_loops`` in ``kernels/walk.cl``) and the nesting that trusts it.

Nesting runs GEOS's validity test only on the loops the screen cannot prove simple, so the screen must never clear
a loop that crosses or touches itself; and it must clear the ordinary ones, or nothing is gained. Loops here are
built in the test: shapes simple by construction (convex, star-shaped with distinct angles, staircases with
horizontal and vertical edges, combs with many monotone chains), shapes that cross or touch themselves, and
random polygons judged by GEOS (shapely) as the oracle.
"""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_arrays, mesh_from_triangles, slice_mesh
from gpuslice.mesh import shapes as S
from gpuslice.slicing.chain import chain_segments
from gpuslice.slicing.crossings import compute_crossings, crossings_numpy
from gpuslice.slicing.nest import _self_crossing_loops
from gpuslice.slicing.rings import _polygons

shapely = pytest.importorskip("shapely")


def pack(loops):
    """(points float32 (P, 2), offsets (R + 1,)) of a list of (n, 2) arrays."""
    offsets = np.zeros(len(loops) + 1, dtype=np.int64)
    np.cumsum([len(p) for p in loops], out=offsets[1:])
    return np.concatenate(loops).astype(np.float32), offsets


def screen(device, loops):
    from gpuslice.slicing.walk import chain_kernels

    points, offsets = pack(loops)
    got = chain_kernels(device).simple_loops(points, offsets)
    if got is None:
        pytest.skip(f"{device.name} has no float64: no screen")
    return got


def ngon(n, r=10.0, c=(0.0, 0.0), phase=0.1):
    t = phase + 2 * np.pi * np.arange(n) / n
    return np.stack([c[0] + r * np.cos(t), c[1] + r * np.sin(t)], axis=1)


def star(n, r0=4.0, r1=10.0):
    t = 2 * np.pi * np.arange(2 * n) / (2 * n)
    r = np.where(np.arange(2 * n) % 2 == 0, r1, r0)
    return np.stack([r * np.cos(t), r * np.sin(t)], axis=1)


def staircase(steps):
    """A rectilinear staircase (horizontal and vertical edges only), counter-clockwise."""
    pts = [(0.0, 0.0), (float(steps), 0.0)]
    for k in range(steps, 0, -1):
        pts += [(float(k), float(steps - k + 1)), (float(k - 1), float(steps - k + 1))]
    return np.array(pts[:-1])


def comb(teeth, width=1.0, gap=1.0, height=8.0):
    """A comb: a base with ``teeth`` vertical teeth, many chains monotone in y (and in x)."""
    pts = [(0.0, 0.0), (teeth * (width + gap), 0.0)]
    x = teeth * (width + gap)
    for _ in range(teeth):
        pts += [(x, height), (x - width, height), (x - width, 1.0), (x - width - gap, 1.0)]
        x -= width + gap
    return np.array(pts[:-1])


SIMPLE = {
    "triangle": ngon(3),
    "square (axis-aligned edges)": np.array([[0, 0], [4, 0], [4, 4], [0, 4]], float),
    "hexagon": ngon(6),
    "circle 500": ngon(500, r=30.0),
    "star 12": star(12),
    "staircase": staircase(9),
    "comb 20": comb(20),
    "comb 20, clockwise": comb(20)[::-1],
    "L rotated 30 degrees": np.array([[0, 0], [6, 0], [6, 2], [2, 2], [2, 7], [0, 7]], float)
    @ np.array([[np.cos(0.52), np.sin(0.52)], [-np.sin(0.52), np.cos(0.52)]]),
    "thin sliver": np.array([[0, 0], [100, 0.001], [200, 0], [100, 0.002]], float),
}

CROSSING = {
    "bowtie": np.array([[0, 0], [2, 2], [2, 0], [0, 2]], float),
    "pentagram": ngon(5)[[0, 2, 4, 1, 3]],
    "square with a vertex pulled across": np.array([[0, 0], [4, 0], [4, 4], [2, -1], [0, 4]], float),
    "lemniscate": np.stack([np.sin(t := 0.05 + 2 * np.pi * np.arange(41) / 41), np.sin(t) * np.cos(t)], axis=1),
    "comb with one tooth bent over the next": np.where(
        np.arange(len(comb(6)))[:, None] == 2, comb(6)[2] - [3.5, 0], comb(6)
    ),
}

TOUCHING = {  # no proper crossing, but not simple: the screen must leave them to GEOS
    "pinched at a vertex": np.array([[0, 0], [2, 1], [4, 0], [4, 2], [2, 1], [0, 2]], float),
    "vertex on an edge": np.array([[0, 0], [4, 0], [4, 4], [2, 0], [0, 4]], float),
    "spike back along an edge": np.array([[0, 0], [4, 0], [4, 4], [4, 2], [4, 5], [0, 4]], float),
    "collinear overlap of two sides": np.array([[0, 0], [6, 0], [6, 1], [1, 1], [1, 0.0], [3, 0], [3, -1],
                                                [0, -1]], float),
}


def test_screen_clears_simple_loops(device):
    got = screen(device, list(SIMPLE.values()))
    assert got.tolist() == [True] * len(SIMPLE), dict(zip(SIMPLE, got.tolist(), strict=True))


@pytest.mark.parametrize("shapes", [CROSSING, TOUCHING], ids=["crossing", "touching"])
def test_screen_never_clears_crossing_or_touching_loops(device, shapes):
    polys = [shapely.Polygon(p) for p in shapes.values()]
    assert not any(p.is_valid for p in polys), "test shapes must be invalid polygons"
    got = screen(device, list(shapes.values()))
    assert not got.any(), dict(zip(shapes, got.tolist(), strict=True))


def test_screen_gives_up_on_repeated_points(device):
    """A repeated consecutive point (GEOS: valid) is left to GEOS, as documented in the kernel."""
    got = screen(device, [np.array([[0, 0], [4, 0], [4, 0], [4, 4], [0, 4]], float), SIMPLE["hexagon"]])
    assert got.tolist() == [False, True]


def random_loops(rng, n_loops):
    """Star-shaped loops (distinct sorted angles: simple) and random walks closed on themselves (mostly crossing),
    some snapped to a coarse grid so that touching and collinear edges occur."""
    out = []
    for k in range(n_loops):
        n = int(rng.integers(4, 60))
        if k % 3 == 0:
            t = np.sort(rng.uniform(0, 2 * np.pi, n))
            r = rng.uniform(1, 10, n)
            p = np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
        else:
            p = np.cumsum(rng.normal(size=(n, 2)), axis=0)
        if k % 5 == 0:
            p = np.round(p)
        keep = np.ones(len(p), bool)
        keep[1:] = np.any(p[1:] != p[:-1], axis=1)
        p = p[keep]
        if len(p) >= 3 and np.any(p[0] != p[-1]):
            out.append(p)
    return out


def test_screen_against_geos_on_random_loops(device):
    loops = random_loops(np.random.default_rng(14), 1500)
    got = screen(device, loops)
    points, offsets = pack(loops)
    valid = shapely.is_valid(_polygons(points, offsets, np.arange(len(loops))))
    assert not np.any(got & ~valid), "the screen cleared loops GEOS finds invalid"
    # star-shaped loops with distinct angles are simple: the screen clears nearly all of them
    star_like = np.array([shapely.Polygon(p).is_valid and len(p) > 3 for p in loops]) & valid
    assert got[star_like].mean() > 0.9, got[star_like].mean()
    # nesting's self-crossing test gives the same loops with and without the screen
    closed = np.ones(len(loops), bool)
    with_screen = _self_crossing_loops(points, offsets, closed, got)
    np.testing.assert_array_equal(with_screen, _self_crossing_loops(points, offsets, closed))
    assert with_screen.size > 100  # the random walks cross themselves


def test_polygons_match_shapely_rings():
    """``_polygons`` builds the same polygons as ``shapely.polygons(shapely.linearrings(...))``, also for a ring
    given closed (first point repeated at its end), which linearrings does not close again."""
    loops = random_loops(np.random.default_rng(7), 60)
    loops[3] = np.vstack([loops[3], loops[3][:1]])
    points, offsets = pack(loops)
    ids = np.arange(0, len(loops), 2)
    ids = np.append(ids, 3)
    got = _polygons(points, offsets, ids)
    want = [shapely.Polygon(points[offsets[i] : offsets[i + 1]].astype(np.float64)) for i in ids]
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(shapely.get_coordinates(g), shapely.get_coordinates(w))
    np.testing.assert_array_equal(shapely.is_valid(got), shapely.is_valid(want))


def test_device_chaining_matches_host_with_planes_through_vertices(device):
    """The device path (points gathered on the device, zero-length segments dropped on the host) gives the same
    loops as the host path, with planes through the sphere's vertices (zero-length segments) and between them."""
    sphere = mesh_from_triangles(S.uv_sphere(10.0, 12, 24))
    zs = np.unique(np.concatenate([np.linspace(0.3, sphere.height - 0.3, 7), sphere.vertices[:, 2].astype(float)]))
    zs = zs[(zs > 0) & (zs < sphere.height)].astype(np.float32)
    host = chain_segments(crossings_numpy(sphere, zs), sphere, zs, zs.size)
    dev = chain_segments(compute_crossings(sphere, zs, device, read_back=False), sphere, zs, zs.size, device=device)
    for name in ("points", "offsets", "layer", "closed"):
        np.testing.assert_array_equal(getattr(dev, name), getattr(host, name), err_msg=name)
    assert host.simple is None
    if dev.simple is not None:
        assert dev.simple.all()  # sections of a convex solid


def test_self_crossing_prism_is_rebuilt_on_both_backends(device):
    """A prism over a bowtie (its side facets cross): the layers' loops cross themselves, the screen must leave
    them to GEOS, and both backends rebuild those layers into the same two triangles; so is the middle layer, whose
    loop passes through the centre point itself (GEOS: ring self-intersection; its lobes wind opposite ways, net
    area 0: it was dropped as bounding nothing before the rebuild took such loops too)."""
    bow = np.array([[0, 0], [10, 10], [10, 0], [0, 10]], float)
    v = np.vstack([np.c_[bow, np.zeros(4)], np.c_[bow, np.full(4, 5.0)]])
    f = [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7]] + [
        q for i in range(4) for q in ([i, (i + 1) % 4, 4 + (i + 1) % 4], [i, 4 + (i + 1) % 4, 4 + i])
    ]
    mesh = mesh_from_arrays(v, f)
    a = slice_mesh(mesh, thickness=1.0, backend="opencl", device=device)
    b = slice_mesh(mesh, thickness=1.0, backend="numpy")
    np.testing.assert_array_equal(a.repairs["overlaps_resolved"], [1, 1, 1, 1, 1])
    np.testing.assert_allclose(a.area, [50, 50, 50, 50, 50], rtol=1e-6)  # two triangles of 25 mm^2 in every layer
    for name in ("points", "loop_offsets", "layer_offsets", "loop_is_hole", "loop_parent", "area"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_gather_index_matches_the_direct_formula():
    """Nesting's output gather (runs of loops that keep their order, reversed loops apart) equals the direct
    per-point formula: source start + local index, or start + count - 1 - local for a reversed loop."""
    from gpuslice.slicing.nest import _gather_index

    rng = np.random.default_rng(3)
    for trial in range(300):
        n = int(rng.integers(0, 30))
        counts = rng.integers(1, 6, n)
        offsets = np.zeros(n + 1, np.int64)
        np.cumsum(counts, out=offsets[1:])
        order = rng.permutation(n) if trial % 2 else np.arange(n)
        if trial % 3 == 0:
            order = order[rng.random(n) < 0.8]  # loops dropped
        flip = rng.random(n) < 0.2
        new_counts = counts[order]
        new_offsets = np.zeros(order.size + 1, np.int64)
        np.cumsum(new_counts, out=new_offsets[1:])
        local = np.arange(new_offsets[-1]) - np.repeat(new_offsets[:-1], new_counts)
        start = np.repeat(offsets[:-1][order], new_counts)
        want = np.where(np.repeat(flip[order], new_counts), start + np.repeat(new_counts, new_counts) - 1 - local,
                        start + local)
        np.testing.assert_array_equal(_gather_index(offsets[:-1][order], new_counts, new_offsets, flip[order]), want)
