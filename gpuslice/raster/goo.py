"""Elegoo GOO files (``.goo``), as Elegoo's "Goo Format Spec V1.2" (github.com/elegooofficial/GOO) lays them out;
Phrozen's ``.prz`` is the same layout (UVtools reads and writes both with one class) and is written by the same
function.

Layout, big-endian throughout (the spec leaves the byte order unsaid; every reader uses big-endian):

* **header**, 195,477 bytes (:data:`HEADER_SIZE`): version ``V3.0``, magic, software, date, machine name/type,
  profile, anti-aliasing/grey/blur levels, two RGB565 previews (116×116 and 290×290, each followed by ``\\r\\n``),
  layer count, resolution, mirror flags, platform size (mm), layer height, the global print settings (bottom and
  normal: exposure, waits, two-stage lift and retract, PWM), "advance mode" (per-layer settings: as asked, and on
  whenever the layers' thicknesses vary, :func:`~gpuslice.raster.settings.per_layer_mode`), print time (s),
  volume (mm³), weight (g), price, the offset of the first layer (= :data:`HEADER_SIZE`), the grey-scale flag and
  the transition-layer count.
* per layer: its **definition** (66 bytes: pause flag and Z, the layer's top Z, exposure, waits, lift, retract,
  PWM, ``\\r\\n``), the data size (u32), the **image data** (``0x55``, RLE chunks, an 8-bit checksum: the bitwise
  NOT of the sum of the chunk bytes) and ``\\r\\n``.
* the ending string ``00 00 00 07 00 00 00 44 4C 50 00``.

The image data runs over every pixel of the image in row-major order (row 0 = the PNG's top row), blank pixels
included (the printer decodes into an uninitialised buffer, so the runs must cover all of it). A chunk's first byte
is ``TTSSLLLL``: T = 0 all-0x00 pixels, 3 all-0xFF, 1 a grey 0x01-0xFE that follows in the next byte (2: a
difference from the previous grey, never written here: UVtools writes none for ``.prz``, whose firmware failed on
them, so one encoding serves both suffixes); S = how many more bytes hold the run length (0-3), most significant
first, above its low 4 bits LLLL: lengths up to 2^28 − 1 pixels per chunk (longer blank gaps are split).

Greys: the header's grey-scale flag is 1 (greys 0x00-0xFF), so each pixel's 8-bit grey is stored as it is, with no
quantisation: a decoded layer equals :func:`gpuslice.raster.masks` exactly. The anti-aliasing level (informational:
the printer reads the pixels) is 1 with ``gamma`` 0 (only 0 and 255) and 8 otherwise. The machine name (and type,
as CHITUBOX writes both) is the printer preset's ``machine``; the platform's Z size (and each layer's pause Z, as
UVtools) is the preset's build height, or the part's height without a preset.

Layers are encoded from their runs in groups on the worker threads (:func:`gpuslice.raster.png.encode_all`): by the
two kernels of ``kernels/goo.cl`` on the runs' OpenCL device (:class:`GooEncoder`; ``target.device``), else with a
few numpy passes (their twin, which also takes the rare group the kernels leave: runs touching across a row end with
one grey, which the format joins into one chunk). The bytes are the same either way. Layers are appended to the
file as they come, and the header (which holds the previews, drawn from the layers as they pass) is written last,
at offset 0, since its size is fixed. The file is written under a temporary name and renamed when complete
(:func:`gpuslice.io.atomic.atomic_path`); with a given ``target.now`` its bytes are reproducible.
"""

from __future__ import annotations

import datetime as _dt
import os
import struct
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from .coverage import Tile
from .layers import RunLayer, batch_image_segments, batch_pixel_runs, image_segments, pixel_runs, run_groups
from .png import encode_all
from .run_encoder import RunImageEncoder
from .settings import header_layer_height, layer_table, per_layer_mode, print_time_s, ramp_layers, resin_ml

__all__ = ["HEADER_SIZE", "LAYER_DEF", "MAGIC", "ENDING", "PREVIEWS", "MAX_RUN", "encode_runs", "encode_batch",
           "GooEncoder", "encode_segments", "header_bytes", "layer_definitions", "rgb565", "write_goo", "write_target"]

MAGIC = b"\x07\x00\x00\x00\x44\x4c\x50\x00"
#: the file's last 11 bytes
ENDING = b"\x00\x00\x00" + MAGIC
DELIMITER = b"\r\n"
LAYER_MAGIC = 0x55
#: preview (width, height) in pixels: the small one first, as stored
PREVIEWS = ((116, 116), (290, 290))
#: the longest run one chunk holds (28 bits)
MAX_RUN = 0xFFFFFFF
VERSION = b"V3.0"

# the header around the previews: strings and levels before them, settings after them
_HEAD = struct.Struct(">4s8s32s24s24s32s32s32sHHH")
_TAIL = struct.Struct(">IHH??fffffBffffffffIffffffffffffffffHH?Ifff8sIBH")
HEADER_SIZE = _HEAD.size + sum(2 * w * h + 2 for w, h in PREVIEWS) + _TAIL.size  # 195,477 (0x2FB95)

#: one layer's definition (what precedes its data size), in file order; times s, lengths mm, speeds mm/min
LAYER_DEF = np.dtype([
    ("pause", ">u2"), ("pause_z", ">f4"), ("z", ">f4"), ("exposure", ">f4"), ("light_off_delay", ">f4"),
    ("wait_after_cure", ">f4"), ("wait_after_lift", ">f4"), ("wait_before_cure", ">f4"),
    ("lift_height", ">f4"), ("lift_speed", ">f4"), ("lift_height2", ">f4"), ("lift_speed2", ">f4"),
    ("retract_height", ">f4"), ("retract_speed", ">f4"), ("retract_height2", ">f4"), ("retract_speed2", ">f4"),
    ("light_pwm", ">u2"), ("delimiter", "S2"),
])


def encode_runs(start: np.ndarray, length: np.ndarray, grey: np.ndarray, n_pixels: int) -> bytes:
    """One layer's GOO image data (``0x55``, the chunks, the checksum) from its runs: ``start`` (row-major pixel
    index), ``length`` (pixels) and ``grey`` (1-255) of the non-blank runs, sorted and not overlapping, over an image
    of ``n_pixels`` pixels. The blank gaps between them (and before the first, after the last) become 0x00 chunks;
    touching runs of one grey (across a row end) are merged. Vectorised: a few numpy passes over the runs."""
    n, v = image_segments(start, length, grey, n_pixels)
    return encode_segments(n, v, np.array([0, n.size], np.int64))[0]


def encode_batch(runs, a: int, b: int, cols: int, n_pixels: int, device=None) -> list[bytes]:
    """:func:`encode_runs` of entries ``a`` … ``b`` − 1 of a batch of runs (:class:`~gpuslice.raster.runs.Runs`,
    ``cols`` columns, images of ``n_pixels``): the same bytes, layer by layer. With an OpenCL ``device``, by the
    kernels of ``kernels/goo.cl`` (:class:`GooEncoder`); else (and for what those leave to it) in one set of numpy
    passes, their twin."""
    if device is not None:
        out = GooEncoder.of(device).encode(runs, a, b, cols, n_pixels)
        if out is not None:
            return out
    start, length, grey, offsets = batch_pixel_runs(runs, a, b, cols)
    return encode_segments(*batch_image_segments(start, length, grey, offsets, n_pixels))


class GooEncoder(RunImageEncoder):
    """Driver of ``kernels/goo.cl`` (:mod:`gpuslice.raster.run_encoder`): GOO image data of a group of layers from
    their runs, the bytes of the numpy twin (``encode_segments(*batch_image_segments(...))``, :func:`encode_batch`
    without a device). Each layer: 0x55, the runs' chunks, the checksum (from the write pass's per-run byte sums)."""

    FILE, SIZES, WRITE = "goo.cl", "goo_sizes", "goo_write"
    MAX_RUN = MAX_RUN
    HEAD = TAIL = 1
    EXTRA = (np.dtype(np.uint8),)  # each run's byte sum mod 256

    def blank(self, n_pixels: int) -> bytes:
        none = np.zeros(0, np.int64)
        return encode_runs(none, none, np.zeros(0, np.uint8), n_pixels)[1:-1]  # (without its 0x55 and checksum)

    def reduce(self, extra: list[np.ndarray], first: np.ndarray, nonempty: np.ndarray, blank: bytes) -> np.ndarray:
        check = np.full(first.size, sum(blank), np.uint64)  # each layer's chunk bytes, summed
        ne = np.flatnonzero(nonempty)
        check[ne] = np.add.reduceat(extra[0], first[ne], dtype=np.uint64)
        return check

    def finish(self, img: np.ndarray, start: np.ndarray, stats: np.ndarray) -> None:
        img[start[:-1]] = LAYER_MAGIC
        img[start[1:] - 1] = ~(stats & np.uint64(0xFF)).astype(np.uint8)


def encode_segments(n: np.ndarray, v: np.ndarray, seg_offsets: np.ndarray) -> list[bytes]:
    """GOO image data of images whose segments (:func:`~gpuslice.raster.layers.image_segments`: lengths ``n`` >= 1,
    greys ``v``) are ``seg_offsets[k]:seg_offsets[k + 1]`` for image k: one ``bytes`` per image."""
    n_img = seg_offsets.size - 1
    img = np.repeat(np.arange(n_img, dtype=np.int64), np.diff(seg_offsets))
    if n.size and int(n.max()) > MAX_RUN:  # only blank gaps get this long (a row holds at most 65,535 pixels)
        pieces = -(-n // MAX_RUN)
        last = np.cumsum(pieces) - 1
        v, img = np.repeat(v, pieces), np.repeat(img, pieces)
        split = np.full(int(last[-1]) + 1, MAX_RUN, np.int64)
        split[last] = n - (pieces - 1) * MAX_RUN
        n = split
    kind = np.where(v == 0, 0, np.where(v == 255, 3, 1)).astype(np.int64)
    size = (n > 0xF).astype(np.int64) + (n > 0xFFF) + (n > 0xFFFFF)  # extra length bytes
    is_grey = kind == 1
    width = 1 + is_grey + size
    # image k: its 0x55, its chunks, its checksum
    cw = np.zeros(width.size + 1, np.int64)
    np.cumsum(width, out=cw[1:])
    img_off = cw[np.searchsorted(img, np.arange(n_img + 1))] + 2 * np.arange(n_img + 1)  # (img is sorted)
    off = cw[:-1] + 1 + 2 * img
    total = int(img_off[-1])
    out = np.empty(total + 1, np.uint8)  # (the last byte: where the chunks without a length byte write theirs)
    out[off] = (kind << 6) | (size << 4) | (n & 0xF)
    out[off[is_grey] + 1] = v[is_grey]
    # the length above its low 4 bits in the chunk's size extra bytes, most significant first: the first extra byte
    # of every chunk in whole-array passes (nearly all chunks have one), the rare second and third apart
    at = off + 1 + is_grey
    out[np.where(size > 0, at, total)] = (n >> (4 + 8 * np.maximum(size - 1, 0))) & 0xFF
    for k in (1, 2):
        sel = np.flatnonzero(size > k)
        out[at[sel] + k] = (n[sel] >> (4 + 8 * (size[sel] - 1 - k))) & 0xFF
    out = out[:total]
    out[img_off[:-1]] = 0  # (image k's sum runs into image k + 1's first byte: 0 until the sums are taken)
    out[img_off[1:] - 1] = 0
    sums = np.add.reduceat(out, img_off[:-1] + 1, dtype=np.uint64) if n_img else np.zeros(0, np.uint64)
    out[img_off[:-1]] = LAYER_MAGIC
    out[img_off[1:] - 1] = ~sums.astype(np.uint8)
    data = out.tobytes()
    return [data[img_off[k] : img_off[k + 1]] for k in range(n_img)]


def rgb565(rgb: np.ndarray) -> bytes:
    """(h, w, 3) uint8 RGB as the previews store it: RGB565 (5 bits red high, 6 green, 5 blue), big-endian."""
    c = rgb.astype(np.uint16)
    return (((c[..., 0] >> 3) << 11) | ((c[..., 1] >> 2) << 5) | (c[..., 2] >> 3)).astype(">u2").tobytes()


def _text(value: str, size: int) -> bytes:
    """A NUL-terminated string field of ``size`` bytes (UTF-8, cut to fit at a character boundary)."""
    return value.encode("utf-8")[: size - 1].decode("utf-8", "ignore").encode("utf-8")


def _image_size(path, spec) -> tuple[int, int]:
    """(columns, rows) of the layer images (the PNG's width and height): the header's x and y resolution (u16)."""
    cols, rows = spec.png_size
    if cols > 0xFFFF or rows > 0xFFFF:
        raise ParameterError(f"{path}: GOO holds at most 65535 pixels a side, not {cols}x{rows}")
    return cols, rows


def _pitch(spec) -> tuple[float, float]:
    """(column, row) pitch of the image in mm: (px, py) in landscape, (py, px) in portrait."""
    return (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)


def layer_definitions(target, pause_z: float) -> np.ndarray:
    """(n,) :data:`LAYER_DEF` records of ``target``'s layers: each layer's top (mm above the plate, the sum of
    thicknesses) and its settings from :func:`~gpuslice.raster.settings.layer_table` (the bottom/transition ramp);
    ``pause_z``: where the plate goes on a pause (the machine's Z)."""
    n = target.result.n_layers
    t = layer_table(target.settings, n)
    d = np.zeros(n, LAYER_DEF)
    d["pause_z"] = pause_z
    d["z"] = np.cumsum(np.asarray(target.result.thickness, np.float64))
    for name in LAYER_DEF.names:
        if name in t:
            d[name] = t[name]
    d["delimiter"] = DELIMITER
    return d


def _global_settings(settings) -> tuple[dict[str, float], dict[str, float]]:
    """(bottom, normal) settings for the header: a bottom layer's and a normal layer's rows of the layer table."""
    t = layer_table(replace(settings, bottom_layers=1, transition_layers=0), 2)
    return ({k: float(c[0]) for k, c in t.items()}, {k: float(c[1]) for k, c in t.items()})


def header_bytes(target, previews: tuple[bytes, bytes], *, machine_z: float) -> bytes:
    """The header of ``target``'s file (:data:`HEADER_SIZE` bytes) with ``previews`` (RGB565, small then big)."""
    from .. import __version__

    spec, s, res = target.spec, target.settings, target.result
    cols, rows = _image_size(target.path, spec)
    cw, rh = _pitch(spec)
    th = np.asarray(res.thickness, np.float64)
    layer_height = header_layer_height(th)
    preset = target.options.preset
    machine = (preset.machine if preset is not None else "") or ""
    when = (target.now or _dt.datetime.now(_dt.timezone.utc)).strftime("%Y-%m-%d %H:%M:%S")
    ml = resin_ml(res.area, th)
    bottom, normal = _global_settings(s)
    aa = 1 if spec.gamma == 0 else 8
    head = _HEAD.pack(VERSION, MAGIC, _text("gpuslice", 32), _text(__version__, 24), _text(when, 24),
                      _text(machine, 32), _text(machine, 32), _text(target.name, 32), aa, 0, 0)
    tail = _TAIL.pack(
        res.n_layers, cols, rows, spec.mirror_x, spec.mirror_y, cols * cw, rows * rh, machine_z, layer_height,
        s.exposure,
        1,  # delay mode 1: the waits below ("static time"), not a light-off delay
        0.0,  # light-off delay
        bottom["wait_after_cure"], bottom["wait_after_lift"], bottom["wait_before_cure"],
        normal["wait_after_cure"], normal["wait_after_lift"], normal["wait_before_cure"],
        s.bottom_exposure, s.bottom_layers,
        # bottom then normal lift, bottom then normal retract (height, speed each); then the second stages
        *(c[f"{move}{stage}"] for stage in ("", "2") for part in ("lift", "retract") for c in (bottom, normal)
          for move in (f"{part}_height", f"{part}_speed")),
        s.bottom_light_pwm, s.light_pwm, per_layer_mode(s, th),  # ("advance mode": the layer table's own values)
        min(round(print_time_s(s, res.n_layers)), 0xFFFFFFFF),
        ml * 1000.0,  # mm³
        ml * s.resin_density,  # g
        0.0, b"",  # price, currency
        HEADER_SIZE,  # where the first layer starts
        1,  # grey-scale level: greys 0x00-0xFF
        min(ramp_layers(s), 0xFFFF),
    )
    small, big = previews
    out = b"".join((head, small, DELIMITER, big, DELIMITER, tail))
    assert len(out) == HEADER_SIZE
    return out


#: the previews' top view samples every ``step``-th pixel: the display's longer side over this (at least 4, as SL1)
PREVIEW_SAMPLES = 1024


def _preview_step(spec) -> int:
    return max(4, max(spec.shape) // PREVIEW_SAMPLES)


def _previews(thumb, spec) -> tuple[bytes, ...]:
    """The previews (:data:`PREVIEWS`) as RGB565: SL1's top view (:class:`gpuslice.raster.sl1._Thumb`, a height map
    of the sampled pixels, whose rows it stretches by the pixels' aspect ratio on a display of non-square pixels)."""
    return tuple(rgb565(np.asarray(thumb.image(size))) for size in PREVIEWS)


def write_goo(layers: Iterable[Tile | RunLayer], target) -> dict[str, Any]:
    """Write ``target.result``'s layers (tiles or runs, in order) as a GOO file at ``target.path``, atomically.

    Returns the layer count, ``png_bytes`` (the layers' image data, bytes: the name the command line reports) and
    ``goo_bytes`` (the file's size)."""
    from .sl1 import _Thumb

    path = Path(os.fspath(target.path))
    spec, res = target.spec, target.result
    n = res.n_layers
    cols, rows = _image_size(path, spec)
    preset = target.options.preset
    top = float(np.sum(res.thickness)) if n else 0.0
    machine_z = float(preset.build_height) if preset is not None and preset.build_height > 0 else top
    defs = layer_definitions(target, machine_z)
    n_pixels = cols * rows
    thumb = _Thumb(spec, n, step=_preview_step(spec))

    def encode(item: Tile | RunLayer) -> bytes:  # on a worker thread
        return encode_runs(*pixel_runs(item, cols), n_pixels)

    device = target.device

    def encode_group(group: list[Tile | RunLayer]) -> list[bytes]:  # on a worker thread
        if isinstance(group[0], RunLayer):
            return encode_batch(group[0].runs, group[0].j, group[-1].j + 1, cols, n_pixels, device=device)
        return [encode(item) for item in group]

    with atomic_path(path) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as f:
        f.seek(HEADER_SIZE)  # the header (with the previews) goes in last

        def sink(k: int, data: bytes) -> None:
            if k >= n:
                raise ParameterError(f"{path}: expected {n} layers, got more")
            f.write(defs[k].tobytes())
            f.write(struct.pack(">I", len(data)))
            f.write(data)
            f.write(DELIMITER)

        stats = encode_all(layers, encode, sink, target.workers, on_tile=thumb.add, progress=target.progress,
                           many=encode_group, chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{path}: expected {n} layers, got {stats['layers']}")
        f.write(ENDING)
        size = f.tell()
        f.seek(0)
        f.write(header_bytes(target, _previews(thumb, spec), machine_z=machine_z))
    return {**stats, "goo_bytes": size}


def write_target(layers: Iterable[Tile | RunLayer], target) -> dict[str, Any]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): a GOO (or PRZ) file of ``target.result``'s layers."""
    return write_goo(layers, target)
