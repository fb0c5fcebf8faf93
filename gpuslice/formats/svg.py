"""``.svg``: all layers in one file, one ``<g id="layer-i">`` per layer; 1 SVG user unit = 1 mm; y is negated
(``y_svg = -y``) so that +y points up on the picture. Output bytes are a pure function of the result."""

from __future__ import annotations

import math
import os
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ParameterError

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

from ..io.atomic import atomic_path
from .numbers import (
    checked_result,
    fmt_scalar,
    format_fixed,
    layer_chunks,
    point_bounds,
)

PathLike = str | os.PathLike

__all__ = ["write_svg"]


def write_svg(
    result: SliceResult,
    path: PathLike,
    *,
    scale: float | None = None,
    decimals: int = 4,
) -> None:
    """Write every layer of ``result`` to one SVG file, atomically.

    Layout of the file:

    * One SVG user unit is 1 mm. Coordinates are written ``x,-y``: **y is negated** (``y_svg = -y``, no
      transform), so +y of the part points up on the picture as it does looking down on the bed from +z;
      outer loops, counter-clockwise in the result, appear clockwise in SVG coordinates.
    * ``viewBox`` is the XY bounding box of all points grown by a margin of 2 % of its larger side (at least
      0.5 mm) on each side, in those flipped coordinates; ``width``/``height`` are the viewBox size times
      ``scale`` in ``mm``, so at the default scale the drawing prints at true size.
    * One ``<g>`` per layer, all visible (overlaid, as Slic3r's ``--export-svg``), in layer order, with
      ``id="layer-{i}"``, ``class="layer"``, ``data-z`` (the cutting plane, mm), ``data-thickness`` (mm),
      ``data-bottom`` (mm), and ``inkscape:groupmode="layer"`` so Inkscape lists the layers and can show
      one at a time. Fill and stroke are presentation attributes on each layer group.
    * Each polygon (an outer loop and its holes) is one ``<path class="polygon" fill-rule="evenodd">`` whose
      ``d`` holds the outer loop then each hole as subpaths ``M x,y L x,y x,y ... Z``, so holes are
      drawn as holes. Open chains (``loop_closed`` False) are ``<path class="open" fill="none">`` with a
      red stroke and no ``Z``. A closed hole whose ``loop_parent`` is not an outer loop written before it
      in its layer is drawn as ``<path class="orphan" fill="none">``, so it never fills. Empty loops are
      skipped.

    Numbers: coordinates with exactly ``decimals`` decimals (4: 0.1 µm), rounded half-to-even from the
    float32 value; z, thickness and the header sizes as the shortest decimal with at most 6 decimals.
    The bytes depend only on the result's geometry (``meta`` and ``repairs`` are not written).

    Parameters
    ----------
    result
        The slicing result.
    path
        Output file, conventionally ``*.svg``.
    scale
        Drawing-size factor applied to ``width``/``height`` only (the viewBox stays in mm); ``None`` means 1,
        true size.
    decimals
        Digits after the decimal point for coordinates, 0 to 9.

    Raises
    ------
    ParameterError
        ``scale`` is not a positive finite number, ``decimals`` is out of range, or the result is
        malformed (inconsistent offsets, non-finite coordinates, coordinates beyond 1e9 mm).
    """
    if scale is None:
        scale = 1.0
    if (
        isinstance(scale, bool)
        or not isinstance(scale, int | float | np.number)
        or not (math.isfinite(scale) and scale > 0)
    ):
        raise ParameterError(f"scale must be a positive finite number, got {scale!r}")
    decimals, points, loop_offsets, layer_offsets = checked_result(result, decimals)
    z = np.asarray(result.z, dtype=np.float64)
    thickness = np.asarray(result.thickness, dtype=np.float64)
    bottom = np.asarray(result.bottom, dtype=np.float64)
    is_hole = np.asarray(result.loop_is_hole, dtype=bool).tolist()
    closed = np.asarray(result.loop_closed, dtype=bool)
    closed_list = closed.tolist()
    parent = np.asarray(result.loop_parent, dtype=np.int64).tolist()

    if points.size:
        lo, hi = point_bounds(points)
    else:
        lo = hi = np.zeros(2)
    size = hi - lo
    margin = max(0.5, 0.02 * float(size.max()))
    vb_x, vb_y = lo[0] - margin, -hi[1] - margin
    vb_w, vb_h = size[0] + 2 * margin, size[1] + 2 * margin
    stroke = fmt_scalar(max(0.01, 0.002 * max(vb_w, vb_h)), 4)
    f = fmt_scalar
    header = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<svg xmlns="http://www.w3.org/2000/svg"'
        ' xmlns:inkscape="http://www.inkscape.org/namespaces/inkscape" version="1.1"'
        f' width="{f(vb_w * scale)}mm" height="{f(vb_h * scale)}mm"'
        f' viewBox="{f(vb_x)} {f(vb_y)} {f(vb_w)} {f(vb_h)}">\n'
        f"<!-- gpuslice: {z.size} layers; 1 user unit = 1 mm; written as x,-y so that +y points up -->\n"
    )
    layer_attrs = (
        f' fill="#3b7dd8" fill-opacity="0.35" stroke="#1b3f73" stroke-width="{stroke}" stroke-linejoin="round"'
    )
    open_attrs = f'class="open" fill="none" stroke="#d62728" stroke-width="{stroke}"'

    counts = np.diff(loop_offsets).tolist()
    cum = loop_offsets[layer_offsets]
    with atomic_path(path) as tmp, open(tmp, "wb", buffering=1 << 20) as fh:
        fh.write(header.encode())
        for l0, l1 in layer_chunks(cum):
            r0, r1 = int(layer_offsets[l0]), int(layer_offsets[l1])
            p0, p1 = int(loop_offsets[r0]), int(loop_offsets[r1])
            buf, starts = _svg_chunk(points[p0:p1], loop_offsets[r0 : r1 + 1] - p0, closed[r0:r1], decimals)
            mv = memoryview(buf)
            # byte range of loop r of the chunk: [lb[r], lb[r + 1]); each loop's text ends with one space
            lb = starts[2 * (loop_offsets[r0 : r1 + 1] - p0)].tolist()
            for i in range(l0, l1):
                zi, ti, bi = f(z[i]), f(thickness[i]), f(bottom[i])
                label = f'inkscape:groupmode="layer" inkscape:label="layer {i} z={zi}"'
                data = f'data-z="{zi}" data-thickness="{ti}" data-bottom="{bi}"'
                fh.write(f'<g id="layer-{i}" class="layer" {label} {data}{layer_attrs}>\n'.encode())
                order: list[tuple[int, list[int]]] = []  # (kind, loops): 0 polygon, 1 open, 2 orphan hole
                polygon_of: dict[int, list[int]] = {}
                for r in range(int(layer_offsets[i]), int(layer_offsets[i + 1])):
                    if counts[r] == 0:
                        continue
                    if not closed_list[r]:
                        order.append((1, [r]))
                    elif not is_hole[r]:
                        loops = [r]
                        polygon_of[r] = loops
                        order.append((0, loops))
                    elif parent[r] in polygon_of:
                        polygon_of[parent[r]].append(r)
                    else:
                        order.append((2, [r]))
                for kind, loops in order:
                    if kind == 0:
                        fh.write(b'<path class="polygon" fill-rule="evenodd" d="')
                    elif kind == 1:
                        fh.write(f'<path {open_attrs} d="'.encode())
                    else:
                        fh.write(b'<path class="orphan" fill="none" d="')
                    for r in loops[:-1]:
                        fh.write(mv[lb[r - r0] : lb[r - r0 + 1]])
                    r = loops[-1]
                    fh.write(mv[lb[r - r0] : lb[r - r0 + 1] - 1])  # drop the trailing space
                    fh.write(b'"/>\n')
                fh.write(b"</g>\n")
        fh.write(b"</svg>\n")


def _svg_chunk(
    pts: np.ndarray, offsets: np.ndarray, closed: np.ndarray, decimals: int
) -> tuple[np.ndarray, np.ndarray]:
    """Path text of every loop of a chunk: ``M x,y L x,y x,y ... Z `` (closed) or ``... x,y `` (open)."""
    n_pts = pts.shape[0]
    values = np.empty((n_pts, 2), dtype=np.float64)
    values[:, 0] = pts[:, 0]
    np.negative(pts[:, 1], out=values[:, 1])
    first, end = offsets[:-1], offsets[1:]
    nonempty = end > first
    lengths = end - first
    before = [
        (2 * first[nonempty], b"M "),
        (2 * (first[lengths >= 2] + 1), b"L "),
    ]
    after = [(2 * end[nonempty & closed] - 1, b"Z ")]
    sep = np.empty(2 * n_pts, dtype=np.uint8)
    sep[0::2] = ord(",")
    sep[1::2] = ord(" ")
    return format_fixed(values, decimals, sep, before, after)


