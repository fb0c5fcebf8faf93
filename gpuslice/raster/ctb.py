"""Chitubox CTB files, unencrypted, layout versions 2, 3 and 4 (the layer data stored plain, ``encryption_key`` 0).

Facts from the public descriptions (cbiffle/catibo ``doc/cbddlp-ctb.adoc``; UVtools ``ChituboxFile.cs`` and its
``Scripts/010 Editor/ctb.bt``); our own code. Little-endian throughout; sections refer to each other by file offset.
What this writer lays out, in this order:

* the header (112 bytes at 0): magic ``0x12FD0086`` (v2, v3) or ``0x12FD0106`` (v4), version, bed size, heights,
  exposures, resolution, the offsets below, print time (s, u32), projector type (1: mirrored; the pixels are stored
  as the display shows them, our mirror flags applied, as UVtools converts SL1 files), light PWM, encryption key 0;
* the large and the small preview (400x300 and 200x125, as Chitubox writes them): a 32-byte record (width, height,
  data offset, length) then RGB15 run-length data: 16-bit words, red bits 15-11, green 10-6, blue 4-0, bit 5 set when
  the next word is ``0x3000 | (copies - 1)`` (at most 0xFFF copies). The previews are drawn from the layers, which
  arrive after the header is laid out, so this region has the worst case's size (2 bytes a pixel) and zero padding
  after the two images: 290 kB at most, and it keeps every offset below 4 GiB (they are u32);
* the print parameters (60 bytes: lifts, retract speed, resin ml, g, light-off delays, bottom layers) and the slicer
  info (76 bytes + the machine name: second lift/retract stages, anti-aliasing flag and level, per-layer-settings
  byte, the date in minutes since 1970, transition layers; in v4 the offset of the v4 parameters);
* v4 only: the v4 parameters (464 bytes: bottom retract speeds, waits, last layer index, disclaimer offset and length,
  380 reserved bytes). Chitubox puts a 320-byte copyright notice of CBD Technology before this block; we write none
  (length 0): it is their notice, not ours. UVtools reads v4 without it; whether some firmware checks it is unknown;
* the layer table: 36 bytes a layer (z of the platform = top of the layer in mm, exposure s, light-off delay s, data
  offset and length, page = offset >> 32 for files over 4 GiB, table size 36 (v2) or 84 (v3, v4));
* the layers in order; from v3 each layer's data follows an 84-byte record (a copy of its table entry, the total size,
  the layer's lift, retract, waits and PWM, the per-layer settings).

Layer data (RLE7): the whole image row-major (rows of ``RasterSpec.shape``), runs crossing rows freely. A run is one
byte ``grey7 | 0x80·(length > 1)`` then, for length > 1, the length in 1-4 bytes, big-endian, its top bits telling how
many: ``0xxxxxxx`` (< 2^7), ``10xxxxxx`` + 1 byte (< 2^14), ``110xxxxx`` + 2 (< 2^21), ``1110xxxx`` + 3 (< 2^28).

**Grey quantisation**: CTB keeps 7 bits a pixel. Grey g (0-255) is stored as ``g >> 1`` (0-127) and read back as
``((g >> 1) << 1) | 1`` when non-zero, 0 otherwise: 0 and 1 → 0, 254 and 255 → 255, any grey within 1 of the
original except 1 (→ 0). There is no per-version difference: every CTB version stores greys this way (CBDDLP, a
different format, stores anti-aliasing as repeated 1-bit layers; that is not CTB and not written here).
Checked against a file Chitubox 1.7 wrote (``tests/data/ctb/pyramid.ctb``): our encoders give its previews' bytes
exactly, and its layers' bytes except where Chitubox leaves two equal 7-bit neighbours unmerged.

**Version**: the printer preset's ``format_version`` when the preset's native format is ``ctb``, else
:data:`DEFAULT_VERSION` = 3: the most widely read unencrypted CTB (Chitubox 1.6.5 to 1.8 wrote it; firmware before and
after Chitubox's 1.9 update reads it; UVtools' PrusaSlicer printer profiles ask for CTB v3 on 25 printers and v4 on 2).
v4 needs firmware from the 1.9 era (2021 on). Printers whose firmware reads only the *encrypted* CTB (magic
``0x12FD0107``) cannot read these files; that variant is out of scope.

**Print settings per version** (:class:`~gpuslice.raster.settings.PrintSettings`, per layer via ``layer_table``):
v2 and v3 have one lift stage and no wait fields: the lift is ``lift_height`` (plus ``lift_height2``, travelled at
``lift_speed``), the retract one stage at ``retract_speed``, and the waits are folded into each layer's light-off
delay as UVtools does (delay = the move time of the lift and retract + the three waits, s; 0 when the layer has no
waits, as Chitubox writes it: the firmware then just moves). v4 stores both lift stages (its lift height field is the
total, the second stage on its own), the slow last retract stage, ``wait_before_cure`` (rest after retract),
``wait_after_cure`` (rest before lift) and ``wait_after_lift``, with the light-off delay 0; its global waits are the
normal layers' (the bottom layers' own are in their per-layer records). CTB has no retract distance: the platform
comes back down the lift's total.
The per-layer-settings byte (slicer info) is 0 unless ``per_layer_settings`` is on or the layers are not all one
thickness (then ``0x10 · version``, as UVtools sets it whenever a layer differs from the global settings, its z
included: the header has one layer height): some firmware misbehaves when it is set, so it is off otherwise.
"""

from __future__ import annotations

import datetime as _dt
import os
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from .coverage import Tile
from .layers import RunLayer, batch_image_segments, batch_pixel_runs, pixel_runs, run_groups
from .png import encode_all
from .run_encoder import RunImageEncoder
from .settings import (
    PrintSettings,
    header_layer_height,
    layer_table,
    per_layer_mode,
    print_time_s,
    ramp_layers,
    resin_ml,
)
from .sl1 import _Thumb
from .spec import RasterSpec

__all__ = ["DEFAULT_VERSION", "MAGIC_CTB", "MAGIC_CTB_V4", "PREVIEW_SIZES", "VERSIONS", "CtbInfo", "ctb_version",
           "quantise", "rgb15_rle", "rle7", "rle7_batch", "rle7_runs", "CtbEncoder", "write_ctb", "write_target"]

MAGIC_CTB = 0x12FD0086  #: v2 and v3
MAGIC_CTB_V4 = 0x12FD0106  #: v4
VERSIONS = (2, 3, 4)
DEFAULT_VERSION = 3
PREVIEW_SIZES = ((400, 300), (200, 125))  #: (large, small), as Chitubox writes them
#: the Chitubox release whose layout each version is (slicer info's software version: major, minor, patch bytes)
SOFTWARE_VERSION = {2: 0x01060300, 3: 0x01060300, 4: 0x01090000}
MAX_RUN = 0x0FFFFFFF  #: the longest RLE7 run (28 bits)
MAX_PREVIEW_RUN = 0xFFF  #: the most copies one RGB15 run word holds (Chitubox's limit)

HEADER = struct.Struct("<2I3f2I5f12I2H3I")  # 112 bytes
PREVIEW = struct.Struct("<8I")  # 32
PRINT_PARAMS = struct.Struct("<10f5I")  # 60
SLICER_INFO = struct.Struct("<7f2IBHB3I2f4I")  # 76, then the machine name
PARAMS_V4 = struct.Struct("<2fIfI6f3I4I3I")  # 84, then 380 reserved bytes
PARAMS_V4_RESERVED = 380
LAYER_DEF = struct.Struct("<3f6I")  # 36
LAYER_EX = struct.Struct("<3f6II11f")  # 84: a copy of the table entry, total size, the layer's own settings
PAGE = 1 << 32


@dataclass(frozen=True)
class CtbInfo:
    """What a CTB file says besides its pixels. ``version`` 2-4; ``machine`` the header's machine name (ASCII);
    ``build_height`` the printer's Z travel (mm; 0: the model's height); ``anti_alias`` the anti-aliasing level the
    slicer info records (1: greys are black or white); ``resin_ml`` resin volume (ml)."""

    version: int = DEFAULT_VERSION
    machine: str = ""
    build_height: float = 0.0
    anti_alias: int = 1
    resin_ml: float = 0.0


def quantise(grey: np.ndarray) -> np.ndarray:
    """The 8-bit greys a CTB reader gets back for ``grey`` (uint8): ``((g >> 1) << 1) | 1``, 0 where ``g >> 1`` is
    0 (module docstring)."""
    g = np.asarray(grey, np.uint8)
    q = g >> 1
    return np.where(q == 0, 0, (q << 1) | 1).astype(np.uint8)


def _split_long(values: np.ndarray, lengths: np.ndarray, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """Runs longer than ``limit`` cut into pieces of ``limit`` and a remainder (same value)."""
    if lengths.size == 0 or int(lengths.max()) <= limit:
        return values, lengths
    pieces = -(-lengths // limit)
    out_v = np.repeat(values, pieces)
    out_l = np.full(out_v.size, limit, np.int64)
    last = np.cumsum(pieces) - 1
    out_l[last] = lengths - (pieces - 1) * limit
    return out_v, out_l


def rle7(start: np.ndarray, length: np.ndarray, grey: np.ndarray, n_pixels: int) -> bytes:
    """A layer's RLE7 bytes (module docstring) from its runs: ``start`` (row-major pixel index), ``length``, ``grey``
    (uint8, never 0), sorted, not overlapping (:func:`gpuslice.raster.layers.pixel_runs`); ``n_pixels`` the image's
    pixel count. Blank gaps are coded as runs of 0; neighbours equal after quantisation are merged."""
    start = np.asarray(start, np.int64)
    return rle7_batch(start, length, grey, np.array([0, start.size], np.int64), n_pixels)[0]


def rle7_batch(start: np.ndarray, length: np.ndarray, grey: np.ndarray, offsets: np.ndarray,
               n_pixels: int) -> list[bytes]:
    """:func:`rle7` of several layers in one set of numpy passes: layer k has the runs ``offsets[k]:offsets[k + 1]``
    (:func:`gpuslice.raster.layers.batch_pixel_runs`); one ``bytes`` per layer, the same as :func:`rle7`'s."""
    start = np.asarray(start, np.int64)
    length = np.asarray(length, np.int64)
    offsets = np.asarray(offsets, np.int64)
    n_img = offsets.size - 1
    end = start + length
    inner = np.ones(start.size, bool)  # a run that has a predecessor in its own layer
    inner[offsets[:-1][offsets[:-1] < offsets[1:]]] = False
    last = offsets[1:][offsets[1:] > offsets[:-1]] - 1
    if start.size and (np.any(start[1:][inner[1:]] < end[:-1][inner[1:]]) or start.min() < 0
                       or np.any(end[last] > n_pixels)):
        raise ParameterError("CTB layer runs overlap or leave the display")
    n, v, seg = batch_image_segments(start, length, np.asarray(grey, np.uint8) >> 1, offsets, n_pixels)
    img = np.repeat(np.arange(n_img, dtype=np.int64), np.diff(seg))
    first = np.flatnonzero(np.concatenate(([True], (v[1:] != v[:-1]) | (img[1:] != img[:-1]))))
    values, lengths, img = v[first], np.add.reduceat(n, first) if n.size else n, img[first]
    pieces = -(-lengths // MAX_RUN)
    if pieces.size and int(pieces.max()) > 1:  # runs longer than a record holds: pieces of MAX_RUN and the rest
        img = np.repeat(img, pieces)
        values, lengths = _split_long(values, lengths, MAX_RUN)
    size = np.where(lengths == 1, 1, np.where(lengths <= 0x7F, 2, np.where(lengths <= 0x3FFF, 3, np.where(
        lengths <= 0x1FFFFF, 4, 5))))
    cs = np.zeros(size.size + 1, np.int64)
    np.cumsum(size, out=cs[1:])
    at, total = cs[:-1], int(cs[-1])
    out = np.empty(total + 1, np.uint8)  # (the last byte: where the one-byte runs write their length byte)
    out[at] = values | np.where(lengths > 1, 0x80, 0).astype(np.uint8)
    # size - 1 length bytes, big-endian, the first one carrying the lead bits 0, 10, 110 or 1110 (sizes 2 to 5):
    # the first in whole-array passes (every run longer than one pixel has it), the others apart
    lead = np.array([0, 0, 0x00, 0x80, 0xC0, 0xE0], np.int64)[size]
    out[np.where(size >= 2, at + 1, total)] = ((lengths >> (8 * np.maximum(size - 2, 0))) & 0xFF) | lead
    for i in (1, 2, 3):
        sel = np.flatnonzero(size > i + 1)
        out[at[sel] + 1 + i] = (lengths[sel] >> (8 * (size[sel] - 2 - i))) & 0xFF
    img_off = cs[np.searchsorted(img, np.arange(n_img + 1))]  # (img is sorted)
    data = out[:total].tobytes()
    return [data[img_off[k] : img_off[k + 1]] for k in range(n_img)]


class CtbEncoder(RunImageEncoder):
    """Driver of ``kernels/ctb.cl`` (:mod:`gpuslice.raster.run_encoder`): the RLE7 layer data of a group of layers
    from their runs, the bytes of :func:`rle7_batch` (its numpy twin, which also takes the groups the kernels leave:
    a record merging more than 64 runs and gaps, or runs it refuses)."""

    FILE, SIZES, WRITE = "ctb.cl", "ctb_sizes", "ctb_write"
    MAX_RUN = MAX_RUN

    def blank(self, n_pixels: int) -> bytes:
        return rle7(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8), n_pixels)


def rle7_runs(runs, a: int, b: int, cols: int, n_pixels: int, device=None) -> list[bytes]:
    """:func:`rle7_batch` of entries ``a`` … ``b`` − 1 of a batch of runs (:class:`~gpuslice.raster.runs.Runs`):
    with an OpenCL ``device``, by the kernels of ``kernels/ctb.cl`` (:class:`CtbEncoder`; the same bytes)."""
    if device is not None:
        out = CtbEncoder.of(device).encode(runs, a, b, cols, n_pixels)
        if out is not None:
            return out
    return rle7_batch(*batch_pixel_runs(runs, a, b, cols), n_pixels)


def rgb15_rle(rgb: np.ndarray) -> bytes:
    """A preview's RGB15 run-length bytes (module docstring) from an (h, w, 3) uint8 RGB image, row-major."""
    c = rgb.reshape(-1, 3).astype(np.uint16) >> 3
    word = (c[:, 0] << 11) | (c[:, 1] << 6) | c[:, 2]
    first = np.flatnonzero(np.concatenate(([True], word[1:] != word[:-1])))
    counts = np.diff(np.append(first, word.size)).astype(np.int64)
    values, counts = _split_long(word[first], counts, MAX_PREVIEW_RUN)
    two = counts >= 2  # a pair as two plain words, longer runs as flagged word + count word
    n_words = np.where(two, 2, 1)
    at = np.cumsum(n_words) - n_words
    out = np.empty(int(n_words.sum()), np.uint16)
    run = counts >= 3
    out[at] = np.where(run, values | 0x20, values)
    out[at[two] + 1] = np.where(run[two], 0x3000 | (counts[two] - 1), values[two]).astype(np.uint16)
    return out.astype("<u2").tobytes()


def _preview_images(thumb: _Thumb) -> list[np.ndarray]:

    return [np.asarray(thumb.image(size)) for size in PREVIEW_SIZES]


def _light_off(table: dict[str, np.ndarray], version: int) -> np.ndarray:
    """Each layer's light-off delay (s): v2/v3 fold the waits in (module docstring), v4 keeps them apart (0)."""
    waits = table["wait_before_cure"] + table["wait_after_cure"] + table["wait_after_lift"]
    if version >= 4:
        return np.zeros_like(waits)
    lift = table["lift_height"] + table["lift_height2"]
    moves = _move_s(lift, table["lift_speed"]) + _move_s(lift, table["retract_speed"])
    return np.where(waits > 0, moves + waits, 0.0)


def _move_s(height: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Seconds to move ``height`` mm at ``speed`` mm/min (0 where the height is 0)."""
    return np.where(height > 0, height / np.where(speed > 0, speed, 1.0) * 60.0, 0.0)


def _timestamp_minutes(now: _dt.datetime | None) -> int:
    when = now if now is not None else _dt.datetime.now(_dt.timezone.utc).replace(tzinfo=None)
    return int((when - _dt.datetime(1970, 1, 1)).total_seconds() // 60) & 0xFFFFFFFF


def _layout(version: int, machine: bytes, n: int) -> dict[str, int]:
    """Offsets of every section (module docstring), from the sizes known before the first layer."""
    at = {"previews": HEADER.size}
    reserved = sum(PREVIEW.size + 2 * w * h for w, h in PREVIEW_SIZES)
    at["params"] = at["previews"] + reserved
    at["slicer"] = at["params"] + PRINT_PARAMS.size
    at["machine"] = at["slicer"] + SLICER_INFO.size
    pos = at["machine"] + len(machine)
    if version >= 4:
        at["disclaimer"] = pos
        at["params_v4"] = pos
        pos += PARAMS_V4.size + PARAMS_V4_RESERVED
    at["table"] = pos
    at["layers"] = pos + LAYER_DEF.size * n
    return at


def write_ctb(
    layers: Iterable[Tile | RunLayer],
    spec: RasterSpec,
    path: str | os.PathLike,
    thickness: np.ndarray,
    settings: PrintSettings | None = None,
    info: CtbInfo | None = None,
    *,
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    now: _dt.datetime | None = None,
    device=None,
) -> dict[str, float]:
    """Write a CTB file at ``path`` (atomically) with one layer per item of ``layers`` (a tile or runs, in order;
    ``len(thickness)`` of them, each that thick, mm). Layers are encoded on ``workers`` threads and written as they
    come (one layer's bytes in flight per thread, never the whole file). ``now``: the date the file records (None:
    now; given, e.g. from ``SOURCE_DATE_EPOCH``, the bytes are reproducible); ``device``: the OpenCL device of the
    layers' runs, to encode them there (:class:`CtbEncoder`; None: numpy). Returns the layer count, ``png_bytes``
    (the layers' image data, bytes: the name the command line reports), ``ctb_bytes`` (the file's size) and
    ``format_version``."""
    p = Path(os.fspath(path))
    settings = settings if settings is not None else PrintSettings()
    info = info if info is not None else CtbInfo()
    version = int(info.version)
    if version not in VERSIONS:
        raise ParameterError(f"{p}: CTB version {info.version} is not written (use {', '.join(map(str, VERSIONS))})")
    try:
        machine = info.machine.encode("ascii")
    except UnicodeEncodeError:
        raise ParameterError(f"{p}: CTB machine name must be ASCII, got '{info.machine}'") from None
    thickness = np.asarray(thickness, np.float64)
    n = int(thickness.size)
    if n == 0:
        raise ParameterError(f"{p}: no layers to write")
    rows, cols = spec.shape
    n_pixels = rows * cols
    z = np.cumsum(thickness).astype(np.float32)  # the platform's height while exposing each layer: its top
    table = layer_table(settings, n)
    light_off = _light_off(table, version).astype(np.float32)
    at = _layout(version, machine, n)
    entries = np.zeros((n, 9), np.uint32)  # the layer table, filled as layers are written
    thumb = _Thumb(spec, n)
    ex_floats = _ex_columns(table, version)

    with atomic_path(p) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as f:
        f.seek(at["layers"])
        pos = at["layers"]

        def encode(item: Tile | RunLayer) -> bytes:  # on a worker thread
            return rle7(*pixel_runs(item, cols), n_pixels)

        def encode_group(group: list[Tile | RunLayer]) -> list[bytes]:  # on a worker thread
            if isinstance(group[0], RunLayer):
                return rle7_runs(group[0].runs, group[0].j, group[-1].j + 1, cols, n_pixels, device)
            return [encode(item) for item in group]

        def sink(k: int, data: bytes) -> None:
            nonlocal pos
            if k >= n:
                raise ParameterError(f"{p}: more than the {n} layers expected")
            if version >= 3:
                start = pos + LAYER_EX.size
                entry = _entry(z[k], table["exposure"][k], light_off[k], start, len(data), version)
                f.write(LAYER_EX.pack(*entry, LAYER_EX.size + len(data), *ex_floats[k]))
            else:
                start = pos
                entry = _entry(z[k], table["exposure"][k], light_off[k], start, len(data), version)
            f.write(data)
            pos = start + len(data)
            entries[k] = np.frombuffer(LAYER_DEF.pack(*entry), "<u4")

        stats = encode_all(layers, encode, sink, workers, on_tile=thumb.add, progress=progress, many=encode_group,
                           chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{p}: expected {n} layers, got {stats['layers']}")
        file_size = pos
        f.seek(at["table"])
        f.write(entries.astype("<u4").tobytes())
        previews, at["small"] = _previews(_preview_images(thumb), at["previews"])
        f.seek(at["previews"])
        f.write(previews)
        f.write(_params_block(settings, info, version, machine, n, at, now, per_layer_mode(settings, thickness)))
        f.seek(0)
        f.write(_header(spec, settings, info, version, z, thickness, n, at))
    return {"layers": stats["layers"], "png_bytes": stats["png_bytes"], "ctb_bytes": file_size,
            "format_version": version}


def _entry(z: float, exposure: float, light_off: float, start: int, size: int, version: int) -> tuple:
    """A layer table entry's 9 values (:data:`LAYER_DEF`)."""
    return (float(z), float(exposure), float(light_off), start % PAGE, size, start // PAGE,
            LAYER_EX.size if version >= 3 else LAYER_DEF.size, 0, 0)


def _ex_columns(table: dict[str, np.ndarray], version: int) -> np.ndarray:
    """(n, 11) float32: each layer's own settings after its record's total size (:data:`LAYER_EX`): lift height,
    lift speed, lift height 2, lift speed 2, retract speed, retract height 2, retract speed 2, rest before lift, rest
    after lift, rest after retract, PWM. v3 has the one-stage lift (both stages' height), retract speed and PWM."""
    n = table["exposure"].size
    out = np.zeros((n, 11), np.float32)
    out[:, 0] = table["lift_height"] + table["lift_height2"]
    out[:, 1] = table["lift_speed"]
    out[:, 4] = table["retract_speed"]
    out[:, 10] = table["light_pwm"]
    if version >= 4:
        out[:, 2] = table["lift_height2"]
        out[:, 3] = table["lift_speed2"]
        out[:, 5] = table["retract_height2"]
        out[:, 6] = table["retract_speed2"]
        out[:, 7] = table["wait_after_cure"]
        out[:, 8] = table["wait_after_lift"]
        out[:, 9] = table["wait_before_cure"]
    return out


def _previews(images: list[np.ndarray], base: int) -> tuple[bytes, int]:
    """The preview region at ``base`` (each image's record and data, zero-padded to the reserved size) and the
    offset of the second (small) preview's record."""
    out = bytearray()
    small = base
    for img in images:
        data = rgb15_rle(img)
        h, w = img.shape[:2]
        small = base + len(out)
        out += PREVIEW.pack(w, h, small + PREVIEW.size, len(data), 0, 0, 0, 0) + data
    reserved = sum(PREVIEW.size + 2 * w * h for w, h in PREVIEW_SIZES)
    return bytes(out) + bytes(reserved - len(out)), small


def _rows(settings: PrintSettings, version: int) -> tuple[dict[str, float], dict[str, float]]:
    """A bottom and a normal layer's values (the columns of ``layer_table``, with ``light_off``): what the header,
    print parameters and slicer info hold (the per-layer records hold every layer's own)."""
    t = layer_table(replace(settings, bottom_layers=1, transition_layers=0), 2)
    t["light_off"] = _light_off(t, version)
    return {k: float(v[0]) for k, v in t.items()}, {k: float(v[1]) for k, v in t.items()}


def _params_block(settings: PrintSettings, info: CtbInfo, version: int, machine: bytes, n: int,
                  at: dict[str, int], now: _dt.datetime | None, per_layer: bool = False) -> bytes:
    """Print parameters, slicer info, machine name and (v4) the v4 parameters, as laid out from ``at["params"]``.
    Lift heights are the lift's total (v4 stores the second stage apart too); ``per_layer``: the per-layer switch
    (:func:`~gpuslice.raster.settings.per_layer_mode`)."""
    s = settings
    b, m = _rows(s, version)
    two = 1.0 if version >= 4 else 0.0  # v4 stores second stages and waits; v2/v3 have no fields for them
    params = PRINT_PARAMS.pack(b["lift_height"] + b["lift_height2"], b["lift_speed"],
                               m["lift_height"] + m["lift_height2"], m["lift_speed"], m["retract_speed"],
                               info.resin_ml, info.resin_ml * s.resin_density, 0.0, b["light_off"], m["light_off"],
                               s.bottom_layers, 0, 0, 0, 0x1234 if version <= 2 else 0)
    aa_flag = 0x0F if info.anti_alias > 1 else 0x07
    per_layer = 0x10 * version if per_layer else 0
    slicer = SLICER_INFO.pack(
        two * b["lift_height2"], two * b["lift_speed2"], two * m["lift_height2"], two * m["lift_speed2"],
        two * m["retract_height2"], two * m["retract_speed2"], two * m["wait_after_lift"], at["machine"],
        len(machine), aa_flag, 0, per_layer, _timestamp_minutes(now), info.anti_alias, SOFTWARE_VERSION[version],
        two * m["wait_before_cure"], two * m["wait_after_lift"], ramp_layers(s), at.get("params_v4", 0), 0, 0)
    out = params + slicer + machine
    if version >= 4:
        v4 = PARAMS_V4.pack(b["retract_speed"], b["retract_speed2"], 0, 4.0, 0, 4.0, m["wait_before_cure"],
                            m["wait_after_lift"], m["wait_after_cure"], b["retract_height2"], 0.0, 0, 5, n - 1,
                            0, 0, 0, 0, at["disclaimer"], 0, 0)
        out += v4 + bytes(PARAMS_V4_RESERVED)
    return out


def _header(spec: RasterSpec, settings: PrintSettings, info: CtbInfo, version: int, z: np.ndarray,
            thickness: np.ndarray, n: int, at: dict[str, int]) -> bytes:
    """The 112-byte file header: bed size along the image's columns and rows (mm), heights, exposures, offsets."""
    rows, cols = spec.shape
    if spec.portrait:  # PNG columns run along the display's y (pitch py), rows along its x (pitch px)
        bed_x, bed_y = cols * spec.py, rows * spec.px
    else:
        bed_x, bed_y = cols * spec.px, rows * spec.py
    height = float(z[-1])
    layer_h = header_layer_height(thickness)
    normal_off = _rows(settings, version)[1]["light_off"]
    magic = MAGIC_CTB_V4 if version >= 4 else MAGIC_CTB
    return HEADER.pack(
        magic, version, bed_x, bed_y, info.build_height or height, 0, 0, height, layer_h, settings.exposure,
        settings.bottom_exposure, normal_off, settings.bottom_layers, cols, rows, at["previews"], at["table"], n,
        at["small"], int(round(print_time_s(settings, n))), 1 if (spec.mirror_x or spec.mirror_y) else 0, at["params"],
        PRINT_PARAMS.size, 1, settings.light_pwm, settings.bottom_light_pwm, 0, at["slicer"],
        SLICER_INFO.size)


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """CTB's settings check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`): v2 and v3 store one lift
    and one retract stage (module docstring), so a second stage at its own speed is refused rather than folded into
    the first (the file would move otherwise than asked, and its print time would not be the one printed)."""
    version = _version(options)
    lost = settings.two_stages_lost() if version < 4 else None
    if lost:
        raise ParameterError(f"{path}: a CTB v{version} file has one lift and one retract stage; {lost} cannot be "
                             "written (CTB v4, for a printer whose preset asks for it, and GOO store two)")


def _version(options) -> int:
    preset = options.preset
    if preset is not None and preset.native_format == "ctb" and preset.format_version is not None:
        return int(preset.format_version)
    return DEFAULT_VERSION


def ctb_version(target) -> int:
    """The CTB version for a :class:`~gpuslice.raster.outputs.ResinTarget`: its printer preset's ``format_version``
    when the preset's native format is CTB, else :data:`DEFAULT_VERSION`."""
    return _version(target.options)


def write_target(layers: Iterable[Tile | RunLayer], target) -> dict[str, float]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): a CTB file of ``target.result``'s layers, version
    :func:`ctb_version`, header values from the preset (machine name, build height) and ``target.settings``."""
    refuse_settings(target.path, "ctb", target.options, target.settings)
    preset = target.options.preset
    result = target.result
    machine = (preset.machine or preset.title) if preset is not None else ""
    info = CtbInfo(version=ctb_version(target), machine=machine,
                   build_height=float(preset.build_height) if preset is not None else 0.0,
                   anti_alias=1 if target.spec.gamma == 0 else 8,
                   resin_ml=resin_ml(result.area, result.thickness))
    return write_ctb(layers, target.spec, target.path, result.thickness, target.settings, info,
                     workers=target.workers, progress=target.progress, now=target.now,
                     device=target.device)
