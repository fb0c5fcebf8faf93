"""Creality Halot ``.cxdlpv4`` files (CXDLP version 4: the Halot Mage and Mage Pro).

Facts (field layouts, units, the checksum, what readers check) from UVtools' ``CrealityCXDLPv4File.cs`` and its 010
Editor template ``cxdlpv4.bt``, gathered in ``docs/research/CXDLP.md`` section 7; our own code. No file another
program wrote could be found to check against, and nothing is verified on a printer.

**Layout.** Despite its name it is not the ``.cxdlp`` layout (:mod:`gpuslice.raster.cxdlp`) but a Chitubox-style one,
little endian after its first fields:

* ``CXSW3DV2`` with its length, the version (4) and the printer's **model code** (``CL-103`` …, from the preset's
  ``machine``: the printer compares it with its own), big endian; then, little endian: the resolution (u16), the
  display's width and height, the machine's Z travel, the print's height and the layer height (f32, mm), the bottom
  layer count, the offsets of the small preview, the layer table and the large preview, the layer count, the print
  time (s), the projector type (1: the display is mirrored, as UVtools writes it for any mirror; the pixels are
  stored as the display shows them, the preset's mirror applied), the print parameters' offset and size, the level
  count 1 (UVtools' writer leaves it so: in Chitu's older formats a count above 1 means that many layer tables), the
  light PWMs (u16), encryption key 0 (plain layers), the slicer info's offset and size;
* two previews, 120x120 and 300x300 (a 32-byte record, then Chitubox's RGB15 run-length words:
  :func:`gpuslice.raster.ctb.rgb15_rle`), drawn from the layers, so their region is reserved at its worst-case size
  and zero-padded (offsets say where each starts);
* the print parameters (68 bytes: the bottom and normal lift, both stages' total, and its speed, the retract speed,
  resin ml and g, light-off delays 0, the bottom layer count, exposure, bottom exposure) and the slicer info (76
  bytes: the second lift and retract stages, the rest after the lift, the per-layer-settings flag, the date in
  minutes since 1970, the anti-aliasing level (1 for ``--gamma 0``, 8 otherwise, as our CTB's), the rests after
  the retract (``--wait-before-cure``) and before the lift (``--wait-after-cure``), exposure, bottom exposure, the
  transition layer count). Speeds in mm/min;
* the layer table, 40 bytes a layer: the platform's z while the layer is exposed (its top, mm; with layers of more
  than one thickness the per-layer-settings flag is set, as UVtools sets it when a layer's z is not what the
  header's layer height gives: whether the printer follows the table's z without it is not known), its exposure (the
  transition ramp included), light-off 0, the offset and size of its data, data type 0 (pixels), 0, the area of its
  largest 4-connected region of lit pixels (mm² x 1000; UVtools writes its largest outer contour's area, holes
  included; what the firmware does with it is not known), two zeros;
* each layer's data: its own settings (11 f32, CTB v4's per-layer record: the lift's total and speed, the second lift
  stage, the retract speed and its slow last stage, the three rests, the PWM), then the whole image as CTB's RLE7
  (:func:`gpuslice.raster.ctb.rle7_batch`, on the device with :class:`~gpuslice.raster.ctb.CtbEncoder`): 7 bits a
  pixel, read back as ``((g >> 1) << 1) | 1`` (0 for 0 and 1), the quantisation :func:`gpuslice.raster.ctb.quantise`
  states;
* a CRC-32 of every byte before it (zero start, no final inversion, as ``.cxdlp`` v3), big endian.

**What the format cannot hold is refused** (:func:`refuse_settings`): a job without a Halot preset before any work,
as for ``.cxdlp``. The file's global settings have one retract speed, one slow retract stage and one set of rests
for the bottom and the normal layers (the bottom layers' own are only in the per-layer records, which the printer
follows only with the per-layer switch on), so bottom values that differ need ``--per-layer-settings`` (off by
default: some firmware misbehaves with it) where the switch does not turn on by itself, as it does for layers of
several thicknesses (:func:`gpuslice.raster.settings.per_layer_mode`); refused once the layers' thicknesses are
known: before the slicing where the options fix them (uniform layers), else before the file is opened.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from .coverage import Tile
from .ctb import _ex_columns, _timestamp_minutes, rgb15_rle, rle7, rle7_runs
from .cxdlp import _model_code, largest_regions
from .layers import RunLayer, batch_pixel_runs, pixel_runs, run_groups
from .png import encode_all
from .settings import header_layer_height, layer_table, per_layer_mode, print_time_s, ramp_layers, resin_ml

__all__ = ["MAGIC", "PREVIEWS", "VERSION", "refuse_layers", "refuse_settings", "write_cxdlpv4", "write_target"]

MAGIC = b"CXSW3DV2\0"
VERSION = 4
PREVIEWS = ((120, 120), (300, 300))  #: (small, large)
HEAD = struct.Struct("<2H5f10I2H3I")  # 80 bytes after the model code
PREVIEW = struct.Struct("<8I")  # 32
PARAMS = struct.Struct("<10fI2f4I")  # 68
SLICER = struct.Struct("<7f4I5f3I")  # 76
LAYER_DEF = struct.Struct("<3f7I")  # 40
LAYER_EX = struct.Struct("<11f")  # 44
#: the settings only the per-layer records hold for the bottom layers (module docstring)
_PER_LAYER_ONLY = ("retract_speed", "retract_height2", "retract_speed2", "wait_before_cure", "wait_after_cure",
                   "wait_after_lift")


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """``.cxdlpv4``'s settings check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`), before any work: a
    Halot preset (its model code) and a display its fields hold."""
    if not _model_code(options):
        raise ParameterError(f"{path}: a .cxdlpv4 file carries its printer's model code, which the printer checks: "
                             "give a Creality Halot --printer preset (gpuslice printers lists them)")
    if spec is not None:
        cols, rows = spec.png_size
        if cols > 0xFFFF or rows > 0xFFFF:
            raise ParameterError(f"{path}: a .cxdlpv4 file holds at most 65535x65535 pixels, not {cols}x{rows}")


def refuse_layers(path, settings, thickness_mm) -> None:
    """``.cxdlpv4``'s check for layers of ``thickness_mm`` (:meth:`gpuslice.raster.outputs.ResinFormat.check_layers`):
    bottom-layer values only per-layer records hold, when the per-layer switch stays off (module docstring: it turns
    on by itself for layers of several thicknesses)."""
    if per_layer_mode(settings, thickness_mm):
        return
    b, n = settings.group(True), settings.group(False)
    for key in _PER_LAYER_ONLY:
        if abs(b[key] - n[key]) > 1e-9:
            flag = key.replace("_", "-")
            raise ParameterError(f"{path}: a .cxdlpv4 file holds one --{flag} for bottom and normal layers unless "
                                 f"per-layer settings are on: give --bottom-{flag} equal to --{flag} "
                                 f"({b[key]:g} vs {n[key]:g}), or --per-layer-settings")


def write_cxdlpv4(layers: Iterable[Tile | RunLayer], target, *, code: str, z_travel: float = 0.0) -> dict[str, Any]:
    """Write ``target.result``'s layers (tiles or runs, in order) as a ``.cxdlpv4`` file (module docstring) for the
    printer of model ``code`` at ``target.path``, atomically. Layers are encoded on ``target.workers`` threads (on
    ``target.device`` where it has the runs) and streamed to disk; the previews, the table and the header are filled
    in last, then the checksum appended. Returns the layer count, ``png_bytes`` (the layers' data bytes),
    ``format_version``, ``machine``, ``print_time_s`` and ``resin_ml``."""
    from .sl1 import _Thumb

    path = Path(os.fspath(target.path))
    spec, res, s = target.spec, target.result, target.settings
    n = target.layer_count()
    cols, rows = spec.png_size
    n_pixels = cols * rows
    pw, ph = (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)
    per_pixel = pw * ph * 1000.0  # one pixel's area in the table's unit, mm² x 1000
    th = np.asarray(res.thickness, np.float64)
    z = np.cumsum(th).astype(np.float32)
    table = layer_table(s, n)
    ex = _ex_columns(table, 4)
    model = code.encode("ascii") + b"\0"
    head_size = 4 + len(MAGIC) + 2 + 4 + len(model) + HEAD.size
    at_small = head_size
    at_large = at_small + PREVIEW.size + 2 * PREVIEWS[0][0] * PREVIEWS[0][1]
    at_params = at_large + PREVIEW.size + 2 * PREVIEWS[1][0] * PREVIEWS[1][1]
    at_slicer = at_params + PARAMS.size
    at_table = at_slicer + SLICER.size
    entries = np.zeros((n, 10), np.uint32)
    thumb = _Thumb(spec, n)
    ml = resin_ml(res.area, th)
    anti_alias = 1 if spec.gamma == 0 else 8
    per_layer = per_layer_mode(s, th)

    def encode(item: Tile | RunLayer) -> tuple[bytes, int]:  # on a worker thread
        start, length, grey = pixel_runs(item, cols)
        area = _largest_lit(start, length, grey, np.array([0, start.size], np.int64), cols)[0]
        return rle7(start, length, grey, n_pixels), int(area)

    def encode_group(group: list[Tile | RunLayer]) -> list[tuple[bytes, int]]:  # on a worker thread
        if not isinstance(group[0], RunLayer):
            return [encode(item) for item in group]
        runs, a, b = group[0].runs, group[0].j, group[-1].j + 1
        start, length, grey, offsets = batch_pixel_runs(runs, a, b, cols)
        areas = _largest_lit(start, length, grey, np.asarray(offsets, np.int64), cols)
        return list(zip(rle7_runs(runs, a, b, cols, n_pixels, target.device), areas.tolist(), strict=True))

    with atomic_path(path) as tmp, open(tmp, "w+b", buffering=WRITE_BUFFER) as f:
        pos = at_table + LAYER_DEF.size * n
        f.seek(pos)

        def sink(k: int, item: tuple[bytes, int]) -> None:
            nonlocal pos
            data, area = item
            if pos + LAYER_EX.size + len(data) >= 1 << 32:
                raise ParameterError(f"{path}: a .cxdlpv4 file's offsets end at 4 GiB; this one would be larger")
            f.write(LAYER_EX.pack(*ex[k]))
            f.write(data)
            entries[k] = np.frombuffer(LAYER_DEF.pack(z[k], table["exposure"][k], 0.0, pos, LAYER_EX.size + len(data),
                                                      0, 0, round(area * per_pixel), 0, 0), "<u4")
            pos += LAYER_EX.size + len(data)

        stats = encode_all(layers, encode, sink, target.workers, on_tile=thumb.add, progress=target.progress,
                           many=encode_group, chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{path}: expected {n} layers, got {stats['layers']}")
        f.seek(at_table)
        f.write(entries.astype("<u4").tobytes())
        for at, size in zip((at_small, at_large), PREVIEWS, strict=True):
            data = rgb15_rle(np.asarray(thumb.image(size)))
            f.seek(at)
            f.write(PREVIEW.pack(*size, at + PREVIEW.size, len(data), 0, 0, 0, 0) + data)
        f.seek(at_params)
        f.write(_settings_blocks(s, ml, anti_alias, target.now, min(s.bottom_layers, n), per_layer))
        f.seek(0)
        layer_height = header_layer_height(th)
        f.write(struct.pack(">I", len(MAGIC)) + MAGIC + struct.pack(">HI", VERSION, len(model)) + model)
        f.write(HEAD.pack(cols, rows, cols * pw, rows * ph, float(z_travel), float(z[-1]), layer_height,
                          min(s.bottom_layers, n), at_small, at_table, n, at_large, int(round(print_time_s(s, n))),
                          int(spec.mirror_x or spec.mirror_y), at_params, PARAMS.size, 1, s.light_pwm,
                          s.bottom_light_pwm, 0, at_slicer, SLICER.size))
        f.flush()
        f.seek(0)
        crc = 0xFFFFFFFF
        while chunk := f.read(1 << 22):  # (the bytes just written: from the page cache)
            crc = zlib.crc32(chunk, crc)
        f.write(struct.pack(">I", crc ^ 0xFFFFFFFF))
    return {**stats, "format_version": VERSION, "machine": code, "print_time_s": print_time_s(s, n), "resin_ml": ml}


def _largest_lit(start, length, grey, offsets: np.ndarray, cols: int) -> np.ndarray:
    """Each layer's largest 4-connected region of the pixels the file lights (grey >= 2: 1 is stored as 0), in
    pixels (:func:`gpuslice.raster.cxdlp.largest_regions`)."""
    lit = np.asarray(grey) >= 2
    if lit.all():
        return largest_regions(start, length, offsets, cols)
    kept = np.concatenate(([0], np.cumsum(lit)))[offsets]
    return largest_regions(np.asarray(start)[lit], np.asarray(length)[lit], kept, cols)


def _settings_blocks(s, ml: float, anti_alias: int, now, bottom_layers: int, per_layer: bool) -> bytes:
    """The print parameters and the slicer info (module docstring): lift heights are both stages' total in the first,
    the second stage on its own in the other; the rests and retract stages are the normal layers'."""
    b, m = s.group(True), s.group(False)
    params = PARAMS.pack(b["lift_height"] + b["lift_height2"], b["lift_speed"], m["lift_height"] + m["lift_height2"],
                         m["lift_speed"], m["retract_speed"], ml, ml * s.resin_density, 0.0, 0.0, 0.0,
                         bottom_layers, s.exposure, s.bottom_exposure, 0, 0, 0, 0)
    slicer = SLICER.pack(b["lift_height2"], b["lift_speed2"], m["lift_height2"], m["lift_speed2"], m["retract_height2"],
                         m["retract_speed2"], m["wait_after_lift"], int(per_layer),
                         _timestamp_minutes(now), anti_alias, 0, m["wait_before_cure"], m["wait_after_cure"],
                         s.exposure, s.bottom_exposure, m["wait_after_lift"], ramp_layers(s), 0, 0)
    return params + slicer


def write_target(layers: Iterable[Tile | RunLayer], target) -> dict[str, Any]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): a ``.cxdlpv4`` file for the Halot the preset names."""
    refuse_settings(target.path, "cxdlpv4", target.options, target.settings, target.spec)
    refuse_layers(target.path, target.settings, target.result.thickness)
    preset = target.options.preset
    return write_cxdlpv4(layers, target, code=_model_code(target.options), z_travel=float(preset.build_height))
