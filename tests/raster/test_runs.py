"""Resin layers as run-length runs (gpuslice.raster.runs): the raster path's greys byte for byte, and corner cases
checked against an independent rasterisation (exact pixel coverage with shapely, pixel centres in polygons)."""

from __future__ import annotations

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.errors import ParameterError
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec, gamma_lut, layer_edges, masks
from gpuslice.raster.runs import Runs, RunsKernel, _units, iter_runs, layer_runs, runs_numpy, runs_to_mask
from gpuslice.slicing.result import SliceResult

FIELDS = ("layers", "layer_offsets", "row", "x", "length", "grey")
SPEC4K = RasterSpec(resolution=(3840, 2400), pixel=0.05)


def assert_runs_equal(a: Runs, b: Runs) -> None:
    for f in FIELDS:
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert a.shape == b.shape


def assert_well_formed(r: Runs) -> None:
    assert r.row.dtype == np.int32 and r.x.dtype == np.int32 and r.length.dtype == np.int32
    assert r.grey.dtype == np.uint8 and r.layer_offsets.dtype == np.int64
    assert np.all(r.length >= 1) and np.all(r.grey > 0)
    rows, cols = r.shape
    assert np.all((r.row >= 0) & (r.row < rows) & (r.x >= 0) & (r.x + r.length <= cols))
    for k in range(len(r.layers)):
        a, b = r.layer_offsets[k], r.layer_offsets[k + 1]
        key = r.row[a:b].astype(np.int64) * cols + r.x[a:b]
        assert np.all(np.diff(key) > 0)  # sorted by (row, x), no overlap:
        end = key[:-1] + r.length[a : b - 1]
        same_row = r.row[a + 1 : b] == r.row[a : b - 1]
        assert np.all(end[same_row] <= key[1:][same_row])
        touching = same_row & (end == key[1:])  # adjacent runs of a row differ in grey
        assert np.all(r.grey[a + 1 : b][touching] != r.grey[a : b - 1][touching])


def check_against_raster(res, spec, layers, device, backends=("numpy", "opencl"), **kw):
    """Masks from runs of every backend == the OpenCL raster masks byte for byte; OpenCL runs == numpy runs."""
    ref = masks(res, spec, backend="opencl-bitmap", device=device, layers=layers, bounds=kw.get("bounds"), clip=True)
    got = {}
    for be in backends:
        r = layer_runs(res, spec, backend=be, device=device, layers=layers, clip=True, **kw)
        assert_well_formed(r)
        assert list(r.layers) == list(layers)
        for k in range(len(layers)):
            m = runs_to_mask(r, k)
            assert np.array_equal(m, ref[k]), (be, layers[k], np.count_nonzero(m != ref[k]))
        got[be] = r
    if len(got) == 2:
        assert_runs_equal(got["numpy"], got["opencl"])
    return got, ref


# ---- built-in solids and shared meshes ---------------------------------------------------------------------------
SOLIDS = {
    "torus": lambda: shapes.torus(40.0, 15.0, 96, 48),
    "hollow_box": lambda: shapes.hollow_box(60.0, 30.0),
    "icosphere": lambda: shapes.icosphere(45.0, 4),
}


@pytest.fixture(scope="module", params=sorted(SOLIDS))
def solid(request):
    return slice_mesh(mesh_from_triangles(SOLIDS[request.param]()), thickness=2.0, backend="numpy")


def _spread(res, n):
    return sorted({int(i) for i in np.linspace(0, res.n_layers - 1, n)})


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_solids_match_raster(device, solid, gamma):
    spec = RasterSpec(resolution=(3840, 2400), pixel=0.05, gamma=gamma)
    check_against_raster(solid, spec, _spread(solid, 6), device)


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_solids_all_layers_opencl_equals_numpy(device, solid, gamma):
    spec = RasterSpec(resolution=(3840, 2400), pixel=0.05, gamma=gamma)
    a = layer_runs(solid, spec, backend="numpy")
    b = layer_runs(solid, spec, backend="opencl", device=device, max_batch_pieces=20_000)  # several batches
    assert_runs_equal(a, b)
    assert np.array_equal(a.layers, np.arange(solid.n_layers))


def _shared(shared_meshes, name, fit):
    import trimesh

    m = trimesh.load(shared_meshes / f"{name}.stl", force="mesh")
    return mesh_from_triangles(m.vertices[m.faces], fit=fit)


@pytest.mark.parametrize("name", ["cow", "nefertiti", "benchy"])
@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_shared_meshes_match_raster(device, shared_meshes, name, gamma):
    if not (shared_meshes / f"{name}.stl").is_file():
        pytest.skip(f"{name}.stl not in the shared meshes")
    res = slice_mesh(_shared(shared_meshes, name, 60.0), thickness=0.05, backend="opencl")
    spec = RasterSpec(resolution=(3840, 2400), pixel=0.05, gamma=gamma)
    check_against_raster(res, spec, _spread(res, 5), device)
    # every layer: the OpenCL runs equal the numpy twin's
    assert_runs_equal(layer_runs(res, spec, backend="numpy"), layer_runs(res, spec, backend="opencl", device=device))


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_numpy_backend_masks_are_the_runs(device, shared_meshes, gamma):
    """``masks(backend="numpy")`` (and so the viewer's and ``raster``'s numpy path) comes from the runs' twin: the
    OpenCL masks byte for byte (the bitmap twin it used before is within a grey level: 67 pixels of prusa_A)."""
    res = slice_mesh(_shared(shared_meshes, "prusa_A", 20.0), thickness=0.5, backend="numpy")
    spec = RasterSpec(resolution=(3840, 2400), pixel=0.05, gamma=gamma)
    got = masks(res, spec, backend="numpy")
    assert got.any() and np.array_equal(got, masks(res, spec, backend="opencl", device=device))
    if gamma:  # (at gamma 0 a grey off by one may cross the threshold: 0 against 255)
        assert np.abs(masks(res, spec, backend="numpy-bitmap").astype(int) - got).max() <= 1


@pytest.mark.parametrize("k", [0, -5, 2.7, True, 65, "2"])
def test_iter_runs_refuses_a_bad_z_samples(k):
    """The library's z_samples is checked as the command line checks it (0 and -5 ran as 1, 2.7 as 2, silently)."""
    res = slice_mesh(mesh_from_triangles(shapes.box()), thickness=1.0, backend="numpy")
    with pytest.raises(ParameterError, match="z_samples must be a whole number from 1 to 64"):
        list(iter_runs(res, RasterSpec(resolution=(500, 500), pixel=0.05), backend="numpy", z_samples=k))


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_12k_display(device, shared_meshes, gamma):
    res = slice_mesh(_shared(shared_meshes, "nefertiti", 80.0), thickness=0.05, backend="opencl")
    spec = RasterSpec(resolution=(11520, 5120), pixel=0.019, gamma=gamma)
    check_against_raster(res, spec, _spread(res, 3), device)


# ---- corner cases: hand-made layers -------------------------------------------------------------------------------
def _ring(x0, y0, x1, y1, hole=False):
    p = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], np.float32)
    return p[::-1].copy() if hole else p


def make_result(layers) -> SliceResult:
    """A SliceResult from ``layers``: each a list of (points (n, 2) mm, is_hole, parent index within the layer,
    closed); outer loops counter-clockwise, holes clockwise."""
    pts, loff, lay, hole, par, closed = [], [0], [], [], [], []
    base = 0
    for i, loops in enumerate(layers):
        for p, is_hole, parent, is_closed in loops:
            pts.append(np.asarray(p, np.float32))
            loff.append(loff[-1] + len(p))
            lay.append(i)
            hole.append(is_hole)
            par.append(base + parent if parent >= 0 else -1)
            closed.append(is_closed)
        base += len(loops)
    n = len(layers)
    layer_offsets = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(np.asarray(lay, np.int64), minlength=n), out=layer_offsets[1:])
    return SliceResult(
        np.concatenate(pts), np.asarray(loff, np.int64), layer_offsets, np.asarray(lay, np.int32),
        np.asarray(hole, bool), np.asarray(par, np.int32), np.asarray(closed, bool),
        np.arange(n, dtype=np.float64) + 0.5, np.ones(n), np.zeros(n),
    )


# a 64 x 48 px display of 1 mm pixels at the model's own XY: u = x, v = 48 - y
SMALL = RasterSpec(resolution=(64, 48), pixel=1.0, keep_xy=True)

CORNERS = {
    # one-pixel-wide holes, aligned to the pixel grid and straddling two pixels
    "hole_one_pixel": [(_ring(5, 5, 40, 30), False, -1, True), (_ring(20, 8, 21, 27, True), True, 0, True),
                       (_ring(30.5, 8.25, 31.5, 27.75, True), True, 0, True)],
    # vertices on row boundaries (integer v) and on pixel-centre lines (v = k + 0.5, u = k + 0.5)
    "vertices_on_lines": [(np.array([[20, 10], [30.5, 20.5], [20, 31], [9.5, 20.5]]), False, -1, True)],
    # horizontal edges lying on row lines, a slanted edge through pixel corners
    "horizontal_on_row_line": [(np.array([[3, 4], [50, 4], [50, 17], [30, 17], [3, 40]]), False, -1, True)],
    # a loop touching the display's left, top and right edges
    "touching_display_edge": [(np.array([[0, 30], [64, 30], [64, 48], [0, 48]]), False, -1, True),
                              (np.array([[0, 0], [10.3, 0], [0, 12.7]]), False, -1, True)],
    # an island inside a hole inside a part
    "island_in_hole": [(_ring(4, 4, 44, 44), False, -1, True), (_ring(10.2, 10.7, 38.4, 37.9, True), True, 0, True),
                       (_ring(18.5, 19.25, 30.75, 29.5), False, -1, True)],
    # an open chain is not filled (layer_edges drops it): same as the square alone
    "open_chain": [(_ring(4, 4, 20, 20), False, -1, True),
                   (np.array([[30, 5], [50, 5], [50, 40], [30.5, 40.2]]), False, -1, False)],
    # a thin sliver whose single row piece spans 60 columns
    "flat_sliver": [(np.array([[1.0, 20.1], [63.0, 20.6], [1.0, 20.35]]), False, -1, True)],
}


def exact_coverage(res: SliceResult, layer: int, spec: RasterSpec) -> np.ndarray:
    """(rows, cols) exact covered fraction of every pixel, by shapely polygon intersection (independent)."""
    shapely = pytest.importorskip("shapely")
    poly = shapely.union_all([shapely.Polygon(o, h) for o, h in res.layer(layer).polygons()])
    a = spec.affine(None)
    rows, cols = spec.shape
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    # pixel (i, j) covers u in [j, j+1), v in [i, i+1): back to mm with the inverse affine (keep_xy, landscape)
    x0, x1 = (jj - a[0, 2]) / a[0, 0], (jj + 1 - a[0, 2]) / a[0, 0]
    y0, y1 = (ii - a[1, 2]) / a[1, 1], (ii + 1 - a[1, 2]) / a[1, 1]
    boxes = shapely.box(np.minimum(x0, x1), np.minimum(y0, y1), np.maximum(x0, x1), np.maximum(y0, y1))
    return shapely.area(shapely.intersection(poly, boxes)) / (spec.px * spec.py)


def check_independent(res: SliceResult, spec: RasterSpec, runs1: Runs, runs0: Runs, layer: int = 0):
    cov = exact_coverage(res, layer, spec)
    soft = runs_to_mask(runs1, 0).astype(np.int64)  # the runs hold just this layer
    hard = runs_to_mask(runs0, 0)
    k = np.minimum(np.floor(256 * cov + 1e-9), 255)
    assert np.abs(soft - k).max() <= 1  # float32 16.16 sums: at most one grey step from exact
    clear = np.abs(cov - 0.5) > 2e-3
    assert np.array_equal(hard[clear] == 255, cov[clear] >= 0.5)
    # pixel centres: where a pixel is wholly in or out, its centre says the same
    from matplotlib.path import Path

    xs, ys = spec.pixel_centres(None)
    inside = np.zeros(cov.shape, bool)
    for outer, holes in res.layer(layer).polygons():
        inside ^= Path(outer).contains_points(np.c_[xs.ravel(), ys.ravel()]).reshape(cov.shape)
        for h in holes:
            inside ^= Path(h).contains_points(np.c_[xs.ravel(), ys.ravel()]).reshape(cov.shape)
    full = (cov > 1 - 1e-9) | (cov < 1e-9)
    assert np.array_equal(inside[full], cov[full] > 0.5)


@pytest.mark.parametrize("case", sorted(CORNERS))
def test_corner_cases(device, case):
    res = make_result([CORNERS[case]])
    spec0 = RasterSpec(resolution=(64, 48), pixel=1.0, keep_xy=True, gamma=0.0)
    got1, _ = check_against_raster(res, SMALL, [0], device)
    got0, _ = check_against_raster(res, spec0, [0], device)
    check_independent(res, SMALL, got1["numpy"], got0["numpy"])
    assert got1["numpy"].n_runs > 0
    if case == "open_chain":
        closed_only = make_result([CORNERS[case][:1]])
        assert_runs_equal(layer_runs(closed_only, SMALL, backend="numpy"), got1["numpy"])


def test_overlapping_bodies(device):
    """Two overlapping boxes: nesting resolves the union (winding 0/1), the runs cover it once."""
    tri = np.concatenate([shapes.box((0, 0, 0), (20, 12, 4)), shapes.box((10.5, 6.3, 0), (30.2, 25.1, 4))])
    res = slice_mesh(mesh_from_triangles(tri, solids=2), thickness=1.0, backend="numpy")
    spec = RasterSpec(resolution=(64, 48), pixel=1.0, keep_xy=True)
    spec0 = RasterSpec(resolution=(64, 48), pixel=1.0, keep_xy=True, gamma=0.0)
    got1, ref = check_against_raster(res, spec, [1], device)
    got0, _ = check_against_raster(res, spec0, [1], device)
    assert ref.max() == 255 and np.all(ref[0][37:41, 11:20] == 255)  # the overlap: full, once
    check_independent(res, spec, got1["numpy"], got0["numpy"], layer=1)


def comb(teeth: int, width: float = 2000.0, y0: float = 10.2, y1: float = 13.7) -> np.ndarray:
    """A comb: a spine from y0 - 2 to y0 and ``teeth`` triangular teeth up to y1 (counter-clockwise)."""
    x = np.linspace(1.0, width - 1.0, 2 * teeth + 1)
    top = np.stack([x, np.where(np.arange(x.size) % 2 == 1, y1, y0)], axis=1)[::-1]
    return np.concatenate([[[1.0, y0 - 2.0], [width - 1.0, y0 - 2.0]], top])


@pytest.mark.parametrize("teeth", [3000])
def test_row_with_thousands_of_pieces(device, teeth):
    """Every row the teeth cross holds ~2·teeth pieces: far more than one work-item's share (RUNS_CH records); a
    flat sliver's one row piece spans 1,990 columns (one descriptor; its row has more than CH cell records: the
    host finishes it)."""
    spec = RasterSpec(resolution=(2000, 20), pixel=1.0, keep_xy=True)
    sliver = np.array([[2.0, 10.1], [1995.0, 10.6], [2.0, 10.35]])
    res = make_result([[(comb(teeth), False, -1, True)], [(sliver, False, -1, True)]])
    le = layer_edges(res, spec)
    e = le.edges.astype(np.float32)
    units = _units(e, np.full(len(e), 20), RunsKernel.ROWS_PER_UNIT)
    assert np.all(units[:, 2] - units[:, 1] < RunsKernel.ROWS_PER_UNIT) and np.all(units[:, 2] >= units[:, 1])
    a = runs_numpy(le, gamma_lut(1.0), spec.shape)
    b = RunsKernel.of(device).run(le, range(2), gamma_lut(1.0), spec.shape)
    assert_runs_equal(a, b)
    ref = masks(res, spec, backend="opencl-bitmap", device=device)
    assert np.array_equal(b.to_masks(), ref)
    # the host finishes the long rows, the device the others: force both in one batch with a tiny share
    kern = RunsKernel.of(device)
    kern.CH, ch, long_rows = 4, kern.CH, kern.long_rows
    try:
        assert_runs_equal(a, kern.run(le, range(2), gamma_lut(1.0), spec.shape))
        assert kern.long_rows > long_rows
    finally:
        kern.CH = ch
    # a capacity bound too low (forced): the batch is redone by the numpy twin, same runs
    kern.CAP_EXTRA, fallbacks = -3, kern.fallbacks
    try:
        assert_runs_equal(a, kern.run(le, range(2), gamma_lut(1.0), spec.shape))
        assert kern.fallbacks == fallbacks + 1
    finally:
        kern.CAP_EXTRA = 0
    spec0 = RasterSpec(resolution=(2000, 20), pixel=1.0, keep_xy=True, gamma=0.0)
    check_against_raster(res, spec0, [0, 1], device)


@pytest.mark.parametrize("seed", [1, 2])
def test_random_slopes(device, seed):
    """Random star polygons (every slope, steep to nearly horizontal, vertices anywhere in a pixel): runs == raster
    masks and the per-row record bound holds (no batch redone)."""
    rng = np.random.default_rng(seed)
    layers = []
    for _ in range(6):
        n = int(rng.integers(3, 40))
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = rng.uniform(2.0, 22.0, n) * rng.choice([1.0, 0.05], n, p=[0.8, 0.2]).clip(0.3)
        c = rng.uniform(24.0, 40.0, 2)
        pts = c + np.c_[np.cos(ang), np.sin(ang)] * rad[:, None]
        snap = rng.random(n) < 0.2  # vertices on pixel corners: horizontal and vertical edges on grid lines
        pts[snap] = np.round(pts[snap])
        layers.append([(pts, False, -1, True)])
    res = make_result(layers)
    for gamma in (1.0, 0.0):
        spec = RasterSpec(resolution=(64, 48), pixel=1.0, keep_xy=True, gamma=gamma)
        check_against_raster(res, spec, list(range(6)), device)


def test_short_nearly_horizontal_edges_reserve_what_they_cover(device):
    """A zigzag of 4,000 edges 0.5 px long and 0.004 px tall across a row boundary, on a 4,000-column display: each
    piece's capacity was bounded by |du/dv| (125 columns here, the whole tile row for flatter ones), reserving
    ~60x a batch's budget on a CAD part (fandisk: 1.3 GB); it is now bounded by the edge's own |du| too."""
    n = 4000
    x = 10.0 + 0.5 * np.arange(n + 1)
    top = np.c_[x, np.where(np.arange(n + 1) % 2, 20.002, 19.998)]
    poly = np.concatenate([top, [[x[-1], 10.0], [x[0], 10.0]]])[::-1]  # counter-clockwise
    res = make_result([[(poly, False, -1, True)]])
    spec = RasterSpec(resolution=(4000, 40), pixel=1.0, keep_xy=True, gamma=1.0)
    kern = RunsKernel.of(device)
    kern.peak_slots, fallbacks = 0, kern.fallbacks
    b = kern.run(layer_edges(res, spec), range(1), gamma_lut(1.0), spec.shape)
    assert kern.fallbacks == fallbacks
    assert 0 < kern.peak_slots < 20 * (n + 2) * 2  # a few cells an edge in each of its two rows (was ~2,000,000)
    assert_runs_equal(runs_numpy(layer_edges(res, spec), gamma_lut(1.0), spec.shape), b)
    check_against_raster(res, spec, [0], device)


def test_iter_runs_batches_and_empty_layers(device):
    res = slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 48, 24)), z=np.array([-1.0, 2.0, 5.0, 50.0]),
                     backend="numpy")
    spec = RasterSpec(resolution=(900, 900), pixel=0.05)
    for be in ("numpy", "opencl"):
        parts = list(iter_runs(res, spec, backend=be, device=device, max_batch_pieces=1))
        assert len(parts) == 4 and [int(p.layers[0]) for p in parts] == [0, 1, 2, 3]
        assert parts[0].n_runs == 0 and parts[3].n_runs == 0 and parts[1].n_runs > 0
        whole = Runs.concat(parts, spec.shape)
        assert_runs_equal(whole, layer_runs(res, spec, backend=be, device=device))
        assert np.array_equal(whole.to_masks(), masks(res, spec, backend="opencl-bitmap", device=device))
        one = whole.layer(2)
        assert one.layers.tolist() == [2] and np.array_equal(one.to_mask(0), whole.to_mask(2))
    sub = layer_runs(res, spec, backend="numpy", layers=[2, 1])
    assert sub.layers.tolist() == [2, 1]
    assert np.array_equal(sub.to_mask(0), masks(res, spec, backend="opencl-bitmap", layers=[2])[0])


def test_lanes_same_runs_in_order_and_errors_where_they_happen(device):
    """Batches made in 1, 2 or 3 lanes (queues and threads of their own): the same runs in the same order; closing
    the iterator early leaves no lane thread behind; an error in one lane's batch is raised where that batch would
    have come, after the batches before it."""
    from gpuslice.prefetch import live_threads
    from gpuslice.raster import runs as runs_mod

    res = slice_mesh(mesh_from_triangles(shapes.torus(15.0, 5.0, 48, 24)), thickness=1.0, backend="numpy")
    spec = RasterSpec(resolution=(900, 900), pixel=0.05)
    parts = {n: list(iter_runs(res, spec, device=device, max_batch_pieces=2_000, lanes=n)) for n in (1, 2, 3)}
    assert len(parts[1]) >= 6  # several batches per lane
    for n in (2, 3):
        assert len(parts[n]) == len(parts[1])
        for a, b in zip(parts[1], parts[n], strict=True):
            assert_runs_equal(a, b)
    it = iter_runs(res, spec, device=device, max_batch_pieces=2_000, lanes=2)
    next(it)
    it.close()
    assert not [name for name in live_threads() if name.startswith("gpuslice-runs-lane")]
    lane1 = RunsKernel.of(device.lane(1))

    def broken(*args):
        raise RuntimeError("lane 1 failed")

    lane1.run = broken
    try:
        got = []
        with pytest.raises(RuntimeError, match="lane 1 failed"):
            for r in iter_runs(res, spec, device=device, max_batch_pieces=2_000, lanes=2):
                got.append(r)
        assert len(got) == 1  # batch 0 (lane 0) came; batch 1 (lane 1) raised
        assert_runs_equal(got[0], parts[1][0])
    finally:
        del lane1.run
    with pytest.raises(Exception, match="lanes must be at least 1"):
        next(iter_runs(res, spec, device=device, lanes=0))
    assert runs_mod.LANES >= 1


def test_edges_cut_into_row_bands_and_overlapping_pieces(device):
    """Every edge cut into units of 2 rows (runs_pieces writes nearly all pieces), star polygons whose vertices put
    two or more pieces in the same cells of a row (summed per cell first in runs_rows): runs == the numpy twin."""
    rng = np.random.default_rng(7)
    layers = []
    for _ in range(4):
        n = int(rng.integers(20, 60))
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = rng.uniform(3.0, 22.0, n)
        pts = np.array([32.0, 24.0]) + np.c_[np.cos(ang), np.sin(ang)] * rad[:, None]
        layers.append([(pts, False, -1, True)])
    res = make_result(layers)
    le = layer_edges(res, SMALL)
    kern = RunsKernel.of(device)
    want = runs_numpy(le, gamma_lut(1.0), SMALL.shape)
    kern.ROWS_PER_UNIT, rpu = 2, kern.ROWS_PER_UNIT
    try:
        assert_runs_equal(want, kern.run(le, range(4), gamma_lut(1.0), SMALL.shape))
    finally:
        kern.ROWS_PER_UNIT = rpu
    assert_runs_equal(want, kern.run(le, range(4), gamma_lut(1.0), SMALL.shape))


@pytest.mark.parametrize("rows_per_unit", [100, 1000])
def test_edges_longer_than_a_work_items_private_pieces(device, rows_per_unit):
    """Work units of up to 100 or 1000 rows of an edge (the default is 32): a work-item makes an edge's pieces 32 rows
    at a time (kernels/runs.cl, RUNS_UNIT_ROWS), its x carried from chunk to chunk; tall polygons whose edges span
    up to ~300 rows, starting anywhere in a pixel: runs == the numpy twin, gamma 1 and 0."""
    rng = np.random.default_rng(11)
    layers = []
    for _ in range(3):
        n = int(rng.integers(5, 12))
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        pts = np.array([32.0, 160.0]) + np.c_[np.cos(ang) * rng.uniform(5.0, 30.0, n), np.sin(ang) * 150.0]
        layers.append([(pts, False, -1, True)])
    res = make_result(layers)
    spec = RasterSpec(resolution=(64, 320), pixel=1.0, keep_xy=True)
    le = layer_edges(res, spec)
    assert (np.abs(le.edges[:, 3] - le.edges[:, 1]) > 64).sum() >= 3  # edges of more than two 32-row chunks
    kern = RunsKernel.of(device)
    kern.ROWS_PER_UNIT, rpu = rows_per_unit, kern.ROWS_PER_UNIT
    try:
        for gamma in (1.0, 0.0):
            lut = gamma_lut(gamma)
            assert_runs_equal(runs_numpy(le, lut, spec.shape), kern.run(le, range(3), lut, spec.shape))
    finally:
        kern.ROWS_PER_UNIT = rpu


def test_tile_wider_than_15_bits(device):
    """A layer 40,000 pixels wide (piece cells are 15-bit columns on the device): the numpy twin's runs, exact."""
    spec = RasterSpec(resolution=(40000, 6), pixel=1.0, keep_xy=True)
    res = make_result([[(np.array([[0.5, 1.2], [39999.5, 2.7], [20000.0, 5.5]]), False, -1, True)]])
    got, _ = check_against_raster(res, spec, [0], device)
    assert got["opencl"].n_runs > 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_layer_edges_against_a_loop_by_loop_reference(dtype):
    """layer_edges (consecutive loops read as one slice of the points, open and two-point loops dropped, each edge's
    end copied from its successor's start) == each kept loop's edges made one by one: float64 pixels from
    RasterSpec.to_pixels minus the tile corner, rounded once; every orientation of the display."""
    rng = np.random.default_rng(3)
    loop = lambda n, c: c + rng.uniform(-9.0, 9.0, (n, 2))  # noqa: E731
    layers = [[(loop(5, 20.0), False, -1, True), (loop(4, 30.0), False, -1, True)],
              [(loop(6, 25.0), False, -1, False), (loop(7, 25.0), False, -1, True)],  # an open loop first: a gap
              [(loop(2, 25.0), False, -1, True)], [],  # a two-point loop only; no loops
              [(loop(3, 15.0), False, -1, True), (loop(9, 35.0), False, -1, False), (loop(8, 22.0), False, -1, True)]]
    res = make_result(layers)
    for spec in (SMALL, RasterSpec(resolution=(640, 480), pixel=0.1, mirror_x=True),
                 RasterSpec(resolution=(640, 480), pixel=0.1, portrait=True, mirror_y=True)):
        for sel in (None, [4, 1, 1]):
            le = layer_edges(res, spec, layers=sel, dtype=dtype)
            assert le.edges.dtype == dtype
            for k, i in enumerate(range(res.n_layers) if sel is None else sel):
                want = []
                for j in range(res.layer_offsets[i], res.layer_offsets[i + 1]):
                    p = res.points[res.loop_offsets[j] : res.loop_offsets[j + 1]]
                    if res.loop_closed[j] and len(p) >= 3:
                        want.append(spec.to_pixels(np.asarray(p, np.float64), res_bounds(res)))
                got = le.edges[le.edge_offsets[k] : le.edge_offsets[k + 1]]
                if not want:
                    assert got.shape == (0, 4) and np.all(le.tiles[k] == 0)
                    continue
                uv = np.concatenate(want)
                r0, c0 = np.floor(uv[:, 1].min()), np.floor(uv[:, 0].min())
                assert le.tiles[k].tolist() == [r0, c0, np.floor(uv[:, 1].max()) + 1 - r0,
                                                np.floor(uv[:, 0].max()) + 1 - c0]
                ref = np.concatenate([np.c_[w, np.roll(w, -1, axis=0)] for w in want]) - [c0, r0, c0, r0]
                assert np.array_equal(got, ref.astype(dtype))


def res_bounds(res):
    lo, hi = res.points.min(axis=0).astype(np.float64), res.points.max(axis=0).astype(np.float64)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def test_batches_cover_the_layers_within_the_estimate(solid):
    """_batches: consecutive ranges covering every layer; a batch of several layers holds at most about max_pieces
    records by the estimate (per edge |du| + |dv| + 2 cells, 64 more a layer), and the next layer would not fit."""
    from gpuslice.raster.runs import _batches

    le = layer_edges(solid, SPEC4K, dtype=np.float32)
    e, off = le.edges.astype(np.float64), le.edge_offsets
    per_edge = np.abs(e[:, 3] - e[:, 1]) + np.abs(e[:, 2] - e[:, 0]) + 2.0
    per = np.array([per_edge[off[i] : off[i + 1]].sum() + 64.0 for i in range(len(le.tiles))])
    for max_pieces in (1, 5_000, 40_000, 10**9):
        parts = list(_batches(le, max_pieces))
        assert parts[0].start == 0 and parts[-1].stop == len(le.tiles)
        assert all(a.stop == b.start and len(a) >= 1 for a, b in zip(parts, parts[1:], strict=False))
        for b in parts:
            est = per[b.start : b.stop].sum()
            assert len(b) == 1 or est <= max_pieces * 1.001
            if b.stop < len(le.tiles):
                assert est + per[b.stop] > max_pieces * 0.999


@pytest.mark.parametrize("gamma", [1.0, 0.0])
def test_no_drift_along_a_long_edge_nearly_parallel_to_the_rows(device, gamma):
    """A strip 200 mm long turned by 1e-5 rad, on a 12K display: its long edges cross ~10,500 cells of the same rows,
    one of them near half of each pixel. Each cell's share used to be rounded apart, the same way in every cell of a
    row, and the running sum drifted: greys off by up to 27 levels against the float64 coverage, and at gamma 0
    10,526 pixels on the wrong side of 50 %. The runs, the bitmap kernel and the runs' numpy twin now stay within
    one level (gamma 0: only pixels whose coverage rounds to 127 or 128 of 256 may differ)."""
    th = 1e-5
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    tri = shapes.box((0.0, 0.0, 0.0), (200.0, 3.019, 1.0)).astype(np.float64)
    tri[..., :2] = tri[..., :2] @ rot.T
    res = slice_mesh(mesh_from_triangles(tri.astype(np.float32)), z=np.array([0.5]), layer_thickness=1.0)
    spec = RasterSpec(resolution=(11520, 5120), pixel=0.019, gamma=gamma)
    cover = masks(res, RasterSpec(resolution=(11520, 5120), pixel=0.019), backend="numpy").astype(int)[0]
    exact = masks(res, spec, backend="numpy").astype(int)[0]
    rows = np.flatnonzero(((cover > 0) & (cover < 255)).sum(axis=1) > 1000)
    assert rows.size == 2 and (np.abs(cover[rows] - 127) <= 1).sum() > 1000  # the long edges' rows, near 50 %
    got = {"runs": masks(res, spec, device=device)[0],
           "bitmap": masks(res, spec, backend="opencl-bitmap", device=device)[0]}
    got["twin"] = runs_to_mask(runs_numpy(layer_edges(res, spec), gamma_lut(gamma), spec.shape), 0)
    for name, m in got.items():
        diff = np.abs(m.astype(int)[rows] - exact[rows])
        if gamma == 0:
            assert np.isin(cover[rows][diff > 0], [127, 128]).all(), (name, int((diff > 0).sum()))
        else:
            assert diff.max() <= 1, (name, int(diff.max()))
