"""Stage after nesting for resin printers: every layer's polygons as an 8-bit mask of the printer's display.

**Mapping model XY → pixels** (one mapping, PrusaSlicer's, see ``docs/ARCHITECTURE.md``). A display of
``nx × ny`` pixels (PrusaSlicer's ``display_pixels_x/y``) of ``px × py`` mm, so ``W = nx·px`` by ``H = ny·py`` mm
(``display_width/height``); the bed is W (X) by H (Y) mm. Pixel coordinates are continuous: column ``j`` covers
``u ∈ [j, j + 1)``, row ``i`` covers ``v ∈ [i, i + 1)``, row 0 is the top row of the PNG.

* The model is first moved so that the centre of its XY bounding box is the centre of the bed (``keep_xy``
  keeps the model's own XY: bed coordinates = model coordinates).
* **Landscape** (default): the PNG is nx wide, ny tall; ``u = X / px``, ``v = (H − Y) / py``: column j has its
  centre at X = (j + 0.5)·px and row 0 is the +Y edge.
* **Portrait**: the PNG is ny wide, nx tall, X running down the rows: ``u = (H − Y) / py``, ``v = (W − X) / px``
  (what PrusaSlicer 2.5 writes for ``display_orientation = portrait``, checked against its SL1 on cow).
* ``mirror_x`` then mirrors the PNG's columns (``u → width − u``), ``mirror_y`` its rows (``v → height − v``), as
  PrusaSlicer's ``display_mirror_x/y`` in both orientations (checked against its SL1s; note that PrusaSlicer's own
  default is ``display_mirror_x = 1``, ours is no mirror).

**Grey levels** are area coverage with PrusaSlicer's (agg's) gamma semantics: the covered fraction ``c`` of a pixel
becomes ``k = min(255, floor(256·c))`` and the grey is ``round(255 · (k / 255)^gamma)``; ``gamma = 0`` is a hard
threshold: 255 where ``c ≥ 0.5``, else 0. Coverage is exact (analytic), not sampled: the signed area of every
edge is accumulated per pixel cell and summed along the row (the polygons of a :class:`SliceResult` are already
resolved under its fill rule, so their winding number is 0 or 1 everywhere and this is exact coverage).

**Tiles**: a layer never touches pixels outside its bounding box. Rasterisers return :class:`Tile`\\ s (the bbox's
rows and columns); :func:`iter_tiles` yields them, :func:`iter_masks` full (ny, nx) masks, :func:`masks` a
(layers, rows, cols) uint8 array (beware: 1,600 layers of 3840×2400 are 14.7 GB; pass ``layers=``).

Backends: ``"opencl"`` (run-length runs, :mod:`gpuslice.raster.runs` + ``kernels/runs.cl``: the greys of
``kernels/raster.cl`` byte for byte, 10x faster, never a display-sized bitmap; tiles are filled from the runs),
``"opencl-bitmap"`` (``kernels/raster.cl``, :class:`RasterKernel`: the bitmap accumulator the runs replaced, kept for
benchmarks), ``"numpy"`` (the runs' numpy twin, :func:`gpuslice.raster.runs_twin.runs_numpy`: the OpenCL runs' greys
byte for byte, so ``masks()``, the viewer and ``raster`` give the same pixels on either backend), ``"numpy-bitmap"``
(:func:`coverage_numpy`, the bitmap kernel's float64 twin, the numpy backend before: it may differ from the runs by
one grey level, on the shared meshes up to 0.8 % of the pixels covered, and at gamma 0 a pixel within a level of
50 % then falls on the other side), ``"gl"`` (moderngl/EGL,
:mod:`gpuslice.raster.gl`, supersampled). ``"auto"`` is the runs (OpenCL): GL is the optional GPU pass, taken only
when asked (probing EGL for a hardware GPU costs 0.1 s at start-up; llvmpipe, Mesa's software GL, is 50-135x slower
than the runs on a CPU: docs/BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..device import KernelDriver, locked
from ..errors import ParameterError
from ..ragged import expand_ranges
from ..slicing.result import SliceResult
from .edges import LayerEdges, check_fits, check_raster_args, layer_edges
from .spec import BACKENDS, RasterSpec, gamma_lut

__all__ = ["Tile", "coverage_numpy", "RasterKernel", "iter_tiles", "iter_masks", "masks", "choose_backend",
           "tile_from_runs"]


#: fixed-point scale of the OpenCL accumulation (coverage 1.0 = 65536); ``|sum| >> 8`` is ``floor(256·c)``
FIXED_ONE = 1 << 16


@dataclass
class Tile:
    """One layer's mask inside its bounding box: ``data`` (rows, cols) uint8 at (``row0``, ``col0``) of the display."""

    index: int
    row0: int
    col0: int
    data: np.ndarray = field(repr=False)

    def full(self, shape: tuple[int, int]) -> np.ndarray:
        """The whole (ny, nx) mask."""
        out = np.zeros(shape, np.uint8)
        h, w = self.data.shape
        out[self.row0 : self.row0 + h, self.col0 : self.col0 + w] = self.data
        return out


def coverage_numpy(edges: np.ndarray, rows: int, cols: int, lut: np.ndarray) -> np.ndarray:
    """The numpy twin of ``kernels/raster.cl``: (rows, cols) uint8 greys of one tile from its edges (E, 4) in
    tile-local pixel coordinates, by exact area accumulation and a prefix sum along each row."""
    if rows == 0 or cols == 0:
        return np.zeros((rows, cols), np.uint8)
    e = np.asarray(edges, dtype=np.float64)
    u0, v0, u1, v1 = e[:, 0], e[:, 1], e[:, 2], e[:, 3]
    k = v0 != v1
    u0, v0, u1, v1 = u0[k], v0[k], u1[k], v1[k]
    sgn = np.where(v1 > v0, 1.0, -1.0)
    va, vb = np.minimum(v0, v1), np.maximum(v0, v1)
    dudv = (u1 - u0) / (v1 - v0)
    ra = np.maximum(np.floor(va), 0).astype(np.int64)
    rb = np.minimum(np.ceil(vb) - 1, rows - 1).astype(np.int64)
    n = np.maximum(rb - ra + 1, 0)
    ei, r = expand_ranges(ra, n)
    ys = np.maximum(va[ei], r)
    ye = np.minimum(vb[ei], r + 1.0)
    ok = ye > ys
    ei, r, ys, ye = ei[ok], r[ok], ys[ok], ye[ok]
    xs = u0[ei] + (ys - v0[ei]) * dudv[ei]
    xe = u0[ei] + (ye - v0[ei]) * dudv[ei]
    dy = (ye - ys) * sgn[ei]
    umin, umax = np.minimum(xs, xe), np.maximum(xs, xe)
    acc = np.zeros(rows * cols + 1, np.float64)
    flat = []
    wts = []
    # wholly left of the tile: all of dy to column 0; wholly right: nothing
    left = umax <= 0
    flat.append(r[left] * cols)
    wts.append(dy[left])
    live = ~left & (umin < cols)
    r, dy, umin, umax = r[live], dy[live], umin[live], umax[live]
    vert = umin == umax
    # vertical pieces: one cell
    c = np.floor(umin[vert]).astype(np.int64)
    xm = umin[vert] - c
    flat += [r[vert] * cols + c, np.where(c + 1 < cols, r[vert] * cols + c + 1, rows * cols)]
    wts += [dy[vert] * (1 - xm), dy[vert] * xm]
    sl = ~vert
    r, dy, umin, umax = r[sl], dy[sl], umin[sl], umax[sl]
    slope = dy / (umax - umin)
    part = umin < 0
    flat.append(r[part] * cols)
    wts.append((0 - umin[part]) * slope[part])
    ca = np.maximum(np.floor(umin), 0).astype(np.int64)
    cb = np.minimum(np.ceil(umax) - 1, cols - 1).astype(np.int64)
    m = np.maximum(cb - ca + 1, 0)
    pi, c = expand_ranges(ca, m)
    a = np.maximum(umin[pi], c)
    b = np.minimum(umax[pi], c + 1.0)
    d = (b - a) * slope[pi]
    xm = (a + b) / 2 - c
    rr = r[pi]
    flat += [rr * cols + c, np.where(c + 1 < cols, rr * cols + c + 1, rows * cols)]
    wts += [d * (1 - xm), d * xm]
    acc += np.bincount(np.concatenate(flat), np.concatenate(wts), minlength=rows * cols + 1)
    cov = np.abs(np.cumsum(acc[:-1].reshape(rows, cols), axis=1))
    kk = np.minimum(np.floor(cov * 256.0), 255).astype(np.int64)
    return lut[kk]


class RasterKernel(KernelDriver):
    """Driver of ``kernels/raster.cl``: many layers' tiles per launch (edges accumulated with integer atomics in
    16.16 fixed point, then one work-item per tile row sums, applies the gamma table and clears the accumulator)."""

    def __init__(self, device) -> None:
        super().__init__(device)
        prog = device.program("raster.cl")
        self._acc = prog.raster_accumulate
        self._resolve = prog.raster_resolve
        self._acc_size = 0
        self._acc_clean = True  # False between the two kernels of a call (see run)

    @locked
    def run(self, le: LayerEdges, batch: range, lut: np.ndarray) -> list[np.ndarray]:
        """Tiles of the layers ``batch`` (indices into ``le``): a list of (rows, cols) uint8 arrays."""
        import pyopencl as cl

        q = self.device.queue
        t = le.tiles[batch.start : batch.stop]
        npx = t[:, 2] * t[:, 3]
        px_off = np.zeros(len(t) + 1, np.int64)
        np.cumsum(npx, out=px_off[1:])
        total_px = int(px_off[-1])
        e0, e1 = int(le.edge_offsets[batch.start]), int(le.edge_offsets[batch.stop])
        n_edges = e1 - e0
        out = np.empty(total_px, np.uint8)
        if total_px == 0:
            return [out[:0].reshape(0, 0) for _ in range(len(t))]
        row_off = np.zeros(len(t) + 1, np.int64)
        np.cumsum(t[:, 2], out=row_off[1:])
        n_rows = int(row_off[-1])
        tiles = np.zeros((len(t), 4), np.int32)
        tiles[:, 0], tiles[:, 1], tiles[:, 2], tiles[:, 3] = px_off[:-1], t[:, 3], t[:, 2], row_off[:-1]
        counts = np.diff(le.edge_offsets[batch.start : batch.stop + 1])
        edge_tile = np.repeat(np.arange(len(t), dtype=np.int32), counts)
        row_tile = np.repeat(np.arange(len(t), dtype=np.int32), t[:, 2])
        need = total_px * 4
        if "acc" not in self._buffers or not self._acc_clean:  # never made, dropped by release_scratch, or left
            self._acc_size = 0  # with sums in it by a call stopped between its two kernels: zeroed whole
        if need > self._acc_size:
            self._acc_size = max(need, int(self._acc_size * 1.5) // 4 * 4)
            acc = self._fill("acc", self._acc_size, np.int32(0))
        else:
            acc = self._buffer("acc", need)
        b_tiles = self._put("tiles", tiles)
        b_lut = self._put("lut", np.ascontiguousarray(lut, np.uint8))
        b_out = self._buffer("out", total_px)
        if n_edges:
            b_edges = self._put("edges", le.edges[e0:e1].astype(np.float32))
            b_et = self._put("edge_tile", edge_tile)
            g, loc = self._grid(n_edges)
            self._acc_clean = False  # (raster_resolve zeroes what raster_accumulate added)
            self._acc(q, g, loc, np.int32(n_edges), b_edges, b_et, b_tiles, acc)
        b_rt = self._put("row_tile", row_tile)
        g, loc = self._grid(n_rows)
        self._resolve(q, g, loc, np.int32(n_rows), b_rt, b_tiles, acc, b_lut, b_out)
        cl.enqueue_copy(q, out, b_out, is_blocking=True)
        self._acc_clean = True
        return [out[px_off[i] : px_off[i + 1]].reshape(t[i, 2], t[i, 3]) for i in range(len(t))]


def choose_backend(backend: str = "auto", device=None) -> str:
    """The rasteriser ``backend`` names: ``"auto"`` → ``"opencl"`` (the runs); the others as given."""
    if backend not in BACKENDS:
        raise ParameterError(f"unknown raster backend '{backend}' (use {', '.join(BACKENDS)})")
    return "opencl" if backend == "auto" else backend


def _batches(tiles: np.ndarray, max_pixels: int) -> Iterator[range]:
    npx = tiles[:, 2] * tiles[:, 3]
    start, acc = 0, 0
    for i, p in enumerate(npx.tolist()):
        if acc + p > max_pixels and i > start:
            yield range(start, i)
            start, acc = i, 0
        acc += p
    if start < len(npx):
        yield range(start, len(npx))


def iter_tiles(
    result: SliceResult,
    spec: RasterSpec | None = None,
    *,
    backend: str = "auto",
    device=None,
    bounds=None,
    layers: Sequence[int] | None = None,
    supersample: int = 8,
    max_batch_pixels: int = 1 << 24,
    clip: bool = False,
) -> Iterator[Tile]:
    """Yield every layer's :class:`Tile` in order (the masks' non-blank part), ``layers`` (default all) only.

    backend : ``auto``, ``opencl``, ``numpy`` or ``gl`` (:func:`choose_backend`); device : the OpenCL device
    (default :func:`gpuslice.device.get_device`). bounds : the (xmin, ymin, xmax, ymax) mm centred on the bed
    (default: the result's points; the CLI gives the mesh's). supersample : GL samples per pixel side (8: 64
    samples; thresholded IoU with the exact backends >= 0.999). clip : keep only what lies on the display of a
    layer that reaches outside it (default: :class:`~gpuslice.errors.ParameterError` "does not fit", as the
    command line says; a cropped mask was returned silently before).
    """
    spec = spec or RasterSpec()
    backend = choose_backend(backend, device)
    le = layer_edges(result, spec, bounds, layers)
    if not clip:
        check_fits(result, spec, bounds, layers=layers)
    index = np.arange(result.n_layers) if layers is None else np.asarray(layers, dtype=np.int64)
    lut = gamma_lut(spec.gamma)
    if backend == "numpy-bitmap":  # the bitmap kernel's float64 twin (the reference of opencl-bitmap's tests)
        for k in range(index.size):
            r0, c0, h, w = (int(x) for x in le.tiles[k])
            e = le.edges[le.edge_offsets[k] : le.edge_offsets[k + 1]]
            yield Tile(int(index[k]), r0, c0, coverage_numpy(e, h, w, lut))
        return
    if backend == "gl":
        from .gl import GLRasteriser

        gl = GLRasteriser.get(supersample)
        for k in range(index.size):
            r0, c0, h, w = (int(x) for x in le.tiles[k])
            e = le.edges[le.edge_offsets[k] : le.edge_offsets[k + 1]]
            yield Tile(int(index[k]), r0, c0, gl.coverage(e, h, w, lut))
        return
    from ..device import get_device
    from .runs import iter_runs

    dev = None if backend == "numpy" else device if device is not None else get_device()
    if backend == "opencl-bitmap":  # the bitmap kernel the runs replaced (kept for benchmarks and tests)
        kern = RasterKernel.of(dev)
        for batch in _batches(le.tiles, max_batch_pixels):
            datas = kern.run(le, batch, lut)
            for k, data in zip(batch, datas, strict=True):
                yield Tile(int(index[k]), int(le.tiles[k, 0]), int(le.tiles[k, 1]), data)
        return
    k = 0  # the runs, OpenCL or their numpy twin (the same bytes)
    for runs in iter_runs(result, spec, backend="numpy" if backend == "numpy" else "opencl", device=dev,
                          layers=layers, edges=le, clip=True):
        for j in range(len(runs.layers)):
            r0, c0, h, w = (int(x) for x in le.tiles[k])
            yield Tile(int(index[k]), r0, c0, tile_from_runs(runs, j, r0, c0, h, w))
            k += 1


def tile_from_runs(runs, j: int, row0: int, col0: int, rows: int, cols: int) -> np.ndarray:
    """The (rows, cols) uint8 bitmap at (``row0``, ``col0``) of the display of entry ``j`` of ``runs``
    (:class:`gpuslice.raster.runs.Runs`): what a PNG row encoder needs, in time proportional to the covered
    pixels (never the display)."""
    out = np.zeros(rows * cols, np.uint8)
    a, b = int(runs.layer_offsets[j]), int(runs.layer_offsets[j + 1])
    if b > a:
        length = runs.length[a:b].astype(np.int64)
        start = (runs.row[a:b].astype(np.int64) - row0) * cols + (runs.x[a:b].astype(np.int64) - col0)
        _, idx = expand_ranges(start, length)
        out[idx] = np.repeat(runs.grey[a:b], length)
    return out.reshape(rows, cols)


def iter_masks(result: SliceResult, spec: RasterSpec | None = None, **options) -> Iterator[np.ndarray]:
    """Yield each layer's full (ny, nx) uint8 mask in order; options as :func:`iter_tiles`."""
    spec = spec or RasterSpec()
    for tile in iter_tiles(result, spec, **options):
        yield tile.full(spec.shape)


def masks(result: SliceResult, spec: RasterSpec | None = None, **options) -> np.ndarray:
    """(layers, ny, nx) uint8 masks (grey = coverage, see the module docstring); options as :func:`iter_tiles`.

    Row 0 is the top of the display (the +Y edge in landscape). Use ``layers=[...]`` or :func:`iter_masks` for
    big displays: every layer costs nx·ny bytes.
    """
    check_raster_args(result, spec, options.get("layers"), options.get("bounds"))
    spec = spec or RasterSpec()
    n = result.n_layers if options.get("layers") is None else len(options["layers"])
    out = np.zeros((n, *spec.shape), np.uint8)
    for k, tile in enumerate(iter_tiles(result, spec, **options)):
        h, w = tile.data.shape
        out[k, tile.row0 : tile.row0 + h, tile.col0 : tile.col0 + w] = tile.data
    return out
