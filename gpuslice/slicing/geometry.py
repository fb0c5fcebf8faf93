"""A :class:`~gpuslice.slicing.result.SliceResult` as shapely 2 geometries, built with shapely's vectorised
constructors straight from the flat arrays (no Python work per point, none per loop or per layer).

* **Polygons**: per layer one ``MultiPolygon`` (empty for an empty layer); each polygon is a closed outer loop
  (counter-clockwise seen from +z) with its closed holes (clockwise) as interiors, coordinates in mm (float64 copies
  of the float32 points; rings closed by repeating the first point, as shapely does).
* **Open chains** (``loop_closed`` False: broken meshes only) are never part of a polygon; they come back
  separately, per layer one ``MultiLineString``, from :func:`open_chains_shapely` or
  ``to_shapely(open_chains=True)``.
* Skipped: closed loops of fewer than 3 points (no area), open chains of fewer than 2, and holes whose
  ``loop_parent`` is not a kept outer loop of the same layer (as :meth:`LayerView.polygons` skips them).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..ragged import expand_ranges

__all__ = ["Contours", "polygon_rings", "polygons_shapely", "open_chains_shapely"]


class Contours(Protocol):
    """The columnar contours these functions read (and :mod:`.plotting`'s): a
    :class:`~gpuslice.slicing.result.SliceResult` has them (layout in its module docstring). Declared here rather
    than imported, so the result's methods may call these functions without an import circle."""

    points: np.ndarray
    loop_offsets: np.ndarray
    layer_offsets: np.ndarray
    loop_layer: np.ndarray
    loop_is_hole: np.ndarray
    loop_parent: np.ndarray
    loop_closed: np.ndarray
    z: np.ndarray

    @property
    def n_layers(self) -> int: ...


def _coords(result: Contours, loops: np.ndarray, counts: np.ndarray, p0: int, p1: int, contiguous: bool):
    """float64 (N, 2) points of ``loops`` in order, and the ring number of each point."""
    ring_of_point = np.repeat(np.arange(loops.size, dtype=np.int64), counts)
    if contiguous:  # every point of the range, in order: no gather
        return np.asarray(result.points[p0:p1], dtype=np.float64), ring_of_point
    _, idx = expand_ranges(np.asarray(result.loop_offsets)[loops], counts)
    return np.asarray(result.points, dtype=np.float64)[idx], ring_of_point


def polygon_rings(result: Contours, start: int = 0, stop: int | None = None):
    """The rings of the polygons of layers ``start .. stop - 1``, polygon by polygon, each shell before its holes.

    Returns ``(rings, ring_poly, poly_layer)``: ``rings`` (K,) int64 loop indices into ``result``; ``ring_poly``
    (K,) the polygon of each ring (0, 1, … in order, non-decreasing); ``poly_layer`` the layer of each polygon,
    relative to ``start`` (non-decreasing). Kept: closed loops of ≥ 3 points; holes only under a kept outer loop
    of their layer. Shared by :func:`polygons_shapely` and the GeoJSON writer.
    """
    stop = result.n_layers if stop is None else stop
    lo_off = np.asarray(result.layer_offsets)
    r0, r1 = int(lo_off[start]), int(lo_off[stop])
    empty = np.zeros(0, dtype=np.int64)
    if r1 <= r0:
        return empty, empty, empty
    counts = np.diff(np.asarray(result.loop_offsets)[r0 : r1 + 1])
    closed = np.asarray(result.loop_closed[r0:r1], dtype=bool)
    hole = np.asarray(result.loop_is_hole[r0:r1], dtype=bool)
    parent = np.asarray(result.loop_parent[r0:r1], dtype=np.int64) - r0
    usable = closed & (counts >= 3)
    outer = usable & ~hole
    # a hole is kept when its parent is a kept outer loop of the same range (so of the same layer)
    in_range = (parent >= 0) & (parent < r1 - r0)
    parent_ok = np.zeros(r1 - r0, dtype=bool)
    parent_ok[in_range] = outer[parent[in_range]]
    keep_hole = usable & hole & parent_ok
    # polygon number of each outer loop, in loop order; a hole takes its parent's
    poly_of_outer = np.cumsum(outer) - 1
    poly = np.where(outer, poly_of_outer, -1)
    poly[keep_hole] = poly_of_outer[parent[keep_hole]]
    kept = np.flatnonzero(outer | keep_hole)
    if kept.size == 0:
        return empty, empty, empty
    # usually already in this order (the stable sort is then the identity)
    order = np.argsort(poly[kept] * 2 + hole[kept], kind="stable")
    kept = kept[order]
    poly_layer = np.asarray(result.loop_layer[r0:r1], dtype=np.int64)[outer] - start
    return kept + r0, poly[kept], poly_layer


def polygons_shapely(result: Contours, start: int = 0, stop: int | None = None, *,
                     with_invalid: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Layers ``start .. stop - 1`` of ``result`` as an (n,) object array of shapely ``MultiPolygon`` (mm);
    ``with_invalid``: also an (n,) bool array, True for the layers that are still not valid for GEOS (below).

    Outer loops are shells, their holes interiors, in the result's orientation (shells CCW, holes CW). Built with
    ``shapely.linearrings(coords, indices=…)``, ``shapely.polygons(rings, indices=…)`` and
    ``shapely.multipolygons(polygons, indices=…)``; layers with no polygon get an empty ``MultiPolygon``. Layers
    whose rings touch themselves (same area, invalid for GEOS) go through ``shapely.make_valid`` where it keeps
    their area to 1e-12: on watertight meshes every layer is valid.
    """
    import shapely

    stop = result.n_layers if stop is None else stop
    n = max(stop - start, 0)
    out = np.full(n, shapely.MultiPolygon(), dtype=object)
    invalid = np.zeros(n, dtype=bool)
    rings, ring_poly, poly_layer = polygon_rings(result, start, stop) if n else (np.zeros(0, np.int64),) * 3
    if rings.size == 0:
        return (out, invalid) if with_invalid else out
    offsets = np.asarray(result.loop_offsets)
    counts = offsets[rings + 1] - offsets[rings]
    lo_off = np.asarray(result.layer_offsets)
    r0, r1 = int(lo_off[start]), int(lo_off[stop])
    contiguous = rings.size == r1 - r0 and rings[0] == r0 and bool(np.all(np.diff(rings) == 1))
    coords, ring_of_point = _coords(result, rings, counts, int(offsets[r0]), int(offsets[r1]), contiguous)
    shells_and_holes = shapely.linearrings(coords, indices=ring_of_point)
    polys = shapely.polygons(shells_and_holes, indices=ring_poly)
    shapely.multipolygons(polys, indices=poly_layer, out=out)
    # a ring that touches itself at a point (or a sliver of a rebuilt layer rounded to float32) bounds the same area
    # but is not a valid polygon: such layers are made valid where that keeps their area (the result stays the
    # truth: overlapping parts that nesting left as they are, on broken non-watertight meshes, stay as they are)
    bad = np.flatnonzero(~shapely.is_valid(out))
    if bad.size:
        fixed = np.array([_as_multipolygon(g) for g in shapely.make_valid(out[bad], method="structure",
                                                                          keep_collapsed=False)], dtype=object)
        before, after = shapely.area(out[bad]), shapely.area(fixed)
        same = np.abs(after - before) <= 1e-12 * np.maximum(before, 1.0)
        out[bad[same]] = fixed[same]
        invalid[bad[~same]] = True
    return (out, invalid) if with_invalid else out


def _as_multipolygon(geom):
    """``geom`` (a polygonal result of ``make_valid``) as one ``MultiPolygon``."""
    import shapely

    parts = []
    for g in shapely.get_parts(geom):  # polygons, or a collection's members
        if g.geom_type == "MultiPolygon":
            parts += list(g.geoms)
        elif g.geom_type == "Polygon" and not g.is_empty:
            parts.append(g)
    return shapely.MultiPolygon(parts)


def open_chains_shapely(result: Contours, start: int = 0, stop: int | None = None) -> np.ndarray:
    """Open chains of layers ``start .. stop - 1`` as an (n,) object array of shapely ``MultiLineString`` (mm),
    empty where a layer has none; chains run in the result's direction (material on their left)."""
    import shapely

    stop = result.n_layers if stop is None else stop
    n = max(stop - start, 0)
    out = np.full(n, shapely.MultiLineString(), dtype=object)
    if n == 0:
        return out
    lo_off = np.asarray(result.layer_offsets)
    r0, r1 = int(lo_off[start]), int(lo_off[stop])
    offsets = np.asarray(result.loop_offsets)
    counts = np.diff(offsets[r0 : r1 + 1])
    loops = np.flatnonzero(~np.asarray(result.loop_closed[r0:r1], dtype=bool) & (counts >= 2))
    if loops.size == 0:
        return out
    coords, line_of_point = _coords(result, loops + r0, counts[loops], 0, 0, False)
    lines = shapely.linestrings(coords, indices=line_of_point)
    layer = np.asarray(result.loop_layer, dtype=np.int64)[loops + r0] - start
    shapely.multilinestrings(lines, indices=layer, out=out)
    return out
