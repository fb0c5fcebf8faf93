"""NanoDLP plates (``.nanodlp``; NanoDLP takes the same bytes named ``.zip``): a zip of numbered layer PNGs and JSON
manifests.

What NanoDLP imports (its manual, "NanoDLP / ZIP File Format", docs.nanodlp.com/manual/format): a zip holding the
layers as ``1.png`` upward (no leading zeros, 8-bit; on a mono display one byte is one pixel) and optionally
``meta.json``, ``plate.json`` (required for ``.nanodlp``; a ``.zip`` is "processed the same with extra checks"),
``profile.json``, ``override.json``, ``info.json`` and ``3d.png``. UVtools (``NanoDLPFile.cs``) requires
``meta.json``, ``plate.json`` and ``profile.json`` and reads ``slicer.json``; mslicer writes NanoDLP's
``options.json`` and the same object as ``slicer.json``. This writer writes all of them (no ``override.json``):

* ``1.png`` … ``N.png``: greyscale 8-bit PNGs exactly as the PNG stack's (:mod:`gpuslice.raster.png`, encoded and
  deflated into the zip on the worker threads), the display's full size (``spec.png_size``), already mirrored and
  turned as the display asks.
* ``meta.json``: ``FormatVersion`` 2, ``Distro`` generic, ``Program`` gpuslice and its version, ``Profile`` false:
  NanoDLP keeps the printer's own resin profile (its G-code templates), so the exposures below are a record.
* ``profile.json``: ``Title``, ``Depth``/``SupportDepth`` (layer and first-layer thickness, µm), ``CureTime``,
  ``SupportCureTime`` (s), ``SupportLayerNumber``, ``TransitionalLayer``, ``WaitHeight``/``SupportWaitHeight`` (the
  lift's total, both stages, mm: the profile has one lift), ``TopWait``/``SupportTopWait`` (wait after the lift,
  s), ``WaitBeforePrint``/``WaitAfterPrint`` (waits before and after the exposure, s; the ``Support*`` ones are the
  bottom layers' values), ``CustomValues.UvPwmValue``
  (the normal layers' light PWM / 255, 2 decimals: the profile has no bottom PWM field), colours; field meanings
  as UVtools maps them.
* ``options.json`` = ``slicer.json``: ``PWidth``/``PHeight`` (the PNG's size), ``XPixelSize``/``YPixelSize`` (mm
  along the PNG's columns and rows), ``XRes``/``YRes`` (the same in µm), ``Thickness``/``SupportDepth`` (µm),
  ``SupportLayerNumber``, ``LayerCount``, ``XOffset``/``YOffset`` (half the PNG), ``ImageMirror`` (1 when the
  display mirrors the columns), ``DisplayController`` 1 (8-bit mono layers), ``Boundary`` (as ``plate.json``'s).
* ``info.json``: per layer ``TotalSolidArea``, ``LargestArea``, ``SmallestArea`` (mm², of the layer's polygons under
  the fill rule), ``AreaCount`` (its polygons), ``MinX``/``MinY``/``MaxX``/``MaxY`` (its lit pixels' box, PNG pixel
  indices; 0 for a blank layer).
* ``plate.json``: ``LayersCount``, ``TotalSolidArea`` (the resin, ml), ``PrintTime``/``PrintEst`` (s,
  :func:`~gpuslice.raster.settings.print_time_s`), ``CreatedDate``/``Updated`` (the archive date, Unix s),
  ``Path`` (the job name), ``Processed`` true, and the part's box ``XMin`` … ``ZMax`` in mm (X/Y in the PNG's frame
  from the display's centre, Z from the plate), ``XMin`` … ``YMax`` also in ``options.json``'s ``Boundary``.
* ``3d.png``: a 200 x 100 top view (the SL1 thumbnail's height map).

One layer height: NanoDLP moves every layer by ``Depth`` (the bottom layers by ``SupportDepth``), so schedules with
other thicknesses (adaptive layers) are refused. Written atomically; with a given ``now`` the bytes are reproducible.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import zipfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from ..slicing.rings import signed_areas
from .coverage import Tile
from .layers import RunLayer, encode_png, pixel_runs, run_groups
from .png import PngEncoder, encode_all
from .png_runs import png_encoders, png_group
from .settings import PrintSettings, print_time_s, ramp_layers, resin_ml
from .sl1 import _member, _Thumb, _write_deflated, _zip_time, check_one_layer_height
from .spec import RasterSpec

__all__ = ["PREVIEW_SIZE", "UNSTORED", "polygon_areas", "refuse_settings", "write_nanodlp", "write_target"]

#: the settings a NanoDLP profile has no field for (each with its bottom twin): its one lift is a height without a
#: speed, it retracts the same way, its one light intensity is the normal layers', and it has no per-layer table
UNSTORED = ("lift_speed", "lift_speed2", "retract_speed", "retract_height2", "retract_speed2", "bottom_light_pwm",
            "per_layer_settings")

#: size of ``3d.png`` (NanoDLP's manual: a 200x100 px render)
PREVIEW_SIZE = (200, 100)


#: loops' points taken at a time by :func:`polygon_areas` (float64 temporaries of ~60 bytes a point: bounded)
AREA_CHUNK_POINTS = 1 << 20


def _signed_areas(result) -> np.ndarray:
    """Each loop's shoelace area (mm², counter-clockwise positive; :func:`gpuslice.slicing.rings.signed_areas`), a
    chunk of whole loops of about
    :data:`AREA_CHUNK_POINTS` points at a time (all of them at once made float64 copies of every point: 1 GB at
    24,000 layers, where the contours held 170 MB)."""
    po = np.asarray(result.loop_offsets, np.int64)
    n_loops = po.size - 1
    signed = np.zeros(max(n_loops, 0))
    r0 = 0
    while r0 < n_loops:
        r1 = min(n_loops, max(r0 + 1, int(np.searchsorted(po, po[r0] + AREA_CHUNK_POINTS, side="right")) - 1))
        p0 = int(po[r0])
        signed[r0:r1] = signed_areas(np.asarray(result.points[p0 : po[r1]]), po[r0 : r1 + 1] - p0)
        r0 = r1
    return signed


def polygon_areas(result) -> tuple[np.ndarray, np.ndarray]:
    """(layer, area) of every polygon of ``result`` (an outer loop with its holes; closed loops of 3 points or
    more), mm²: the outer loop's shoelace area less its holes'. Sorted by layer."""
    n = np.diff(np.asarray(result.loop_offsets, np.int64))
    signed = _signed_areas(result)
    closed = np.asarray(result.loop_closed, bool) & (n >= 3)
    hole = np.asarray(result.loop_is_hole, bool)
    parent = np.asarray(result.loop_parent, np.int64)
    outer = closed & ~hole
    ok_parent = (parent >= 0) & (parent < n.size)
    pid = np.where(ok_parent, parent, 0)
    hole_ok = closed & hole & ok_parent & outer[pid]
    area = np.zeros(n.size)
    np.add.at(area, np.flatnonzero(outer), np.abs(signed[outer]))
    np.add.at(area, pid[hole_ok], -np.abs(signed[hole_ok]))
    polys = np.flatnonzero(outer)
    layer = np.asarray(result.loop_layer, np.int64)[polys]
    return layer, area[polys]


def _lit_box(item: Tile | RunLayer, cols: int) -> tuple[int, int, int, int]:
    """(min x, min y, max x, max y) PNG pixel indices of the layer's non-blank pixels; zeros when blank."""
    start, length, _ = pixel_runs(item, cols)
    if start.size == 0:
        return 0, 0, 0, 0
    row, x = np.divmod(start, cols)
    return int(x.min()), int(row.min()), int((x + length - 1).max()), int(row.max())


def um(mm: float) -> float:
    """Millimetres as micrometres (NanoDLP's unit for thicknesses and resolutions), 3 decimals."""
    return round(float(mm) * 1000.0, 3)


def _json(obj: Any) -> bytes:
    return (json.dumps(obj, indent=2, ensure_ascii=False) + "\n").encode()


def write_nanodlp(
    tiles: Iterable[Tile | RunLayer],
    result,
    spec: RasterSpec,
    path: str | os.PathLike,
    settings: PrintSettings,
    *,
    name: str,
    title: str = "",
    bounds=None,
    level: int = 1,
    deflater: str = "auto",
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    now: _dt.datetime | None = None,
    device=None,
) -> dict[str, float]:
    """Write a NanoDLP plate of ``result``'s layers (``tiles``: tiles or runs, in order) at ``path``, atomically
    (module docstring). ``bounds``: the box the layers were centred by (only for the part's box in the manifests;
    None: the result's). ``device``: the OpenCL device of the layers' runs, where their PNGs are made
    (``kernels/png.cl``) at ``level`` 1 (None: numpy). Returns the layer count and PNG bytes."""
    from .. import __version__
    from .edges import pixel_box, result_bounds

    p = Path(os.fspath(path))
    n = result.n_layers
    th = np.asarray(result.thickness, np.float64)
    depth = check_one_layer_height(th, p, first_may_differ=settings.bottom_layers <= 1)
    first = float(th[0]) if th.size else depth
    cols, rows = spec.png_size
    pitch = (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)  # mm along the PNG's columns, rows
    when = now or _dt.datetime.now(_dt.timezone.utc).replace(tzinfo=None)
    stamp = int(when.replace(tzinfo=_dt.timezone.utc).timestamp())
    # the part's box: display frame (PNG orientation) from the display's centre, mm
    box = {"XMin": 0.0, "XMax": 0.0, "YMin": 0.0, "YMax": 0.0}
    if result.points.shape[0]:  # (from the points' box: no copy of every point in pixels)
        lo, hi = pixel_box(result.points, spec, bounds if bounds is not None else result_bounds(result))
        box = {"XMin": round((lo[0] - cols / 2) * pitch[0], 4), "XMax": round((hi[0] - cols / 2) * pitch[0], 4),
               "YMin": round((lo[1] - rows / 2) * pitch[1], 4), "YMax": round((hi[1] - rows / 2) * pitch[1], 4)}
    z_max = float(result.bottom[-1] + th[-1]) if n else 0.0
    s = settings
    bot = s.group(True)  # the bottom layers' values (their twins where given)
    waits = {"WaitBeforePrint": s.wait_before_cure, "WaitAfterPrint": s.wait_after_cure,
             "SupportWaitBeforePrint": bot["wait_before_cure"], "SupportWaitAfterPrint": bot["wait_after_cure"]}
    meta = {"FormatVersion": 2, "Distro": "generic", "Program": "gpuslice", "Version": __version__, "OS": "",
            "Arch": "", "Profile": False}
    profile = {"ResinID": 0, "ProfileID": 0, "Title": title or "gpuslice", "Desc": "", "Depth": um(depth),
               "SupportDepth": um(first), "CureTime": s.exposure, "SupportCureTime": s.bottom_exposure,
               "SupportLayerNumber": s.bottom_layers, "TransitionalLayer": ramp_layers(s),
               "WaitHeight": s.lift_height + s.lift_height2,  # (one lift: the total, as CTB v3 and Photon fold it)
               "SupportWaitHeight": bot["lift_height"] + bot["lift_height2"],
               "TopWait": s.wait_after_lift, "SupportTopWait": bot["wait_after_lift"], **waits, "Updated": stamp,
               "CustomValues": {"UvPwmValue": f"{round(s.light_pwm / 255, 2):g}"}, "FillColor": "#ffffff",
               "BlankColor": "#000000", "IgnoreMask": 1}
    options = {"PWidth": cols, "PHeight": rows, "XPixelSize": pitch[0], "YPixelSize": pitch[1],
               "XRes": um(pitch[0]), "YRes": um(pitch[1]), "Thickness": um(depth), "SupportDepth": um(first),
               "SupportLayerNumber": s.bottom_layers, "LayerCount": n, "XOffset": cols // 2, "YOffset": rows // 2,
               "ImageMirror": int(spec.mirror_x), "DisplayController": 1, "IgnoreMask": 1,
               "FillColor": "#ffffff", "BlankColor": "#000000",
               "FillColorRGB": {"R": 255, "G": 255, "B": 255, "A": 255},
               "BlankColorRGB": {"R": 0, "G": 0, "B": 0, "A": 255},
               "Boundary": {**box, "ZMin": 0.0, "ZMax": round(z_max, 4)}}
    poly_layer, poly_area = polygon_areas(result)
    cut = np.searchsorted(poly_layer, np.arange(n + 1))
    area = np.asarray(result.area, np.float64)
    enc = PngEncoder(cols, rows, level, deflater)
    thumb = _Thumb(spec, n)
    boxes: list[tuple[int, int, int, int]] = []
    with atomic_path(p) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as fh, \
            zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as z:
        zstamp = _zip_time(now)

        def entry(member: str) -> zipfile.ZipInfo:
            zi = zipfile.ZipInfo(member, zstamp)
            zi.compress_type = zipfile.ZIP_DEFLATED
            return zi

        for member, obj in (("meta.json", meta), ("profile.json", profile), ("options.json", options),
                            ("slicer.json", options)):
            z.writestr(entry(member), _json(obj))

        def encode(item: Tile | RunLayer) -> tuple[bytes, bytes, tuple[int, int, int, int]]:  # on a worker
            png = encode_png(item, enc)
            return png, _member(enc, png), _lit_box(item, cols)

        from .png_procs import encode_group as encode_procs
        from .png_procs import threads_for

        device, pool = png_encoders(level, device, workers)

        def encode_group(group: list[Tile | RunLayer]) -> list[tuple[bytes, bytes, tuple[int, int, int, int]]]:
            pngs = png_group(device, group, enc.nx, enc.ny)
            if pngs is not None:  # made on the device; members deflated here (on a worker thread)
                return [(png, _member(enc, png), _lit_box(item, cols)) for png, item in zip(pngs, group, strict=True)]
            if pool is None or not isinstance(group[0], RunLayer):  # (on a worker thread)
                return [encode(item) for item in group]
            done = encode_procs(pool, group, enc.nx, enc.ny, deflater)  # PNGs and members made in the processes
            return [(png, member, _lit_box(item, cols)) for (png, member), item in zip(done, group, strict=True)]

        def sink(k: int, item: tuple[bytes, bytes, tuple[int, int, int, int]]) -> None:
            _write_deflated(z, entry(f"{k + 1}.png"), item[0], item[1])
            boxes.append(item[2])

        stats = encode_all(tiles, encode, sink, threads_for(pool, workers), on_tile=thumb.add, progress=progress,
                           many=encode_group, chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{p}: expected {n} layers, got {stats['layers']}")
        info = []
        for i, (x0, y0, x1, y1) in enumerate(boxes):
            a = poly_area[cut[i] : cut[i + 1]]
            info.append({"TotalSolidArea": round(float(area[i]), 4),
                         "LargestArea": round(float(a.max()), 4) if a.size else 0.0,
                         "SmallestArea": round(float(a.min()), 4) if a.size else 0.0,
                         "MinX": x0, "MinY": y0, "MaxX": x1, "MaxY": y1, "AreaCount": int(a.size)})
        z.writestr(entry("info.json"), _json(info))
        seconds = int(round(print_time_s(s, n)))
        plate = {"PlateID": 0, "ProfileID": 0, "CreatedDate": stamp, "Updated": stamp, "Path": name,
                 "LayersCount": n, "TotalSolidArea": round(resin_ml(area, th), 4), "PrintTime": seconds,
                 "PrintEst": seconds, "Processed": True, **box, "ZMin": 0.0, "ZMax": round(z_max, 4)}
        z.writestr(entry("plate.json"), _json(plate))
        z.writestr(entry("3d.png"), thumb.png(PREVIEW_SIZE))
    return stats


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """NanoDLP's settings check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`): a setting of
    :data:`UNSTORED` given beyond the preset's (:func:`~gpuslice.raster.settings.changed_settings`) is refused
    before any work rather than dropped (the plate would say nothing of it; the lift's two stages are stored as
    their total height)."""
    from .settings import changed_settings

    unstored = changed_settings(settings, UNSTORED, base=options.settings() if options is not None else None)
    if unstored:
        raise ParameterError(f"{path}: a NanoDLP plate stores lift heights, waits, exposures and the normal layers' "
                             "light, not speeds, a slow retract stage, the bottom layers' light or per-layer settings "
                             f"(NanoDLP moves as its own profile says): {', '.join(unstored)} cannot be written (leave "
                             "them out)")


def write_target(tiles: Iterable[Tile | RunLayer], target) -> dict[str, float]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): a NanoDLP plate of ``target.result``'s layers."""
    preset = target.options.preset
    return write_nanodlp(tiles, target.result, target.spec, target.path, target.settings, name=target.name,
                         title=preset.title if preset is not None else "", bounds=target.bounds,
                         level=target.options.png_level, deflater=target.deflater, workers=target.workers,
                         progress=target.progress, now=target.now, device=target.device)
