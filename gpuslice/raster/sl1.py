"""SL1 archives, as PrusaSlicer 2.5 writes them (a zip).

Members: ``config.ini``, ``prusaslicer.ini``, ``<jobDir>00000.png`` upward, ``thumbnail/thumbnail400x400.png`` and
``thumbnail/thumbnail800x480.png`` (a shaded top view: a height map), every member deflated (the layers' on the
worker threads, with their PNGs: :mod:`gpuslice.raster.png`). Archives are written under a temporary name and
renamed when complete (:func:`gpuslice.io.atomic.atomic_path`). With a given ``now`` (``SOURCE_DATE_EPOCH`` on the
command line) the bytes are reproducible.
"""

from __future__ import annotations

import datetime as _dt
import io
import math
import os
import zipfile
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from .coverage import Tile
from .layers import HeightMap, RunLayer, encode_png, run_groups, top_view
from .png import PngEncoder, encode_all
from .png_runs import png_encoders, png_group
from .settings import header_layer_height, median
from .spec import RasterSpec

__all__ = ["SL1Info", "config_ini", "prusaslicer_ini", "read_sl1_config", "write_sl1", "info_from",
           "used_material_ml", "write_target", "THUMBNAILS"]


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
    printer_variant: str = ""  # the Prusa firmware expects "default" (else it warns of a variant mismatch)
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


#: layers PrusaSlicer's estimate exposes for the initial exposure time before the fade starts
SL1_INITIAL_LAYERS = 3


def sl1_print_time(info: SL1Info, n_layers: int) -> float:
    """config.ini's ``printTime`` (s), as PrusaSlicer estimates a tilting SL1 (no lift moves): the first
    :data:`SL1_INITIAL_LAYERS` layers at ``initial_exposure_time``, then ``faded_layers`` + 1 layers stepping down by
    (initial − exposure) / (faded_layers + 1) each to ``exposure_time``, the rest at ``exposure_time``; and one tilt
    per layer (``tilt_time``, the fast tilt)."""
    n = max(int(n_layers), 0)
    first = min(n, SL1_INITIAL_LAYERS)
    init, exp = float(info.initial_exposure_time), float(info.exposure_time)
    fade = 0
    total = first * init
    if init > exp:
        fade = min(n - first, int(info.faded_layers) + 1)
        step = (init - exp) / (int(info.faded_layers) + 1)
        total += fade * init - step * fade * (fade + 1) / 2  # init − j·step for j = 1 … fade
    return total + (n - first - fade) * exp + n * float(info.tilt_time)


def tilt_print_time(settings, n_layers: int, tilt_s: float | None = None) -> float:
    """The SL1's own print time (s) of ``n_layers`` at ``settings`` (:func:`sl1_print_time`: exposures and one tilt a
    layer, ``tilt_s``, default :attr:`SL1Info.tilt_time`): what its ``config.ini`` states
    (``ResinFormat.print_time``)."""
    tilt = SL1Info.tilt_time if tilt_s is None else tilt_s
    info = SL1Info(job_dir="", exposure_time=settings.exposure, initial_exposure_time=settings.bottom_exposure,
                   faded_layers=settings.transition_layers, tilt_time=tilt)
    return sl1_print_time(info, n_layers)


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """The SL1 family's settings check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`): config.ini has
    no count of bottom layers, so ``bottom_layers`` other than 1 is refused rather than dropped, and no lift,
    retract, rest or light-intensity setting (the printer tilts its vat and keeps its own), so any of those given
    beyond the preset's (:func:`~gpuslice.raster.settings.changed_settings`) is refused too."""
    from .settings import MOTION_REST_LIGHT, changed_settings

    if settings.bottom_layers != 1:
        raise ParameterError(f"{path}: an SL1 archive has one bottom layer (expTimeFirst), then "
                             f"--transition-layers fade layers; --bottom-layers {settings.bottom_layers} cannot be "
                             "written")
    unstored = changed_settings(settings, (*MOTION_REST_LIGHT, "per_layer_settings"),
                                base=options.settings() if options is not None else None)
    if unstored:
        raise ParameterError(f"{path}: an SL1 archive stores no lift, retract, rest, light-intensity or per-layer "
                             f"settings (the printer tilts its vat): {', '.join(unstored)} cannot be written (leave "
                             "them out)")


def sl1_values(target) -> dict[str, object]:
    """The :class:`SL1Info` values of a job's print settings and preset, for the SL1 family's writers. SL1's
    config.ini exposes the first layer with ``expTimeFirst`` and fades over ``numFade`` layers; it has no count of
    bottom layers and no lift settings (the printer tilts its vat): ``bottom_layers`` other than 1 is refused
    (:class:`ParameterError` naming the output) rather than dropped."""
    s, preset = target.settings, target.options.preset
    refuse_settings(target.path, "sl1", target.options, s)
    values: dict[str, object] = {"exposure_time": s.exposure, "initial_exposure_time": s.bottom_exposure,
                                 "faded_layers": s.transition_layers}
    if preset is not None and preset.machine:  # the firmware refuses a project made for another model
        values.update(printer_model=preset.machine, printer_variant="default")
    return values


def config_ini(info: SL1Info, n_layers: int, now: _dt.datetime | None = None) -> str:
    """``config.ini`` text: the keys PrusaSlicer 2.5 writes, sorted as it writes them."""
    from .. import __version__

    now = now or _dt.datetime.now(_dt.timezone.utc)
    n_fade = min(info.faded_layers, max(n_layers - 1, 0))
    print_time = sl1_print_time(info, n_layers)
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
        "printerVariant": info.printer_variant,
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


class _Thumb(HeightMap):
    """Top view of the part for the thumbnails: a height map (:class:`~gpuslice.raster.layers.HeightMap`: the
    highest layer covering each spot, shaded from dark at the bed to bright at the top) on every ``step``-th pixel
    of the display, shown as seen from above (:func:`~gpuslice.raster.layers.top_view`: not mirrored or turned as
    the display's layers are)."""

    def __init__(self, spec: RasterSpec, n_layers: int, step: int | None = None) -> None:
        # every 4th pixel up to 4K displays; coarser above, so the map stays about 960 samples wide (the largest
        # thumbnail is 800 wide) and sampling costs the same on any display (a 12K display at 4 took 4 s)
        super().__init__(spec.shape, n_layers, step if step is not None else max(4, -(-max(spec.shape) // 960)))
        # a row's height over a column's width in the top view (non-square pixels, e.g. a 12K Saturn's 0.019 x
        # 0.024 mm): the thumbnails stretch the rows by it so that the part keeps its shape
        self.spec, self.aspect = spec, spec.py / spec.px

    def png(self, size: tuple[int, int]) -> bytes:
        """The top view fitted into ``size`` (width, height) pixels, as a PNG file's bytes (:meth:`image`)."""
        buf = io.BytesIO()
        self.image(size).save(buf, format="PNG")
        return buf.getvalue()

    def image(self, size: tuple[int, int]):
        """The top view as an RGB ``PIL.Image`` of ``size`` (width, height): the part cropped with a margin,
        scaled to fit with its aspect kept, on a dark background (the formats with raw previews take its pixels,
        the PNG-based ones :meth:`png`)."""
        from PIL import Image

        src = top_view(self.img, self.spec)
        if src.shape[0] and abs(self.aspect - 1.0) > 1e-9:  # nearest rows: the map at square cells
            h = src.shape[0]
            rows = max(1, round(h * self.aspect))
            src = src[(np.arange(rows) * h) // rows]
        ys, xs = np.nonzero(src)
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
        return canvas


THUMBNAILS = ((400, 400), (800, 480))



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
    device=None,
) -> dict[str, float]:
    """Write an SL1 archive at ``path`` (atomically) with one PNG per tile; ``n_layers`` tiles are expected.
    ``device``: the OpenCL device of the layers' runs, where their PNGs are made (``kernels/png.cl``) at ``level``
    1; None: numpy, in processes where the command allows them.

    Every member is deflated, as PrusaSlicer does (our PNGs shrink to ~0.6 in the zip: their deflate streams repeat
    row after row); the layers' members are deflated on the worker threads with the PNGs.
    """
    p = Path(os.fspath(path))
    if not info.job_dir or any(ch in info.job_dir for ch in "/\\"):
        raise ParameterError(f"{p}: bad job name '{info.job_dir}'")
    enc = PngEncoder(*spec.png_size, level, deflater)
    thumb = _Thumb(spec, n_layers)
    with atomic_path(p) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as fh, \
            zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as z:
        stamp = _zip_time(now)  # every entry carries the same date: with a given ``now`` the bytes are reproducible

        def entry(name: str, kind: int = zipfile.ZIP_DEFLATED) -> zipfile.ZipInfo:
            zi = zipfile.ZipInfo(name, stamp)
            zi.compress_type = kind
            return zi

        z.writestr(entry("config.ini"), config_ini(info, n_layers, now))
        z.writestr(entry("prusaslicer.ini"), prusaslicer_ini(info, spec))

        def encode(item: Tile | RunLayer) -> tuple[bytes, bytes]:  # on a worker: the PNG and its deflated member
            png = encode_png(item, enc)
            return png, _member(enc, png)

        from .png_procs import encode_group as encode_procs
        from .png_procs import threads_for

        device, pool = png_encoders(level, device, workers)

        def encode_group(group: list[Tile | RunLayer]) -> list[tuple[bytes, bytes]]:  # on a worker thread
            pngs = png_group(device, group, enc.nx, enc.ny)
            if pngs is not None:  # made on the device; the members deflated here (zlib releases the GIL)
                return [(png, _member(enc, png)) for png in pngs]
            if pool is not None and isinstance(group[0], RunLayer):  # PNGs and members made in the processes
                return encode_procs(pool, group, enc.nx, enc.ny, deflater)
            return [encode(item) for item in group]

        def sink(k: int, item: tuple[bytes, bytes]) -> None:
            _write_deflated(z, entry(f"{info.job_dir}{k:05d}.png"), *item)

        stats = encode_all(tiles, encode, sink, threads_for(pool, workers), on_tile=thumb.add, progress=progress,
                           many=encode_group, chunk=run_groups)
        if stats["layers"] != n_layers:
            raise ParameterError(f"{p}: expected {n_layers} layers, got {stats['layers']}")
        for w, h in THUMBNAILS:
            z.writestr(entry(f"thumbnail/thumbnail{w}x{h}.png"), thumb.png((w, h)))
    return stats


def _member(enc: PngEncoder, png: bytes) -> bytes:
    """A PNG's zip member data: raw deflate at level 1 (as the archive's other members)."""
    c = enc.z.compressobj(1, enc.z.DEFLATED, -15)
    return c.compress(png) + c.flush()


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
    lh = header_layer_height(th, empty=0.05)
    info = SL1Info(job_dir=job_dir, layer_height=round(lh, 6), initial_layer_height=round(float(th[0]), 6)
                   if th.size else None, used_material_ml=used_material_ml(result.area, th))
    for k, v in (values or {}).items():
        setattr(info, k, v)
    return info


def check_one_layer_height(thickness: np.ndarray, path: Path, first_may_differ: bool = True) -> float:
    """The one layer height (mm) of a schedule whose layers all have it (the first may differ when
    ``first_may_differ``); :class:`ParameterError` naming ``path`` otherwise (adaptive layers)."""
    th = np.asarray(thickness, np.float64)
    rest = th[1:] if first_may_differ and th.size > 1 else th
    if rest.size == 0:
        return float(th[0]) if th.size else 0.0
    lo, hi = float(rest.min()), float(rest.max())
    if hi - lo > 1e-6 * max(hi, 1.0):
        raise ParameterError(f"{path}: this format holds one layer height, the layers here are {lo:g} to {hi:g} mm "
                             f"thick (adaptive layers need another format)")
    return median(rest)


def write_target(tiles: Iterable[Tile], target) -> dict[str, float]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): an SL1 archive of ``target.result``'s layers."""
    check_one_layer_height(target.result.thickness, Path(target.path))
    info = info_from(target.result, target.name, sl1_values(target))
    n = target.result.n_layers
    stats = write_sl1(tiles, target.spec, target.path, info, n, level=target.options.png_level,
                      deflater=target.deflater, workers=target.workers, progress=target.progress, now=target.now,
                      device=target.device)
    return {**stats, "print_time_s": sl1_print_time(info, n)}
