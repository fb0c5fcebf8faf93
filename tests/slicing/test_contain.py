"""Nesting's containment tests in numpy (``slicing/contain.py``, issue 14): the point-in-loop test agrees with
GEOS's strict ``contains_xy`` wherever it is sure, and is unsure for every point on a loop's boundary; nesting
through it gives, array for array, what the R-tree and GEOS path gives (forced here by a pair limit of -1)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from test_overlap_groups import bowtie, make_loops, square, twice_around

from gpuslice.slicing import contain
from gpuslice.slicing.nest import nest_loops
from gpuslice.slicing.rings import _as_complex

FIELDS = ("points", "loop_offsets", "layer_offsets", "loop_layer", "loop_is_hole", "loop_parent", "loop_closed",
          "area", "unfilled_loops", "overlaps_resolved")


def star(rng, cx, cy, r0, r1, n):
    t = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = rng.uniform(r0, r1, n)
    return np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1).astype(np.float32)


def pentagram(cx, cy, r):
    t = np.pi / 2 + np.arange(5) * 4 * np.pi / 5
    return np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1).astype(np.float32)


def loops_and_points(rng):
    """Loops of every kind (simple stars, a pentagram, a bow-tie, a loop around twice, axis-aligned squares, one
    with a repeated closing point) and query points: random ones, the loops' vertices, midpoints of their edges,
    points a float step off an edge, points on the squares' sides."""
    rings = [star(rng, 0, 0, 2, 5, 40), star(rng, 1, 1, 1, 3, 7), pentagram(0, 0, 4), bowtie(-3, -3, 6),
             twice_around(-5, -5), square(-2, -2, 4), square(-4, 0, 8, ccw=False)]
    rings.append(np.vstack([rings[-1], rings[-1][:1]]))
    rings = [np.asarray(r, np.float32) for r in rings]
    pts = [rng.uniform(-6, 6, (400, 2))]
    for r in rings:
        a, b = r.astype(float), np.roll(r, -1, axis=0).astype(float)
        mid = (a + b) / 2
        pts += [a, mid, np.nextafter(mid, mid + 1), np.nextafter(mid, mid - 1), a + (b - a) * rng.random((len(a), 1))]
    pts += [np.array([[-2, 0.5], [2, -1.25], [0.75, -2], [-4, 3], [1.5, 8]], float)]
    return rings, np.concatenate(pts)


def test_point_in_loops_matches_contains_xy():
    rng = np.random.default_rng(7)
    rings, pts = loops_and_points(rng)
    loops = make_loops([rings])
    pc = _as_complex(loops.points)
    q = pts[:, 0] + 1j * pts[:, 1]
    pi = np.repeat(np.arange(q.size), len(rings))
    pj = np.tile(np.arange(len(rings)), q.size)
    chunks = contain.Chunks(loops.points, loops.offsets)
    chunks.cut(np.arange(len(rings)))
    inside, unsure = contain.point_in_loops(pc, chunks, pi, pj, q)
    polys = np.array([shapely.Polygon(r.astype(float)) for r in rings])
    truth = shapely.contains_xy(polys[pj], q.real[pi], q.imag[pi])
    on = shapely.intersects_xy(shapely.get_exterior_ring(polys[pj]), q.real[pi], q.imag[pi])
    assert truth.any() and (~truth).any() and on.sum() > 100
    assert np.array_equal(inside[~unsure], truth[~unsure])
    assert unsure[on].all()  # every point on a boundary is left to GEOS
    assert unsure.mean() < 0.3  # and most points are not


def test_rings_meet_matches_intersects(monkeypatch):
    """Pairs of loops that cross, touch at a vertex, share part of a side, pass near each other or not at all: where
    the numpy test is sure, GEOS says the same; touching pairs are left to GEOS; crossing ones are found sure."""
    monkeypatch.setattr(contain, "CHUNK", 4)  # several chunks per loop
    rng = np.random.default_rng(5)
    rings = [star(rng, 0, 0, 2, 5, 40), star(rng, 6, 0, 1, 3, 25), square(4, -1, 2), square(-10, -1, 2),
             square(-8, -1, 2), square(-8, 0, 1), pentagram(0, 8, 3), star(rng, 1, 7, 0.5, 2, 9), bowtie(-3, 5, 4),
             np.array([[5, 5], [9, 5], [9, 9.000001]], float), np.array([[9, 9.0000011], [12, 9], [12, 12]], float)]
    loops = make_loops([rings])
    pc = _as_complex(loops.points)
    bi, bj = np.triu_indices(len(rings), 1)
    chunks = contain.Chunks(loops.points, loops.offsets)
    chunks.cut(np.arange(len(rings)))
    meet, sure = contain.rings_meet_numpy(pc, chunks, bi, bj)
    ext = np.array([shapely.LinearRing(np.asarray(r, np.float32).astype(float)) for r in rings])
    truth = shapely.intersects(ext[bi], ext[bj])
    assert np.array_equal(meet[sure], truth[sure])
    assert truth.sum() >= 4 and (meet & sure).sum() >= 2 and (~truth & sure).sum() > 20
    touch = shapely.touches(shapely.polygons(ext[bi]), shapely.polygons(ext[bj]))
    assert touch.any() and not sure[touch].any()


def nested_equal(a, b) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f)) and getattr(a, f).dtype == getattr(b, f).dtype
               for f in FIELDS)


def random_layers(rng, n_layers):
    """Layers of squares and stars: nested, side by side, overlapping, touching, sharing a side."""
    layers = []
    for _ in range(n_layers):
        rings = [square(0, 0, 20), square(2, 2, 6, ccw=False), square(12, 2, 6, ccw=False), square(3, 3, 2)]
        kind = rng.integers(0, 5)
        if kind == 1:
            rings.append(square(15, 15, 10))  # overlapping the first
        elif kind == 2:
            rings.append(square(20, 0, 5))  # touching it
        elif kind == 3:
            rings.append(star(rng, 10, 14, 1, 4, 12))
        elif kind == 4:
            rings.append(square(8, 2, 4, ccw=False))  # a hole sharing a side with another
        layers.append(rings)
    return layers


@pytest.mark.parametrize("fill_rule", ["nonzero", "evenodd", "positive"])
def test_nesting_same_with_and_without_the_numpy_path(monkeypatch, fill_rule):
    rng = np.random.default_rng(3)
    loops = make_loops(random_layers(rng, 30) + [[bowtie(0, 0, 4), square(-1, -1, 6)], [twice_around(0, 0)]])
    fast = nest_loops(loops, 32, fill_rule)
    monkeypatch.setattr(contain, "MAX_PAIRS", -1)
    slow = nest_loops(loops, 32, fill_rule)
    assert nested_equal(fast, slow)
    assert fast.overlaps_resolved.sum() > 0 and fast.loop_is_hole.sum() > 30


def test_equal_area_parents_take_the_tree(monkeypatch):
    """Two outer contours of equal area around one hole: the R-tree's order picks the parent, so the numpy path
    steps aside (the result is the tree's either way)."""
    loops = make_loops([[square(0, 0, 10), square(0, 0, 10), square(2, 2, 3, ccw=False)]])
    calls = []
    real = contain.containment_pairs
    monkeypatch.setattr("gpuslice.slicing.nest.containment_pairs", lambda *a: calls.append(real(*a)) or calls[-1])
    fast = nest_loops(loops, 1)
    assert calls == [None]
    monkeypatch.setattr(contain, "MAX_PAIRS", -1)
    assert nested_equal(fast, nest_loops(loops, 1))


def test_real_mesh_same_with_and_without_the_numpy_path(shared_meshes, monkeypatch):
    from gpuslice import load_mesh, slice_mesh

    mesh = load_mesh(shared_meshes / "benchy.stl", fit=25)
    fast = slice_mesh(mesh, thickness=0.2, backend="numpy")
    monkeypatch.setattr(contain, "MAX_PAIRS", -1)
    slow = slice_mesh(mesh, thickness=0.2, backend="numpy")
    for f in ("points", "loop_offsets", "loop_layer", "loop_is_hole", "loop_parent", "loop_closed", "area"):
        assert np.array_equal(getattr(fast, f), getattr(slow, f)), f
    assert fast.loop_is_hole.any()


def test_device_chunk_boxes_match_the_host(device):
    """``chunk_boxes`` in ``kernels/walk.cl`` against its twin, :class:`contain.Chunks` cutting every loop on the
    host: the same float32 boxes (as float64), the same loop boxes; loops of 1 to 300 points (one and several
    chunks, a last chunk of one edge), signed zeros (of +0.0 and -0.0 tied, either sign may be kept: equal values),
    coordinates far apart in size. A loop without points: no boxes (the host cuts)."""
    from gpuslice.slicing.walk import chain_kernels

    rng = np.random.default_rng(11)
    sizes = [1, 2, 3, 63, 64, 65, 127, 128, 129, 300] + list(rng.integers(1, 300, 40))
    pts = [rng.normal(0, 10.0 ** rng.integers(-3, 4), (n, 2)).astype(np.float32) for n in sizes]
    pts[3][::7] = np.float32(-0.0)
    pts[4][::5] = np.float32(0.0)
    pts[5][::2] = np.float32(-0.0)  # both zeros in one chunk
    pts[5][1::4] = np.float32(0.0)
    points = np.concatenate(pts)
    offsets = np.cumsum([0, *sizes]).astype(np.int64)
    boxes = chain_kernels(device).chunk_boxes(points, offsets)
    host = contain.Chunks(points, offsets)
    host.cut(np.arange(len(sizes)))
    made = contain.Chunks(points, offsets, boxes)
    assert boxes.shape == (host.lo.shape[0], 4) and boxes.dtype == np.float32
    for f in ("off", "loop", "start", "end", "lo", "hi", "loop_lo", "loop_hi"):
        assert np.array_equal(getattr(made, f), getattr(host, f)), f
    waiting = chain_kernels(device).chunk_boxes(points, offsets, wait=False)  # (the form chaining leaves running)
    assert callable(waiting) and np.array_equal(waiting(), boxes)
    assert chain_kernels(device).chunk_boxes(points, np.append(offsets, offsets[-1])) is None


@pytest.mark.parametrize("fill_rule", ["nonzero", "evenodd", "positive"])
def test_nesting_same_with_the_device_chunk_boxes(device, fill_rule):
    """Nesting with the device's chunk boxes (as chaining on the device leaves them) gives, array for array, what it
    gives with the host's."""
    from gpuslice.slicing.walk import chain_kernels

    rng = np.random.default_rng(4)
    loops = make_loops(random_layers(rng, 30) + [[bowtie(0, 0, 4), square(-1, -1, 6)], [twice_around(0, 0)]])
    host = nest_loops(loops, 32, fill_rule)
    loops.boxes = chain_kernels(device).chunk_boxes(loops.points, loops.offsets, wait=False)
    assert nested_equal(nest_loops(loops, 32, fill_rule), host)
    assert isinstance(loops.boxes, np.ndarray)  # (waited for once, then kept)
