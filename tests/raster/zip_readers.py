"""Readers of the zip-of-layers archives (SL1/SL1S, SL1_SVG, NanoDLP), for the tests only.

Written apart from the writers in ``gpuslice/raster`` (``zipfile``, PIL and a small SVG path parser; nothing from
the writers' modules), so that a test compares what a writer meant with an independent reading of its bytes. The SL1
reader also reads PrusaSlicer's own SL1S export (``tests/raster/test_zip_formats.py``, where PrusaSlicer is
installed); no SL1_SVG or NanoDLP file written by another program was found to test against.
"""

from __future__ import annotations

import io
import json
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


def parse_ini(text: str) -> dict[str, str]:
    """``key = value`` lines (PrusaSlicer's config.ini / prusaslicer.ini) as a dict of strings."""
    out: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition("=")
        if sep and not line.lstrip().startswith(("#", ";")):
            out[key.strip()] = value.strip()
    return out


def png_layer(data: bytes) -> np.ndarray:
    """A layer PNG as a (rows, cols) uint8 array; it must be 8-bit greyscale."""
    from PIL import Image

    im = Image.open(io.BytesIO(data))
    assert im.mode == "L", f"layer PNG mode {im.mode}, expected 8-bit greyscale"
    return np.asarray(im)


@dataclass
class Sl1Archive:
    """An SL1 / SL1S / SL1_SVG archive: its two ini files, layer member names in order (``ext``), thumbnails."""

    path: Path
    config: dict[str, str]
    prusaslicer: dict[str, str]
    layers: list[str]
    thumbnails: dict[str, tuple[int, int]] = field(default_factory=dict)

    def read(self, name: str) -> bytes:
        with zipfile.ZipFile(self.path) as z:
            return z.read(name)


def read_sl1(path, ext: str = ".png") -> Sl1Archive:
    """The ini files, the ``<jobDir>NNNNN<ext>`` layers (sorted; every one must start with ``jobDir``, as the Prusa
    firmware lists them) and the thumbnails' sizes of an SL1-family archive."""
    from PIL import Image

    with zipfile.ZipFile(path) as z:
        assert z.testzip() is None
        names = z.namelist()
        config = parse_ini(z.read("config.ini").decode("utf-8"))
        ini = parse_ini(z.read("prusaslicer.ini").decode("utf-8")) if "prusaslicer.ini" in names else {}
        layers = sorted(n for n in names if n.endswith(ext) and "/" not in n)
        job = config.get("jobDir", "")
        assert all(n.startswith(job) and n[len(job) : -len(ext)].isdigit() for n in layers), layers[:3]
        thumbs = {n: Image.open(io.BytesIO(z.read(n))).size for n in names if n.startswith("thumbnail/")}
    return Sl1Archive(Path(path), config, ini, layers, thumbs)


# ---- SVG ---------------------------------------------------------------------------------------------------------
_SVG_TAG = re.compile(r"<svg\s([^>]*)>")
_ATTR = re.compile(r'([\w:-]+)="([^"]*)"')
_PATH = re.compile(r'<path\s+d="([^"]*)"\s*/>')
_SUBPATH = re.compile(r"M (-?\d+) (-?\d+) l((?: -?\d+ -?\d+)*) z")


@dataclass
class SvgLayer:
    """One SL1_SVG layer: the header's ``width``/``height`` (mm), ``viewbox`` (w, h units), ``style``, and its
    paths, each a list of loops ((n, 2) int64 absolute points, units of the viewBox)."""

    width_mm: float
    height_mm: float
    viewbox: tuple[int, int]
    style: str
    paths: list[list[np.ndarray]]


def parse_svg_layer(text: str) -> SvgLayer:
    """Parse one layer SVG: PrusaSlicer's header and ``<path d="M x y l dx dy … z …" />`` elements (``M`` absolute,
    ``l`` relative, ``z`` closes); anything else in a path is an error."""
    head = _SVG_TAG.search(text)
    assert head is not None, "no <svg> element"
    attrs = dict(_ATTR.findall(head.group(1)))
    vb = attrs["viewBox"].split()
    assert vb[:2] == ["0", "0"], attrs["viewBox"]
    paths = []
    for d in _PATH.findall(text):
        loops = []
        rest = d.strip()
        pos = 0
        while pos < len(rest):
            m = _SUBPATH.match(rest, pos)
            assert m is not None, f"unexpected path data at {rest[pos:pos + 40]!r}"
            start = np.array([int(m.group(1)), int(m.group(2))], np.int64)
            rel = np.array(m.group(3).split(), np.int64).reshape(-1, 2)
            loops.append(np.vstack([start, start + np.cumsum(rel, axis=0)]))
            pos = m.end()
            while pos < len(rest) and rest[pos] == " ":
                pos += 1
        paths.append(loops)
    assert text.count("<path") == len(paths), "a <path> element the parser did not read"
    return SvgLayer(float(attrs["width"].removesuffix("mm")), float(attrs["height"].removesuffix("mm")),
                    (int(vb[2]), int(vb[3])), attrs.get("style", ""), paths)


def ring_area2(ring: np.ndarray) -> int:
    """Twice the signed (shoelace) area of an integer ring, exact."""
    x, y = ring[:, 0], ring[:, 1]
    return int(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def rasterise_rings(rings: list[np.ndarray], scale: tuple[float, float], shape: tuple[int, int],
                    gamma: float = 1.0) -> np.ndarray:
    """Greys of ``rings`` (SVG units, any winding; nonzero-summed exactly as the raster does) on a display of
    ``shape`` (rows, cols), ``scale`` = pixels per unit along x and y: the project's analytic coverage twin."""
    from gpuslice.raster import coverage_numpy, gamma_lut

    edges = []
    for r in rings:
        p = r.astype(np.float64) * np.asarray(scale)
        edges.append(np.hstack([p, np.roll(p, -1, axis=0)]))
    e = np.vstack(edges) if edges else np.zeros((0, 4))
    return coverage_numpy(e, shape[0], shape[1], gamma_lut(gamma))


# ---- NanoDLP -----------------------------------------------------------------------------------------------------
@dataclass
class NanoDlpPlate:
    """A NanoDLP plate zip: its JSON manifests by file name and the layer PNG names ``1.png`` … in order."""

    path: Path
    manifests: dict[str, object]
    layers: list[str]
    names: list[str]

    def read(self, name: str) -> bytes:
        with zipfile.ZipFile(self.path) as z:
            return z.read(name)


def read_nanodlp(path) -> NanoDlpPlate:
    """Manifests and layers of a NanoDLP plate; layers must be ``1.png`` … ``N.png`` without gaps or leading zeros
    (NanoDLP's manual)."""
    with zipfile.ZipFile(path) as z:
        assert z.testzip() is None
        names = z.namelist()
        manifests = {n: json.loads(z.read(n)) for n in names if n.endswith(".json")}
    layers = [n for n in names if re.fullmatch(r"[1-9]\d*\.png", n)]
    layers.sort(key=lambda n: int(n[:-4]))
    assert [int(n[:-4]) for n in layers] == list(range(1, len(layers) + 1))
    assert not [n for n in names if re.fullmatch(r"0\d*\.png", n)], "a layer PNG with a leading zero"
    return NanoDlpPlate(Path(path), manifests, layers, names)
