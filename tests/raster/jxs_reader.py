"""A ``.jxs`` reader for the tests, written from the format description (``docs/research/UNIFORMATION.md`` section 2,
from UVtools' ``JXSFile.cs`` reader), apart from the writer (``gpuslice/raster/jxs.py``): the zip's members, the
``config.ini`` keys, the ``control.json`` program, and each layer's RGB PNG unpacked to display pixels (R, G, B =
columns 3j, 3j + 1, 3j + 2) through Pillow, which the writer does not use. :func:`replay` runs the program: the
platform's height and the light at each shown layer."""

from __future__ import annotations

import io
import json
import re
import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image


@dataclass
class Jxs:
    names: list[str]
    config: dict[str, str]
    control: dict
    zf: zipfile.ZipFile

    @property
    def n_layers(self) -> int:
        return int(self.config["NumLayers"])

    def layer_image(self, i: int) -> np.ndarray:
        """Layer ``i`` as (rows, 3 x PNG width) uint8 display pixels."""
        img = Image.open(io.BytesIO(self.zf.read(f"{i:05d}.png")))
        assert img.mode == "RGB", img.mode
        a = np.asarray(img, np.uint8)
        return a.reshape(a.shape[0], a.shape[1] * 3)


    def layer_quick(self, i: int) -> np.ndarray:
        """:meth:`layer_image` by inflating the PNG's IDAT here (its chunks parsed, an 8-bit RGB image with filter 0
        on every row checked): ~10x faster than Pillow at this size, for the every-layer checks."""
        data = self.zf.read(f"{i:05d}.png")
        at, idat, size = 8, [], None
        while at < len(data):
            (n,) = struct.unpack(">I", data[at : at + 4])
            kind, body = data[at + 4 : at + 8], data[at + 8 : at + 8 + n]
            if kind == b"IHDR":
                size = struct.unpack(">IIBBBBB", body)
                assert size[2:] == (8, 2, 0, 0, 0), size  # 8-bit RGB, no interlace
            elif kind == b"IDAT":
                idat.append(body)
            at += 12 + n
        w, h = size[0], size[1]
        rows = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, 1 + 3 * w)
        if rows[:, 0].any():  # (another filter: Pillow undoes it)
            return self.layer_image(i)
        return rows[:, 1:]


def read_jxs(path: str | Path) -> Jxs:
    zf = zipfile.ZipFile(path)
    names = zf.namelist()
    assert "config.ini" in names and "control.json" in names
    config = {}
    for line in zf.read("config.ini").decode("utf-8").splitlines():
        if "=" in line:
            k, v = line.split("=", 1)
            config[k.strip()] = v.strip()
    control = json.loads(zf.read("control.json"))
    f = Jxs(names, config, control, zf)
    layers = sorted(int(m.group(1)) for n in names if (m := re.fullmatch(r"(\d+)\.png", n)))
    assert layers == list(range(f.n_layers)), "layer PNGs missing"
    return f


def replay(actions: list) -> list[dict]:
    """Run ``action_list``: per shown layer (``slice {PWD}/NNNNN.png``), its 1-based ``layerno``, the platform's z
    when the light goes on (relative G0 moves summed), the PWM, the exposure (the delay while the light is on), the
    delays before it since the image was shown, and whether every move was followed by a delay."""
    z, out, cur, light, pending_move = 0.0, [], None, 0, False
    for kind, value in actions:
        if kind == "layerno":
            cur = {"layerno": int(value), "waits": []}
        elif kind == "slice" and value != "<BLANK>":
            assert cur is not None and value == f"{{PWD}}/{cur['layerno'] - 1:05d}.png", value
            out.append(cur)
        elif kind == "gcode":
            m = re.fullmatch(r"G0 Z(-?[0-9.]+) F([0-9.]+)", value)
            if m:
                z += float(m.group(1))
                pending_move = True
            elif value.startswith("M106 S"):
                light = int(value[6:])
                if light and cur is not None:
                    cur["z"], cur["pwm"], cur["moved_then_waited"] = z, light, not pending_move
        elif kind == "delay":
            assert isinstance(value, int) and value > 0
            if pending_move:
                pending_move = False
            elif light and cur is not None:
                cur["exposure_ms"] = value
            elif cur is not None and "z" not in cur:
                cur["waits"].append(value)
    return out
