"""PrusaSlicer's vector SL1 archive (``.sl1_svg``, its format id ``SL1SVG``, PrusaSlicer 2.6 and later): the SL1
archive with one SVG of the layer's contours in place of each PNG.

Members, as PrusaSlicer's ``SL1_SVGArchive`` writes them (``src/libslic3r/Format/SL1_SVG.cpp``): ``config.ini`` and
``prusaslicer.ini`` (:mod:`gpuslice.raster.sl1`; ``sla_archive_format = SL1SVG``, ``sla_output_precision``),
``<jobDir>00000.svg`` upward, ``thumbnail/thumbnail400x400.png`` and ``thumbnail800x480.png``; every member deflated
at level 9 (PrusaSlicer's "tight" compression: SVG is text).

**A layer's SVG** is in the display's frame, exactly PrusaSlicer's: the contours go through the same mapping as the
PNG layers (:mod:`gpuslice.raster.coverage`: the centred placement, portrait's X/Y swap, the mirrors), then are
written in integer units of ``precision`` mm (PrusaSlicer's ``sla_output_precision``, 0.001 by default):
``x = round(u · res_x / cols)``, ``y = round(v · res_y / rows)`` with (u, v) the continuous pixel coordinates,
(cols, rows) the PNG's size and ``res = round(display size along it in mm / precision)``, rounded half away from
zero. The header is ``<svg height="Hmm" width="Wmm" viewBox="0 0 res_x res_y" style="fill: white; stroke: none;
fill-rule: nonzero">`` (W x H: the display in the PNG's orientation). Each polygon of the layer (an outer loop and
its holes: :class:`~gpuslice.slicing.result.SliceResult`'s layout) is one ``<path d="M x y l dx dy … z M … z" />``:
per loop the first point absolute, then relative moves, points that round onto the previous one skipped, loops
left with fewer than 3 points dropped (an outer loop with its holes). Holes wind against their outer loop, so under
``nonzero`` they are holes both in a viewer and for PrusaSlicer's reader (which unions every path, nonzero).
Polygons come largest outer loop first, so that an island inside another polygon's hole is drawn after it.
Differences from PrusaSlicer's bytes: it writes every loop as its own ``<path>`` (holes then fill white in a
viewer), simplifies loops by one unit first and ends the file without a newline. Open chains (never filled) and
holes without an outer loop (broken meshes) are left out.

The layers handed in (tiles or runs) are used only for the thumbnails (a height map, as SL1's); the contours come
from ``target.result``. Written atomically; with a given ``now`` the bytes are reproducible.
"""

from __future__ import annotations

import datetime as _dt
import os
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..formats.numbers import format_fixed
from ..io.atomic import WRITE_BUFFER, atomic_path
from ..ragged import expand_ranges
from .coverage import Tile
from .edges import result_bounds
from .sl1 import (
    THUMBNAILS,
    SL1Info,
    _Thumb,
    _zip_time,
    check_one_layer_height,
    config_ini,
    info_from,
    prusaslicer_ini,
    sl1_print_time,
    sl1_values,
)
from .spec import RasterSpec

__all__ = ["PRECISION_MM", "svg_resolution", "svg_header", "layer_svgs", "write_sl1svg", "write_target"]

#: PrusaSlicer's default ``sla_output_precision``: one SVG unit, mm
PRECISION_MM = 0.001
#: deflate level of every member (PrusaSlicer's ``Zipper::TIGHT_COMPRESSION``)
ZIP_LEVEL = 9
#: loops whose points are formatted in one vectorised batch
_CHUNK_POINTS = 1 << 18


def _display_png_mm(spec: RasterSpec) -> tuple[float, float]:
    """(width, height) mm of the display in the PNG's orientation (portrait swaps PrusaSlicer's width and height)."""
    w, h = spec.display_mm
    return (h, w) if spec.portrait else (w, h)


def svg_resolution(spec: RasterSpec, precision: float = PRECISION_MM) -> tuple[int, int]:
    """(res_x, res_y): the SVG's viewBox size in units of ``precision`` mm, as PrusaSlicer rounds it."""
    w, h = _display_png_mm(spec)
    return int(np.floor(w / precision + 0.5)), int(np.floor(h / precision + 0.5))


def _fmt_mm(v: float) -> str:
    return f"{v:.6f}".rstrip("0").rstrip(".")


def svg_header(spec: RasterSpec, precision: float = PRECISION_MM) -> bytes:
    """The text every layer's SVG starts with (PrusaSlicer's header)."""
    w, h = _display_png_mm(spec)
    rx, ry = svg_resolution(spec, precision)
    return (
        '<?xml version="1.0" encoding="UTF-8" standalone="yes"?>\n'
        '<!DOCTYPE svg PUBLIC "-//W3C//DTD SVG 1.0//EN" "http://www.w3.org/TR/2001/REC-SVG-20010904/DTD/svg10.dtd">\n'
        f'<svg height="{_fmt_mm(h)}mm" width="{_fmt_mm(w)}mm" viewBox="0 0 {rx} {ry}" '
        'style="fill: white; stroke: none; fill-rule: nonzero" xmlns="http://www.w3.org/2000/svg" '
        'xmlns:svg="http://www.w3.org/2000/svg" xmlns:xlink="http://www.w3.org/1999/xlink">\n'
    ).encode()


SVG_END = b"</svg>\n"


def _round_half_away(x: np.ndarray) -> np.ndarray:
    return (np.sign(x) * np.floor(np.abs(x) + 0.5)).astype(np.int64)


def _chunk_text(result, spec: RasterSpec, bounds, l0: int, l1: int, scale: np.ndarray) -> list[bytes]:
    """The path text (no header) of layers ``l0 .. l1 - 1``, one ``bytes`` each; vectorised over the chunk."""
    lo, po = result.layer_offsets, result.loop_offsets
    r0, r1 = int(lo[l0]), int(lo[l1])
    out = [b""] * (l1 - l0)
    if r1 == r0:
        return out
    p0, p1 = int(po[r0]), int(po[r1])
    n = np.diff(po[r0 : r1 + 1]).astype(np.int64)
    nr = r1 - r0
    owner = np.repeat(np.arange(nr, dtype=np.int64), n)
    pts = np.asarray(result.points[p0:p1], np.float64)
    q = _round_half_away(spec.to_pixels(pts, bounds) * scale) if pts.size else np.zeros((0, 2), np.int64)
    # a point is kept unless it rounds onto its predecessor in the loop (then it equals the last kept point too)
    keep = np.ones(q.shape[0], bool)
    if q.shape[0] > 1:
        keep[1:] = (q[1:] != q[:-1]).any(axis=1) | (owner[1:] != owner[:-1])
    kept = np.bincount(owner[keep], minlength=nr)
    closed = np.asarray(result.loop_closed[r0:r1], bool)
    hole = np.asarray(result.loop_is_hole[r0:r1], bool)
    parent = np.asarray(result.loop_parent[r0:r1], np.int64) - r0
    layer = np.asarray(result.loop_layer[r0:r1], np.int64)
    valid = closed & (kept >= 3)
    outer = valid & ~hole
    has_parent = (parent >= 0) & (parent < nr)
    pidx = np.where(has_parent, parent, 0)
    hole_ok = valid & hole & has_parent & outer[pidx] & (layer[pidx] == layer)
    use = outer | hole_ok
    poly = np.where(hole, pidx, np.arange(nr))
    # outer loops' areas (model mm², shoelace) order the polygons, largest first
    nxt = np.arange(pts.shape[0]) + 1
    ends = np.cumsum(n)
    nonempty = n > 0
    nxt[ends[nonempty] - 1] = (ends - n)[nonempty]
    cross = pts[:, 0] * pts[nxt, 1] - pts[nxt, 0] * pts[:, 1] if pts.size else np.zeros(0)
    area = np.abs(np.bincount(owner, weights=cross, minlength=nr))
    rings = np.flatnonzero(use)
    order = rings[np.lexsort((rings, hole[rings], poly[rings], -area[poly[rings]], layer[rings]))]
    # values: per kept point, the first of its loop absolute, the others relative to the previous kept one
    kq = q[keep]
    rel = kq.copy()
    rel[1:] -= kq[:-1]
    k_start = np.zeros(nr + 1, np.int64)
    np.cumsum(kept, out=k_start[1:])
    rel[k_start[:-1][kept > 0]] = kq[k_start[:-1][kept > 0]]
    _, take = expand_ranges(k_start[order], kept[order])
    vals = rel[take].astype(np.float64)
    m = kept[order]
    s = np.zeros(order.size + 1, np.int64)
    np.cumsum(m, out=s[1:])
    first_of_poly = np.ones(order.size, bool)
    first_of_poly[1:] = poly[order[1:]] != poly[order[:-1]]
    last_of_poly = np.ones(order.size, bool)
    last_of_poly[:-1] = first_of_poly[1:]
    start = s[:-1]
    before = [(2 * start[first_of_poly], b'<path d="M '), (2 * start[~first_of_poly], b"M "), (2 * (start + 1), b"l ")]
    after = [(2 * (start + m - 1) + 1, [b'z" />\n' if e else b"z " for e in last_of_poly.tolist()])]
    buf, starts = format_fixed(vals, 0, ord(" "), before, after)
    mv = memoryview(buf)
    # byte ranges per layer: its rings are consecutive in ``order``
    ring_layer = layer[order] - l0
    first_ring = np.searchsorted(ring_layer, np.arange(l1 - l0), side="left")
    last_ring = np.searchsorted(ring_layer, np.arange(l1 - l0), side="right")
    for i in np.flatnonzero(last_ring > first_ring).tolist():
        a, b = int(s[first_ring[i]]), int(s[last_ring[i]])
        out[i] = bytes(mv[int(starts[2 * a]) : int(starts[2 * b])])
    return out


def layer_svgs(result, spec: RasterSpec, bounds=None, precision: float = PRECISION_MM):
    """Every layer's SVG (``bytes``), in order: contours of ``result`` placed on ``spec``'s display as the PNG layers
    are (``bounds`` centred; None: the result's own), in units of ``precision`` mm (module docstring)."""
    if not (isinstance(precision, float | int) and precision > 0):
        raise ParameterError(f"precision must be > 0 mm, got {precision}")
    if bounds is None:
        bounds = result_bounds(result)
    header = svg_header(spec, precision)
    cols, rows = spec.png_size
    rx, ry = svg_resolution(spec, precision)
    scale = np.array([rx / cols, ry / rows])
    po, lo = result.loop_offsets, result.layer_offsets
    pts_cum = po[lo]
    l0 = 0
    while l0 < result.n_layers:
        # the next chunk: at least one layer, about _CHUNK_POINTS points
        l1 = int(np.searchsorted(pts_cum, pts_cum[l0] + _CHUNK_POINTS, side="right")) - 1
        l1 = min(max(l1, l0 + 1), result.n_layers)
        for text in _chunk_text(result, spec, bounds, l0, l1, scale):
            yield header + text + SVG_END
        l0 = l1


def write_sl1svg(
    tiles: Iterable[Tile],
    result,
    spec: RasterSpec,
    path: str | os.PathLike,
    info: SL1Info,
    *,
    bounds=None,
    precision: float = PRECISION_MM,
    progress: Callable[[int], None] | None = None,
    now: _dt.datetime | None = None,
) -> dict[str, float]:
    """Write an SL1_SVG archive of ``result`` at ``path`` (atomically); ``tiles`` (the same layers rasterised, in
    order) feed the thumbnails. Returns ``{"layers": n, "svg_bytes": total SVG text}``."""
    p = Path(os.fspath(path))
    if not info.job_dir or any(ch in info.job_dir for ch in "/\\"):
        raise ParameterError(f"{p}: bad job name '{info.job_dir}'")
    n_layers = result.n_layers
    thumb = _Thumb(spec, n_layers)
    stamp = _zip_time(now)
    info.extra = {"sla_archive_format": "SL1SVG", "sla_output_precision": float(precision), **info.extra}
    svg_bytes = 0
    with atomic_path(p) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as fh, \
            zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as z:

        def put(name: str, data: bytes) -> None:
            z.writestr(zipfile.ZipInfo(name, stamp), data, zipfile.ZIP_DEFLATED, ZIP_LEVEL)

        put("config.ini", config_ini(info, n_layers, now).encode())
        put("prusaslicer.ini", prusaslicer_ini(info, spec).encode())
        svgs = layer_svgs(result, spec, bounds, precision)
        k = 0
        for item in tiles:
            if k >= n_layers:
                raise ParameterError(f"{p}: more layers than the {n_layers} sliced")
            thumb.add(item)
            text = next(svgs)
            svg_bytes += len(text)
            put(f"{info.job_dir}{k:05d}.svg", text)
            k += 1
            if progress is not None:
                progress(k)
        if k != n_layers:
            raise ParameterError(f"{p}: expected {n_layers} layers, got {k}")
        for w, h in THUMBNAILS:
            put(f"thumbnail/thumbnail{w}x{h}.png", thumb.png((w, h)))
    return {"layers": float(n_layers), "svg_bytes": float(svg_bytes)}


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """The settings check of the SL1 family (:func:`gpuslice.raster.sl1.refuse_settings`), and ``z_samples``: its
    layers are contours, which anti-aliasing in Z cannot change (it only reached the thumbnails)."""
    from .sl1 import refuse_settings as sl1_refuse

    sl1_refuse(path, name, options, settings, spec)
    if options.z_samples > 1:
        raise ParameterError(f"{path}: an SL1_SVG archive stores each layer's contours, not its pixels; "
                             f"--z-samples {options.z_samples} cannot be written (use .sl1 for grey layers)")


def write_target(tiles: Iterable[Tile], target) -> dict[str, float]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): an SL1_SVG archive of ``target.result``."""
    path = Path(target.path)
    check_one_layer_height(target.result.thickness, path)
    preset = target.options.preset
    values = sl1_values(target)
    if preset is not None and preset.machine:
        values.update(printer_profile=preset.title)
    info = info_from(target.result, target.name, values)
    stats = write_sl1svg(tiles, target.result, target.spec, path, info, bounds=target.bounds,
                         progress=target.progress, now=target.now)
    return {**stats, "print_time_s": sl1_print_time(info, target.result.n_layers)}
