"""``.geojson``: a GeoJSON ``FeatureCollection`` (RFC 7946 structure), one ``Feature`` per layer, coordinates in mm
(no CRS: the file's x, y are the bed's, not longitude and latitude). Output bytes are a pure function of the result.
"""

from __future__ import annotations

import json
import os
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import MeshFileError
from ..io.atomic import atomic_path
from ..ragged import expand_ranges
from .numbers import CHUNK_POINTS, checked_result, format_fixed, layer_chunks

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

PathLike = str | os.PathLike

__all__ = ["write_geojson", "read_geojson", "geojson_rings"]


def write_geojson(result: SliceResult, path: PathLike, *, decimals: int = 6) -> None:
    """Write ``result`` as one GeoJSON ``FeatureCollection``, atomically.

    Layout: ``{"type": "FeatureCollection", "features": [...]}`` with one ``Feature`` per layer, in layer order,
    every layer present (an empty layer has ``"coordinates": []``):

    * ``properties``: ``layer`` (index), ``z`` (the cutting plane, mm), ``thickness`` (mm), ``bottom`` (mm),
      ``area`` (mm², the result's filled area), ``open_chains`` (how many open chains the layer has: they are not
      written, since a layer's geometry is its filled region);
    * ``geometry``: a ``MultiPolygon``, one polygon per outer loop with its holes, rings closed (first point
      repeated last), outer rings counter-clockwise and holes clockwise (as RFC 7946 asks), coordinates ``[x, y]``
      in mm with exactly ``decimals`` decimals (rounded half-to-even from the float32 value). Closed loops of
      fewer than 3 points and holes without a written outer loop are left out (as ``to_shapely``).

    No ``crs`` member (RFC 7946 has none; these are not geographic coordinates).

    Raises
    ------
    ParameterError
        ``decimals`` out of 0..9, or a malformed result (inconsistent offsets, coordinates beyond 1e9 mm).
    """
    from ..slicing.geometry import polygon_rings

    decimals, points, loop_offsets, layer_offsets = checked_result(result, decimals)
    z, thickness, bottom = (np.asarray(a, dtype=np.float64) for a in (result.z, result.thickness, result.bottom))
    area = np.asarray(result.area, dtype=np.float64)
    open_per_layer = result.open_chains_per_layer
    cum = loop_offsets[layer_offsets]
    with atomic_path(path) as tmp, open(tmp, "wb", buffering=1 << 20) as fh:
        fh.write(b'{"type":"FeatureCollection","features":[')
        for l0, l1 in layer_chunks(cum, CHUNK_POINTS // 4):  # (~40 bytes of JSON a point)
            rings, ring_poly, poly_layer = polygon_rings(result, l0, l1)
            buf, span = _chunk_text(points, loop_offsets, rings, ring_poly, decimals)
            # each layer's rings are a run of `rings`: ring_layer is non-decreasing
            ring_layer = poly_layer[ring_poly] if rings.size else np.zeros(0, np.int64)
            bounds = np.searchsorted(ring_layer, np.arange(l1 - l0 + 1)).tolist()
            for i in range(l0, l1):
                props = {
                    "layer": i,
                    "z": float(z[i]),
                    "thickness": float(thickness[i]),
                    "bottom": float(bottom[i]),
                    "area": float(area[i]),
                    "open_chains": int(open_per_layer[i]),
                }
                head = "," if i else ""
                fh.write(f'{head}\n{{"type":"Feature","properties":{json.dumps(props)},'
                         '"geometry":{"type":"MultiPolygon","coordinates":['.encode())
                a, b = bounds[i - l0], bounds[i - l0 + 1]
                if b > a:
                    fh.write(memoryview(buf)[span[a] + 1 : span[b]])  # + 1: no comma before the first polygon
                fh.write(b"]}}")
        fh.write(b"\n]}\n")


def _chunk_text(points, loop_offsets, rings, ring_poly, decimals) -> tuple[np.ndarray, list[int]]:
    """Text of ``rings`` as GeoJSON polygons (``,[[[x,y],...],[...]]`` each), and the byte offset where each
    ring's text starts (+ the end)."""
    if rings.size == 0:
        return np.zeros(0, np.uint8), [0]
    counts = loop_offsets[rings + 1] - loop_offsets[rings]
    _, idx = expand_ranges(loop_offsets[rings], counts + 1)  # one more point per ring: the first, repeated
    last = np.cumsum(counts + 1) - 1
    idx[last] = loop_offsets[rings]
    values = points[idx].astype(np.float64).reshape(-1)  # x0, y0, x1, y1, ...
    n_pts = idx.size
    first_pt = last - counts
    first_x = 2 * first_pt
    last_y = 2 * last + 1
    new_poly = np.ones(rings.size, dtype=bool)
    new_poly[1:] = ring_poly[1:] != ring_poly[:-1]
    end_poly = np.ones(rings.size, dtype=bool)
    end_poly[:-1] = new_poly[1:]
    not_last = np.ones(n_pts, dtype=bool)
    not_last[last] = False
    sep = np.empty(2 * n_pts, dtype=np.uint8)
    sep[0::2] = ord(",")
    sep[1::2] = ord("]")
    before = [
        (first_x[~new_poly], b","),  # between the rings of a polygon
        (first_x[new_poly], b",["),  # a polygon opens (the writer drops the comma before a layer's first one)
        (first_x, b"["),  # a ring opens
        (np.arange(0, 2 * n_pts, 2), b"["),  # a point opens
    ]
    after = [
        (2 * np.flatnonzero(not_last) + 1, b","),
        (last_y, b"]"),  # the ring closes
        (last_y[end_poly], b"]"),  # the polygon closes
    ]
    buf, starts = format_fixed(values, decimals, sep, before, after)
    # ring k's text (its tokens included) starts at starts[first_x[k]]; a layer's first ring opens a polygon,
    # whose leading comma the writer skips
    return buf, starts[first_x].tolist() + [int(buf.size)]


def read_geojson(path: PathLike) -> dict[str, Any]:
    """Read a GeoJSON file into a dict (:func:`json.load`), with a one-line :class:`MeshFileError` on failure."""
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except (OSError, ValueError) as exc:
        raise MeshFileError(f"{path}: not a readable GeoJSON file ({exc})") from None


def geojson_rings(feature: dict[str, Any]) -> list[list[np.ndarray]]:
    """A layer Feature's polygons as ``[[shell (n, 2), hole (m, 2), ...], ...]``, float64 mm, rings without the
    repeated closing point."""
    return [[np.asarray(ring, dtype=np.float64)[:-1] for ring in poly] for poly in feature["geometry"]["coordinates"]]
