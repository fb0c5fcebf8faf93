"""The layer viewer: one self-contained HTML page (data, code and style inline) to inspect a :class:`SliceResult`.

The page (template ``view/viewer.html``) has a layer slider with keyboard stepping, the current layer's polygons
drawn on a 2D canvas (filled under the result's fill rule, so holes show as holes; outer contours blue, holes orange,
open chains red with their ends marked), the layer's z, slab, thickness, area, points, loops and repairs, and the
points-per-layer curve (the paper's Fig. 11) with the current layer marked (click or drag on it to jump; layers with
repairs or open chains are ticked in red; an adaptive schedule adds its thickness curve). An optional resin mask
(a PNG per layer) is shown beside the contours. With a check report (``view --check``, :mod:`gpuslice.checks`) the
islands, resin traps and suction cups are outlined on their layers and listed, each a link to its layer. It needs no
network: a Content-Security-Policy forbids every fetch but ``data:`` images, and nothing refers to any URL.

Data layout inside the page: one ``<script type="application/json">`` holding base64 strings of little-endian
typed arrays (decoded once at load, then every layer is a view into them), built from the result's columns::

    points        float32  (2P,)   x, y in mm, as SliceResult.points
    loop_offsets  int32    (R+1,)  as SliceResult.loop_offsets
    layer_offsets int32    (L+1,)  as SliceResult.layer_offsets
    loop_flags    uint8    (R,)    bit 0: hole (clockwise), bit 1: open chain (loop_closed false)
    z, thickness, bottom, area  float64 (L,)   mm, mm, mm, mm^2 (bottom: each slab's, SliceResult.bottom)
    layer_points  int32    (L,)    points per layer
    repairs[kind] int32    (L,)    per-layer repair counts (kinds with a non-zero total only)

So a page costs about 10.7 bytes per point (8 bytes of float32 x, y in base64) plus ~50 bytes per layer and loop;
``gpuslice view`` prints its size. Layer numbers on the page are 0-based, as in the ``.npz``, the SVG ids and the
JSON report.
"""

from __future__ import annotations

import base64
import html
import io
import itertools
import json
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MeshFileError, ParameterError
from ..formats.numbers import point_bounds
from ..slicing.result import SliceResult

__all__ = ["MaskLayers", "raster_masks", "build_view_html", "write_view", "read_view_data", "MAX_VIEW_POINTS"]

#: Most points one page may hold: about 430 MB of HTML, under Chromium's 512 MB limit on a single string.
MAX_VIEW_POINTS = 40_000_000

_DATA_MARK = "/*__GPUSLICE_DATA__*/"
_TITLE_MARK = "__GPUSLICE_TITLE__"
_DTYPES = {"f4": "<f4", "f8": "<f8", "i4": "<i4", "u1": "u1"}


def _template() -> str:
    return resources.files("gpuslice.view").joinpath("viewer.html").read_text(encoding="utf-8")


def _pack(values: np.ndarray, code: str) -> dict[str, Any]:
    arr = np.ascontiguousarray(values, dtype=_DTYPES[code]).reshape(-1)
    return {"dtype": code, "n": int(arr.size), "b64": base64.b64encode(arr.tobytes()).decode("ascii")}


def _unpack(entry: Mapping[str, Any]) -> np.ndarray:
    return np.frombuffer(base64.b64decode(entry["b64"]), dtype=_DTYPES[entry["dtype"]])


def _columns(result: SliceResult) -> dict[str, dict[str, Any]]:
    n_points = int(result.points.shape[0])
    if n_points > MAX_VIEW_POINTS:
        raise ParameterError(
            f"{n_points:,} points are too many for one page (at most {MAX_VIEW_POINTS:,}); slice with thicker layers"
        )
    flags = result.loop_is_hole.astype(np.uint8) | ((~result.loop_closed.astype(bool)).astype(np.uint8) << 1)
    return {
        "points": _pack(result.points, "f4"),
        "loop_offsets": _pack(result.loop_offsets, "i4"),
        "layer_offsets": _pack(result.layer_offsets, "i4"),
        "loop_flags": _pack(flags, "u1"),
        "z": _pack(result.z, "f8"),
        "thickness": _pack(result.thickness, "f8"),
        "bottom": _pack(result.bottom, "f8"),  # (the slabs where the exports put them: explicit planes' own)
        "area": _pack(result.area, "f8"),
        "layer_points": _pack(result.points_per_layer, "i4"),
    }


def _bbox(points: np.ndarray) -> list[float]:
    if points.shape[0] == 0:
        return [0.0, 0.0, 1.0, 1.0]
    lo, hi = point_bounds(points)
    return [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]


def _info(result: SliceResult) -> list[list[str]]:
    meta = result.meta
    out = []
    if "facets" in meta:
        out.append(["facets", f"{int(meta['facets']):,}"])
    if meta.get("scale") not in (None, 1, 1.0):
        out.append(["scale", f"{float(meta['scale']):.6g}"])
    if meta.get("schedule_mode"):
        out.append(["schedule", str(meta["schedule_mode"])])
    if meta.get("device"):
        out.append(["sliced on", str(meta["device"])])
    return out


@dataclass
class MaskLayers:
    """Resin masks to show in the viewer: a PNG per layer (all layers or some), placed on the display.

    png : ``{layer: PNG bytes}`` of each layer's tile (the non-blank part of its mask, see :mod:`gpuslice.raster`).
    origin : ``{layer: (row0, col0)}``: where each tile lies on the display, pixels (row 0 is the PNG's top).
    to_mm : (2, 3) float64 affine map from display pixel coordinates (u = column, v = row) to model mm, so the page
        draws each tile under the layer's contours; None: the tiles are shown only beside the drawing.
    label : a caption, e.g. ``"3840×2400 px, 0.05 mm"``.
    blank : layers rasterised without a lit pixel (no PNG: the page says "blank mask", not "no mask stored").
    """

    png: dict[int, bytes]
    origin: dict[int, tuple[int, int]] = field(default_factory=dict)
    to_mm: np.ndarray | None = None
    label: str = ""
    blank: tuple[int, ...] = ()


def raster_masks(
    result: SliceResult,
    spec: Any = None,
    *,
    every: int = 1,
    bounds: Sequence[float] | None = None,
    backend: str = "auto",
    device: Any = None,
    name: str = "model",
) -> MaskLayers:
    """Rasterise every ``every``-th layer of ``result`` with :mod:`gpuslice.raster` into PNG tiles for the viewer.

    spec : a :class:`gpuslice.raster.RasterSpec` (default: its default display); bounds : the (xmin, ymin, xmax, ymax)
    mm that is centred on the display (default: the result's points, as :mod:`gpuslice.raster` does); name : the file
    named in the error when the model does not fit on the display. Needs pillow.
    """
    from PIL import Image

    from ..raster.coverage import iter_tiles
    from ..raster.edges import check_fits, result_bounds
    from ..raster.spec import RasterSpec

    if every < 1:
        raise ParameterError(f"every must be >= 1 (a mask for every n-th layer), got {every}")
    spec = spec or RasterSpec()
    if bounds is None:
        bounds = result_bounds(result)
    check_fits(result, spec, bounds, name=name)
    affine = np.vstack([spec.affine(bounds), [0.0, 0.0, 1.0]])
    to_mm = np.linalg.inv(affine)[:2]
    layers = list(range(0, result.n_layers, every))
    png: dict[int, bytes] = {}
    origin: dict[int, tuple[int, int]] = {}
    blank: list[int] = []
    for tile in iter_tiles(result, spec, layers=layers, bounds=bounds, backend=backend, device=device, clip=True):
        if tile.data.size == 0 or not tile.data.any():
            blank.append(int(tile.index))
            continue
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(tile.data), mode="L").save(buf, format="PNG")
        png[tile.index] = buf.getvalue()
        origin[tile.index] = (tile.row0, tile.col0)
    label = f"{spec.nx}×{spec.ny} px, {spec.px:g} mm"
    return MaskLayers(png, origin, to_mm, label, tuple(blank))


def build_view_html(
    result: SliceResult,
    *,
    title: str | None = None,
    masks: MaskLayers | Mapping[int, bytes] | None = None,
    mask_label: str = "",
    checks: Any = None,
) -> str:
    """The viewer page for ``result`` as one HTML string (UTF-8, self-contained, no network; :func:`write_view`
    writes the same page without holding it whole).

    title : shown in the header and the window title (default: the sliced file's name from ``result.meta``).
    masks : optional resin masks for some or all layers: a :class:`MaskLayers` (drawn under the contours, in place,
        and beside them; see :func:`raster_masks`) or a plain ``{layer index: PNG bytes}`` (beside them only). The
        page shows the current layer's mask or says there is none for it. ``mask_label`` (e.g.
        ``"1920×1080 px, 0.05 mm"``) is shown with it (default: the :class:`MaskLayers` label).
    checks : a :class:`gpuslice.checks.CheckReport`: its islands and cavities are marked on their layers (islands
        red, traps purple, suction cups orange) and listed, each a link to its layer.

    Raises :class:`~gpuslice.errors.ParameterError` for a result with more than :data:`MAX_VIEW_POINTS` points or
    a mask for a layer that does not exist.
    """
    head, data, tail = _page(result, title=title, masks=masks, mask_label=mask_label, checks=checks)
    return head + "".join(_json_chunks(data)) + tail


def _json_chunks(data: dict[str, Any]) -> Iterator[str]:
    """``data`` as compact ASCII JSON, in the encoder's pieces; no "<" or ">" raw (inside <script>, a "</script>"
    would end the element)."""
    for chunk in json.JSONEncoder(separators=(",", ":"), ensure_ascii=True).iterencode(data):
        yield chunk.replace("<", "\\u003c").replace(">", "\\u003e")


def _page(result: SliceResult, title=None, masks=None, mask_label: str = "", checks=None) -> tuple[str, dict, str]:
    """The viewer page for ``result`` (:func:`build_view_html`'s arguments): the HTML before its data, the data
    (JSON-ready), the HTML after."""
    meta = result.meta
    if title is None:
        title = Path(str(meta.get("file", "gpuslice result"))).name
    fill_rule = str(meta.get("params", {}).get("fill_rule", "nonzero"))
    n_layers, n_points = result.n_layers, int(result.points.shape[0])
    thickness = np.asarray(result.thickness)
    # uniform: one thickness, but for a first layer of its own (--first-layer), which is said apart
    uniform = n_layers < 3 or float(np.ptp(thickness[1:])) <= 1e-9
    t_text = "adaptive layers"
    if n_layers and uniform:
        rest = float(thickness[1] if n_layers > 1 else thickness[0])
        t_text = f"{rest:g} mm layers" + (f" (the first {float(thickness[0]):g} mm)"
                                          if abs(float(thickness[0]) - rest) > 1e-9 else "")
    data: dict[str, Any] = {
        "version": 1,
        "summary": f"{n_layers:,} layer{'' if n_layers == 1 else 's'} · {t_text} · {result.n_loops:,} loop"
                   f"{'' if result.n_loops == 1 else 's'} · {n_points:,} points",
        "fill_rule": fill_rule,
        "bbox": _bbox(result.points),
        "info": _info(result),
        "arrays": _columns(result),
        "repairs": {k: _pack(v, "i4") for k, v in sorted(result.repairs.items()) if np.any(v)},
        "masks": None,
        "checks": None,
    }
    if checks is not None:
        data["checks"] = checks.view_data()
        bad = [row[0] for row in data["checks"]["islands"] if not 0 <= row[0] < n_layers]
        if bad:
            raise ParameterError(f"check report for layer {bad[0]}, but the result has {n_layers} layers")
    if masks is not None:
        placed = masks if isinstance(masks, MaskLayers) else MaskLayers(dict(masks))
        bad = [i for i in placed.png if not 0 <= int(i) < n_layers]
        if bad:
            raise ParameterError(f"mask for layer {bad[0]}, but the result has {n_layers} layers")
        to_mm = None
        if placed.to_mm is not None and placed.origin:
            t = np.asarray(placed.to_mm, dtype=np.float64)
            to_mm = [t[0, 0], t[1, 0], t[0, 1], t[1, 1], t[0, 2], t[1, 2]]  # canvas setTransform order a b c d e f
        data["masks"] = {
            "size": mask_label or placed.label,
            "png": {str(int(i)): base64.b64encode(bytes(p)).decode("ascii") for i, p in sorted(placed.png.items())},
            "origin": {str(int(i)): [int(r), int(c)] for i, (r, c) in sorted(placed.origin.items())},
            "to_mm": [float(v) for v in to_mm] if to_mm is not None else None,
            "blank": sorted(int(i) for i in placed.blank),
        }
    # (the template is cut at the data mark first: a title holding the mark's text must not be taken for it)
    head, mark, tail = _template().partition(_DATA_MARK)
    if not mark:  # pragma: no cover - the template ships with the package
        raise RuntimeError("viewer.html has no data mark")
    safe = html.escape(title)
    return head.replace(_TITLE_MARK, safe), data, tail.replace(_TITLE_MARK, safe)


def write_view(result: SliceResult, path: str | os.PathLike, **kwargs: Any) -> int:
    """Write the viewer page for ``result`` to ``path`` atomically; returns its size in bytes.

    Keyword arguments are those of :func:`build_view_html`. Errors name ``path``. The page is written as its JSON
    is encoded, never held whole (the page, its escaped copies and its UTF-8 bytes at once made the peak 6-9x the
    page: 2 GB for a 234 MB page).
    """
    from ..io.atomic import WRITE_BUFFER, atomic_path, utf8

    try:
        head, data, tail = _page(result, **kwargs)
    except ParameterError as exc:
        raise ParameterError(f"{path}: {exc}") from None
    size = 0
    with atomic_path(path) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as fh:
        for piece in itertools.chain((utf8(head),), (c.encode("ascii") for c in _json_chunks(data)), (utf8(tail),)):
            fh.write(piece)
            size += len(piece)
    return size


_DATA_RE = re.compile(r'<script type="application/json" id="gpuslice-data">(.*?)</script>', re.S)


def read_view_data(page: str | os.PathLike) -> dict[str, Any]:
    """The data embedded in a viewer page (a path or the HTML text), with every packed array decoded to numpy.

    Returns the page's JSON with ``arrays`` and ``repairs`` mapped to arrays and ``masks["png"]`` to
    ``{layer: PNG bytes}``; for tests and for getting the numbers back out of a page someone sent you.
    """
    is_text = isinstance(page, str) and page.lstrip().startswith("<")
    try:
        text = page if is_text else Path(page).read_text("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise MeshFileError(f"{page}: cannot read ({exc})") from None
    m = _DATA_RE.search(text)
    if not m:
        raise MeshFileError(f"{'the page' if is_text else page}: not a gpuslice viewer page")
    data = json.loads(m.group(1))
    data["arrays"] = {k: _unpack(v) for k, v in data["arrays"].items()}
    data["repairs"] = {k: _unpack(v) for k, v in data["repairs"].items()}
    if data.get("masks"):
        data["masks"]["png"] = {int(k): base64.b64decode(v) for k, v in data["masks"]["png"].items()}
    return data
