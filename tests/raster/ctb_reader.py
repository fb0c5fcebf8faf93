"""A CTB reader for the tests, written from the public format description (cbiffle/catibo ``doc/cbddlp-ctb.adoc``,
UVtools' ``Scripts/010 Editor/ctb.bt``), apart from the writer (``gpuslice/raster/ctb.py``): it shares no code
with it, so a misreading of the format in one does not hide in the other.

It reads versions 2 to 4 (magic 0x12FD0086 or 0x12FD0106): the header, the print parameters, the slicer info and
machine name, the v4 parameters, the previews (RGB15 run-length words), the layer table, the per-layer records of
v3+ and the layers' RLE7 data. Layer data of files whose ``encryption_key`` is not 0 (what Chitubox 1.6-1.8 wrote) is
XORed with catibo's documented keystream before decoding; the AES-encrypted CTB (magic 0x12FD0107) is not read.
Decoding is vectorised (pointer doubling finds where each run record starts), so 12K layers decode in milliseconds.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MAGICS = {0x12FD0086: "ctb", 0x12FD0106: "ctb-v4"}

_HEADER = [  # (name, struct code), in file order: 112 bytes
    ("magic", "I"), ("version", "I"), ("bed_x", "f"), ("bed_y", "f"), ("bed_z", "f"), ("unknown1", "I"),
    ("unknown2", "I"), ("total_height", "f"), ("layer_height", "f"), ("exposure", "f"), ("bottom_exposure", "f"),
    ("light_off", "f"), ("bottom_layers", "I"), ("res_x", "I"), ("res_y", "I"), ("large_preview", "I"),
    ("layer_table", "I"), ("layer_count", "I"), ("small_preview", "I"), ("print_time", "I"), ("projector", "I"),
    ("params_offset", "I"), ("params_size", "I"), ("level_sets", "I"), ("pwm", "H"), ("bottom_pwm", "H"),
    ("key", "I"), ("slicer_offset", "I"), ("slicer_size", "I"),
]
_PARAMS = [
    ("bottom_lift_height", "f"), ("bottom_lift_speed", "f"), ("lift_height", "f"), ("lift_speed", "f"),
    ("retract_speed", "f"), ("volume_ml", "f"), ("weight_g", "f"), ("cost", "f"), ("bottom_light_off", "f"),
    ("light_off", "f"), ("bottom_layers", "I"), ("pad1", "I"), ("pad2", "I"), ("pad3", "I"), ("pad4", "I"),
]
_SLICER = [
    ("bottom_lift_height2", "f"), ("bottom_lift_speed2", "f"), ("lift_height2", "f"), ("lift_speed2", "f"),
    ("retract_height2", "f"), ("retract_speed2", "f"), ("rest_after_lift", "f"), ("machine_offset", "I"),
    ("machine_size", "I"), ("aa_flag", "B"), ("pad", "H"), ("per_layer", "B"), ("minutes", "I"), ("aa_level", "I"),
    ("software", "I"), ("rest_after_retract", "f"), ("rest_after_lift2", "f"), ("transition_layers", "I"),
    ("v4_offset", "I"), ("pad2", "I"), ("pad3", "I"),
]
_V4 = [
    ("bottom_retract_speed", "f"), ("bottom_retract_speed2", "f"), ("pad1", "I"), ("four1", "f"), ("pad2", "I"),
    ("four2", "f"), ("rest_after_retract", "f"), ("rest_after_lift", "f"), ("rest_before_lift", "f"),
    ("bottom_retract_height2", "f"), ("unknown1", "f"), ("unknown2", "I"), ("unknown3", "I"),
    ("last_layer", "I"), ("pad3", "I"), ("pad4", "I"), ("pad5", "I"), ("pad6", "I"), ("disclaimer_offset", "I"),
    ("disclaimer_size", "I"), ("resin_offset", "I"),
]
_LAYER = [
    ("z", "f"), ("exposure", "f"), ("light_off", "f"), ("offset", "I"), ("size", "I"), ("page", "I"),
    ("table_size", "I"), ("unknown3", "I"), ("unknown4", "I"),
]
_LAYER_EX = [
    ("total_size", "I"), ("lift_height", "f"), ("lift_speed", "f"), ("lift_height2", "f"), ("lift_speed2", "f"),
    ("retract_speed", "f"), ("retract_height2", "f"), ("retract_speed2", "f"), ("rest_before_lift", "f"),
    ("rest_after_lift", "f"), ("rest_after_retract", "f"), ("pwm", "f"),
]


def _read(fields, data: bytes, at: int) -> dict:
    fmt = "<" + "".join(code for _, code in fields)
    if at + struct.calcsize(fmt) > len(data):
        raise ValueError(f"record at {at} runs past the end of the file ({len(data)} bytes)")
    return dict(zip((name for name, _ in fields), struct.unpack_from(fmt, data, at), strict=True))


def _size(fields) -> int:
    return struct.calcsize("<" + "".join(code for _, code in fields))


@dataclass
class Preview:
    width: int
    height: int
    rgb: np.ndarray  # (height, width, 3) uint8, channels expanded from 5 bits as value << 3
    words: int  # 16-bit words in the data


@dataclass
class CtbFile:
    """Everything in a CTB file; layers are decoded on demand (:meth:`runs`, :meth:`image`)."""

    path: Path
    data: bytes
    header: dict
    params: dict
    slicer: dict
    machine: str
    v4: dict | None
    previews: list[Preview]
    layers: list[dict]
    layers_ex: list[dict] | None
    extra: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.header["res_y"], self.header["res_x"]

    def layer_bytes(self, i: int) -> bytes:
        """Layer ``i``'s RLE7 bytes, decrypted when the header has a key."""
        e = self.layers[i]
        at = e["page"] * (1 << 32) + e["offset"]
        raw = self.data[at : at + e["size"]]
        if len(raw) != e["size"]:
            raise ValueError(f"layer {i}: data runs past the end of the file")
        key = self.header["key"]
        return raw if key == 0 else _xor(raw, key, i)

    def segments(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(value7 uint8, length int64) of every RLE7 record of layer ``i``, in order (blank ones included)."""
        return decode_rle7(self.layer_bytes(i), self.shape[0] * self.shape[1])

    def runs(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Layer ``i``'s non-blank pixels as (start, length, grey8), grey8 = (value7 << 1) | 1, neighbours with the
        same grey merged."""
        v, n = self.segments(i)
        start = np.cumsum(n) - n
        keep = v > 0
        return canonical(start[keep], n[keep], (v[keep].astype(np.uint8) << 1) | 1)

    def image(self, i: int) -> np.ndarray:
        """Layer ``i`` as an 8-bit (rows, cols) image, greys as a reader expands them."""
        v, n = self.segments(i)
        grey = np.where(v > 0, (v.astype(np.uint8) << 1) | 1, 0).astype(np.uint8)
        return np.repeat(grey, n).reshape(self.shape)


def canonical(start, length, grey) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs (row-major start, length, grey), sorted, with touching neighbours of equal grey merged (also across a
    row end): one form for two descriptions of the same pixels."""
    start = np.asarray(start, np.int64)
    length = np.asarray(length, np.int64)
    grey = np.asarray(grey, np.uint8)
    if start.size == 0:
        return start, length, grey
    joins = (start[1:] == start[:-1] + length[:-1]) & (grey[1:] == grey[:-1])
    first = np.flatnonzero(np.concatenate(([True], ~joins)))
    return start[first], np.add.reduceat(length, first), grey[first]


def _xor(raw: bytes, key: int, index: int) -> bytes:
    """catibo's keystream for layer ``index``: c = key·0x2D83CDAC + 0xD8A83423, X0 = (index·0x1E1530CD +
    0xEC3D47CD)·c, X[n+1] = X[n] + c (mod 2^32), each word little-endian XORed over the data."""
    m = 0xFFFFFFFF
    c = (key * 0x2D83CDAC + 0xD8A83423) & m
    x0 = ((index * 0x1E1530CD + 0xEC3D47CD) * c) & m
    nw = (len(raw) + 3) // 4
    words = (np.uint64(x0) + np.arange(nw, dtype=np.uint64) * np.uint64(c)) & np.uint64(m)
    stream = words.astype("<u4").view(np.uint8)[: len(raw)]
    return (np.frombuffer(raw, np.uint8) ^ stream).tobytes()


def decode_rle7(data: bytes, n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """(value7, length) of each RLE7 record: a byte ``v | 0x80·run``, for a run 1-4 length bytes, big-endian, their
    count told by the first's top bits (0xxxxxxx, 10xxxxxx, 110xxxxx, 1110xxxx). Checks that the records cover
    exactly ``n_pixels`` and end with the data."""
    b = np.frombuffer(data, np.uint8)
    n = b.size
    if n == 0:
        raise ValueError("empty layer data")
    nxt_byte = np.append(b[1:], 0).astype(np.int64)
    extra = np.select([nxt_byte < 0x80, nxt_byte < 0xC0, nxt_byte < 0xE0, nxt_byte < 0xF0], [1, 2, 3, 4], 0)
    size = np.where(b & 0x80, 1 + extra, 1)
    bad = (b & 0x80).astype(bool) & (extra == 0)
    jump = np.minimum(np.arange(n) + np.where(size > 0, size, 1), n)
    jump = np.append(jump, n)  # n: past the end, a fixed point
    reached = np.zeros(n + 1, bool)
    reached[0] = True
    for _ in range(max(1, int(np.ceil(np.log2(n + 1))) + 1)):  # pointer doubling: 2^k records per step
        reached[jump[np.flatnonzero(reached)]] = True
        jump = jump[jump]
    starts = np.flatnonzero(reached[:n])
    if bad[starts].any():
        raise ValueError(f"bad run length code at byte {int(starts[bad[starts]][0])}")
    ends = starts + size[starts]
    if ends[-1] != n or np.any(ends[:-1] != starts[1:]):
        raise ValueError("records do not end with the data")
    value = b[starts] & 0x7F
    length = np.ones(starts.size, np.int64)
    k = size[starts] - 1  # length bytes
    first = np.where(k > 0, b[np.minimum(starts + 1, n - 1)].astype(np.int64), 0)
    length = np.where(k == 1, first, length)
    lead_mask = np.select([k == 2, k == 3, k == 4], [0x3F, 0x1F, 0x0F], 0xFF)
    acc = first & lead_mask
    for j in (2, 3, 4):
        more = k >= j
        nb = b[np.minimum(starts + j, n - 1)].astype(np.int64)
        acc = np.where(more, (acc << 8) | nb, acc)
    length = np.where(k >= 2, acc, length)
    if (length <= 0).any():
        raise ValueError("zero-length run")
    if int(length.sum()) != n_pixels:
        raise ValueError(f"layer covers {int(length.sum())} pixels, not {n_pixels}")
    return value.astype(np.uint8), length


def decode_rgb15(data: bytes, width: int, height: int) -> tuple[np.ndarray, int]:
    """A preview's pixels: 16-bit words R 15-11, G 10-6, B 4-0; bit 5 set: the next word 0x3nnn gives nnn more
    copies. Returns the (height, width, 3) image (channels << 3) and the word count."""
    w = np.frombuffer(data, "<u2")
    out = []
    i = 0
    while i < w.size:  # previews are small: a plain loop
        word = int(w[i])
        count = 1
        if word & 0x20:
            nxt = int(w[i + 1])
            if nxt & 0xF000 != 0x3000:
                raise ValueError(f"preview run word {nxt:#06x} is not 0x3nnn")
            count += nxt & 0x0FFF
            i += 1
        out.append((word, count))
        i += 1
    words = np.array([c for c, _ in out], np.uint16)
    counts = np.array([n for _, n in out], np.int64)
    px = np.repeat(words, counts)
    if px.size != width * height:
        raise ValueError(f"preview has {px.size} pixels, not {width}x{height}")
    rgb = np.stack([(px >> 11) & 0x1F, (px >> 6) & 0x1F, px & 0x1F], axis=-1).astype(np.uint8) << 3
    return rgb.reshape(height, width, 3), int(w.size)


def read_ctb(path) -> CtbFile:
    """Read a CTB file (versions 2-4); ValueError where it is not one or is inconsistent."""
    path = Path(path)
    data = path.read_bytes()
    h = _read(_HEADER, data, 0)
    if h["magic"] not in MAGICS:
        raise ValueError(f"{path}: magic {h['magic']:#x} is not an unencrypted CTB")
    params = _read(_PARAMS, data, h["params_offset"]) if h["params_offset"] else {}
    slicer = _read(_SLICER, data, h["slicer_offset"]) if h["slicer_offset"] else {}
    machine = ""
    if slicer.get("machine_size"):
        machine = data[slicer["machine_offset"] : slicer["machine_offset"] + slicer["machine_size"]].decode("ascii")
    v4 = _read(_V4, data, slicer["v4_offset"]) if h["version"] >= 4 else None
    previews = []
    for at in (h["large_preview"], h["small_preview"]):
        if at:
            w, hh, off, size = struct.unpack_from("<4I", data, at)
            rgb, words = decode_rgb15(data[off : off + size], w, hh)
            previews.append(Preview(w, hh, rgb, words))
    n = h["layer_count"]
    sets = max(1, h["level_sets"])
    layers = [_read(_LAYER, data, h["layer_table"] + i * _size(_LAYER)) for i in range(n * sets)]
    layers_ex = None
    if h["version"] >= 3:
        layers_ex = []
        for e in layers[:n]:
            at = e["page"] * (1 << 32) + e["offset"] - 84
            copy = _read(_LAYER, data, at)
            ex = _read(_LAYER_EX, data, at + _size(_LAYER))
            ex["copy"] = copy
            layers_ex.append(ex)
    return CtbFile(path, data, h, params, slicer, machine, v4, previews, layers, layers_ex)


def reference_runs(mask_or_tile, cols: int, row0: int = 0, col0: int = 0):
    """The canonical runs (:func:`canonical`) a CTB reader should get back for 8-bit greys ``mask_or_tile`` (an
    (h, w) array at (row0, col0) of a display ``cols`` wide): grey g → (g >> 1) << 1 | 1, 0 where g >> 1 is 0."""
    a = np.asarray(mask_or_tile, np.uint8)
    q = a >> 1
    g = np.where(q == 0, 0, (q << 1) | 1).astype(np.uint8)
    h, w = g.shape
    if not h or not w:
        return canonical([], [], [])
    change = np.ones((h, w), bool)
    change[:, 1:] = g[:, 1:] != g[:, :-1]
    r, c = np.nonzero(change)
    first = r * w + c
    ends = np.minimum(np.append(first[1:], h * w), (r + 1) * w)
    grey = g.reshape(-1)[first]
    keep = grey != 0
    start = (r[keep] + row0).astype(np.int64) * cols + c[keep] + col0
    return canonical(start, (ends - first)[keep], grey[keep])
