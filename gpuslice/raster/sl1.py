"""Resin outputs: 8-bit PNG layer stacks and SL1 archives (PrusaSlicer's layout), encoded in parallel.

**PNG encoding without touching blank pixels.** A layer's PNG is greyscale, 8 bits, filter 0 on every row, one
IDAT. Most rows of a resin layer are blank, so the zlib stream is assembled from pieces that each end with a full
flush (byte-aligned raw deflate that references nothing before it, so pieces can be concatenated):

* ``k`` blank rows (filter byte + zeros): precomputed once per display width for every power of two, at level 9,
  and concatenated for the binary digits of ``k`` (above and below the layer's bounding box);
* the bounding box's rows (full width), compressed per layer at ``level`` (default 1);
* an empty final block (``03 00``), then the Adler-32 of the whole image, carried arithmetically over the blank
  runs (n zeros leave A unchanged and add n·A to B) and over the box rows from the tile's row and column sums.

The deflater is ISA-L's (``isal``, optional, 4-5x faster than zlib at level 1 here, see docs/BENCHMARKS.md) when
installed, else zlib's. Both release the GIL, so a thread pool encodes layers while the rasteriser runs.

**SL1** (a zip, as PrusaSlicer 2.5 writes it): ``config.ini``, ``prusaslicer.ini``, ``<jobDir>00000.png`` upward,
``thumbnail/thumbnail400x400.png`` and ``thumbnail/thumbnail800x480.png`` (a shaded top view: a height map), every
member deflated (the layers' on the worker threads). Archives and PNG stacks are written under a temporary name and
renamed when complete (:func:`gpuslice.export.atomic_path`).
"""

from __future__ import annotations

import datetime as _dt
import io
import math
import os
import re
import struct
import zipfile
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..io.atomic import atomic_path
from .coverage import RasterSpec, Tile

__all__ = ["PngEncoder", "deflate_module", "SL1Info", "write_png_stack", "write_sl1", "read_sl1_config"]

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_MOD_ADLER = 65521
_FINAL_EMPTY_BLOCK = b"\x03\x00"


def deflate_module(prefer: str = "auto"):
    """The deflate implementation: ``isal.isal_zlib`` when installed (``prefer="auto"`` or ``"isal"``), else
    :mod:`zlib`. Both have the zlib API (``compressobj``, ``Z_FULL_FLUSH``)."""
    if prefer in ("auto", "isal"):
        try:
            from isal import isal_zlib

            return isal_zlib
        except ImportError:
            if prefer == "isal":
                raise ParameterError("isal is not installed (pip install isal)") from None
    if prefer not in ("auto", "isal", "zlib"):
        raise ParameterError(f"unknown deflater '{prefer}' (use auto, isal or zlib)")
    return zlib


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def _adler_zeros(value: int, n: int) -> int:
    a, b = value & 0xFFFF, value >> 16
    return (((b + n * a) % _MOD_ADLER) << 16) | a


def _adler_tile(value: int, data: np.ndarray, c0: int, row_bytes: int) -> int:
    """Adler-32 continued over ``h`` full PNG rows that are zero except ``data`` (h, w) at byte ``1 + c0`` of each:
    from (a0, b0), n bytes d_i give a = a0 + Σ d_i and b = b0 + n·a0 + Σ (n − i)·d_i, and Σ i·d_i needs only the
    tile's row and column sums (a fraction of the cost of ``adler32`` over the zeros)."""
    h, w = data.shape
    n = h * row_bytes
    rs = np.add.reduce(data, axis=1, dtype=np.uint64)
    cs = np.add.reduce(data, axis=0, dtype=np.uint64)
    total = int(rs.sum())
    weighted = row_bytes * int(np.dot(np.arange(h, dtype=np.uint64), rs)) + int(
        np.dot(np.arange(1 + c0, 1 + c0 + w, dtype=np.uint64), cs)
    )
    a0, b0 = value & 0xFFFF, value >> 16
    a = (a0 + total) % _MOD_ADLER
    b = (b0 + n * a0 + n * total - weighted) % _MOD_ADLER
    return (b << 16) | a


class PngEncoder:
    """Encodes one display's layers (nx × ny greyscale) as PNG bytes from their :class:`~gpuslice.raster.Tile`.

    level : deflate level of the bounding-box rows (1: fastest; the blank rows are precomputed at 9).
    deflater : ``"auto"`` (isal if installed), ``"isal"`` or ``"zlib"``. Thread-safe: :meth:`encode` keeps no state.
    """

    def __init__(self, nx: int, ny: int, level: int = 1, deflater: str = "auto") -> None:
        if not 0 <= level <= 9:
            raise ParameterError(f"PNG level must be 0..9, got {level}")
        self.nx, self.ny, self.level = int(nx), int(ny), int(level)
        self.z = deflate_module(deflater)
        if self.z is not zlib and self.level > 3:  # isal has levels 0..3
            self.level = 3
        self.row_bytes = self.nx + 1
        self._blank: list[bytes] = []  # _blank[j]: 2**j blank rows, raw deflate ending in a full flush
        j = 0
        while (1 << j) <= self.ny:
            c = zlib.compressobj(9, zlib.DEFLATED, -15, 9)
            self._blank.append(c.compress(bytes(self.row_bytes << j)) + c.flush(zlib.Z_FULL_FLUSH))
            j += 1
        self._header = _PNG_SIG + _chunk(b"IHDR", struct.pack(">IIBBBBB", self.nx, self.ny, 8, 0, 0, 0, 0))
        self._end = _chunk(b"IEND", b"")

    def _blank_rows(self, k: int) -> list[bytes]:
        return [self._blank[j] for j in range(len(self._blank)) if (k >> j) & 1]

    def encode(self, tile: Tile) -> bytes:
        """The PNG file of the layer whose non-blank part is ``tile``."""
        h, w = tile.data.shape
        r0, c0 = tile.row0, tile.col0
        if h == 0 or w == 0:
            r0, h = self.ny, 0
        parts = [b"\x78\x01", *self._blank_rows(r0)]
        adler = _adler_zeros(1, r0 * self.row_bytes)
        if h:
            rows = np.zeros((h, self.row_bytes), np.uint8)
            rows[:, 1 + c0 : 1 + c0 + w] = tile.data
            buf = rows.data
            c = self.z.compressobj(self.level, self.z.DEFLATED, -15)
            parts += [c.compress(buf), c.flush(self.z.Z_FULL_FLUSH)]
            adler = _adler_tile(adler, tile.data, c0, self.row_bytes)
        rest = self.ny - r0 - h
        parts += self._blank_rows(rest)
        adler = _adler_zeros(adler, rest * self.row_bytes)
        parts += [_FINAL_EMPTY_BLOCK, struct.pack(">I", adler)]
        return self._header + _chunk(b"IDAT", b"".join(parts)) + self._end


@dataclass
class SL1Info:
    """What goes into ``config.ini`` / ``prusaslicer.ini`` besides the display (times in s, lengths in mm)."""

    job_dir: str = "gpuslice"
    layer_height: float = 0.05
    initial_layer_height: float | None = None
    exposure_time: float = 10.0
    initial_exposure_time: float = 15.0
    faded_layers: int = 10
    material_name: str = ""
    printer_model: str = ""
    printer_profile: str = ""
    print_profile: str = ""
    used_material_ml: float = 0.0
    tilt_time: float = 5.0  # fast tilt, s per layer (PrusaSlicer's default)
    extra: dict[str, str] = field(default_factory=dict)


def _fmt(v) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return f"{v:.6f}".rstrip("0").rstrip(".") if not v.is_integer() else str(int(v))
    return str(v)


def config_ini(info: SL1Info, n_layers: int, now: _dt.datetime | None = None) -> str:
    """``config.ini`` text: the keys PrusaSlicer 2.5 writes, sorted as it writes them."""
    from .. import __version__

    now = now or _dt.datetime.now(_dt.timezone.utc)
    n_fade = min(info.faded_layers, max(n_layers - 1, 0))
    print_time = (
        info.initial_exposure_time
        + max(n_layers - 1, 0) * info.exposure_time
        + n_layers * info.tilt_time
    )
    keys = {
        "action": "print",
        "expTime": info.exposure_time,
        "expTimeFirst": info.initial_exposure_time,
        "expUserProfile": 0,
        "fileCreationTimestamp": now.strftime("%Y-%m-%d at %H:%M:%S UTC"),
        "hollow": 0,
        "jobDir": info.job_dir,
        "layerHeight": info.layer_height,
        "materialName": info.material_name,
        "numFade": n_fade,
        "numFast": n_layers,
        "numSlow": 0,
        "printProfile": info.print_profile,
        "printTime": round(print_time, 6),
        "printerModel": info.printer_model,
        "printerProfile": info.printer_profile,
        "printerVariant": "",
        "prusaSlicerVersion": f"gpuslice {__version__}",
        "usedMaterial": round(info.used_material_ml, 6),
    }
    return "".join(f"{k} = {_fmt(v)}\n" for k, v in keys.items())


def prusaslicer_ini(info: SL1Info, spec: RasterSpec) -> str:
    """``prusaslicer.ini`` text: the display and layer settings PrusaSlicer reads back (UVtools uses them too)."""
    bx, by = spec.bed_mm
    w, h = spec.display_mm  # PrusaSlicer's display_width/height (along display_pixels_x/y)
    keys = {
        "bed_shape": f"0x0,{_fmt(float(bx))}x0,{_fmt(float(bx))}x{_fmt(float(by))},0x{_fmt(float(by))}",
        "display_height": float(h),
        "display_mirror_x": spec.mirror_x,
        "display_mirror_y": spec.mirror_y,
        "display_orientation": "portrait" if spec.portrait else "landscape",
        "display_pixels_x": spec.nx,
        "display_pixels_y": spec.ny,
        "display_width": float(w),
        "exposure_time": info.exposure_time,
        "faded_layers": info.faded_layers,
        "gamma_correction": float(spec.gamma),
        "initial_exposure_time": info.initial_exposure_time,
        "initial_layer_height": info.initial_layer_height or info.layer_height,
        "layer_height": info.layer_height,
        "material_print_speed": "fast",
        "pad_enable": 0,
        "printer_technology": "SLA",
        "supports_enable": 0,
        **info.extra,
    }
    return "".join(f"{k} = {_fmt(v)}\n" for k, v in sorted(keys.items()))


def read_sl1_config(path: str | os.PathLike) -> tuple[dict[str, str], dict[str, str], list[str]]:
    """(config.ini, prusaslicer.ini, layer PNG names in order) of an SL1 archive."""
    with zipfile.ZipFile(path) as z:
        def ini(name: str) -> dict[str, str]:
            if name not in z.namelist():
                return {}
            out = {}
            for line in z.read(name).decode().splitlines():
                k, sep, v = line.partition("=")
                if sep:
                    out[k.strip()] = v.strip()
            return out

        names = sorted(n for n in z.namelist() if n.endswith(".png") and "/" not in n)
        return ini("config.ini"), ini("prusaslicer.ini"), names


class _Thumb:
    """Top view of the part for the thumbnails: a height map (the highest layer covering each spot, shaded from dark
    at the bed to bright at the top) at a quarter of the display's resolution."""

    def __init__(self, spec: RasterSpec, n_layers: int, step: int = 4) -> None:
        self.step = step
        self.n = max(n_layers - 1, 1)
        rows, cols = spec.shape
        self.img = np.zeros(((rows + step - 1) // step, (cols + step - 1) // step), np.uint8)

    def add(self, tile: Tile) -> None:
        s = self.step
        h, w = tile.data.shape
        if not h or not w:
            return
        dr, dc = (-tile.row0) % s, (-tile.col0) % s
        level = np.uint8(1 + (254 * tile.index) // self.n)
        sub = np.where(tile.data[dr::s, dc::s] >= 128, level, np.uint8(0))
        r, c = (tile.row0 + dr) // s, (tile.col0 + dc) // s
        view = self.img[r : r + sub.shape[0], c : c + sub.shape[1]]
        np.maximum(view, sub, out=view)

    def png(self, size: tuple[int, int]) -> bytes:
        from PIL import Image

        ys, xs = np.nonzero(self.img)
        src = self.img
        if ys.size:  # crop to the part with a margin, keep the aspect ratio
            m = 4
            src = src[max(ys.min() - m, 0) : ys.max() + m + 1, max(xs.min() - m, 0) : xs.max() + m + 1]
        tw, th = size
        scale = min(tw / src.shape[1], th / src.shape[0])
        sw, sh = max(1, int(src.shape[1] * scale)), max(1, int(src.shape[0] * scale))
        shade = 0.3 + 0.7 * src.astype(np.float32)[..., None] / 255.0
        rgb = np.where(src[..., None] > 0, shade * np.array([255, 140, 40], np.float32), 40).astype(np.uint8)
        part = Image.fromarray(rgb, "RGB").resize((sw, sh), Image.BILINEAR)
        canvas = Image.new("RGB", size, (40, 40, 40))
        canvas.paste(part, ((tw - sw) // 2, (th - sh) // 2))
        buf = io.BytesIO()
        canvas.save(buf, format="PNG")
        return buf.getvalue()


THUMBNAILS = ((400, 400), (800, 480))


def _encode_all(
    tiles: Iterable[Tile],
    encoder: PngEncoder | Callable[[Tile], bytes | tuple[bytes, bytes]],
    sink: Callable[[int, object], None],
    workers: int | None,
    on_tile: Callable[[Tile], None] | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, float]:
    """Encode ``tiles`` on a thread pool (``encoder.encode`` or ``encoder(tile)``: the PNG, or (PNG, more)) and hand
    ``(k, encoded)`` to ``sink`` in order; returns the layer count and PNG bytes."""
    workers = workers or os.cpu_count() or 1
    encode = getattr(encoder, "encode", encoder)
    n_bytes = 0
    count = 0

    def drain_one() -> None:
        nonlocal n_bytes, count
        data = pending.popleft().result()
        sink(count, data)
        n_bytes += len(data if isinstance(data, bytes) else data[0])
        count += 1
        if progress:
            progress(count)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque = deque()
        for tile in tiles:
            if on_tile is not None:
                on_tile(tile)
            pending.append(pool.submit(encode, tile))
            while len(pending) > 4 * workers or (pending and pending[0].done()):
                drain_one()
        while pending:
            drain_one()
    return {"layers": count, "png_bytes": n_bytes}


class _Precompressed:
    """Stands in for a zip member's compressor: hands over raw deflate bytes made beforehand (on a worker thread)."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def compress(self, _raw) -> bytes:
        data, self.data = self.data, b""
        return data

    def flush(self) -> bytes:
        return b""


def _write_deflated(z: zipfile.ZipFile, info: zipfile.ZipInfo, raw: bytes, deflated: bytes) -> None:
    """Add a ZIP_DEFLATED member whose raw deflate stream ``deflated`` (of ``raw``) is already made; ``zipfile``
    still computes the CRC and sizes from ``raw``. Where its writer lacks the private ``_compressor`` hook (other
    Python versions), it deflates ``raw`` itself: same archive, slower."""
    with z.open(info, "w") as w:
        if getattr(w, "_compressor", None) is not None:
            w._compressor = _Precompressed(deflated)
        w.write(raw)


def write_png_stack(
    tiles: Iterable[Tile],
    spec: RasterSpec,
    directory: str | os.PathLike,
    *,
    prefix: str = "",
    digits: int = 5,
    level: int = 1,
    deflater: str = "auto",
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, float]:
    """Write one greyscale PNG per tile into ``directory`` (``<prefix>00000.png`` upward), atomically: the
    directory is built under a temporary name and renamed over ``directory`` when complete. An existing
    ``directory`` is replaced only when it holds nothing but ``<prefix>NNNNN.png`` files (an earlier run)."""
    out = Path(os.fspath(directory))
    if out.exists() and not out.is_dir():
        raise ParameterError(f"{out}: exists and is not a directory")
    if out.is_dir():  # replaced as a whole: only if it holds nothing but an earlier stack of this name
        layer = re.compile(re.escape(prefix) + r"\d+\.png")
        others = [p.name for p in out.iterdir() if not (p.is_file() and layer.fullmatch(p.name))]
        if others:
            raise ParameterError(f"{out}: directory holds other files ({others[0]}, ...); give a new or empty one")
    enc = PngEncoder(*spec.png_size, level, deflater)
    with atomic_path(out) as tmp:
        tmp.mkdir()

        def sink(k: int, data: bytes) -> None:
            (tmp / f"{prefix}{k:0{digits}d}.png").write_bytes(data)

        stats = _encode_all(tiles, enc, sink, workers, progress=progress)
    return stats


def write_sl1(
    tiles: Iterable[Tile],
    spec: RasterSpec,
    path: str | os.PathLike,
    info: SL1Info,
    n_layers: int,
    *,
    level: int = 1,
    deflater: str = "auto",
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    now: _dt.datetime | None = None,
) -> dict[str, float]:
    """Write an SL1 archive at ``path`` (atomically) with one PNG per tile; ``n_layers`` tiles are expected.

    Every member is deflated, as PrusaSlicer does (our PNGs shrink to ~0.6 in the zip: their deflate streams repeat
    row after row); the layers' members are deflated on the worker threads with the PNGs.
    """
    p = Path(os.fspath(path))
    if not info.job_dir or any(ch in info.job_dir for ch in "/\\"):
        raise ParameterError(f"{p}: bad job name '{info.job_dir}'")
    enc = PngEncoder(*spec.png_size, level, deflater)
    thumb = _Thumb(spec, n_layers)
    with atomic_path(p) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as z:
        stamp = _zip_time(now)  # every entry carries the same date: with a given ``now`` the bytes are reproducible

        def entry(name: str, kind: int = zipfile.ZIP_DEFLATED) -> zipfile.ZipInfo:
            zi = zipfile.ZipInfo(name, stamp)
            zi.compress_type = kind
            return zi

        z.writestr(entry("config.ini"), config_ini(info, n_layers, now))
        z.writestr(entry("prusaslicer.ini"), prusaslicer_ini(info, spec))

        def encode(tile: Tile) -> tuple[bytes, bytes]:  # on a worker: the PNG and its deflated zip member
            png = enc.encode(tile)
            c = enc.z.compressobj(1, enc.z.DEFLATED, -15)
            return png, c.compress(png) + c.flush()

        def sink(k: int, item: tuple[bytes, bytes]) -> None:
            _write_deflated(z, entry(f"{info.job_dir}{k:05d}.png"), *item)

        stats = _encode_all(tiles, encode, sink, workers, on_tile=thumb.add, progress=progress)
        if stats["layers"] != n_layers:
            raise ParameterError(f"{p}: expected {n_layers} layers, got {stats['layers']}")
        for w, h in THUMBNAILS:
            z.writestr(entry(f"thumbnail/thumbnail{w}x{h}.png"), thumb.png((w, h)))
    return stats


def _zip_time(now: _dt.datetime | None) -> tuple[int, int, int, int, int, int]:
    t = (now or _dt.datetime.now()).timetuple()
    return (max(t.tm_year, 1980), t.tm_mon, t.tm_mday, t.tm_hour, t.tm_min, t.tm_sec)


def used_material_ml(area_mm2: np.ndarray, thickness: np.ndarray) -> float:
    """Resin volume in ml (= cm³) of layers with these areas (mm²) and thicknesses (mm)."""
    v = float(np.dot(np.asarray(area_mm2, np.float64), np.asarray(thickness, np.float64))) / 1000.0
    return v if math.isfinite(v) else 0.0


def info_from(result, job_dir: str, values: Mapping[str, object] | None = None) -> SL1Info:
    """An :class:`SL1Info` for a sliced result (layer height from its thickness, material from its volume)."""
    th = np.asarray(result.thickness, np.float64)
    lh = float(np.median(th[1:])) if th.size > 1 else (float(th[0]) if th.size else 0.05)
    info = SL1Info(job_dir=job_dir, layer_height=round(lh, 6), initial_layer_height=round(float(th[0]), 6)
                   if th.size else None, used_material_ml=used_material_ml(result.area, th))
    for k, v in (values or {}).items():
        setattr(info, k, v)
    return info
