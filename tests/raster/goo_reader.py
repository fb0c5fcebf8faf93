"""A GOO reader for the tests, written from Elegoo's "Goo Format Spec V1.2" (github.com/elegooofficial/GOO),
separately from the writer (:mod:`gpuslice.raster.goo`): the header's fields one by one, the RGB565 previews, each
layer's definition and its RLE image data, decoded to runs or to a uint8 mask, every chunk type (the grey
differences too, which our writer never emits but other slicers may).

Everything is big-endian. The image data of a layer: ``0x55``, chunks, an 8-bit checksum (bitwise NOT of the sum of
the chunk bytes). A chunk's first byte ``TTSSLLLL``: T 0 = 0x00 pixels, 1 = a grey in the next byte, 3 = 0xFF
pixels, with a run length of LLLL plus SS more bytes (most significant first, above the low 4 bits); T 2 = the
previous pixel's grey plus (bit 5 clear) or minus (bit 5 set) LLLL, run length 1 (bit 4 clear) or the next byte.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MAGIC = bytes([0x07, 0x00, 0x00, 0x00, 0x44, 0x4C, 0x50, 0x00])
ENDING = bytes([0x00, 0x00, 0x00]) + MAGIC

# (name, struct code) in file order; "s<n>" strings are NUL-terminated in n bytes; "preview<w>" a w×w RGB565 image
# followed by "\r\n"
HEADER_FIELDS = [
    ("version", "4s"), ("magic", "8s"), ("software_info", "32s"), ("software_version", "24s"),
    ("file_time", "24s"), ("printer_name", "32s"), ("printer_type", "32s"), ("profile_name", "32s"),
    ("anti_aliasing_level", "H"), ("grey_level", "H"), ("blur_level", "H"),
    ("small_preview", "preview116"), ("big_preview", "preview290"),
    ("total_layers", "I"), ("x_resolution", "H"), ("y_resolution", "H"), ("x_mirror", "?"), ("y_mirror", "?"),
    ("x_size", "f"), ("y_size", "f"), ("z_size", "f"), ("layer_thickness", "f"), ("exposure_time", "f"),
    ("exposure_delay_mode", "?"), ("turn_off_time", "f"),
    ("bottom_before_lift_time", "f"), ("bottom_after_lift_time", "f"), ("bottom_after_retract_time", "f"),
    ("before_lift_time", "f"), ("after_lift_time", "f"), ("after_retract_time", "f"),
    ("bottom_exposure_time", "f"), ("bottom_layers", "I"),
    ("bottom_lift_distance", "f"), ("bottom_lift_speed", "f"), ("lift_distance", "f"), ("lift_speed", "f"),
    ("bottom_retract_distance", "f"), ("bottom_retract_speed", "f"), ("retract_distance", "f"),
    ("retract_speed", "f"),
    ("bottom_second_lift_distance", "f"), ("bottom_second_lift_speed", "f"), ("second_lift_distance", "f"),
    ("second_lift_speed", "f"),
    ("bottom_second_retract_distance", "f"), ("bottom_second_retract_speed", "f"),
    ("second_retract_distance", "f"), ("second_retract_speed", "f"),
    ("bottom_light_pwm", "H"), ("light_pwm", "H"), ("advance_mode", "?"), ("printing_time", "I"),
    ("total_volume", "f"), ("total_weight", "f"), ("total_price", "f"), ("price_unit", "8s"),
    ("layer_content_offset", "I"), ("gray_scale_level", "?"), ("transition_layers", "H"),
]

LAYER_FIELDS = [
    ("pause_flag", "H"), ("pause_position_z", "f"), ("layer_position_z", "f"), ("layer_exposure_time", "f"),
    ("layer_off_time", "f"), ("before_lift_time", "f"), ("after_lift_time", "f"), ("after_retract_time", "f"),
    ("lift_distance", "f"), ("lift_speed", "f"), ("second_lift_distance", "f"), ("second_lift_speed", "f"),
    ("retract_distance", "f"), ("retract_speed", "f"), ("second_retract_distance", "f"),
    ("second_retract_speed", "f"), ("light_pwm", "H"), ("delimiter", "2s"), ("data_size", "I"),
]


class GooFormatError(ValueError):
    pass


@dataclass
class GooLayer:
    definition: dict
    data: np.ndarray  # the image data: 0x55, chunks, checksum (a view into the file's bytes)


@dataclass
class GooFile:
    header: dict
    previews: list[np.ndarray]  # (h, w, 3) uint8 RGB, small then big
    layers: list[GooLayer] = field(default_factory=list)
    size: int = 0

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of a layer image."""
        return self.header["y_resolution"], self.header["x_resolution"]


def _rgb565(raw: bytes, w: int, h: int) -> np.ndarray:
    v = np.frombuffer(raw, ">u2").astype(np.uint32).reshape(h, w)
    r, g, b = (v >> 11) & 0x1F, (v >> 5) & 0x3F, v & 0x1F
    return np.stack([(r * 255 + 15) // 31, (g * 255 + 31) // 63, (b * 255 + 15) // 31], axis=-1).astype(np.uint8)


def _read_fields(buf: bytes, pos: int, fields_: list[tuple[str, str]], previews: list | None = None):
    out = {}
    for name, code in fields_:
        if code.startswith("preview"):
            w = int(code[len("preview"):])
            n = 2 * w * w
            previews.append(_rgb565(buf[pos : pos + n], w, w))
            if buf[pos + n : pos + n + 2] != b"\r\n":
                raise GooFormatError(f"{name}: no \\r\\n after the preview")
            pos += n + 2
            continue
        (value,) = struct.unpack_from(">" + code, buf, pos)
        pos += struct.calcsize(">" + code)
        if code.endswith("s") and name not in ("magic", "delimiter"):
            value = value.split(b"\0", 1)[0].decode("utf-8", "replace")
        out[name] = value
    return out, pos


def read_goo(path: str | Path) -> GooFile:
    """Parse a GOO file: header, previews, every layer's definition and image data (not decoded)."""
    buf = Path(path).read_bytes()
    previews: list[np.ndarray] = []
    header, pos = _read_fields(buf, 0, HEADER_FIELDS, previews)
    if header["magic"] != MAGIC:
        raise GooFormatError("bad magic")
    if header["layer_content_offset"] != pos:
        raise GooFormatError(f"layer content offset {header['layer_content_offset']} != header end {pos}")
    arr = np.frombuffer(buf, np.uint8)
    goo = GooFile(header, previews, size=len(buf))
    for i in range(header["total_layers"]):
        d, pos = _read_fields(buf, pos, LAYER_FIELDS)
        if d["delimiter"] != b"\r\n":
            raise GooFormatError(f"layer {i}: bad delimiter before the data size")
        data = arr[pos : pos + d["data_size"]]
        pos += d["data_size"]
        if buf[pos : pos + 2] != b"\r\n":
            raise GooFormatError(f"layer {i}: no \\r\\n after the image data")
        pos += 2
        goo.layers.append(GooLayer(d, data))
    if buf[pos:] != ENDING:
        raise GooFormatError(f"bad ending string {buf[pos:pos + 16].hex()} at {pos} of {len(buf)}")
    return goo


def _chunk_starts(b: np.ndarray) -> np.ndarray:
    """Positions of the chunks in ``b`` (the chunk bytes): every chunk's width follows from its first byte, so the
    starts are the orbit of 0 under p → p + width(b[p]); found by pointer doubling (log2 rounds of numpy gathers)."""
    n = b.size
    t, s = b >> 6, (b >> 4) & 3
    width = np.where(t == 2, 1 + (s & 1), 1 + s + (t == 1)).astype(np.int64)
    jump = np.minimum(np.arange(n, dtype=np.int64) + width, n)
    jump = np.append(jump, n)  # n: past the end, a fixed point
    reach = np.zeros(n + 1, bool)
    reach[0] = True
    while True:
        reach[jump[reach]] = True
        if jump[0] >= n:
            break
        jump = jump[jump]
    return np.flatnonzero(reach[:n])


def decode_runs(data: np.ndarray, n_pixels: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lengths int64, greys uint8) of one layer's image data, chunk by chunk; checks the magic byte and the
    checksum (and the pixel count when ``n_pixels`` is given). Vectorised."""
    data = np.asarray(data, np.uint8)
    if data.size < 2 or data[0] != 0x55:
        raise GooFormatError("image data does not start with 0x55")
    b = data[1:-1]
    if (~int(b.sum(dtype=np.uint64))) & 0xFF != int(data[-1]):
        raise GooFormatError("checksum mismatch")
    p = _chunk_starts(b)
    bb = np.append(b, np.zeros(4, np.uint8)).astype(np.int64)
    head = bb[p]
    t, s, low = head >> 6, (head >> 4) & 3, head & 0xF
    is_grey = t == 1
    q = p + 1 + is_grey  # first length byte
    length = low.copy()
    for k in range(3):
        more = (t != 2) & (s > k)
        length[more] += bb[q[more] + k] << (4 + 8 * (s[more] - 1 - k))
    diff = t == 2
    length[diff] = np.where(s[diff] & 1, bb[p[diff] + 1], 1)
    absolute = np.where(t == 0, 0, np.where(t == 3, 255, bb[q - 1]))  # for t 1: the byte after the head
    delta = np.where(diff, np.where(s & 2, -low, low), 0)
    # a diff chunk's grey: the last absolute chunk's grey (0 before any) plus the deltas since
    idx = np.arange(p.size)
    last_abs = np.maximum.accumulate(np.where(~diff, idx, -1))
    cs = np.cumsum(delta)
    base = np.where(last_abs >= 0, absolute[np.maximum(last_abs, 0)], 0)
    grey = (base + cs - np.where(last_abs >= 0, cs[np.maximum(last_abs, 0)], 0)) & 0xFF
    if n_pixels is not None and int(length.sum()) != n_pixels:
        raise GooFormatError(f"runs cover {int(length.sum())} pixels, not {n_pixels}")
    return length, grey.astype(np.uint8)


def canonical_runs(start: np.ndarray, length: np.ndarray, grey: np.ndarray) -> np.ndarray:
    """Non-blank runs in a canonical form, as one (3, m) int64 array: row-major ``start``, ``length``, ``grey``
    (none 0), touching runs of one grey merged (also across row ends). Any two encodings of one image agree."""
    start, length, grey = (np.asarray(a, np.int64) for a in (start, length, grey))
    keep = (grey != 0) & (length > 0)
    start, length, grey = start[keep], length[keep], grey[keep]
    if start.size:
        end = start + length
        new = np.ones(start.size, bool)
        new[1:] = (start[1:] != end[:-1]) | (grey[1:] != grey[:-1])
        first = np.flatnonzero(new)
        last = np.append(first[1:], start.size) - 1
        start, grey, length = start[first], grey[first], end[last] - start[first]
    return np.stack([start, length, grey])


def layer_runs(layer: GooLayer, n_pixels: int) -> np.ndarray:
    """A layer's non-blank runs in :func:`canonical_runs` form."""
    length, grey = decode_runs(layer.data, n_pixels)
    start = np.cumsum(length) - length
    return canonical_runs(start, length, grey)


def layer_mask(goo: GooFile, i: int) -> np.ndarray:
    """Layer ``i`` as a (rows, cols) uint8 image."""
    rows, cols = goo.shape
    length, grey = decode_runs(goo.layers[i].data, rows * cols)
    return np.repeat(grey, length).reshape(rows, cols)
