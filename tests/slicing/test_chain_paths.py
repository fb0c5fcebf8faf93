"""The shortcuts of the device chaining and of nesting against their plain versions (issue 14: contour speed).

The device walk places each closed loop once and rotates it to its smallest segment; the host then moves whole
chains into the canonical order (runs of chains copied as slices); the driver may trust the per-layer segment
counts of the slicer (and must fall back when they are wrong); the crossings may take the host's vertex and facet
layer ranges; and nesting splits some GEOS calls over two threads. Each must give exactly what the plain path gives.
"""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles
from gpuslice.mesh import shapes as S
from gpuslice.slicing.chain import chain_segments, order_chains
from gpuslice.slicing.crossings import compute_crossings, crossings_numpy, facet_layer_ranges, vertex_layers
from gpuslice.slicing.rings import move_chains
from gpuslice.slicing.walk import canonical_chain_order, chain_kernels, layer_lists


def random_cycles(rng, n_layers: int, per_layer: int) -> tuple[np.ndarray, np.ndarray]:
    """A successor array made only of closed loops (random lengths) within layers, segment ids shuffled so that a
    loop's smallest segment sits anywhere in it; and each segment's layer."""
    layer = np.repeat(np.arange(n_layers, dtype=np.int32), per_layer)
    ids = rng.permutation(layer.size)
    layer = layer[np.argsort(ids)]  # segment ids[i] is in layer i // per_layer
    nxt = np.empty(layer.size, dtype=np.int32)
    for k in range(n_layers):
        seg = ids[k * per_layer : (k + 1) * per_layer]
        cuts = np.sort(rng.choice(np.arange(1, per_layer), size=rng.integers(0, 6), replace=False))
        for loop in np.split(seg, cuts):
            nxt[loop] = np.roll(loop, -1)
    return nxt, layer


def test_move_chains_matches_concatenated_chains():
    rng = np.random.default_rng(3)
    lengths = rng.integers(1, 40, 300)
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    n = int(lengths.sum())
    data = (rng.integers(0, 1 << 30, n).astype(np.int32), rng.random(n).astype(np.complex64), rng.random(n) < 0.5)
    for swaps in (0, 5, 290):  # in place, a few runs, many runs
        o = np.arange(lengths.size)
        for i in rng.choice(lengths.size - 1, swaps, replace=False):
            o[[i, i + 1]] = o[[i + 1, i]]
        offsets = np.zeros(lengths.size + 1, dtype=np.int64)
        np.cumsum(lengths[o], out=offsets[1:])
        want = [np.concatenate([x[starts[c] : starts[c] + lengths[c]] for c in o]) for x in data]
        got = move_chains(starts[o], offsets, data)
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and np.array_equal(g, w)


def test_walk_rotates_loops_met_anywhere_to_their_smallest_segment(device):
    """The walk meets each loop at the first of its segments in the layer's list, which the lists here make the
    largest one: every loop is rotated, and the chains still come out as ``order_chains`` orders them."""
    rng = np.random.default_rng(11)
    nxt, layer = random_cycles(rng, n_layers=40, per_layer=50)
    perm, off = layer_lists(layer, 40)
    perm = np.concatenate([perm[off[k] : off[k + 1]][::-1] for k in range(40)]).astype(np.int32)  # descending
    kern = chain_kernels(device)
    has_prev = np.ones(nxt.size, dtype=np.uint8)
    order, flag = kern._run_walk(kern._put("next", nxt), kern._put("has_prev", has_prev), kern._put("perm", perm),
                                 kern._put("layer_off", off), nxt.size, 40)
    got = canonical_chain_order(order, flag, off)[:3]
    for g, w in zip(got, order_chains(nxt, layer), strict=True):
        assert np.array_equal(g, w)


@pytest.fixture(scope="module")
def sphere_cut():
    sphere = mesh_from_triangles(S.uv_sphere(10.0, 12, 24))
    zs = np.linspace(0.25, sphere.height - 0.25, 23).astype(np.float32)
    return sphere, zs


def test_wrong_layer_counts_fall_back_to_counting_or_the_host(device, sphere_cut):
    sphere, zs = sphere_cut
    host = chain_segments(crossings_numpy(sphere, zs), sphere, zs, zs.size)
    lo, count = facet_layer_ranges(sphere, zs)
    n = zs.size + 1
    right = np.cumsum(np.bincount(lo, minlength=n) - np.bincount(lo + count, minlength=n))[:-1]
    moved = right.copy()
    moved[3] += 5  # the same total, wrong per layer: a layer overflows, the device says so
    moved[4] -= 5
    for counts in (right, moved, right + 1, None):
        dev = chain_segments(compute_crossings(sphere, zs, device, read_back=False), sphere, zs, zs.size,
                             device=device, layer_counts=counts)
        for name in ("points", "offsets", "layer", "closed"):
            assert np.array_equal(getattr(dev, name), getattr(host, name)), name


def test_host_layer_ranges_give_the_kernels_segments(device, sphere_cut):
    """The crossings of a batch of planes from the host's facet ranges and the batch's own facets (as
    ``slice_mesh`` passes them: :func:`batch_facets`, :func:`batch_layers`) equal those the kernels compute
    themselves over every facet, in the same order; every facet crossing a batch's planes is among its facets."""
    from gpuslice.slicing.crossings import batch_facets, batch_layers

    sphere, zs = sphere_cut
    vl = vertex_layers(sphere, zs)
    ranges = (vl, *facet_layer_ranges(sphere, zs, vl))
    got = compute_crossings(sphere, zs, device, read_back=False, layers=ranges).fetch()
    want = compute_crossings(sphere, zs, device)
    for name in ("layer", "edges", "points"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    for batches in ([(0, 5), (5, 14), (14, zs.size)], [(k, k + 1) for k in range(zs.size)]):
        facets = batch_facets(ranges, batches)
        for (a, b), ids in zip(batches, facets, strict=True):
            lo, count = ranges[1], ranges[2]
            crossing = np.flatnonzero((lo < b) & (lo + count > a))
            assert np.array_equal(ids, crossing), (a, b)  # all of them, increasing, nothing else
            want = compute_crossings(sphere, zs[a:b], device)
            got = compute_crossings(sphere, zs[a:b], device, read_back=False, layers=batch_layers(ranges, a, b, ids),
                                    facets=ids).fetch()
            for name in ("layer", "edges", "points"):
                assert np.array_equal(getattr(got, name), getattr(want, name)), (a, b, name)


def test_geos_calls_in_halves_equal_one_call(monkeypatch):
    shapely = pytest.importorskip("shapely")
    from gpuslice.slicing import rings

    rng = np.random.default_rng(5)
    loops = [np.c_[np.cos(t), np.sin(t)] * r + c for r, c in zip(rng.random(9) + 1, rng.random((9, 2)) * 3,
                                                                    strict=True)
             for t in [np.sort(rng.random(int(rng.integers(5, 30)))) * 2 * np.pi]]
    offsets = np.zeros(len(loops) + 1, dtype=np.int64)
    np.cumsum([len(p) for p in loops], out=offsets[1:])
    points = np.concatenate(loops).astype(np.float32)
    ids = np.arange(len(loops))
    one = rings._polygons(points, offsets, ids)
    lines = shapely.get_exterior_ring(one)
    groups = np.array([shapely.multilinestrings(lines[:4]), shapely.multilinestrings(lines[4:])])
    node_one = shapely.node(groups)
    monkeypatch.setattr(rings, "HALVES_MIN_POINTS", 0)
    halves = rings._polygons(points, offsets, ids)
    assert all(shapely.equals_exact(a, b, 0) for a, b in zip(one, halves, strict=True))
    node_halves = rings.node_lines(groups)
    for a, b in zip(node_one, node_halves, strict=True):
        assert np.array_equal(shapely.get_coordinates(a), shapely.get_coordinates(b))


def test_in_halves_splits_once_not_again_on_its_own_thread():
    """A large call is split in two, one half on nesting's thread; on that thread it is not split again (a review
    found every half split anew once the threads stopped being ``threading.Thread`` objects: more threads than
    cores)."""
    from gpuslice.slicing import rings

    calls = []

    def fn(x):
        calls.append(x.size)
        return x * 2

    x = np.arange(100_000)
    work = np.ones(x.size)
    assert np.array_equal(rings.in_halves(fn, work, x), x * 2) and len(calls) == 2 and sum(calls) == x.size
    calls.clear()
    assert np.array_equal(rings.beside(rings.in_halves, fn, work, x).result(10), x * 2) and calls == [100_000]


@pytest.mark.parametrize("bad", [(3, 80), (80,), (3,)])
def test_in_halves_raises_what_one_call_raises_after_both_halves(bad):
    """A half that raises: the other half is waited for (nothing of the call runs on after it has raised: a review
    found the first half still at work), and the exception is the one a single call over all the elements raises
    (the first failing element's)."""
    import time

    from gpuslice.slicing import rings

    calls, done = [], []

    def fn(x):
        calls.append(int(x[0]))
        time.sleep(0.2 if x[0] == 0 else 0.0)  # (the first half, beside, is the slower)
        for v in bad:
            if v in x:
                raise ValueError(f"element {v}")
        done.append(int(x[0]))
        return x

    x = np.arange(100)
    with pytest.raises(ValueError, match=f"^element {bad[0]}$"):
        rings.in_halves(fn, np.full(x.size, 1_000_000), x)
    ended = len(calls), len(done)
    time.sleep(0.3)
    assert (len(calls), len(done)) == ended and len(calls) == 2


@pytest.mark.parametrize("n_squares", [5, 90])  # few reversed loops (turned after the run copy), many (a gather)
def test_nesting_turns_clockwise_outer_loops(n_squares):
    """Separate squares in one layer, every other one clockwise: each comes out counter-clockwise as an outer loop,
    its points reversed, in input order; a counter-clockwise square inside the first bounds nothing (filled on
    both sides under nonzero) and is dropped, points included."""
    from gpuslice.slicing.chain import Loops
    from gpuslice.slicing.nest import nest_loops

    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float32)
    loops = [(sq + [3 * i, 0])[::-1] if i % 2 else sq + [3 * i, 0] for i in range(n_squares)]
    inner = sq * 0.5 + 0.25
    points = np.concatenate(loops[:1] + [inner] + loops[1:]).astype(np.float32)
    offsets = np.arange(n_squares + 2, dtype=np.int64) * 4
    got = nest_loops(Loops(points, offsets, np.zeros(n_squares + 1, np.int32), np.ones(n_squares + 1, bool)), 1)
    want = np.concatenate([p[::-1] if i % 2 else p for i, p in enumerate(loops)])
    assert np.array_equal(got.points, want)
    assert np.array_equal(got.loop_offsets, np.arange(n_squares + 1) * 4)
    assert not got.loop_is_hole.any() and got.area[0] == n_squares and got.unfilled_loops[0] == 1


@pytest.fixture
def chained_on_device(monkeypatch) -> list[bool]:
    """Whether each call of ``ChainKernels.chain_on_device`` chained on the device (False: the host's fallback)."""
    from gpuslice.slicing.walk import ChainKernels

    calls: list[bool] = []
    plain = ChainKernels.chain_on_device

    def spy(self, *args, **kwargs):
        out = plain(self, *args, **kwargs)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(ChainKernels, "chain_on_device", spy)
    return calls


def test_layer_lists_in_parts_give_the_host_chains(device, chained_on_device):
    """Each layer's segment list is filled in parts, one per stripe of work-groups (``STRIPES``): on a sphere cut
    finely enough that every stripe holds segments of most layers, with the slicer's counts and without them, the
    device's chains are the host's."""
    from gpuslice.device import STRIPES

    sphere = mesh_from_triangles(S.uv_sphere(10.0, 96, 192))
    zs = np.linspace(0.05, sphere.height - 0.05, 120).astype(np.float32)
    host = chain_segments(crossings_numpy(sphere, zs), sphere, zs, zs.size)
    lo, count = facet_layer_ranges(sphere, zs)
    n = zs.size + 1
    counts = np.cumsum(np.bincount(lo, minlength=n) - np.bincount(lo + count, minlength=n))[:-1]
    assert counts.sum() > 8 * STRIPES * device.local_size  # (every stripe used several times)
    for given in (counts, None):
        dev = chain_segments(compute_crossings(sphere, zs, device, read_back=False), sphere, zs, zs.size,
                             device=device, layer_counts=given)
        assert chained_on_device.pop() is True  # (not the host's fallback)
        for name in ("points", "offsets", "layer", "closed"):
            assert np.array_equal(getattr(dev, name), getattr(host, name)), name


@pytest.mark.parametrize("fin, why", [([(10, 0, 0), (10, 0, 10), (15, -5, 5)], 8),  # (walk_layers: met twice)
                                     ([(10, 0, 10), (10, 0, 0), (15, -5, 5)], 1)])  # (place_segments: two starts)
def test_a_slot_with_two_ends_falls_back_to_the_host(device, fin, why, chained_on_device):
    """A box with a fin on one of its upright edges: the fin's segment starts at its open side and ends at the box's
    edge, where a box segment ends too (the first fin; the walk finds a segment met twice), or starts there beside
    a box segment (the second; two starts at one slot): either way the device gives up and the host's chains are
    the numpy backend's."""
    from gpuslice import slice_mesh

    mesh = mesh_from_triangles(np.concatenate([S.box((0, 0, 0), (10, 10, 10)), np.array([fin], float)]))
    want = slice_mesh(mesh, thickness=2.5, backend="numpy")
    got = slice_mesh(mesh, thickness=2.5, backend="opencl", device=device)
    assert chained_on_device == [False]
    import pyopencl as cl

    from gpuslice.slicing.walk import chain_kernels

    flags = np.zeros(1, np.int32)  # (the conflict flags the device's chaining left)
    cl.enqueue_copy(device.queue, flags, chain_kernels(device).buffer("conflict"), is_blocking=True)
    assert flags[0] & why
    for name in ("points", "loop_offsets", "layer_offsets", "area"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name


@pytest.mark.parametrize("bodies", [1, 2])
def test_chunk_boxes_left_on_the_device_only_for_layers_of_two_loops(device, bodies):
    """Chaining on the device leaves nesting the boxes of the loops' chunks (``Loops.chunk_boxes``) when some layer
    has two closed loops, equal to the host's :class:`~gpuslice.slicing.contain.Chunks`; with one loop a layer
    nesting tests no containment, and no boxes are made."""
    from gpuslice.slicing.contain import Chunks

    tri = np.concatenate([S.box((0, 0, 0), (6, 6, 6)), S.box((10, 0, 0), (16, 6, 6))][:bodies])
    mesh = mesh_from_triangles(tri)
    zs = np.linspace(0.5, 5.5, 6)
    loops = chain_segments(compute_crossings(mesh, zs, device, read_back=False), mesh, zs, zs.size, device=device)
    assert loops.closed.all() and np.bincount(loops.layer).max() == bodies
    if bodies == 1:
        assert loops.chunk_boxes is None
        return
    host = Chunks(loops.points, loops.offsets)
    host.cut(np.arange(loops.layer.size))
    boxes = loops.chunk_boxes.astype(np.float64)
    assert np.array_equal(boxes[:, :2], host.lo) and np.array_equal(boxes[:, 2:], host.hi)
