"""Anycubic Photon Workshop files: the one container behind ``.pwmo``, ``.pwms``, ``.pwma``, ``.pwmx``, ``.pmsq``,
``.pm3``, ``.pm3m``, ``.pm3n``, ``.pm4n``, ``.pwmb``, ``.pmx2``, ``.pm3r``, ``.px6s``, ``.pm5``, ``.pm5s``, ``.m5sp``.

Facts (field layouts, version differences) from public readers and writers: UVtools ``AnycubicFile.cs`` and its
``Scripts/010 Editor/PhotonWorkshop.bt``, PrusaSlicer's ``AnycubicSLA.cpp``, ole00's ``pwmx_info``, checked against
four files written by Photon Workshop (versions 515 and 516) in futurelink/msla-imaging's ``sample_data``; our code.

**Layout** (little endian; every address a uint32, so a file stays under 4 GiB): a file mark (``ANYCUBIC``, the
version, the table count 4/5/8/9/11 for versions 1/515/516/517/518, then the tables' addresses), then the tables,
each (except two) opened by a 12-byte name and a uint32 length, in the order Photon Workshop writes them:
HEADER (print settings, resolution; 80 bytes, +4 from 516: advanced mode, +8 from 517: grey, blur, resin type, +4 in
518: intelligent mode), PREVIEW (224×168 RGB565: red in the high 5 bits, little endian, top row first), from 515 the
layer grey table (no name: full-greyscale flag, 16 greys, a uint32), LAYERDEF (per layer 32 bytes: data address and
length, lift mm and mm/s, exposure s, thickness mm, lit pixels, 0), from 516 EXTRA (two lift stages each for the
bottom and the normal layers: height mm, lift and retract speeds mm/s) and MACHINE (name, ``pw0Img``, display mm,
machine Z, highest file version; in 518 also the pixel pitch µm and the resolution), from 517 SOFTWARE (no name) and
MODEL (the part's box, mm from the display centre), in 518 SUBIMGS (per layer address, length, lit pixels) and
PREVIEW2 (320×190). The layers' images follow. The tables' sizes depend only on the version and the layer count, so
the images are streamed to disk first and the tables written last, once the layers have been seen.

**Layer image (PW0)**: run-length code over the whole display, row after row, runs crossing rows freely. A byte's
high nibble is the colour code c; for c = 0 (blank) and c = 15 (full) the low nibble and the next byte hold the run
length (12 bits, at most 4095), for c = 1..14 the low nibble is the length (at most 15). **Quantisation**: PW0 keeps
4 bits a pixel; grey g (0-255) is stored as ``c = g >> 4`` (as PrusaSlicer's and UVtools' writers do) and read back
as ``17·c``: 0-15 → 0 (blank), 16-31 → 17, ..., 240-255 → 255 (:func:`quantise`). With ``--gamma 0`` every pixel is
0 or 255 and the file holds the layers exactly. The header's anti-aliasing level is 1 when no layer holds a grey
between (Photon Workshop's grey table then is sixteen 255s, as in its files) and 16 otherwise (table 15, 31, ..., 255,
UVtools' rule); how a firmware maps grey codes to exposure is its own business.

**Print settings** (:class:`~gpuslice.raster.settings.PrintSettings`; speeds are stored in mm/s): the header holds the
bottom and normal exposures, bottom layer count, transition layer count, one rest before every exposure (the normal
layers' ``wait_before_cure + wait_after_cure + wait_after_lift``: the format has no other wait; bottom waits that differ
are refused), the normal lift (its total over both stages) at the first stage's speed and the retract speed; LAYERDEF
repeats each layer's exposure (with the transition ramp), lift total, first-stage speed and thickness; the
per-layer-settings flag is ``per_layer_settings`` (off by default: UVtools reports M5s firmware that never ends the
first layer when it is on), and on whenever the layers' thicknesses vary (the printer must then follow LAYERDEF's
heights: :func:`~gpuslice.raster.settings.per_layer_mode`; on the M5s, :data:`PER_LAYER_HANGS`, such layers are refused
unless ``per_layer_settings`` asks for the switch). From 516, two-stage motion goes to EXTRA, for the bottom and the
normal layers, with the advanced mode on: stage 1 = (``lift_height``, ``lift_speed``, the slow retract speed
``retract_speed2``, or ``retract_speed`` when ``retract_height2`` is 0), stage 2 = (``lift_height2``, ``lift_speed2``,
``retract_speed``), placed as UVtools places them; the format stores no retract heights (the retract stages follow the
lift stages' heights). One-stage motion is written as Photon Workshop writes it in basic mode: stage 1 = (lift, lift
speed, 0), stage 2 = (0, 0, retract speed), advanced mode off. The pixel size in the header is the larger pitch, µm.

**Machine and version**: the output's suffix names the machine (:data:`MACHINES`: its name as Photon Workshop writes
it, display, Z travel and file version). A printer preset (``--printer``) overrides the name (``machine``), the Z
travel (``build_height``) and, when its native format is this suffix, the version (``format_version``: 1, 515, 516,
517 or 518). The display, pitch and resolution written are the job's (:class:`RasterSpec`); the firmware checks
them against its own, so a job whose display is not the named machine's (the suffix's, or the preset's) is refused
before any work (:func:`refuse_settings`; with a preset, the preset's display:
:meth:`gpuslice.raster.spec.ResinOptions.check_display`).
Mirroring is the display's (``--mirror-x``): UVtools' Anycubic printer profiles mirror X. Photon Workshop files
carry no date, so the bytes depend only on the layers and the options. The M7 generation (``.pm7``, ``.pm7m``,
``.pwsz``) uses another, zip-based container of the same PW0 layers: :mod:`gpuslice.raster.anycubic_zip`.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from .coverage import Tile
from .layers import HeightMap, RunLayer, batch_image_segments, batch_pixel_runs, pixel_runs, run_groups, top_view
from .photon_machines import MACHINES, VERSIONS, Machine, machine_version, refuse_settings, wait_s
from .png import encode_all
from .run_encoder import RunImageEncoder
from .settings import header_layer_height, layer_table, per_layer_mode, print_time_s, ramp_layers, resin_ml

__all__ = ["MACHINES", "VERSIONS", "Machine", "refuse_settings", "PhotonEncoder", "encode_pw0", "encode_pw0_batch",
           "encode_pw0_runs", "quantise", "write_photon", "write_target"]

PREVIEW = (224, 168)
PREVIEW2 = (320, 190)
#: Photon Workshop's preview background (RGB565 0x5ACB) and our part colour
BACKGROUND = (90, 89, 90)
PART = (255, 165, 40)
MARK_SIZE = {1: 48, 515: 48, 516: 52, 517: 56, 518: 64}
N_TABLES = {1: 4, 515: 5, 516: 8, 517: 9, 518: 11}
HEADER_LENGTH = {1: 80, 515: 80, 516: 84, 517: 92, 518: 96}
#: MACHINE's property-field count: 7 in Photon Workshop's 516 files, 15 in 518 (UVtools)
PROPERTIES = {516: 7, 517: 7, 518: 15}
MACHINE_BACKGROUND = 6506241  # in every Photon Workshop MACHINE table seen
LAYER_DEF = np.dtype([("address", "<u4"), ("length", "<u4"), ("lift_height", "<f4"), ("lift_speed", "<f4"),
                      ("exposure", "<f4"), ("thickness", "<f4"), ("nonzero", "<u4"), ("padding", "<u4")])
SUB_DEF = np.dtype([("address", "<u4"), ("length", "<u4"), ("nonzero", "<u4"), ("padding", "<u4", 8)])


def quantise(grey: np.ndarray) -> np.ndarray:
    """The grey a reader gets back for grey ``grey`` (uint8): ``17·(g >> 4)`` (module docstring)."""
    return ((np.asarray(grey, np.uint8) >> 4) * 17).astype(np.uint8)


def encode_pw0(start: np.ndarray, length: np.ndarray, grey: np.ndarray, n_pixels: int) -> tuple[bytes, int, bool]:
    """One layer's PW0 image from its runs (``start`` row-major pixel index, ``length``, ``grey`` 1-255; sorted, not
    overlapping) over an image of ``n_pixels``: (bytes, lit pixels after quantisation, whether any grey lies strictly
    between 0 and 255 after it). Vectorised: a few numpy passes over the runs and their records."""
    start = np.asarray(start, np.int64)
    data, lit, mid, _ = encode_pw0_batch(start, length, grey, np.array([0, start.size], np.int64), n_pixels)
    return data[0], int(lit[0]), bool(mid[0])


def encode_pw0_batch(start: np.ndarray, length: np.ndarray, grey: np.ndarray, offsets: np.ndarray, n_pixels: int,
                     cols: int = 1) -> tuple[list[bytes], np.ndarray, np.ndarray, np.ndarray]:
    """:func:`encode_pw0` of several layers in one set of numpy passes (layer k: the runs ``offsets[k]:offsets[k +
    1]``): each layer's bytes, and per layer its lit pixels (int64), whether it has a middle grey (bool), and the
    box of its lit pixels on an image of ``cols`` columns, (row0, col0, row1, col1) int64 rows (-1 where unlit)."""
    start = np.asarray(start, np.int64)
    length = np.asarray(length, np.int64)
    offsets = np.asarray(offsets, np.int64)
    n_img = offsets.size - 1
    code = np.asarray(grey, np.uint8) >> 4
    keep = code > 0
    run_img = np.repeat(np.arange(n_img, dtype=np.int64), np.diff(offsets))[keep]
    start, length, code = start[keep], length[keep], code[keep]
    lit_off = np.zeros(n_img + 1, np.int64)
    np.cumsum(np.bincount(run_img, minlength=n_img), out=lit_off[1:])
    n, c, seg_off = batch_image_segments(start, length, code, lit_off, n_pixels)
    img = np.repeat(np.arange(n_img, dtype=np.int64), np.diff(seg_off))
    two = (c == 0) | (c == 15)
    cap = np.where(two, 0xFFF, 0xF)
    pieces = -(-n // cap)  # records a segment needs: full ones, then the rest
    cp = np.zeros(n.size + 1, np.int64)
    np.cumsum(pieces, out=cp[1:])
    seg = np.repeat(np.arange(n.size), pieces)
    rec = cap[seg]
    rec[cp[1:] - 1] = n - (pieces - 1) * cap
    rc, r2 = c[seg].astype(np.int64), two[seg]
    cw = np.zeros(seg.size + 1, np.int64)
    np.cumsum(1 + r2, out=cw[1:])
    off, total = cw[:-1], int(cw[-1])
    out = np.empty(total + 1, np.uint8)  # (the last byte: where the one-byte records write their second)
    out[off] = (rc << 4) | np.where(r2, rec >> 8, rec)
    out[np.where(r2, off + 1, total)] = rec & 0xFF
    img_off = cw[cp[seg_off]]
    data = out[:total].tobytes()
    lit = np.bincount(run_img, weights=length, minlength=n_img).astype(np.int64)
    mid = np.bincount(img[(c > 0) & ~two], minlength=n_img) > 0
    box = np.full((n_img, 4), -1, np.int64)
    has = np.flatnonzero(lit_off[1:] > lit_off[:-1])
    if has.size:  # runs never cross a row end
        first, last = lit_off[:-1][has], lit_off[1:][has] - 1
        end = start + length - 1
        box[has, 0], box[has, 2] = start[first] // cols, end[last] // cols
        box[has, 1] = np.minimum.reduceat(start % cols, first)
        box[has, 3] = np.maximum.reduceat(end % cols, first)
    return [data[img_off[i] : img_off[i + 1]] for i in range(n_img)], lit, mid, box


class PhotonEncoder(RunImageEncoder):
    """Driver of ``kernels/photon.cl`` (:mod:`gpuslice.raster.run_encoder`): PW0 layer images of a group of layers
    from their runs, the bytes of :func:`encode_pw0_batch` (its numpy twin, which also takes the groups the kernels
    leave), and its per-layer lit pixels, middle-grey flags and lit boxes from per-run values."""

    FILE, SIZES, WRITE = "photon.cl", "pw_sizes", "pw_write"
    MAX_RUN = 0x7FFFFFFF  # (records are split: any image whose pixel index fits an int)
    EXTRA = tuple(np.dtype(d) for d in (np.int32, np.uint8, np.int32, np.int32, np.int32, np.int32))

    def blank(self, n_pixels: int) -> bytes:
        return encode_pw0(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8), n_pixels)[0]

    def reduce(self, extra: list[np.ndarray], first: np.ndarray, nonempty: np.ndarray, blank: bytes):
        lit_run, mid_run, r0, c0, r1, c1 = extra
        n_img = first.size
        lit, mid = np.zeros(n_img, np.int64), np.zeros(n_img, bool)
        box = np.full((n_img, 4), -1, np.int64)
        ne = np.flatnonzero(nonempty)
        if ne.size:
            at = first[ne]
            lit[ne] = np.add.reduceat(lit_run, at, dtype=np.int64)
            mid[ne] = np.maximum.reduceat(mid_run, at) > 0
            on = lit[ne] > 0
            for col, (arr, op) in enumerate(((r0, np.minimum), (c0, np.minimum), (r1, np.maximum), (c1, np.maximum))):
                box[ne[on], col] = op.reduceat(arr, at)[on]
        return lit, mid, box


def encode_pw0_runs(runs, a: int, b: int, cols: int, n_pixels: int, device=None):
    """:func:`encode_pw0_batch` of entries ``a`` … ``b`` − 1 of a batch of runs (:class:`~gpuslice.raster.runs.Runs`
    of ``cols`` columns): ``(images, lit, mid, box)``; with an OpenCL ``device``, by the kernels of
    ``kernels/photon.cl`` (:class:`PhotonEncoder`; the same values)."""
    if device is not None:
        out = PhotonEncoder.of(device).encode_stats(runs, a, b, cols, n_pixels)
        if out is not None:
            return (out[0], *out[1])
    start, length, grey, offsets = batch_pixel_runs(runs, a, b, cols)
    return encode_pw0_batch(start, length, grey, offsets, n_pixels, cols)


def _pitch(spec) -> tuple[float, float]:
    """(column, row) pitch of the image in mm: (px, py) in landscape, (py, px) in portrait."""
    return (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)


class _TopView(HeightMap):
    """The part seen from above for the previews: per sampled pixel the highest layer covering it, not mirrored as
    the layers are (:func:`~gpuslice.raster.layers.top_view`)."""

    def __init__(self, spec, n_layers: int) -> None:
        rows, cols = spec.shape
        super().__init__(spec.shape, n_layers, max(1, min(rows, cols) // 512))
        self.spec, self.pitch = spec, (spec.px, spec.py)  # (a top view's cell: along its rows, down its columns)

    def rgb565(self, size: tuple[int, int]) -> bytes:
        """The view fitted into ``size`` (width, height) with its true aspect, as RGB565 little endian."""
        w, h = size
        img = top_view(self.img, self.spec)
        ys, xs = np.nonzero(img)
        out = np.empty((h, w, 3), np.float32)
        out[:] = BACKGROUND
        if ys.size:
            src = img[ys.min() : ys.max() + 1, xs.min() : xs.max() + 1]
            sw, sh = src.shape[1] * self.pitch[0], src.shape[0] * self.pitch[1]  # mm / step
            scale = 0.9 * min(w / sw, h / sh)
            dw, dh = max(1, min(w, round(sw * scale))), max(1, min(h, round(sh * scale)))
            rows = np.minimum((np.arange(dh) + 0.5) * src.shape[0] / dh, src.shape[0] - 1).astype(np.int64)
            cols = np.minimum((np.arange(dw) + 0.5) * src.shape[1] / dw, src.shape[1] - 1).astype(np.int64)
            level = src[rows[:, None], cols[None, :]].astype(np.float32)
            shade = (0.35 + 0.65 * level / 255.0)[..., None] * np.array(PART, np.float32)
            y0, x0 = (h - dh) // 2, (w - dw) // 2
            view = out[y0 : y0 + dh, x0 : x0 + dw]
            view[:] = np.where(level[..., None] > 0, shade, view)
        q = out.astype(np.uint16)
        v = ((q[..., 0] >> 3) << 11) | ((q[..., 1] >> 2) << 5) | (q[..., 2] >> 3)
        return v.astype("<u2").tobytes()


def _name(text: str, size: int) -> bytes:
    """A NUL-padded string field of ``size`` bytes (UTF-8, cut to fit at a character boundary)."""
    return text.encode("utf-8")[: size - 1].decode("utf-8", "ignore").encode("utf-8").ljust(size, b"\0")


def _table(name: str, length: int, body: bytes) -> bytes:
    return _name(name, 12) + struct.pack("<I", length) + body


def _sizes(version: int, n: int) -> dict[str, int]:
    """Bytes of each table before the images, in file order."""
    s = {"mark": MARK_SIZE[version], "header": 16 + HEADER_LENGTH[version], "preview": 28 + 2 * PREVIEW[0] * PREVIEW[1]}
    if version >= 515:
        s["colors"] = 28
    s["layerdef"] = 20 + LAYER_DEF.itemsize * n
    if version >= 516:
        s["extra"], s["machine"] = 72, 224 if version >= 518 else 156
    if version >= 517:
        s["software"], s["model"] = 164, 48
    if version >= 518:
        s["sublayers"], s["preview2"] = 24 + SUB_DEF.itemsize * n, 28 + 2 * PREVIEW2[0] * PREVIEW2[1]
    return s


def _stages(s, bottom: bool) -> tuple[bool, tuple[float, ...]]:
    """(two stages?, the six EXTRA values (height mm, lift and retract speeds mm/s, twice)) of the bottom or the normal
    layers (module docstring)."""
    g = s.group(bottom)
    if g["lift_height2"] > 0 or g["retract_height2"] > 0:
        slow = g["retract_speed2"] if g["retract_height2"] > 0 else g["retract_speed"]
        fast = g["lift_speed2"] if g["lift_speed2"] > 0 else g["lift_speed"]
        return True, (g["lift_height"], g["lift_speed"] / 60, slow / 60, g["lift_height2"], fast / 60,
                      g["retract_speed"] / 60)
    return False, (g["lift_height"], g["lift_speed"] / 60, 0.0, 0.0, 0.0, g["retract_speed"] / 60)


def _tables(target, machine: Machine, version: int, name: str, machine_z: float, defs: np.ndarray, aa: int,
            box: tuple[int, int, int, int] | None, view: _TopView) -> bytes:
    """Everything before the layer images: the file mark and the tables, at the addresses :func:`_sizes` gives."""
    from .. import __version__

    spec, res, s = target.spec, target.result, target.settings
    n = res.n_layers
    cols, rows = spec.png_size
    pw, ph = _pitch(spec)
    th = np.asarray(res.thickness, np.float64)
    layer_height = header_layer_height(th)
    sizes = _sizes(version, n)
    at, pos = {}, 0
    for key, size in sizes.items():
        at[key], pos = pos, pos + size
    images = pos
    volume = resin_ml(res.area, th)
    two_b, bottom = _stages(s, True)
    two_n, normal = _stages(s, False)
    head = struct.pack("<10f3I2f5I", max(pw, ph) * 1000, layer_height, s.exposure, wait_s(s, target.path),
                       s.bottom_exposure, min(s.bottom_layers, n), s.lift_height + s.lift_height2, s.lift_speed / 60,
                       s.retract_speed / 60, volume, aa, cols, rows, volume * s.resin_density, 0.0, 0x24,
                       int(per_layer_mode(s, th)), round(print_time_s(s, n)),
                       min(ramp_layers(s), max(n - s.bottom_layers, 0)), 0)
    if version >= 516:
        head += struct.pack("<I", int(two_b or two_n))
    if version >= 517:
        head += struct.pack("<HHI", 0, 0, 0)  # grey, blur level, resin type: Photon Workshop's own settings
    if version >= 518:
        head += struct.pack("<I", 0)  # intelligent mode off: the exposures are used as given
    parts = [_table("HEADER", HEADER_LENGTH[version], head)]
    w, h = PREVIEW
    mark, length = (42, sizes["preview"] - 16) if version == 1 else (ord("x"), sizes["preview"])
    parts.append(_table("PREVIEW", length, struct.pack("<III", w, mark, h) + view.rgb565(PREVIEW)))
    if version >= 515:
        greys = [255] * 16 if aa == 1 else [min(255, int((i + 1) * 255 / aa)) for i in range(16)]
        parts.append(struct.pack("<II16BI", 0, 16, *greys, 0))
    parts.append(_table("LAYERDEF", sizes["layerdef"] - 16, struct.pack("<I", n) + defs.tobytes()))
    if version >= 516:
        parts.append(_table("EXTRA", 24, struct.pack("<I6fI6f", 2, *bottom, 2, *normal)))
        body = _name(name, 96) + _name("pw0Img", 16) + struct.pack(
            "<IIfffII", 16, PROPERTIES[version], cols * pw, rows * ph, machine_z, max(version, machine.version),
            MACHINE_BACKGROUND)
        if version >= 518:
            body += struct.pack("<2f8I2I2H4I", pw * 1000, ph * 1000, *([0] * 8), 1, 0, cols, rows, 0, 0, 0, 0)
        parts.append(_table("MACHINE", sizes["machine"], body))
    if version >= 517:
        parts.append(_name("gpuslice", 32) + struct.pack("<I", 164) + _name(__version__, 32) + _name("", 64)
                     + _name("", 32))
        if box is None:
            lo = hi = (0.0, 0.0)
        else:  # the lit pixels' box in mm from the display's centre, x right and y down the image (as UVtools)
            r0, c0, r1, c1 = box
            lo = (c0 * pw - cols * pw / 2, r0 * ph - rows * ph / 2)
            hi = ((c1 + 1) * pw - cols * pw / 2, (r1 + 1) * ph - rows * ph / 2)
        parts.append(_table("MODEL", sizes["model"], struct.pack("<6fIf", *lo, 0.0, *hi, float(th.sum()), 0, 0.0)))
    if version >= 518:
        sub = np.zeros(n, SUB_DEF)
        for k in ("address", "length", "nonzero"):
            sub[k] = defs[k]
        parts.append(_table("SUBIMGS", sizes["sublayers"], struct.pack("<II", n, 1) + sub.tobytes()))
        w, h = PREVIEW2
        parts.append(_table("PREVIEW2", sizes["preview2"], struct.pack("<IHHI", w, 4293, 0, h)
                            + view.rgb565(PREVIEW2)))
    addr = [at["header"], at.get("software", 0), at["preview"], at.get("colors", 0), at["layerdef"],
            at.get("extra", 0)]
    if version >= 516:
        addr.append(at["machine"])
    addr.append(images)
    if version >= 517:
        addr.append(at["model"])
    if version >= 518:
        addr += [at["sublayers"], at["preview2"]]
    out = _name("ANYCUBIC", 12) + struct.pack(f"<{2 + len(addr)}I", version, N_TABLES[version], *addr)
    out += b"".join(parts)
    assert len(out) == images, (len(out), images)
    return out


def write_photon(layers: Iterable[Tile | RunLayer], target, *, machine: Machine, version: int | None = None,
                 name: str | None = None, machine_z: float | None = None) -> dict[str, Any]:
    """Write ``target.result``'s layers (tiles or runs, in order) as a Photon Workshop file of ``machine`` at
    ``target.path``, atomically: file ``version`` (default the machine's), machine ``name`` and Z travel
    ``machine_z`` (mm) in MACHINE (defaults: the machine's). Layers are encoded on ``target.workers`` threads and
    streamed to disk; the tables go in last. Returns the layer count, ``png_bytes`` (the layers' image bytes, the
    name the command line reports), ``photon_bytes`` (the file), ``format_version``, ``machine``, ``antialiasing``."""
    path = Path(os.fspath(target.path))
    version = machine.version if version is None else version
    if version not in VERSIONS:
        raise ParameterError(f"{path}: Photon Workshop file version must be one of "
                             f"{', '.join(map(str, VERSIONS))}, not {version}")
    spec, res = target.spec, target.result
    n = res.n_layers
    cols, rows = spec.png_size
    if version >= 518 and max(cols, rows) > 0xFFFF:
        raise ParameterError(f"{path}: a version 518 file holds at most 65535 pixels a side, not {cols}x{rows}")
    n_pixels = cols * rows
    wait_s(target.settings, path)
    table = layer_table(target.settings, n)
    defs = np.zeros(n, LAYER_DEF)
    defs["lift_height"] = table["lift_height"] + table["lift_height2"]
    defs["lift_speed"] = table["lift_speed"] / 60
    defs["exposure"] = table["exposure"]
    defs["thickness"] = np.asarray(res.thickness, np.float64)
    view = _TopView(spec, n)
    images = sum(_sizes(version, n).values())
    box = [rows, cols, -1, -1]  # lit pixels' row0, col0, row1, col1
    greys = False

    def encode(item: Tile | RunLayer) -> tuple[bytes, int, bool, tuple[int, int, int, int] | None]:  # on a worker
        start, length, grey = pixel_runs(item, cols)
        data, lit, mid = encode_pw0(start, length, grey, n_pixels)
        lit_runs = (grey >> 4) > 0
        if not lit_runs.any():
            return data, lit, mid, None
        s, e = start[lit_runs], start[lit_runs] + length[lit_runs] - 1  # runs never cross a row end
        return data, lit, mid, (int(s[0] // cols), int((s % cols).min()), int(e[-1] // cols), int((e % cols).max()))

    device = target.device

    def encode_group(group: list[Tile | RunLayer]) -> list:  # on a worker thread
        if not isinstance(group[0], RunLayer):
            return [encode(item) for item in group]
        data, lit, mid, box = encode_pw0_runs(group[0].runs, group[0].j, group[-1].j + 1, cols, n_pixels, device)
        return [(d, int(n), bool(m), None if b[0] < 0 else tuple(int(v) for v in b))
                for d, n, m, b in zip(data, lit, mid, box, strict=True)]

    with atomic_path(path) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as f:
        f.seek(images)

        def sink(k: int, item) -> None:
            nonlocal greys
            data, lit, mid, b = item
            address = f.tell()
            if address + len(data) > 0xFFFFFFFF:
                raise ParameterError(f"{path}: a Photon Workshop file holds at most 4 GiB (its addresses are 32-bit)")
            f.write(data)
            defs["address"][k], defs["length"][k], defs["nonzero"][k] = address, len(data), lit
            greys |= mid
            if b is not None:
                box[:2] = min(box[0], b[0]), min(box[1], b[1])
                box[2:] = max(box[2], b[2]), max(box[3], b[3])

        stats = encode_all(layers, encode, sink, target.workers, on_tile=view.add, progress=target.progress,
                           many=encode_group, chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{path}: expected {n} layers, got {stats['layers']}")
        size = f.tell()
        f.seek(0)
        aa = 16 if greys else 1
        f.write(_tables(target, machine, version, name or machine.name, machine.height if machine_z is None
                        else machine_z, defs, aa, tuple(box) if box[2] >= 0 else None, view))
    return {"layers": n, "png_bytes": stats["png_bytes"], "photon_bytes": size, "format_version": version,
            "machine": name or machine.name, "antialiasing": aa}


#: the machines whose firmware hangs with the per-layer settings on (UVtools reports the M5s never ending the first
#: layer): layers of several thicknesses, which need them, are refused unless asked for
PER_LAYER_HANGS = ("pm5s",)


def write_target(layers: Iterable[Tile | RunLayer], target) -> dict[str, Any]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): the format's name (``target.format``, the registry's
    name of each suffix), else the suffix of ``target.path``, picks the machine (:data:`MACHINES`); a printer preset
    overrides its name, Z travel and (native format here) version."""
    path = Path(os.fspath(target.path))
    suffix = target.format if target.format is not None else path.suffix.lower().lstrip(".")
    if suffix not in MACHINES:
        raise ParameterError(f"{path}: not a Photon Workshop suffix (use .{', .'.join(MACHINES)})")
    refuse_settings(path, suffix, target.options, target.settings)  # (the display: checked by the job, up front)
    th = np.asarray(target.result.thickness, np.float64)
    if suffix in PER_LAYER_HANGS and not target.settings.per_layer_settings and per_layer_mode(target.settings, th):
        raise ParameterError(f"{path}: layers of several thicknesses need the per-layer settings on, and the "
                             f"{MACHINES[suffix].name}'s firmware never ends the first layer with them on (UVtools): "
                             "slice it with one layer thickness, or give --per-layer-settings to write them anyway")
    machine, version = machine_version(suffix, target.options)
    preset = target.options.preset
    name = machine_z = None
    if preset is not None:
        name = preset.machine or None
        machine_z = float(preset.build_height) if preset.build_height > 0 else None
    return write_photon(layers, target, machine=machine, version=version, name=name, machine_z=machine_z)
