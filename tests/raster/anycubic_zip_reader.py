"""A reader of Anycubic's zip archives (``.pm7``, ``.pm7m``, ``.pwsz``), written for the tests and kept apart from the
writer (:mod:`gpuslice.raster.anycubic_zip`): it parses what the archive says, by the layout public readers describe
(UVtools' ``AnycubicZipFile.cs``; docs/research/ANYCUBIC-ZIP.md), with none of the writer's code or tables.

Members: ``anycubic_photon_resins.pwsp`` (JSON: ``machine_type`` with the resolution and pixel pitch µm,
``machine_extern`` with the resins whose ``slicepara`` / ``slice_extpara`` are the print settings),
``layers_controller.conf`` (JSON: per layer exposure, Z, thickness, lift), ``print_info.json``, ``software_info.conf``,
``lcd_function.json``, ``preview_images/preview_<i>.png``, ``layer_images/layer_<i>.pw0Img`` (PW0, decoded by the
Photon reader's :func:`photon_reader.decode_pw0`), ``scene.slice`` (``ANYCUBIC-PWSZ``, 396-byte header, 64-byte layer
records, ``--->``) and ``calc_layer_volumes.data`` (16-byte header, 48-byte slab records), little endian.
"""

from __future__ import annotations

import io
import json
import struct
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from photon_reader import decode_pw0


@dataclass
class AnycubicZip:
    path: Path
    zf: zipfile.ZipFile
    pwsp: dict[str, Any]
    layers: list[dict[str, Any]]
    print_info: dict[str, Any]
    software: dict[str, Any]
    lcd: dict[str, Any]
    scene: dict[str, Any] = field(default_factory=dict)
    volumes: dict[str, Any] = field(default_factory=dict)

    @property
    def machine(self) -> dict[str, Any]:
        return self.pwsp["machine_type"]

    @property
    def resin(self) -> dict[str, Any]:
        """The active resin: the first of ``user_resins``, then ``factory_resins``, named by ``active_resins[0]``."""
        ext = self.pwsp["machine_extern"]
        want = ext["active_resins"][0]
        for r in ext["user_resins"] + ext["factory_resins"]:
            if r["property"]["name"] == want:
                return r
        raise ValueError(f"{self.path}: no resin named {want!r}")

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.machine["res_y"]), int(self.machine["res_x"])

    def layer_image(self, i: int) -> np.ndarray:
        rows, cols = self.shape
        code = np.frombuffer(self.zf.read(f"layer_images/layer_{i}.pw0Img"), np.uint8)
        start, length, grey = decode_pw0(code, rows * cols)
        out = np.zeros(rows * cols, np.uint8)
        for s, n, g in zip(start.tolist(), length.tolist(), grey.tolist(), strict=True):
            out[s : s + n] = g
        return out.reshape(rows, cols)

    def preview(self, i: int):
        from PIL import Image

        return Image.open(io.BytesIO(self.zf.read(f"preview_images/preview_{i}.png")))


def _scene(data: bytes) -> dict[str, Any]:
    magic = data[:16].split(b"\0", 1)[0]
    if magic != b"ANYCUBIC-PWSZ":
        raise ValueError(f"scene.slice: magic {magic!r}")
    software = data[16:80].split(b"\0", 1)[0].decode()
    kind, version, slice_type, unit, ratio, count = struct.unpack_from("<4IfI", data, 80)
    box = struct.unpack_from("<6f", data, 104)
    if data[388:392] != b"<---" or data[-4:] != b"--->":
        raise ValueError("scene.slice: section marks")
    (n,) = struct.unpack_from("<I", data, 392)
    if len(data) != 396 + 64 * n + 4:
        raise ValueError(f"scene.slice: {len(data)} bytes for {n} layers")
    rec = np.frombuffer(data, np.dtype([("z", "<f4"), ("area", "<f4"), ("xmin", "<f4"), ("ymin", "<f4"),
                                        ("xmax", "<f4"), ("ymax", "<f4"), ("objects", "<u4"), ("largest", "<f4"),
                                        ("zero", "<u4", 8)]), n, 396)
    return {"software": software, "binary_type": kind, "version": version, "slice_type": slice_type, "unit": unit,
            "ratio": ratio, "count": count, "box": box, "records": rec.copy()}


def _volumes(data: bytes) -> dict[str, Any]:
    magic, step, one, n = struct.unpack_from("<IfII", data, 0)
    if len(data) != 16 + 48 * n:
        raise ValueError(f"calc_layer_volumes.data: {len(data)} bytes for {n} entries")
    rec = np.frombuffer(data, np.dtype([("layer", "<u4"), ("z", "<f4"), ("thickness", "<f4"), ("zero", "<u4", 8),
                                        ("volume", "<f4")]), n, 16)
    return {"magic": magic, "step": step, "one": one, "records": rec.copy()}


def read_anycubic_zip(path: str | Path) -> AnycubicZip:
    p = Path(path)
    zf = zipfile.ZipFile(p)
    if zf.testzip() is not None:
        raise ValueError(f"{p}: a member fails its CRC")

    def js(name: str) -> dict[str, Any]:
        return json.loads(zf.read(name).decode("utf-8"))

    lc = js("layers_controller.conf")
    if not lc["paras"] or lc["count"] != len(lc["paras"]):
        raise ValueError(f"{p}: layers_controller.conf count {lc['count']} for {len(lc['paras'])} layers")
    out = AnycubicZip(p, zf, js("anycubic_photon_resins.pwsp"), lc["paras"], js("print_info.json"),
                      js("software_info.conf"), js("lcd_function.json"))
    out.scene = _scene(zf.read("scene.slice"))
    out.volumes = _volumes(zf.read("calc_layer_volumes.data"))
    return out
