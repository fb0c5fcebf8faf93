"""Islands and unsupported area: what a layer adds with nothing under it in the layer below.

An **island** is a connected region of layer i (a polygon with its holes, or a component of solid pixels) that
shares no area with layer i − 1: it cures onto nothing. Layer 0 lies on the build plate and has none. The
**unsupported area** of layer i is the area of layer i farther than a tolerance ``t`` from layer i − 1 (layer
i − 1 grown by ``t``, then subtracted): the overhang signal, 0 for layer 0.

Two exact versions:

* **contours** (:func:`contour_islands`): shapely/GEOS on the result's polygons. A polygon is supported when a
  point inside it lies strictly inside the layer below (``point_on_surface`` + prepared ``contains_properly``, the
  usual case, with no outline of either within the radius of a disk of half a pixel's area around the point) or,
  failing that, when its overlap with the layer below holds it (:func:`_holds`): at least half a pixel (``support``
  mm², default half the tolerance squared: 0.00125 mm² at the default 0.05 mm; at least :data:`TOUCH_AREA_MM2`), or
  half its own area where that is less (a part thinner than a pixel that goes on up), and for a larger part not a
  sliver narrower than half a pixel throughout. Touching along an edge or at a point is no support, and neither is
  a contact no pixel prints, so a region hung from a sub-pixel tip is an island here as on the printer's grid (an
  audit found armadillo's 0.5 mm² region held by a 0.0001 mm² tip, a 748 mm² part of an open bunny by a 0.0001 mm²
  sliver). A layer's polygons within half a pixel of each other (``tolerance``/2: a gap the printer does not
  resolve) are one connected region, held when one of them is, as the pixels' 8-connected components are. The
  unsupported area is
  ``area(layer_i - buffer(layer_{i-1}, t))`` (buffer arcs of 2 segments per quarter circle: at most 0.076·t inside
  the true offset), measured on the layers simplified first (Douglas-Peucker, ``shapely.simplify``) by
  ε = :data:`SIMPLIFY` · t where it pays: in chunks where at least :data:`SIMPLIFY_SHARE` of the points lie within
  ε of their neighbours' chord (CAD meshes, whose arcs are cut into many tiny edges: benchy 80 %, the overlays 1.8x
  faster; a scanned bust has ~15 % and keeps its true outlines). Every point of a simplified outline lies within ε
  of the true one and back, so a layer's value moves by at most 2ε·(P_i + P_{i-1} + 2π·t) (P the perimeters: 0.2 mm²
  for two 100 mm outlines at the default t; on benchy at most 0.006 mm², 3 % of that bound, ``tests/checks``).
  Where a simplified layer is not a valid polygon, the true one is used. Islands are found on the true polygons.
  Layers go through GEOS in chunks on a thread pool (shapely releases the GIL). A broken mesh's
  invalid layer is made valid first (``make_valid``, structure method); an overlay GEOS still refuses gives NaN
  (no support, unknown unsupported area).
* **pixels** (:class:`PixelIslands`): the solid pixels (coverage ≥ 50 %) of a display's grid as row intervals
  (:mod:`gpuslice.checks.intervals`). Components are 8-connected; a component is supported when one of its pixels
  is solid in the layer below; the unsupported pixels are those with no solid pixel of the layer below within
  ``t`` (pixel centres' distance, mm), counted times the pixel's area.

Both report each island's layer, area (mm²), centroid (x, y mm) and bounding box (mm, model coordinates).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ..prefetch import Workers
from .intervals import Lines, components, expand_pairs

__all__ = ["Islands", "contour_islands", "PixelIslands", "TOUCH_AREA_MM2", "SIMPLIFY"]

#: overlap below this area (mm²) is touching, not support (float32 contours give ~1e-12 on shared edges); polygons
#: this small are degenerate slivers (zero-area facets cut edge-on), never islands
TOUCH_AREA_MM2 = 1e-6
#: layers per GEOS chunk (one task of the thread pool)
CHUNK_LAYERS = 128
#: the unsupported area is measured on outlines simplified by this fraction of the tolerance (module docstring)
SIMPLIFY = 0.01
#: ... in the chunks where at least this share of the points lie within that distance of their neighbours' chord
SIMPLIFY_SHARE = 0.5


@dataclass
class Islands:
    """Islands as columns (K rows, in layer order): ``layer`` int64, ``area`` mm², ``x``, ``y`` centroid mm,
    ``bbox`` (K, 4) xmin, ymin, xmax, ymax mm; and ``unsupported`` (L,) mm² per layer."""

    layer: np.ndarray
    area: np.ndarray
    x: np.ndarray
    y: np.ndarray
    bbox: np.ndarray
    unsupported: np.ndarray

    @classmethod
    def concat(cls, parts: list[tuple], n_layers: int, unsupported: np.ndarray | None = None) -> Islands:
        """From ``(layer, area, x, y, bbox)`` parts; sorted by layer then x, y."""
        if parts:
            layer, area, x, y, bbox = (np.concatenate([np.asarray(p[k]) for p in parts]) for k in range(5))
        else:
            layer, area, x, y, bbox = (np.zeros(0, np.int64), *(np.zeros(0) for _ in range(3)), np.zeros((0, 4)))
        order = np.lexsort((y, x, layer))
        unsup = np.zeros(n_layers) if unsupported is None else unsupported
        return cls(layer[order].astype(np.int64), area[order].astype(np.float64), x[order].astype(np.float64),
                   y[order].astype(np.float64), bbox[order].reshape(-1, 4).astype(np.float64), unsup)


# ---- contours ------------------------------------------------------------------------------------------------------
def _contour_chunk(result, a: int, b: int, tolerance: float | None, simplify: float, support: float, join: float):
    """Islands and unsupported area of layers a .. b-1 (each against the one below; tolerance None: no area;
    ``simplify``: ε in mm, 0 for the true outlines; ``support``: the least overlap that holds a polygon, mm²;
    ``join``: polygons of a layer this near (mm) are one region)."""
    import shapely

    from ..slicing.geometry import polygons_shapely

    lo = max(a - 1, 0)
    # layers lo .. b-1; bad: those a broken mesh left invalid (self-crossing rings that GEOS's overlays refuse)
    lay, bad = polygons_shapely(result, lo, b, with_invalid=True)
    if bad.any():
        lay[bad] = shapely.make_valid(lay[bad], method="structure", keep_collapsed=False)
    shapely.prepare(lay)
    parts, idx = shapely.get_parts(lay, return_index=True)
    layer = idx + lo
    sel = (layer >= max(a, 1)) & (shapely.area(parts) > TOUCH_AREA_MM2)  # layer 0 is on the plate; no slivers
    poly, layer = parts[sel], layer[sel]
    below = lay[layer - 1 - lo]
    supported = np.zeros(poly.size, bool)
    if poly.size:
        # held at once: a point of the polygon deep inside the layer below, a disk of area ``support`` around it in
        # both (the usual case); the others by the area of their overlay
        pt = shapely.point_on_surface(poly)
        supported = shapely.contains_properly(below, pt)
        deep = np.flatnonzero(supported)
        r = math.sqrt(support / math.pi)
        edges = shapely.boundary(lay)
        near = shapely.dwithin(pt[deep], edges[layer[deep] - 1 - lo], r) | \
            shapely.dwithin(pt[deep], shapely.boundary(poly[deep]), r)
        supported[deep[near]] = False
        rest = np.flatnonzero(~supported)
        if rest.size:
            hit = shapely.intersects(below[rest], poly[rest])
            r2 = rest[hit]
            if r2.size:
                supported[r2] = _holds(poly[r2], below[r2], support, join)
    found = _regions(poly, layer, supported, join)
    # unsupported area: layer i outside layer i-1 grown by the tolerance; 0 where layer i lies inside layer i-1
    first = max(a, 1)
    unsup = np.zeros(b - a)
    if b > first and tolerance is not None:
        cur, prev = lay[first - lo : b - lo], lay[first - 1 - lo : b - 1 - lo]
        todo = np.flatnonzero(~shapely.contains(prev, cur) & ~shapely.is_empty(cur))
        if todo.size:
            if simplify > 0 and _collinear_share(result, lo, b, simplify) >= SIMPLIFY_SHARE:
                need = np.zeros(lay.size, bool)  # each layer once: the upper of one pair is the lower of the next
                need[todo + first - lo] = need[todo + first - 1 - lo] = True
                simple = lay.copy()
                simple[need] = _simplified(lay[need], simplify)
                cur, prev = simple[first - lo : b - lo], simple[first - 1 - lo : b - 1 - lo]
            cur, prev = cur[todo], prev[todo]
            grown = shapely.buffer(prev, tolerance, quad_segs=2) if tolerance > 0 else prev
            shapely.prepare(grown)
            out = ~shapely.contains(grown, cur)  # a prepared test first: about half the layers lie inside
            unsup[todo[out] + first - a] = _overlay_area(shapely.difference, cur[out], grown[out])
    return found, unsup


def _regions(poly: np.ndarray, layer: np.ndarray, supported: np.ndarray, join: float) -> tuple:
    """The islands among polygons ``poly`` (of layers ``layer``, each ``supported`` or not): a layer's polygons
    within ``join`` mm of each other (half a pixel: a gap the printer does not resolve; 0: touching) form one region,
    supported when one of them is, as the pixel islands' 8-connected components are; each unsupported region is one
    island (its area, its area-weighted centroid, the union of its boxes). Returns (layer, area, x, y, bbox)."""
    import shapely

    if supported.all():
        return (layer[:0], np.zeros(0), np.zeros(0), np.zeros(0), np.zeros((0, 4)))
    label = np.arange(poly.size)
    loose = np.flatnonzero(~supported)
    tree = shapely.STRtree(poly)
    if join > 0:
        q, j = tree.query(poly[loose], predicate="dwithin", distance=join)
    else:
        q, j = tree.query(poly[loose], predicate="intersects")
    i = loose[q]
    keep = (layer[i] == layer[j]) & (i != j)
    if keep.any():
        label = components(poly.size, i[keep], j[keep])
    held = np.zeros(int(label.max()) + 1, bool)
    held[label[supported]] = True
    free = np.flatnonzero(~held[label])
    comp, at = np.unique(label[free], return_inverse=True)
    area = shapely.area(poly[free])
    cen = shapely.centroid(poly[free])
    total = np.bincount(at, area, minlength=comp.size)
    x = np.bincount(at, area * shapely.get_x(cen), minlength=comp.size) / total
    y = np.bincount(at, area * shapely.get_y(cen), minlength=comp.size) / total
    b = shapely.bounds(poly[free]).reshape(-1, 4)
    box = np.empty((comp.size, 4))
    box[:, :2], box[:, 2:] = np.inf, -np.inf
    np.minimum.at(box[:, 0], at, b[:, 0])
    np.minimum.at(box[:, 1], at, b[:, 1])
    np.maximum.at(box[:, 2], at, b[:, 2])
    np.maximum.at(box[:, 3], at, b[:, 3])
    lay = np.zeros(comp.size, layer.dtype)
    lay[at] = layer[free]
    return lay, total, x, y, box


def _collinear_share(result, a: int, b: int, eps: float, samples: int = 4096) -> float:
    """The share of the points of layers a .. b-1 within ``eps`` mm of the chord of their two neighbours, from about
    ``samples`` of them (a point next to a loop's end is measured against another loop's: a few samples off)."""
    lo_off, offsets = np.asarray(result.layer_offsets), np.asarray(result.loop_offsets)
    p0, p1 = int(offsets[lo_off[a]]), int(offsets[lo_off[b]])
    if p1 - p0 < 3:
        return 0.0
    i = np.arange(p0 + 1, p1 - 1, max(1, (p1 - p0) // samples))
    pts = np.asarray(result.points)
    u, v, w = (pts[i + k].astype(np.float64) for k in (-1, 0, 1))
    chord = w - u
    length = np.hypot(chord[:, 0], chord[:, 1])
    dist = np.abs(chord[:, 0] * (v[:, 1] - u[:, 1]) - chord[:, 1] * (v[:, 0] - u[:, 0]))
    return float(np.mean(dist <= eps * np.maximum(length, 1e-300)))


def _simplified(geoms: np.ndarray, eps: float) -> np.ndarray:
    """``geoms`` simplified by ``eps`` mm (Douglas-Peucker), each kept as it is where that is not a valid polygon."""
    import shapely

    if eps <= 0 or geoms.size == 0:
        return geoms
    out = shapely.simplify(geoms, eps, preserve_topology=False)
    bad = ~shapely.is_valid(out)
    out[bad] = geoms[bad]
    return out


def _overlay(op, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``op(a, b)`` element-wise; where GEOS still fails (a topology exception on a broken mesh's layer), that
    element is retried on a 1e-6 mm precision grid, then left None."""
    from shapely.errors import GEOSException

    try:
        return op(a, b)
    except GEOSException:
        out = np.full(a.size, None, dtype=object)
        for k in range(a.size):  # only on failure: a loop over the chunk's elements
            for grid in (None, 1e-6):
                try:
                    out[k] = op(a[k], b[k], grid_size=grid)
                    break
                except GEOSException:
                    continue
        return out


def _overlay_area(op, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``area(op(a, b))`` element-wise (:func:`_overlay`), NaN where GEOS failed."""
    import shapely

    return shapely.area(_overlay(op, a, b))


def _holds(poly: np.ndarray, below: np.ndarray, support: float, join: float) -> np.ndarray:
    """Whether each polygon's overlap with its layer below holds it: at least ``support`` mm² (or half the polygon's
    own area, for a part itself below a pixel), and, for a polygon wider than ``join`` somewhere, not a sliver
    narrower than ``join`` mm throughout (an overlap that ``buffer(-join / 2)`` erases prints no pixel: a wall
    0.009 mm thick held a 5 mm² strip of p_ascii_multibody)."""
    import shapely

    inter = _overlay(shapely.intersection, poly, below)
    area = shapely.area(inter)  # (NaN where GEOS failed: not held)
    own = shapely.area(poly)
    held = area >= np.minimum(support, 0.5 * own)
    wide = np.flatnonzero(held & (own >= 2 * support))
    if join > 0 and wide.size:
        # a part that is itself narrower than that throughout (a fin 0.02 mm thick going on up) keeps the area rule
        wide = wide[~shapely.is_empty(shapely.buffer(poly[wide], -0.5 * join, quad_segs=1))]
        held[wide] = ~shapely.is_empty(shapely.buffer(inter[wide], -0.5 * join, quad_segs=1))
    return held


#: the pixel whose half-area is the least support when no tolerance is given, mm (the default display's)
DEFAULT_PIXEL_MM = 0.05


def contour_islands(result, tolerance: float | None, *, workers: int | None = None,
                    simplify: float | None = None, support: float | None = None) -> Islands:
    """Islands (contour-exact) and the unsupported area per layer of ``result`` (module docstring); ``tolerance``
    in mm (None: islands only, the unsupported area left 0); ``workers``: threads (default: the CPUs);
    ``simplify``: the outlines of the unsupported area are simplified by this fraction of ``tolerance`` (default
    :data:`SIMPLIFY`; 0: the true outlines everywhere, the reference); ``support``: the least overlap with the layer
    below that holds a polygon, mm² (default half a pixel: ``tolerance``²/2, or :data:`DEFAULT_PIXEL_MM`'s without
    one; never below :data:`TOUCH_AREA_MM2`)."""
    simplify = SIMPLIFY if simplify is None else simplify
    if not (math.isfinite(simplify) and 0 <= simplify <= 0.1):
        from ..errors import ParameterError

        raise ParameterError(f"simplify must be within [0, 0.1] (a fraction of the tolerance), got {simplify}",
                             param="simplify")
    eps = float(simplify) * float(tolerance or 0.0)
    pixel = DEFAULT_PIXEL_MM if tolerance is None else float(tolerance)
    join = 0.5 * pixel
    if support is None:
        support = 0.5 * pixel * pixel
    if not (math.isfinite(support) and support >= 0):
        from ..errors import ParameterError

        raise ParameterError(f"support must be >= 0 mm², got {support}", param="support")
    support = max(float(support), TOUCH_AREA_MM2)
    n = result.n_layers
    chunks = [(a, min(a + CHUNK_LAYERS, n)) for a in range(0, n, CHUNK_LAYERS)]
    workers = max(1, min(workers or os.cpu_count() or 1, len(chunks) or 1))
    if workers == 1:
        done = [_contour_chunk(result, a, b, tolerance, eps, support, join) for a, b in chunks]
    else:
        with Workers(workers, "gpuslice-islands") as pool:
            done = pool.map(lambda ab: _contour_chunk(result, ab[0], ab[1], tolerance, eps, support, join), chunks)
    unsup = np.concatenate([d[1] for d in done]) if done else np.zeros(0)
    return Islands.concat([d[0] for d in done], n, unsup)


# ---- pixels ----------------------------------------------------------------------------------------------------------
class PixelIslands:
    """Islands and unsupported area on a display's pixel grid, fed batches of consecutive layers' solid intervals
    (:meth:`feed`), then :meth:`result`.

    to_mm : (2, 3) affine map from pixel coordinates (u = column, v = row) to model mm; col_mm, row_mm : a pixel's
    width and height in mm (along the columns and the rows); tolerance : mm.
    """

    def __init__(self, n_layers: int, rows: int, cols: int, to_mm: np.ndarray, col_mm: float, row_mm: float,
                 tolerance: float) -> None:
        self.n_layers, self.rows, self.cols = n_layers, rows, cols
        self.to_mm = np.asarray(to_mm, np.float64)
        self.pixel_area = col_mm * row_mm
        self.unsupported = np.zeros(n_layers)
        self.parts: list[tuple] = []
        # the grown neighbourhood: for each row offset dy, the columns +-hx(dy) within the tolerance (mm)
        ry = int(math.floor(tolerance / row_mm + 1e-9))
        dys = np.arange(-ry, ry + 1)
        rest = np.maximum(tolerance**2 - (dys * row_mm) ** 2, 0.0)
        self.grow = [(int(dy), int(math.floor(math.sqrt(r) / col_mm + 1e-9))) for dy, r in zip(dys, rest, strict=True)]
        self.context: tuple | None = None  # the last layer of the previous batch: (layer, row, start, end)

    def feed(self, layer0: int, n: int, parts: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> None:
        """Layers ``layer0 .. layer0 + n - 1``: their solid intervals ``(layer, row, start, end)``."""
        ctx = self.context if self.context is not None and self.context[0].size and \
            int(self.context[0][0]) == layer0 - 1 else None
        base = layer0 - 1
        lines = Lines.from_parts(base, n + 1, self.rows, self.cols, [ctx, parts] if ctx is not None else [parts])
        own = lines.line >= self.rows  # intervals of this batch (not the context layer)
        idx = np.flatnonzero(own)
        if idx.size:
            self._islands(lines, idx)
            self._unsupported(lines, idx)
        last = lines.layer_slice(n)
        sel = slice(last.start, last.stop)
        self.context = (lines.layer[sel], lines.row[sel], lines.start[sel], lines.end[sel]) if n else self.context

    def _islands(self, lines: Lines, idx: np.ndarray) -> None:
        line, a, b = lines.line[idx], lines.start[idx], lines.end[idx]
        # support: a solid pixel of the same row in the layer below (layer 0: the plate)
        lay = lines.layer[idx]
        lo, hi = lines.overlapping(line - lines.rows, a, b, lay >= 1)
        sup = (hi > lo) | (lay == 0)
        loose = np.flatnonzero(~sup)
        if not loose.size:
            return
        # islands: the 8-connected components (an interval touches those of the rows above and below within one
        # column) with no supported interval, i.e. the components of the unsupported intervals alone that touch no
        # supported one: searched from those few intervals only
        pos = np.full(lines.n, -1, np.int64)
        pos[idx] = np.arange(idx.size)
        at = np.full(idx.size, -1, np.int64)
        at[loose] = np.arange(loose.size)
        row_l = lines.row[idx][loose]
        held = np.zeros(loose.size, bool)
        src, dst = [], []
        for dy in (1, -1):
            valid = (row_l + dy >= 0) & (row_l + dy < lines.rows)
            lo, hi = lines.overlapping(line[loose] + dy, a[loose] - 1, b[loose] + 1, valid)
            q, j = expand_pairs(lo, hi)
            j = pos[j]  # (the same layer: one of this batch's own intervals)
            s = sup[j]
            held[q[s]] = True
            src.append(q[~s])
            dst.append(at[j[~s]])
        comp = components(loose.size, np.concatenate(src), np.concatenate(dst))
        comp_held = np.zeros(int(comp.max()) + 1, bool)
        comp_held[comp[held]] = True
        free = ~comp_held[comp]
        if not free.any():
            return
        bad = loose[free]  # (in order, as the intervals)
        c, a, b, row, lay = comp[free], a[bad], b[bad], row_l[free], lay[bad]
        uniq, c = np.unique(c, return_inverse=True)
        length = (b - a).astype(np.float64)
        cells = np.bincount(c, length)
        su = np.bincount(c, length * (a + b) / 2.0) / cells  # mean column centre (u)
        sv = np.bincount(c, length * (row + 0.5)) / cells
        umin = np.full(uniq.size, np.inf)
        np.minimum.at(umin, c, a)
        umax = np.full(uniq.size, -np.inf)
        np.maximum.at(umax, c, b)
        vmin = np.full(uniq.size, np.inf)
        np.minimum.at(vmin, c, row)
        vmax = np.full(uniq.size, -np.inf)
        np.maximum.at(vmax, c, row + 1)
        comp_layer = np.zeros(uniq.size, np.int64)
        comp_layer[c] = lay
        x, y = self._mm(su, sv)
        corners = [self._mm(u, v) for u, v in ((umin, vmin), (umax, vmin), (umin, vmax), (umax, vmax))]
        xs, ys = np.stack([p[0] for p in corners]), np.stack([p[1] for p in corners])
        bbox = np.stack([xs.min(0), ys.min(0), xs.max(0), ys.max(0)], axis=1)
        self.parts.append((comp_layer, cells * self.pixel_area, x, y, bbox))

    def _mm(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = self.to_mm
        return t[0, 0] * u + t[0, 1] * v + t[0, 2], t[1, 0] * u + t[1, 1] * v + t[1, 2]

    def _unsupported(self, lines: Lines, idx: np.ndarray) -> None:
        """Pixels of each layer with no solid pixel of the layer below within the tolerance. First against the
        layer below's own row, widened (one merge in order, no sort): that holds most intervals whole; then, for
        those it leaves, against the rows the tolerance reaches too, the grown pieces of those lines only merged."""
        from .intervals import merge_intervals

        below = np.flatnonzero(lines.line < (lines.n_layers - 1) * lines.rows)  # every layer but the last
        line, a, b = lines.line[idx], lines.start[idx], lines.end[idx]
        lay = lines.layer[idx]
        free = np.zeros(idx.size, np.int64)
        if below.size:
            up = lines.line[below] + lines.rows  # (the same row of the layer above, on the batch's axis)
            hx = dict(self.grow)[0]
            k, row, s, e = merge_intervals(up // lines.rows, up % lines.rows,
                                           np.maximum(lines.start[below] - hx, 0),
                                           np.minimum(lines.end[below] + hx, lines.cols))
            same = Lines(lines.layer0, lines.n_layers, lines.rows, lines.cols, k * lines.rows + row, s, e)
            free = (b - a) - same.covered(line, a, b)
        else:
            free = b - a
        free[lay == 0] = 0
        rest = np.flatnonzero(free > 0)
        if rest.size and len(self.grow) > 1 and below.size:
            need = np.unique(line[rest])  # the lines whose intervals the widened row leaves partly uncovered
            pieces = []
            for dy, hx in self.grow:  # a few offsets: the tolerance in pixels
                row = lines.row[below] + dy
                target = lines.line[below] + lines.rows + dy  # the line of the layer above this piece reaches
                ok = (row >= 0) & (row < lines.rows)
                pos = np.searchsorted(need, target)
                ok &= need[np.minimum(pos, need.size - 1)] == target
                pieces.append((target[ok], np.maximum(lines.start[below][ok] - hx, 0),
                               np.minimum(lines.end[below][ok] + hx, lines.cols)))
            tl, s, e = (np.concatenate([p[i] for p in pieces]) for i in range(3))
            k, row, s, e = merge_intervals(tl // lines.rows, tl % lines.rows, s, e, sort=True)
            grown = Lines(lines.layer0, lines.n_layers, lines.rows, lines.cols, k * lines.rows + row, s, e)
            free[rest] = (b[rest] - a[rest]) - grown.covered(line[rest], a[rest], b[rest])
        self.unsupported += np.bincount(lay, free.astype(np.float64), minlength=self.n_layers)[: self.n_layers] \
            * self.pixel_area

    def result(self) -> Islands:
        return Islands.concat(self.parts, self.n_layers, self.unsupported)
