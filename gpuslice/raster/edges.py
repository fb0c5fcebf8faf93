"""The nested polygons of a result in a display's pixel space, the input of every rasteriser (the runs of
:mod:`gpuslice.raster.runs`, the bitmap kernel and twins of :mod:`gpuslice.raster.coverage`, the GL pass): each
layer's closed loops as edges relative to its tile (the layer's bounding box in pixels), the check that the model
fits the display, and the z sub-planes of ``--z-samples`` merged back into their layers. The mapping model XY →
pixels is :class:`~gpuslice.raster.spec.RasterSpec`'s (see :mod:`gpuslice.raster.coverage`).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..formats.numbers import point_bounds
from ..ragged import expand_ranges
from ..slicing.result import SliceResult
from .spec import RasterSpec

__all__ = ["LayerEdges", "box_tiles", "check_fits", "check_points_fit", "check_printer_fits", "iter_layer_edges",
           "layer_edges", "merge_layer_groups", "merge_tiles", "pixel_box", "result_bounds", "splice_layers",
           "z_sample_planes"]


@dataclass
class LayerEdges:
    """Every closed loop's edges in pixel coordinates, layer by layer, and each layer's tile.

    edges (E, 4) float64 (u0, v0, u1, v1) relative to the layer's tile corner; edge_offsets (L + 1,);
    tiles (L, 4) int64 (row0, col0, rows, cols), an empty layer has rows = cols = 0.
    """

    edges: np.ndarray
    edge_offsets: np.ndarray
    tiles: np.ndarray


def result_bounds(result: SliceResult) -> tuple[float, float, float, float] | None:
    """(xmin, ymin, xmax, ymax) of all points of ``result``, mm; None when it has none."""
    if result.points.shape[0] == 0:
        return None
    lo, hi = point_bounds(result.points)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def pixel_box(xy: np.ndarray, spec: RasterSpec, bounds) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) pixel coordinates (u, v) of the points ``xy`` ((n > 0, 2) mm) on ``spec``'s display, placed by
    ``bounds``: from the four corners of their box alone, since u and v each move with one of x and y
    (:meth:`RasterSpec.affine`) through correctly rounded steps that never reverse an order (exact, not a bound)."""
    (x0, y0), (x1, y1) = point_bounds(xy)
    corners = np.array([[x0, y0], [x0, y1], [x1, y0], [x1, y1]], np.float64)
    return point_bounds(spec.to_pixels(corners, bounds))


def check_points_fit(xy: np.ndarray, spec: RasterSpec, bounds, name: str = "model") -> None:
    """Raise :class:`ParameterError` naming ``name`` when any of the model points ``xy`` ((n, 2) mm, placed on the
    display by ``bounds`` as :meth:`RasterSpec.offset_for` does) lands outside the display."""
    xy = np.asarray(xy)
    if xy.shape[0] == 0:
        return
    (x0, y0), (x1, y1) = point_bounds(xy)
    lo, hi = pixel_box(xy, spec, bounds)
    # two float32 steps of the largest coordinate, in pixels: a part exactly the display's size (whose float32
    # points lie a step over it, as 68.04 rounds up) fits; what lies past the edge by that much is not drawn
    ulp = float(np.spacing(np.float32(max(abs(x0), abs(x1), abs(y0), abs(y1)))))
    eps = max(1e-6, 2.0 * ulp / min(spec.px, spec.py))
    cols, rows = spec.png_size
    if lo[0] < -eps or lo[1] < -eps or hi[0] > cols + eps or hi[1] > rows + eps:
        bx, by = spec.bed_mm
        w, h = (float(v) for v in np.subtract(*point_bounds(xy)[::-1]))
        where = ""
        if getattr(spec, "keep_xy", False):  # (its own XY: say where it is, and where the display is)
            where = (f": --keep-xy keeps its own x {x0:.2f} to {x1:.2f} and y {y0:.2f} to {y1:.2f} mm, and the display "
                     f"spans x 0 to {bx:.2f} and y 0 to {by:.2f} mm (move the model, or leave --keep-xy out to centre "
                     "it)")
        over = max(-lo[0], -lo[1], hi[0] - cols, hi[1] - rows)
        by_px = f" (it reaches {over:.3g} pixels past an edge)" if over < 1 and not where else ""
        raise ParameterError(f"{name}: the model ({w:.2f} x {h:.2f} mm) does not fit on the display "
                             f"({bx:.2f} x {by:.2f} mm) at this placement{where}{by_px}")


def check_printer_fits(name: str, mesh, spec: RasterSpec | None, preset, bounds) -> None:
    """:class:`ParameterError` when the placed ``mesh``'s XY box leaves the display ``spec`` (placed by ``bounds``)
    or its height exceeds the printer ``preset``'s build height, before slicing (the exact per-layer check follows
    after it: :func:`check_fits`)."""
    if spec is not None:
        check_points_fit(mesh.bounds[:, :2].astype(np.float64), spec, bounds, name)  # the XY box's corners
    if preset is not None and preset.build_height > 0 and mesh.height > preset.build_height + 1e-6:
        raise ParameterError(f"{name}: the model is {mesh.height:.2f} mm tall, more than the "
                             f"{preset.name}'s build height ({preset.build_height:g} mm)")


def check_fits(result: SliceResult, spec: RasterSpec, bounds=None, name: str = "model",
               layers: Sequence[int] | None = None) -> None:
    """Raise :class:`ParameterError` when any layer (of ``layers``, default all) reaches outside the display, placed
    by ``bounds`` (default: the result's points)."""
    if not result.points.shape[0]:
        return
    bounds = bounds if bounds is not None else result_bounds(result)
    if layers is None:
        check_points_fit(result.points, spec, bounds, name)
        return
    lo = np.asarray(result.loop_offsets)[np.asarray(result.layer_offsets)]
    sel = np.asarray(layers, dtype=np.int64)
    _, idx = expand_ranges(lo[sel], lo[sel + 1] - lo[sel])
    check_points_fit(np.asarray(result.points)[idx], spec, bounds, name)


def _to_pixels(spec: RasterSpec, pc: np.ndarray, bounds) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`RasterSpec.to_pixels_xy` of the points ``pc`` (complex64: x + iy, mm): (u, v) float64, the same bits.
    Each of u and v depends on one of x and y (the other coefficient is 0, see :meth:`RasterSpec.affine`): there
    ``a * x + 0 * y + c`` is ``a * x + c`` exactly (adding a zero changes at most the sign of a zero sum, which adding
    c != 0 then drops), computed in place; any other matrix goes through ``to_pixels_xy``."""
    a = spec.affine(bounds)
    out = []
    for cx, cy, c in a:
        if (cx == 0) == (cy == 0) or c == 0 or not np.isfinite([cx, cy, c]).all():
            return spec.to_pixels_xy(pc.real, pc.imag, bounds)
        w = (pc.real if cy == 0 else pc.imag).astype(np.float64)
        w *= cx if cy == 0 else cy
        w += c
        out.append(w)
    return out[0], out[1]


def box_tiles(c_lo, c_hi, r_lo, r_hi, spec: RasterSpec) -> np.ndarray:
    """(n, 4) int64 tiles (row0, col0, rows, cols) of pixel boxes given as the floors of their points' smallest and
    largest u (columns) and v (rows), clipped to the display; a box left empty by the clipping has rows = cols = 0."""
    cols, rows = spec.png_size
    c0 = np.clip(c_lo, 0, cols).astype(np.int64)
    c1 = np.clip(np.asarray(c_hi) + 1, 0, cols).astype(np.int64)
    r0 = np.clip(r_lo, 0, rows).astype(np.int64)
    r1 = np.clip(np.asarray(r_hi) + 1, 0, rows).astype(np.int64)
    empty = (c1 <= c0) | (r1 <= r0)
    return np.stack([r0, c0, np.where(empty, 0, r1 - r0), np.where(empty, 0, c1 - c0)], axis=1)


def check_raster_args(result, spec, layers=None, bounds=None) -> None:
    """One-line :class:`ParameterError` for a ``result``, ``spec``, ``layers`` or ``bounds`` of the wrong kind, as
    every rasteriser takes them (the layers' range is checked by :func:`layer_edges`)."""
    if not isinstance(result, SliceResult):
        raise ParameterError(f"result must be a SliceResult (gpuslice.slice_mesh's), got {type(result).__name__}")
    if spec is not None and not isinstance(spec, RasterSpec):
        raise ParameterError(f"spec must be a RasterSpec (RasterSpec(...) or with_printer(name)), got "
                             f"{type(spec).__name__}", param="spec")
    if layers is not None:
        try:
            sel = np.asarray(layers)
        except (TypeError, ValueError):
            sel = np.zeros((0, 0))
        # floats would be truncated and booleans read as layers 0 and 1: neither is what was meant
        if sel.ndim != 1 or (sel.size and sel.dtype.kind not in "iu"):
            raise ParameterError(f"layers must be a sequence of whole layer indices, got {layers!r}"[:200],
                                 param="layers")
    if bounds is not None:
        try:
            b = np.asarray(bounds, dtype=np.float64)
        except (TypeError, ValueError):
            b = np.zeros(0)
        if b.shape != (4,) or not np.isfinite(b).all():
            raise ParameterError(f"bounds must be four finite numbers (xmin, ymin, xmax, ymax) in mm, got {bounds!r}",
                                 param="bounds")
        if not (b[0] <= b[2] and b[1] <= b[3]):  # (a reversed box made a display of negative size, named wrongly)
            raise ParameterError(f"bounds must be (xmin, ymin, xmax, ymax) with xmin <= xmax and ymin <= ymax, got "
                                 f"{bounds!r}", param="bounds")


def layer_edges(result: SliceResult, spec: RasterSpec, bounds=None, layers: Sequence[int] | None = None,
                dtype=np.float64) -> LayerEdges:
    """The edges of the closed loops of ``layers`` (default all) in tile-local pixel coordinates; see
    :class:`LayerEdges`. ``bounds`` (xmin, ymin, xmax, ymax) mm is what gets centred (default: the result's).
    ``dtype``: of the edges (computed in float64, rounded once: float32 is what the rasterisers take)."""
    check_raster_args(result, spec, layers, bounds)
    if bounds is None:
        bounds = result_bounds(result)
    n_layers = result.n_layers
    sel = np.arange(n_layers) if layers is None else np.asarray(layers, dtype=np.int64)
    if sel.size and (sel.min() < 0 or sel.max() >= n_layers):
        bad = int(sel[(sel < 0) | (sel >= n_layers)][0])
        raise ParameterError(f"layer index {bad} out of range 0..{n_layers - 1} (layers count from 0; no negative "
                             "indices here)", param="layers")
    lo_off = result.loop_offsets
    # loops of the selected layers, closed ones only
    loop_start = result.layer_offsets[sel]
    loop_count = result.layer_offsets[sel + 1] - loop_start
    loops = np.repeat(loop_start - np.concatenate(([0], np.cumsum(loop_count)[:-1])), loop_count) + np.arange(
        int(loop_count.sum())
    )
    loop_sel_layer = np.repeat(np.arange(sel.size), loop_count)
    keep = result.loop_closed[loops] if loops.size else np.zeros(0, bool)
    loops, loop_sel_layer = loops[keep], loop_sel_layer[keep]
    first, n = lo_off[loops], lo_off[loops + 1] - lo_off[loops]
    keep = n >= 3
    loops, loop_sel_layer, first, n = loops[keep], loop_sel_layer[keep], first[keep], n[keep]
    total = int(n.sum())
    start = np.zeros(n.size, np.int64)
    np.cumsum(n[:-1], out=start[1:])
    pts = np.ascontiguousarray(result.points, dtype=np.float32).view(np.complex64).reshape(-1)  # 1-D: fast
    if n.size and np.array_equal(first[1:], first[:-1] + n[:-1]):  # consecutive loops (the usual case): a view
        pc = pts[first[0] : first[0] + total]
    else:
        pc = pts[np.repeat(first - start, n) + np.arange(total, dtype=np.int64)]
    u, v = _to_pixels(spec, pc, bounds)
    counts = np.bincount(loop_sel_layer, weights=n, minlength=sel.size).astype(np.int64)
    offsets = np.zeros(sel.size + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    tiles = np.zeros((sel.size, 4), np.int64)
    nonempty = counts > 0
    if total:
        nz = offsets[:-1][nonempty]
        tiles[nonempty] = box_tiles(*(np.floor(f.reduceat(w, nz)) for f, w in ((np.minimum, u), (np.maximum, u),
                                                                               (np.minimum, v), (np.maximum, v))),
                                    spec)
    # each point relative to its layer's tile corner: a float64 difference rounded once to dtype (written straight
    # into the edges); an edge's end is its successor in the loop (the last point's: the first), of the same layer,
    # so its coordinates are the successor's start coordinates, copied
    edges = np.empty((total, 4), dtype)
    np.subtract(u, np.repeat(tiles[:, 1].astype(np.float64), counts), out=edges[:, 0])
    np.subtract(v, np.repeat(tiles[:, 0].astype(np.float64), counts), out=edges[:, 1])
    pair = edges.view({4: np.int64, 8: np.complex128}[edges.itemsize]) if edges.itemsize in (4, 8) else None
    if pair is not None:  # (u, v) pairs as one 8- or 16-byte item: a copy of the bits ~20x faster than [:, :2]
        pair[:-1, 1] = pair[1:, 0]
        pair[start + n - 1, 1] = pair[start, 0]
    else:
        edges[:-1, 2:] = edges[1:, :2]
        edges[start + n - 1, 2:] = edges[start, :2]
    return LayerEdges(edges, offsets, tiles)


#: layers whose pixel edges are made at once (memory: their edges, not the model's; 1,900 12K layers of a 346k-facet
#: scan held 170 MB of float64 temporaries at once)
EDGE_CHUNK = 256


def iter_layer_edges(result: SliceResult, spec: RasterSpec, bounds=None, layers: Sequence[int] | None = None,
                     edges: LayerEdges | None = None, k: int = 1, dtype=np.float64) -> Iterator[tuple[int, LayerEdges]]:
    """The :func:`layer_edges` of ``layers`` (default all) chunk by chunk of :data:`EDGE_CHUNK` layers, each with the
    position of its first entry among the selected layers (memory: one chunk's edges, not the model's). ``k`` > 1:
    the result holds ``k`` sub-layers per layer, merged per layer (:func:`merge_layer_groups`). ``edges`` given:
    one chunk, as given. ``bounds`` default: the whole result's, so every chunk is centred alike. ``dtype``: of the
    edges made (:func:`layer_edges`)."""
    if edges is not None:
        yield 0, merge_layer_groups(edges, k) if k > 1 else edges
        return
    check_raster_args(result, spec, layers, bounds)
    if bounds is None:  # one centring for every chunk: the whole result's
        bounds = result_bounds(result)
    sel = np.arange(result.n_layers) if layers is None else np.asarray(layers, dtype=np.int64)
    step = EDGE_CHUNK * max(k, 1)
    for a in range(0, max(sel.size, 1), step):
        if k > 1:  # sub-layers moved to their layer's tile in float64, then rounded once
            le = merge_layer_groups(layer_edges(result, spec, bounds, sel[a : a + step]), k)
            le = LayerEdges(le.edges.astype(dtype, copy=False), le.edge_offsets, le.tiles)
        else:
            le = layer_edges(result, spec, bounds, sel[a : a + step], dtype)
        yield a // max(k, 1), le


def z_sample_planes(result: SliceResult, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(z, thickness) of ``k`` sub-planes in each layer's slab, mm: layer i's slab [bottom_i, bottom_i + t_i) cut in
    ``k`` equal parts, each cut at its middle (z = bottom_i + (j + 0.5)·t_i/k); layer i's sub-planes are entries
    k·i … k·i + k − 1. Slicing at them and rasterising with ``z_samples=k`` averages each layer over its slab."""
    b = np.repeat(result.bottom, k)
    t = np.repeat(np.asarray(result.thickness, np.float64), k) / k
    j = np.tile(np.arange(k, dtype=np.float64), result.n_layers)
    return b + (j + 0.5) * t, t


def merge_layer_groups(le: LayerEdges, k: int) -> LayerEdges:
    """Entries k·i … k·i + k − 1 of ``le`` (the sub-planes of one layer) as entry i: the union of their tiles, and
    their edges moved to its corner (by whole pixels)."""
    n = len(le.tiles) // k
    tiles = merge_tiles(le.tiles, k)
    counts = np.diff(le.edge_offsets[: n * k + 1])
    group = np.repeat(np.arange(n * k) // k, counts)
    sub = np.repeat(np.arange(n * k), counts)
    dc = (le.tiles[sub, 1] - tiles[group, 1]).astype(np.float64)
    dr = (le.tiles[sub, 0] - tiles[group, 0]).astype(np.float64)
    edges = np.asarray(le.edges[: le.edge_offsets[n * k]], np.float64).copy()
    edges[:, 0] += dc
    edges[:, 2] += dc
    edges[:, 1] += dr
    edges[:, 3] += dr
    return LayerEdges(edges, np.ascontiguousarray(le.edge_offsets[: n * k + 1 : k]), tiles)


def merge_tiles(tiles: np.ndarray, k: int) -> np.ndarray:
    """The tiles (row0, col0, rows, cols) of entries k·i … k·i + k − 1 as one per i: the union of the non-empty
    ones ((0, 0, 0, 0) where all are empty)."""
    n = len(tiles) // k
    t = tiles[: n * k].reshape(n, k, 4)
    has = (t[:, :, 2] > 0) & (t[:, :, 3] > 0)
    big = np.iinfo(np.int64).max
    r0 = np.where(has, t[:, :, 0], big).min(axis=1)
    c0 = np.where(has, t[:, :, 1], big).min(axis=1)
    r1 = np.where(has, t[:, :, 0] + t[:, :, 2], -1).max(axis=1)
    c1 = np.where(has, t[:, :, 1] + t[:, :, 3], -1).max(axis=1)
    empty = ~has.any(axis=1)
    return np.stack([np.where(empty, 0, r0), np.where(empty, 0, c0), np.where(empty, 0, r1 - r0),
                     np.where(empty, 0, c1 - c0)], axis=1).astype(np.int64)


def splice_layers(base: LayerEdges, at: np.ndarray, other: LayerEdges, other_at: np.ndarray) -> LayerEdges:
    """``base`` with its entries ``at`` (increasing) replaced by the entries ``other_at`` of ``other`` (edges and
    tiles); the rest of ``base`` is copied in slices (a few layers replaced among many)."""
    at, other_at = np.asarray(at, np.int64), np.asarray(other_at, np.int64)
    if at.size == 0:
        return base
    bo, oo = base.edge_offsets, other.edge_offsets
    parts, counts, start = [], np.diff(bo), 0
    for i, j in zip(at.tolist(), other_at.tolist(), strict=True):  # (one step per replaced layer)
        parts += [base.edges[bo[start] : bo[i]], other.edges[oo[j] : oo[j + 1]]]
        start = i + 1
    parts.append(base.edges[bo[start] : bo[-1]])
    counts[at] = np.diff(oo)[other_at]
    tiles = base.tiles.copy()
    tiles[at] = other.tiles[other_at]
    offsets = np.zeros(len(base.tiles) + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    edges = np.concatenate(parts).astype(base.edges.dtype, copy=False)
    return LayerEdges(edges, offsets, tiles)
