"""A ``.cxdlpv4`` reader for the tests, written from the format description (UVtools' ``Scripts/010 Editor/
cxdlpv4.bt`` and ``docs/research/CXDLP.md`` section 7), apart from the writer (``gpuslice/raster/cxdlpv4.py``).

It checks what UVtools checks before reading (the magic's length and ``CXSW3D`` prefix, the CRC-32 with a zero start
and no final inversion over every byte before the last four), then reads the header (big endian up to the model code,
little endian after), the previews (RGB15 run-length words), the print parameters and slicer info, the layer table,
each layer's own 11-float record and its RLE7 image (decoded by the CTB reader's vectorised decoder: the same run
coding, which that reader has from catibo's description, not from the writer).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from ctb_reader import canonical, decode_rle7

_HEAD = [("res_x", "H"), ("res_y", "H"), ("bed_x", "f"), ("bed_y", "f"), ("bed_z", "f"), ("print_height", "f"),
         ("layer_height", "f"), ("bottom_layers", "I"), ("small_preview", "I"), ("layer_table", "I"),
         ("layer_count", "I"), ("large_preview", "I"), ("print_time", "I"), ("projector", "I"), ("params_offset", "I"),
         ("params_size", "I"), ("aa_level", "I"), ("pwm", "H"), ("bottom_pwm", "H"), ("key", "I"),
         ("slicer_offset", "I"), ("slicer_size", "I")]
_PARAMS = [("bottom_lift_height", "f"), ("bottom_lift_speed", "f"), ("lift_height", "f"), ("lift_speed", "f"),
           ("retract_speed", "f"), ("volume_ml", "f"), ("weight_g", "f"), ("cost", "f"), ("bottom_light_off", "f"),
           ("light_off", "f"), ("bottom_layers", "I"), ("exposure", "f"), ("bottom_exposure", "f"), ("pad1", "I"),
           ("pad2", "I"), ("pad3", "I"), ("pad4", "I")]
_SLICER = [("bottom_lift_height2", "f"), ("bottom_lift_speed2", "f"), ("lift_height2", "f"), ("lift_speed2", "f"),
           ("retract_height2", "f"), ("retract_speed2", "f"), ("rest_after_lift", "f"), ("per_layer", "I"),
           ("minutes", "I"), ("aa_level", "I"), ("software", "I"), ("rest_after_retract", "f"),
           ("rest_before_lift", "f"), ("exposure", "f"), ("bottom_exposure", "f"), ("rest_after_lift2", "f"),
           ("transition_layers", "I"), ("pad1", "I"), ("pad2", "I")]
_LAYER = [("z", "f"), ("exposure", "f"), ("light_off", "f"), ("address", "I"), ("size", "I"), ("data_type", "I"),
          ("centroid", "I"), ("largest_area", "I"), ("unknown1", "I"), ("unknown2", "I")]
_LAYER_EX = [("lift_height", "f"), ("lift_speed", "f"), ("lift_height2", "f"), ("lift_speed2", "f"),
             ("retract_speed", "f"), ("retract_height2", "f"), ("retract_speed2", "f"), ("rest_before_lift", "f"),
             ("rest_after_lift", "f"), ("rest_after_retract", "f"), ("pwm", "f")]


def _read(fields, data: bytes, at: int) -> tuple[dict, int]:
    fmt = "<" + "".join(c for _, c in fields)
    values = struct.unpack_from(fmt, data, at)
    return dict(zip([k for k, _ in fields], values, strict=True)), at + struct.calcsize(fmt)


def _rgb15(words: np.ndarray, w: int, h: int) -> np.ndarray:
    """Decode RGB15 run-length words (bit 5 set: the next word is 0x3000 | (count - 1)) to (h, w, 3) uint8."""
    out, i = [], 0
    while i < words.size:
        v = int(words[i])
        count = 1
        if v & 0x20:
            i += 1
            assert int(words[i]) & 0xF000 == 0x3000, "bad RGB15 repeat word"
            count = (int(words[i]) & 0x0FFF) + 1
        out.extend([v] * count)
        i += 1
    a = np.array(out, np.int64)
    assert a.size == w * h, f"preview decodes to {a.size} pixels, not {w}x{h}"
    rgb = np.stack([(a >> 11) & 31, (a >> 6) & 31, a & 31], axis=1) << 3
    return rgb.reshape(h, w, 3).astype(np.uint8)


@dataclass
class Cxdlpv4:
    data: bytes
    model: str
    version: int
    header: dict
    params: dict
    slicer: dict
    previews: list[np.ndarray] = field(default_factory=list)  # small, large: (h, w, 3) uint8
    layers: list[dict] = field(default_factory=list)  # table entry + "ex" (the layer's own record) + "rle" bytes

    @property
    def n_layers(self) -> int:
        return len(self.layers)

    def runs(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Layer ``i``'s lit pixels as canonical runs (row-major start, length, grey widened from 7 bits)."""
        h = self.header
        v, n = decode_rle7(self.layers[i]["rle"], h["res_x"] * h["res_y"])
        start = np.cumsum(n) - n
        keep = v > 0
        return canonical(start[keep], n[keep], (v[keep].astype(np.uint8) << 1) | 1)

    def layer_image(self, i: int) -> np.ndarray:
        """Layer i as (res_y, res_x) uint8, greys widened from 7 bits (0 stays 0, v -> (v << 1) | 1)."""
        h = self.header
        v, n = decode_rle7(self.layers[i]["rle"], h["res_x"] * h["res_y"])
        grey = np.where(v > 0, (v.astype(np.uint8) << 1) | 1, 0).astype(np.uint8)
        return np.repeat(grey, n).reshape(h["res_y"], h["res_x"])


def read_cxdlpv4(path: str | Path) -> Cxdlpv4:
    data = Path(path).read_bytes()
    (size,) = struct.unpack_from(">I", data, 0)
    magic = data[4 : 4 + size]
    assert magic.rstrip(b"\0") == magic[:-1] and magic.startswith(b"CXSW3D"), f"bad magic {magic!r}"
    crc = zlib.crc32(data[:-4], 0xFFFFFFFF) ^ 0xFFFFFFFF  # (zlib's CRC-32 with its start and final inversion undone)
    assert struct.unpack_from(">I", data, len(data) - 4)[0] == crc, "checksum fails"
    at = 4 + size
    (version,) = struct.unpack_from(">H", data, at)
    (mlen,) = struct.unpack_from(">I", data, at + 2)
    model_raw = data[at + 6 : at + 6 + mlen]
    assert model_raw.endswith(b"\0"), "model code not NUL-terminated"
    header, _ = _read(_HEAD, data, at + 6 + mlen)
    assert header["key"] == 0
    params, _ = _read(_PARAMS, data, header["params_offset"])
    assert header["params_size"] == 68 and header["slicer_size"] == 76
    slicer, _ = _read(_SLICER, data, header["slicer_offset"])
    previews = []
    for off in (header["small_preview"], header["large_preview"]):
        w, h, img_at, length = struct.unpack_from("<4I", data, off)
        assert img_at == off + 32
        previews.append(_rgb15(np.frombuffer(data, "<u2", length // 2, img_at), w, h))
    layers = []
    at = header["layer_table"]
    for _ in range(header["layer_count"]):
        entry, at = _read(_LAYER, data, at)
        ex, rle_at = _read(_LAYER_EX, data, entry["address"])
        entry["ex"] = ex
        entry["rle"] = data[rle_at : entry["address"] + entry["size"]]
        assert entry["data_type"] == 0 and entry["size"] >= 44
        layers.append(entry)
    return Cxdlpv4(data, model_raw[:-1].decode("ascii"), version, header, params, slicer, previews, layers)
