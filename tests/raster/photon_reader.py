"""A reader of Anycubic Photon Workshop files (``.pwmx``, ``.pwma``, ``.pm3``, ``.pwmb``, ``.pm5s``, ...), written
for the tests and kept apart from the writer (:mod:`gpuslice.raster.photon`): it parses what the file says, by the
layout public readers describe (UVtools' ``AnycubicFile.cs`` and ``PhotonWorkshop.bt``, ole00's ``pwmx_info``),
with none of the writer's code or tables.

Layout (little endian): a file mark (``ANYCUBIC``, version 1/515/516/517/518, table count, then table addresses),
then tables each opened by a 12-byte name and a uint32 length: HEADER, PREVIEW, the layer grey table (515+; no name),
LAYERDEF (one 32-byte record per layer), EXTRA and MACHINE (516+), SOFTWARE and MODEL (517+), SUBIMGS and PREVIEW2
(518), then the layer images. A layer image is PW0 run-length code over the whole display, row after row: a byte's
high nibble is the colour code c (grey ``17·c``); for c = 0 or 15 the low nibble and the next byte are a 12-bit
count, otherwise the low nibble is the count.
"""

from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

HEADER_FIELDS = (
    ("pixel_um", "f"), ("layer_height", "f"), ("exposure", "f"), ("wait_before_cure", "f"),
    ("bottom_exposure", "f"), ("bottom_layers", "f"), ("lift_height", "f"), ("lift_speed", "f"),
    ("retract_speed", "f"), ("volume_ml", "f"), ("antialiasing", "I"), ("res_x", "I"), ("res_y", "I"),
    ("weight_g", "f"), ("price", "f"), ("currency", "I"), ("per_layer", "I"), ("print_time", "I"),
    ("transition_layers", "I"), ("transition_type", "I"),
)


def _name(buf: bytes) -> str:
    return bytes(buf).split(b"\0", 1)[0].decode("latin-1")


@dataclass
class PhotonFile:
    """What a Photon Workshop file holds, by table (dicts of field → value), with its layers' images on demand."""

    path: Path
    data: Any
    version: int
    n_tables: int
    addresses: dict[str, int]
    header: dict[str, Any]
    header_length: int
    preview: dict[str, Any] | None = None
    preview2: dict[str, Any] | None = None
    colors: dict[str, Any] | None = None
    layers: list[dict[str, Any]] = field(default_factory=list)
    layerdef_length: int = 0
    extra: dict[str, Any] | None = None
    machine: dict[str, Any] | None = None
    software: dict[str, Any] | None = None
    model: dict[str, Any] | None = None
    sublayers: dict[str, Any] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of a layer image: (res_y, res_x)."""
        return int(self.header["res_y"]), int(self.header["res_x"])

    def layer_bytes(self, i: int) -> np.ndarray:
        d = self.layers[i]
        return np.frombuffer(self.data, np.uint8, d["length"], d["address"])

    def layer_runs(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Layer ``i`` as maximal runs of one non-zero grey: (start, length, grey), start the row-major pixel index
        (int64), grey ``17·code`` (uint8); checks that the records cover the display exactly."""
        return decode_pw0(self.layer_bytes(i), self.shape[0] * self.shape[1])

    def layer_image(self, i: int) -> np.ndarray:
        """Layer ``i`` as a (rows, cols) uint8 image."""
        rows, cols = self.shape
        start, length, grey = self.layer_runs(i)
        out = np.zeros(rows * cols, np.uint8)
        owner = np.repeat(np.arange(start.size), length)
        local = np.arange(owner.size) - np.repeat(np.cumsum(length) - length, length)
        out[start[owner] + local] = grey[owner]
        return out.reshape(rows, cols)


def decode_pw0(code: np.ndarray, n_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """PW0 bytes → the non-zero runs (start, length, grey), merged where equal greys touch; ``ValueError`` unless
    the records cover exactly ``n_pixels`` pixels, each at least one (Photon Workshop's files hold no empty record).

    Record starts without a loop: a byte after a one-byte record or after a record's second byte starts a record,
    so every byte that follows a byte whose nibble is neither 0 nor 15 starts one, and inside a stretch of bytes
    whose nibbles are 0 or 15 the starts alternate from the stretch's first byte."""
    b = np.asarray(code, np.uint8)
    n = b.size
    if n == 0:
        raise ValueError("empty layer image")
    hi = b >> 4
    two = (hi == 0) | (hi == 15)
    idx = np.arange(n, dtype=np.int64)
    last_one = np.maximum.accumulate(np.where(~two, idx, -1))  # last one-byte-nibble byte at or before j
    before = np.empty(n, np.int64)  # bytes of 0/15 nibble right before i
    before[0] = 0
    before[1:] = idx[:-1] - last_one[:-1]
    starts = np.flatnonzero(before % 2 == 0)
    s_two = two[starts]
    if s_two[-1] and starts[-1] + 1 >= n:
        raise ValueError("layer image ends inside a two-byte record")
    nxt = b[np.minimum(starts + 1, n - 1)].astype(np.int64)
    low = (b[starts] & 0xF).astype(np.int64)
    count = np.where(s_two, (low << 8) | nxt, low)
    colour = hi[starts]
    if np.any(count == 0):
        raise ValueError(f"a record of length 0 at byte {int(starts[np.argmax(count == 0)])}")
    if count.sum() != n_pixels:
        raise ValueError(f"layer image covers {int(count.sum())} pixels, the display has {n_pixels}")
    pos = np.cumsum(count) - count
    keep = colour != 0
    pos, count, colour = pos[keep], count[keep], colour[keep]
    if pos.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8)
    joins = (pos[1:] == pos[:-1] + count[:-1]) & (colour[1:] == colour[:-1])
    head = np.flatnonzero(np.concatenate(([True], ~joins)))
    length = np.add.reduceat(count, head)
    return pos[head], length, (colour[head] * 17).astype(np.uint8)


def _table(buf, at: int, name: str) -> tuple[int, int]:
    """(length field, first byte after the 16-byte table opening) of the table ``name`` at ``at``."""
    got = _name(buf[at : at + 12])
    if got != name:
        raise ValueError(f"table {name} expected at {at}, found {got!r}")
    return struct.unpack_from("<I", buf, at + 12)[0], at + 16


def _rgb565(buf, at: int, w: int, h: int) -> np.ndarray:
    return np.frombuffer(buf, "<u2", w * h, at).reshape(h, w)


def read_photon(path: str | Path) -> PhotonFile:
    """Parse a Photon Workshop file (every table its version holds); layer images are decoded on demand."""
    p = Path(path)
    with open(p, "rb") as fh:
        buf = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    if _name(buf[:12]) != "ANYCUBIC":
        raise ValueError(f"{p}: not a Photon Workshop file")
    version, n_tables = struct.unpack_from("<II", buf, 12)
    names = ["header", "software", "preview", "colors", "layerdef", "extra"]
    if version >= 516:
        names.append("machine")
    names.append("images")
    if version >= 517:
        names.append("model")
    if version >= 518:
        names += ["sublayers", "preview2"]
    addr = dict(zip(names, struct.unpack_from(f"<{len(names)}I", buf, 20), strict=True))
    length, at = _table(buf, addr["header"], "HEADER")
    values = struct.unpack_from("<" + "".join(t for _, t in HEADER_FIELDS), buf, at)
    header: dict[str, Any] = dict(zip((k for k, _ in HEADER_FIELDS), values, strict=True))
    at += 80
    if length >= 84:
        header["advanced_mode"] = struct.unpack_from("<I", buf, at)[0]
    if length >= 92:
        header["grey"], header["blur_level"], header["resin_type"] = struct.unpack_from("<HHI", buf, at + 4)
    if length >= 96:
        header["intelligent_mode"] = struct.unpack_from("<I", buf, at + 12)[0]
    f = PhotonFile(p, buf, version, n_tables, addr, header, length)
    if addr["preview"]:
        length, at = _table(buf, addr["preview"], "PREVIEW")
        w, mark, h = struct.unpack_from("<III", buf, at)
        f.preview = {"length": length, "width": w, "mark": mark, "height": h, "rgb565": _rgb565(buf, at + 12, w, h)}
    if version >= 515 and addr["colors"]:
        full, count = struct.unpack_from("<II", buf, addr["colors"])
        grey = list(buf[addr["colors"] + 8 : addr["colors"] + 8 + count])
        unknown = struct.unpack_from("<I", buf, addr["colors"] + 8 + count)[0]
        f.colors = {"use_full_greyscale": full, "count": count, "grey": grey, "unknown": unknown}
    f.layerdef_length, at = _table(buf, addr["layerdef"], "LAYERDEF")
    (n,) = struct.unpack_from("<I", buf, at)
    recs = np.frombuffer(buf, np.dtype([("address", "<u4"), ("length", "<u4"), ("lift_height", "<f4"),
                                        ("lift_speed", "<f4"), ("exposure", "<f4"), ("thickness", "<f4"),
                                        ("nonzero", "<u4"), ("padding", "<u4")]), n, at + 4)
    f.layers = [{k: (int(r[k]) if k in ("address", "length", "nonzero", "padding") else float(r[k]))
                 for k in recs.dtype.names} for r in recs]
    if version >= 516 and addr["extra"]:
        length, at = _table(buf, addr["extra"], "EXTRA")
        v = struct.unpack_from("<I6fI6f", buf, at)
        f.extra = {"length": length, "bottom_count": v[0], "bottom": [v[1:4], v[4:7]], "normal_count": v[7],
                   "normal": [v[8:11], v[11:14]]}
    if version >= 516 and addr["machine"]:
        length, at = _table(buf, addr["machine"], "MACHINE")
        m: dict[str, Any] = {"length": length, "name": _name(buf[at : at + 96]),
                             "image_format": _name(buf[at + 96 : at + 112])}
        (m["max_aa"], m["properties"], m["display_width"], m["display_height"], m["machine_z"],
         m["max_version"], m["background"]) = struct.unpack_from("<IIfffII", buf, at + 112)
        if length >= 224:
            m["pixel_width_um"], m["pixel_height_um"] = struct.unpack_from("<ff", buf, at + 140)
            m["display_count"] = struct.unpack_from("<I", buf, at + 180)[0]
            m["res_x"], m["res_y"] = struct.unpack_from("<HH", buf, at + 188)
        f.machine = m
    if version >= 517 and addr["software"]:
        at = addr["software"]
        f.software = {"name": _name(buf[at : at + 32]), "length": struct.unpack_from("<I", buf, at + 32)[0],
                      "version": _name(buf[at + 36 : at + 68]), "os": _name(buf[at + 68 : at + 132]),
                      "opengl": _name(buf[at + 132 : at + 164])}
    if version >= 517 and addr["model"]:
        length, at = _table(buf, addr["model"], "MODEL")
        v = struct.unpack_from("<6fIf", buf, at)
        f.model = {"length": length, "min": v[0:3], "max": v[3:6], "supports": v[6], "support_density": v[7]}
    if version >= 518 and addr["sublayers"]:
        length, at = _table(buf, addr["sublayers"], "SUBIMGS")
        count, index = struct.unpack_from("<II", buf, at)
        sub = np.frombuffer(buf, np.dtype([("address", "<u4"), ("length", "<u4"), ("nonzero", "<u4"),
                                           ("padding", "<8f4")]), count, at + 8)
        f.sublayers = {"length": length, "count": count, "index": index, "records": sub.copy()}
    if version >= 518 and addr["preview2"]:
        length, at = _table(buf, addr["preview2"], "PREVIEW2")
        w, bg1, bg2, h = struct.unpack_from("<IHHI", buf, at)
        f.preview2 = {"length": length, "width": w, "background": (bg1, bg2), "height": h,
                      "rgb565": _rgb565(buf, at + 12, w, h)}
    return f
