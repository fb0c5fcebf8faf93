"""A reader of Creality Halot ``.cxdlp`` files (versions 2 and 3), written for the tests and kept apart from the writer
(:mod:`gpuslice.raster.cxdlp`): it parses what the file says, by the layout public readers describe (UVtools'
``CrealityCXDLPFile.cs`` and its 010 Editor template; docs/research/CXDLP.md), with none of the writer's code.

Big endian throughout: u32 9 + ``CXSW3DV2\\0``, u16 version, u32 length + model code + NUL, u16 layers, resolution
x and y, 64 bytes, previews 116², 290², 290² RGB565 each followed by CRLF, three u32-length UTF-16 texts (display
width, height, layer height, mm), eleven u16 settings, u32 area per layer + CRLF, (v3) a block of two u32-length
strings and 20 bytes + CRLF, then per layer u32 area, u32 line count, 6-byte lines, CRLF; u32-length closing mark and
a u32 checksum (v3: CRC-32 with a zero start and no final inversion, over every byte before it; v2: the XOR of them).
A line: 40 bits (13 start row, 13 end row inclusive, 14 column), then the grey.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

SETTINGS = ("exposure_tenths", "wait_before_cure", "bottom_exposure", "bottom_layers", "bottom_lift_height",
            "bottom_lift_speed", "lift_height", "lift_speed", "retract_speed", "bottom_light_pwm", "light_pwm")


@dataclass
class CxdlpFile:
    path: Path
    version: int
    model: str
    n_layers: int
    res_x: int
    res_y: int
    block: bytes
    previews: list[np.ndarray]
    display_mm: tuple[float, float]
    layer_height: float
    settings: dict[str, int]
    areas: np.ndarray
    info: dict[str, Any] | None
    layers: list[dict[str, Any]] = field(default_factory=list)
    footer: bytes = b""
    checksum: int = 0

    def layer_image(self, i: int) -> np.ndarray:
        """Layer ``i`` as a (res_y, res_x) uint8 image: each line drawn down its column."""
        img = np.zeros((self.res_y, self.res_x), np.uint8)
        lines = self.layers[i]["lines"]
        for x, y0, y1, g in lines.tolist():
            img[y0 : y1 + 1, x] = g
        return img


def _text(buf: bytes, at: int) -> tuple[str, int]:
    (n,) = struct.unpack_from(">I", buf, at)
    return buf[at + 4 : at + 4 + n].decode("utf-16-be"), at + 4 + n


def _cstring(buf: bytes, at: int) -> tuple[str, int]:
    (n,) = struct.unpack_from(">I", buf, at)
    raw = buf[at + 4 : at + 4 + n]
    if not raw.endswith(b"\0"):
        raise ValueError(f"string at {at} is not NUL-terminated")
    return raw[:-1].decode("utf-8"), at + 4 + n


def _crlf(buf: bytes, at: int) -> int:
    if buf[at : at + 2] != b"\r\n":
        raise ValueError(f"CRLF expected at {at}, found {buf[at:at + 2]!r}")
    return at + 2


def decode_lines(raw: bytes) -> np.ndarray:
    """(n, 4) int64 lines (x, y0, y1, grey) from their 6-byte records."""
    a = np.frombuffer(raw, np.uint8).reshape(-1, 6).astype(np.uint64)
    v = np.zeros(a.shape[0], np.uint64)
    for k in range(5):
        v = (v << np.uint64(8)) | a[:, k]
    y0 = (v >> np.uint64(27)) & np.uint64(0x1FFF)
    y1 = (v >> np.uint64(14)) & np.uint64(0x1FFF)
    x = v & np.uint64(0x3FFF)
    return np.stack([x, y0, y1, a[:, 5]], axis=1).astype(np.int64)


def read_cxdlp(path: str | Path) -> CxdlpFile:
    p = Path(path)
    buf = p.read_bytes()
    (n,) = struct.unpack_from(">I", buf, 0)
    magic = buf[4 : 4 + n]
    if not magic.startswith(b"CXSW3D"):
        raise ValueError(f"{p}: magic {magic!r}")
    at = 4 + n
    (version,) = struct.unpack_from(">H", buf, at)
    model, at = _cstring(buf, at + 2)
    n_layers, res_x, res_y = struct.unpack_from(">HHH", buf, at)
    at += 6
    block = buf[at : at + 64]
    at += 64
    previews = []
    for w, h in ((116, 116), (290, 290), (290, 290)):
        previews.append(np.frombuffer(buf, ">u2", w * h, at).reshape(h, w))
        at = _crlf(buf, at + 2 * w * h)
    width, at = _text(buf, at)
    height, at = _text(buf, at)
    lh, at = _text(buf, at)
    settings = dict(zip(SETTINGS, struct.unpack_from(">11H", buf, at), strict=True))
    at += 22
    areas = np.frombuffer(buf, ">u4", n_layers, at).astype(np.int64)
    at = _crlf(buf, at + 4 * n_layers)
    info = None
    if version >= 3:
        software, at = _cstring(buf, at)
        material, at = _cstring(buf, at)
        rest = buf[at : at + 20]
        info = {"software": software, "material": material, "aa_enabled": rest[15], "aa_min": rest[16],
                "aa_max": rest[17], "blur_enabled": rest[18], "blur_level": rest[19], "raw": rest}
        at = _crlf(buf, at + 20)
    f = CxdlpFile(p, version, model, n_layers, res_x, res_y, block, previews, (float(width), float(height)),
                  float(lh), settings, areas, info)
    for _ in range(n_layers):
        area, count = struct.unpack_from(">II", buf, at)
        lines = decode_lines(buf[at + 8 : at + 8 + 6 * count])
        at = _crlf(buf, at + 8 + 6 * count)
        f.layers.append({"area": area, "lines": lines})
    (k,) = struct.unpack_from(">I", buf, at)
    f.footer = buf[at + 4 : at + 4 + k]
    at += 4 + k
    if at + 4 != len(buf):
        raise ValueError(f"{p}: {len(buf) - at} bytes after the layers and closing mark, 4 expected")
    (f.checksum,) = struct.unpack_from(">I", buf, at)
    body = buf[:at]
    want = (zlib.crc32(body, 0xFFFFFFFF) ^ 0xFFFFFFFF) if version >= 3 else \
        int(np.bitwise_xor.reduce(np.frombuffer(body, np.uint8)))
    if f.checksum != want:
        raise ValueError(f"{p}: checksum {f.checksum:#x}, computed {want:#x}")
    return f
