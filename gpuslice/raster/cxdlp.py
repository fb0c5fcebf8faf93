"""Creality Halot ``.cxdlp`` files, versions 2 and 3 (the Halot One, One Pro, One Plus, Sky, Lite, Sky Plus, Ray and
Max; the Mage family reads another layout, v4: :mod:`gpuslice.raster.cxdlpv4`).

Facts (field layouts, units, checksums, what the firmware checks) from public readers and writers, gathered in
``docs/research/CXDLP.md``: UVtools' ``CrealityCXDLPFile.cs`` and its 010 Editor template, checked against a file
Chitubox wrote for a Halot One Plus (futurelink/msla-imaging's test data); our code.

**Layout** (big endian): ``CXSW3DV2`` (with its length), the version (3 by default; 2 where the preset's
``format_version`` asks), the printer's **model code** (``CL-60`` …, which the firmware compares with its own:
taken from the ``--printer`` preset's ``machine``), the layer count and resolution, a 64-byte block (its first
uint32 the machine's Z travel in mm, as the native file has it), three RGB565 previews (116², 290², 290²), the
display width and height and the layer height as UTF-16 text (mm), then the print settings as 16-bit integers in the
format's units: the exposure in tenths of a second, the bottom exposure and the one rest before every exposure in
whole seconds, the bottom layer count, the bottom and normal lift in whole mm at whole mm/s, one retract speed
(mm/s), the bottom and normal light PWM; then per layer the pixel count of its largest 4-connected lit region (the
native file's "area", which the firmware hands to its motion controller), in v3 a block naming the slicer and the
resin, the layers, a closing ``CXSW3D`` mark (as Chitubox writes it) and a checksum: CRC-32 with a zero start value
and no final inversion (v3), or the XOR of every byte (v2).

**Layers**: each a list of 6-byte *lines*, vertical runs of one grey inside one pixel column: 13 bits of start row,
13 of end row (inclusive), 14 of column, then the grey (0-255, all 8 bits: exact), sorted by column then row. The
rasteriser's runs are horizontal; :func:`column_lines` turns them into these lines without a bitmap, in numpy passes
over a group of layers at once (a vertical run starts where a pixel's grey differs from the one above it, and ends
where it differs from the one below; the starts and ends of one column pair up in order).

**What the format cannot hold is refused before any work** (:func:`refuse_settings`): no transition ramp, one lift
stage, one retract speed, one rest for every layer (before the exposure; none after the exposure or the lift), no
per-layer settings, values off the format's units (e.g. a lift speed that is not a whole number of mm/s), a wait
before cure under 1 s (the firmware does not print with none, as UVtools found), one layer height. The Halot presets'
settings are ones it holds. A job with no Halot preset is refused: the model code must be the printer's (a Halot Lite
refuses a Halot Sky's file of the same display).
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
from ..ragged import expand_ranges
from .coverage import Tile
from .layers import RunLayer, batch_pixel_runs, pixel_runs, run_groups
from .png import encode_all
from .settings import print_time_s, resin_ml

__all__ = ["column_lines", "largest_regions", "refuse_settings", "write_cxdlp", "write_target", "MAGIC", "PREVIEWS",
           "VERSIONS", "checksum"]

MAGIC = b"CXSW3DV2\0"
FOOTER = b"CXSW3D\0"  # (Chitubox's closing mark; UVtools writes MAGIC again)
VERSIONS = (2, 3)
DEFAULT_VERSION = 3
PREVIEWS = ((116, 116), (290, 290), (290, 290))
CRLF = b"\r\n"
#: the largest row and column a line holds (13 and 14 bits), and the most layers (a uint16)
MAX_ROWS, MAX_COLS, MAX_LAYERS = 1 << 13, 1 << 14, 0xFFFF


# ---- layers --------------------------------------------------------------------------------------------------------
def _uncovered(key_a: np.ndarray, key_b: np.ndarray, g: np.ndarray, step: int, line: np.ndarray, a: np.ndarray,
               b: np.ndarray, cols: int):
    """The pieces of each run ``[a, b)`` (of row line ``line``, grey ``g``) that no run of the row ``line + step``
    with the same grey covers; ``key_a``, ``key_b``: every run's ``line * cols + a`` (``+ b``), sorted (the runs'
    own order). Returns (owner, left, right) of each piece."""
    base = (line + step) * cols
    lo = np.searchsorted(key_b, base + a, side="right")  # (queries in order: cache-friendly searches)
    hi = np.searchsorted(key_a, base + b, side="left")
    q, j = expand_ranges(lo, np.maximum(hi - lo, 0))  # runs of that row sharing a column with the query
    same = g[j] == g[q]
    q, j = q[same], j[same]  # the covers: sorted by query, then column
    cnt = np.bincount(q, minlength=a.size)
    at = np.zeros(a.size + 1, np.int64)
    np.cumsum(cnt, out=at[1:])
    owner, k = expand_ranges(np.zeros(a.size, np.int64), cnt + 1)  # gap k of query owner: before cover k
    pos = at[owner] + k
    first, last = k == 0, k == cnt[owner]
    jl = j[np.maximum(np.minimum(pos - 1, j.size - 1), 0)] if j.size else np.zeros(pos.size, np.int64)
    jr = j[np.minimum(pos, j.size - 1)] if j.size else np.zeros(pos.size, np.int64)
    left = np.where(first, a[owner], (key_b[jl] - base[owner]) if j.size else 0)
    right = np.where(last, b[owner], (key_a[jr] - base[owner]) if j.size else 0)
    left, right = np.maximum(left, a[owner]), np.minimum(right, b[owner])
    keep = right > left
    return owner[keep], left[keep], right[keep]


def column_lines(start: np.ndarray, length: np.ndarray, grey: np.ndarray, offsets: np.ndarray, cols: int):
    """The vertical lines of several layers (layer k: runs ``offsets[k]:offsets[k + 1]`` of ``start`` row-major pixel
    index, ``length``, ``grey`` non-zero; sorted, never overlapping, never crossing a row end, never touching with
    one grey): ``(line_offsets, x, y0, y1, grey)``, layer k's lines ``line_offsets[k]:line_offsets[k + 1]``, each a
    maximal vertical run of one grey (rows ``y0`` to ``y1`` inclusive of column ``x``), sorted by (x, y0)."""
    start = np.asarray(start, np.int64)
    length = np.asarray(length, np.int64)
    g = np.asarray(grey)
    n_img = offsets.size - 1
    img = np.repeat(np.arange(n_img, dtype=np.int64), np.diff(offsets))
    row, a = np.divmod(start, cols)
    b = a + length
    rows = int(row.max()) + 3 if row.size else 3
    line = img * rows + row + 1  # a line per (layer, row); the runs' own order is (line, a)
    key_a, key_b = line * cols + a, line * cols + b
    ends = []
    for step in (-1, 1):  # pieces with no pixel of their grey above (starts) and below (ends)
        owner, left, right = _uncovered(key_a, key_b, g, step, line, a, b, cols)
        pix_owner, dx = expand_ranges(np.zeros(owner.size, np.int64), right - left)
        x = left[pix_owner] + dx
        o = owner[pix_owner]
        ends.append((np.argsort((img[o] * cols + x) * rows + row[o]), x, row[o], o))  # (layer, column, row) order
    (s_ord, sx, sy, so), (e_ord, _, ey, _) = ends
    counts = np.bincount(img[so], minlength=n_img)
    line_offsets = np.zeros(n_img + 1, np.int64)
    np.cumsum(counts, out=line_offsets[1:])
    return line_offsets, sx[s_ord], sy[s_ord], ey[e_ord], g[so[s_ord]].astype(np.uint8)


def largest_regions(start: np.ndarray, length: np.ndarray, offsets: np.ndarray, cols: int) -> np.ndarray:
    """Per layer (runs as :func:`column_lines` takes them) the pixel count of its largest 4-connected lit region."""
    from ..mesh.graph import components

    start = np.asarray(start, np.int64)
    length = np.asarray(length, np.int64)
    n_img = offsets.size - 1
    out = np.zeros(n_img, np.int64)
    if start.size == 0:
        return out
    img = np.repeat(np.arange(n_img, dtype=np.int64), np.diff(offsets))
    row, a = np.divmod(start, cols)
    b = a + length
    rows = int(row.max()) + 3
    line = img * rows + row + 1
    # runs of a row that touch (two greys) are one region: merged into intervals first (far fewer at anti-aliased
    # edges, where every boundary pixel is a run of its own)
    head = np.flatnonzero(np.concatenate(([True], (line[1:] != line[:-1]) | (a[1:] != b[:-1]))))
    tail = np.append(head[1:], start.size) - 1
    line, a, b, img = line[head], a[head], b[tail], img[head]
    base = line * cols  # (sorted already: layer, then row, then column)
    # an interval overlaps those of the next row sharing a column
    lo = np.searchsorted(base + b, (line + 1) * cols + a, side="right")
    hi = np.searchsorted(base + a, (line + 1) * cols + b, side="left")
    q, j = expand_ranges(lo, np.maximum(hi - lo, 0))
    label = components(head.size, q, j)
    size = np.bincount(label, weights=b - a)
    comp_img = np.zeros(size.size, np.int64)
    comp_img[label] = img
    np.maximum.at(out, comp_img, size.astype(np.int64))
    return out


def _pack(x: np.ndarray, y0: np.ndarray, y1: np.ndarray, grey: np.ndarray) -> np.ndarray:
    """(n, 6) uint8 lines: 13 bits start row, 13 bits end row, 14 bits column (big endian), grey."""
    v = (y0.astype(np.uint64) << np.uint64(27)) | (y1.astype(np.uint64) << np.uint64(14)) | x.astype(np.uint64)
    out = np.empty((x.size, 6), np.uint8)
    out[:, :5] = v.astype(">u8").view(np.uint8).reshape(-1, 8)[:, 3:]
    out[:, 5] = grey
    return out


def _layer_records(start, length, grey, offsets, cols: int) -> list[tuple[bytes, int]]:
    """Each layer's record (area, line count, lines, CRLF) and its area, from its runs."""
    line_off, x, y0, y1, g = column_lines(start, length, grey, offsets, cols)
    area = largest_regions(start, length, offsets, cols)
    packed = _pack(x, y0, y1, g)
    out = []
    for k in range(offsets.size - 1):
        lines = packed[line_off[k] : line_off[k + 1]]
        out.append((struct.pack(">II", int(area[k]), lines.shape[0]) + lines.tobytes() + CRLF, int(area[k])))
    return out


# ---- the settings --------------------------------------------------------------------------------------------------
def _model_code(options) -> str:
    preset = options.preset
    code = preset.machine if preset is not None else ""
    if not (code.startswith(("CL", "CT")) and any(c.isdigit() for c in code)):
        return ""
    return code


def _version(options) -> int:
    preset = options.preset
    if preset is not None and preset.native_format == "cxdlp" and preset.format_version is not None:
        return int(preset.format_version)
    return DEFAULT_VERSION


def _whole(value: float, unit: float) -> bool:
    return abs(value / unit - round(value / unit)) < 1e-6


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """CXDLP's settings check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`), before any work: a Halot
    preset (its model code), a version this writer has, and settings the format holds (module docstring)."""
    from .settings import transition_step

    code = _model_code(options)
    if not code:
        raise ParameterError(f"{path}: a .cxdlp file carries its printer's model code, which the printer checks: give "
                             "a Creality Halot --printer preset (gpuslice printers lists them)")
    version = _version(options)
    if version not in VERSIONS:
        raise ParameterError(f"{path}: this writer has CXDLP versions {' and '.join(map(str, VERSIONS))}, not "
                             f"{version} (the Halot Mage's v4 is another layout: -o part.cxdlpv4)")
    if spec is not None:
        cols, rows = spec.png_size
        if cols > MAX_COLS or rows > MAX_ROWS:
            raise ParameterError(f"{path}: a .cxdlp file holds at most {MAX_COLS}x{MAX_ROWS} pixels, not "
                                 f"{cols}x{rows}")
    s = settings
    b, n = s.group(True), s.group(False)
    problems = []
    lost = s.two_stages_lost()  # (a second stage at the first one's speed is one longer lift: written so)
    if lost:
        problems.append(f"{lost} (one lift stage)")
    if abs(b["retract_speed"] - n["retract_speed"]) > 1e-9:
        problems.append("--bottom-retract-speed other than --retract-speed (one retract speed)")
    if s.transition_layers > 0 and transition_step(s) > 0:
        problems.append(f"--transition-layers {s.transition_layers} (no exposure ramp: give 0)")
    if s.per_layer_settings:
        problems.append("--per-layer-settings (none)")
    for key in ("wait_after_cure", "wait_after_lift"):
        if b[key] > 0 or n[key] > 0:
            problems.append(f"--{key.replace('_', '-')} (one rest, before the exposure)")
    if abs(b["wait_before_cure"] - n["wait_before_cure"]) > 1e-9:
        problems.append("--bottom-wait-before-cure other than --wait-before-cure (one rest for every layer)")
    if n["wait_before_cure"] < 1 or not _whole(n["wait_before_cure"], 1):
        problems.append(f"--wait-before-cure {n['wait_before_cure']:g} s (whole seconds, at least 1: the printer does "
                        "not print with none)")
    if not _whole(s.exposure, 0.1):
        problems.append(f"--exposure {s.exposure:g} s (tenths of a second)")
    if not _whole(s.bottom_exposure, 1):
        problems.append(f"--bottom-exposure {s.bottom_exposure:g} s (whole seconds)")
    for twin, g in (("--bottom-", b), ("--", n)):
        lift = g["lift_height"] + g["lift_height2"]
        if lift < 1 or not _whole(lift, 1):
            problems.append(f"{twin}lift-height {lift:g} mm, both stages (whole mm, at least 1)")
        for key in ("lift_speed", "retract_speed"):
            if g[key] < 60 or not _whole(g[key], 60):
                problems.append(f"{twin}{key.replace('_', '-')} {g[key]:g} mm/min (whole mm/s: a multiple of 60)")
    if problems:
        raise ParameterError(f"{path}: a .cxdlp file cannot hold {problems[0]}"
                             + (f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""))


# ---- the file ------------------------------------------------------------------------------------------------------
def checksum(data: bytes | memoryview, version: int) -> int:
    """The closing checksum of ``data`` (every byte before it): v3 CRC-32 with a zero start and no final inversion,
    v2 the XOR of every byte."""
    if version >= 3:
        return zlib.crc32(data, 0xFFFFFFFF) ^ 0xFFFFFFFF
    return int(np.bitwise_xor.reduce(np.frombuffer(data, np.uint8))) if len(data) else 0


def _text(value: float) -> bytes:
    t = f"{round(float(value), 4):g}".encode("utf-16-be")
    return struct.pack(">I", len(t)) + t


def _rgb565_be(image) -> bytes:
    a = np.asarray(image.convert("RGB"), np.uint16)
    v = ((a[..., 0] >> 3) << 11) | ((a[..., 1] >> 2) << 5) | (a[..., 2] >> 3)
    return v.astype(">u2").tobytes()


def _string(text: str) -> bytes:
    data = text.encode("utf-8") + b"\0"
    return struct.pack(">I", len(data)) + data


def write_cxdlp(layers: Iterable[Tile | RunLayer], target, *, code: str, version: int = DEFAULT_VERSION,
                z_travel: float = 0.0) -> dict[str, Any]:
    """Write ``target.result``'s layers (tiles or runs, in order) as a CXDLP file (module docstring) for the printer
    of model ``code`` at ``target.path``, atomically. The layers' lines are made on ``target.workers`` threads and
    streamed to disk; the area table before them is filled in last, then the checksum appended. Returns the layer
    count, ``png_bytes`` (the layers' bytes), ``format_version`` and ``print_time_s``."""
    from .. import __version__
    from .sl1 import _Thumb, check_one_layer_height

    path = Path(os.fspath(target.path))
    spec, res, s = target.spec, target.result, target.settings
    n = res.n_layers
    if n > MAX_LAYERS:
        raise ParameterError(f"{path}: a .cxdlp file holds at most {MAX_LAYERS} layers, not {n}")
    cols, rows = spec.png_size
    pw, ph = (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)
    th = np.asarray(res.thickness, np.float64)
    layer_height = check_one_layer_height(th, path, first_may_differ=False)
    thumb = _Thumb(spec, n)
    b = s.group(True)
    head = struct.pack(">I", len(MAGIC)) + MAGIC + struct.pack(">H", version) + _string(code)
    head += struct.pack(">HHH", n, cols, rows) + struct.pack(">I", max(0, int(z_travel))) + bytes(60)
    settings = (_text(cols * pw) + _text(rows * ph) + _text(layer_height) + struct.pack(
        ">11H", round(s.exposure * 10), round(s.wait_before_cure), round(s.bottom_exposure), min(s.bottom_layers, n),
        round(b["lift_height"] + b["lift_height2"]), round(b["lift_speed"] / 60), round(s.lift_height + s.lift_height2),
        round(s.lift_speed / 60),
        round(s.retract_speed / 60), s.bottom_light_pwm, s.light_pwm))
    info = b""
    if version >= 3:  # the slicer, the resin, then no compensation, anti-aliasing as drawn, no blur
        aa = spec.gamma != 0
        info = (_string(f"gpuslice {__version__}") + _string("") + bytes(15)
                + bytes([int(aa), 1 if aa else 0, 255, 0, 2]) + CRLF)

    def encode_runs(start, length, grey, offsets) -> list[tuple[bytes, int]]:  # on a worker thread
        return _layer_records(start, length, grey, offsets, cols)

    def encode(item: Tile | RunLayer) -> tuple[bytes, int]:
        start, length, grey = pixel_runs(item, cols)
        return encode_runs(start, length, grey, np.array([0, start.size], np.int64))[0]

    def encode_group(group: list[Tile | RunLayer]) -> list[tuple[bytes, int]]:
        if not isinstance(group[0], RunLayer):
            return [encode(item) for item in group]
        start, length, grey, offsets = batch_pixel_runs(group[0].runs, group[0].j, group[-1].j + 1, cols)
        return encode_runs(start, length, grey, np.asarray(offsets, np.int64))

    areas = np.zeros(n, np.int64)
    with atomic_path(path) as tmp, open(tmp, "w+b", buffering=WRITE_BUFFER) as f:
        f.write(head)
        for w, h in PREVIEWS:
            f.write(bytes(2 * w * h) + CRLF)  # (drawn once the layers are seen)
        f.write(settings)
        table_at = f.tell()
        f.write(bytes(4 * n) + CRLF + info)

        def sink(k: int, item: tuple[bytes, int]) -> None:
            f.write(item[0])
            areas[k] = item[1]

        stats = encode_all(layers, encode, sink, target.workers, on_tile=thumb.add, progress=target.progress,
                           many=encode_group, chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{path}: expected {n} layers, got {stats['layers']}")
        f.write(struct.pack(">I", len(FOOTER)) + FOOTER)
        f.seek(len(head))
        for size in PREVIEWS:
            f.write(_rgb565_be(thumb.image(size)) + CRLF)
        f.seek(table_at)
        f.write(areas.astype(">u4").tobytes())
        f.flush()
        f.seek(0)
        crc, xor = 0xFFFFFFFF, 0
        while chunk := f.read(1 << 22):  # (the bytes just written: from the page cache)
            if version >= 3:
                crc = zlib.crc32(chunk, crc)
            else:
                xor ^= int(np.bitwise_xor.reduce(np.frombuffer(chunk, np.uint8)))
        f.write(struct.pack(">I", (crc ^ 0xFFFFFFFF) if version >= 3 else xor))
    seconds = print_time_s(s, n)
    return {**stats, "format_version": version, "machine": code, "print_time_s": seconds,
            "resin_ml": resin_ml(res.area, th)}


def write_target(layers: Iterable[Tile | RunLayer], target) -> dict[str, Any]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): a CXDLP file for the Halot the preset names."""
    refuse_settings(target.path, "cxdlp", target.options, target.settings, target.spec)
    preset = target.options.preset
    return write_cxdlp(layers, target, code=_model_code(target.options), version=_version(target.options),
                       z_travel=float(preset.build_height))
