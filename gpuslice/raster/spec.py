"""What a resin printer's display is and how a model is placed on it (:class:`RasterSpec`), the printer presets
(:data:`PRINTERS`, from :mod:`gpuslice.raster.printers`), the grey levels (:func:`gamma_lut`) and the options of a
resin job (:class:`ResinOptions`): each option declared once (:mod:`gpuslice.options`). The mapping model XY → pixels
is described in :mod:`gpuslice.raster.coverage`."""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import ParameterError
from ..options import check_flag, is_real, option, parse_resolution, python_number
from .printers import MAX_PIXEL_MM, MIN_PIXEL_MM, PRINTERS, Printer, find_printer
from .settings import PrintSettings

__all__ = ["RasterSpec", "ResinOptions", "PRINTERS", "BACKENDS", "gamma_lut", "with_printer"]

#: rasterisers: ``auto`` (= ``opencl``), ``opencl`` (runs), ``numpy`` (the runs' numpy twin: the same bytes), ``gl``
#: (moderngl), ``opencl-bitmap`` (the bitmap kernel runs replaced) and ``numpy-bitmap`` (its float64 twin)
BACKENDS = ("auto", "opencl", "numpy", "gl", "opencl-bitmap", "numpy-bitmap")


@dataclass(frozen=True)
class RasterSpec:
    """A resin printer's display and how the model is placed on it (lengths in mm).

    resolution : (nx, ny) pixels: the PNG's width and height.
    pixel : pixel width px, mm; ``pixel_y`` its height py (default: square, = px).
    mirror_x, mirror_y, portrait : display orientation (module docstring).
    keep_xy : keep the model's own XY (bed = model coordinates) instead of centring its bbox on the bed.
    gamma : PrusaSlicer's gamma correction: 1 linear coverage, 0 hard threshold at 50 % coverage.
    """

    resolution: tuple[int, int] = option(
        (3840, 2400), "Display pixels NXxNY along X and Y; PNGs are NXxNY (landscape) or NYxNX (portrait)",
        parse=parse_resolution, metavar="NXxNY", show=lambda r: f"{r[0]}x{r[1]}")
    pixel: float = option(0.05, "Pixel size along X (the display's width)", unit="mm")
    pixel_y: float | None = option(None, "Pixel size along Y (default: square)", unit="mm")
    mirror_x: bool = option(False, "Mirror the columns", negatable=True)
    mirror_y: bool = option(False, "Mirror the rows", negatable=True)
    portrait: bool = option(False, "Display orientation: portrait or landscape", flags=("--portrait/--landscape",),
                            negatable=True)
    keep_xy: bool = option(False, "Keep the model's own XY instead of centring it on the display")
    gamma: float = option(1.0, "Antialiasing gamma (PrusaSlicer's): 1 linear coverage, 0 hard threshold at 50 %")

    def __post_init__(self) -> None:
        res = self.resolution
        whole = (isinstance(res, tuple | list) and len(res) == 2
                 and all(isinstance(v, numbers.Integral) and not isinstance(v, bool) for v in res))
        if not (whole and res[0] > 0 and res[1] > 0):
            raise ParameterError(f"resolution must be two positive integers NXxNY, got {res!r}", param="resolution")
        nx, ny = int(res[0]), int(res[1])
        if nx * ny > 2**31 - 1:
            raise ParameterError(f"resolution {nx}x{ny} is too large", param="resolution")
        object.__setattr__(self, "resolution", (nx, ny))  # (Python ints: numpy ones would reach the headers)
        for name in ("pixel", "pixel_y"):
            v = getattr(self, name)
            if v is None and name == "pixel_y":
                continue
            if not (is_real(v) and math.isfinite(v) and MIN_PIXEL_MM <= v <= MAX_PIXEL_MM):
                raise ParameterError(f"{name} must be a positive number of mm from {MIN_PIXEL_MM:g} up to "
                                     f"{MAX_PIXEL_MM:g}, got {v!r}", param=name)
            object.__setattr__(self, name, python_number(v))
        if not (is_real(self.gamma) and math.isfinite(self.gamma) and self.gamma >= 0):
            raise ParameterError(f"gamma must be a number >= 0, got {self.gamma!r}", param="gamma")
        for name in ("mirror_x", "mirror_y", "portrait", "keep_xy"):
            object.__setattr__(self, name, check_flag(getattr(self, name), name))

    @property
    def nx(self) -> int:
        return int(self.resolution[0])

    @property
    def ny(self) -> int:
        return int(self.resolution[1])

    @property
    def px(self) -> float:
        return float(self.pixel)

    @property
    def py(self) -> float:
        return float(self.pixel if self.pixel_y is None else self.pixel_y)

    @property
    def png_size(self) -> tuple[int, int]:
        """(width, height) of a layer's PNG in pixels: (nx, ny) in landscape, (ny, nx) in portrait."""
        return (self.ny, self.nx) if self.portrait else (self.nx, self.ny)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of a mask: the PNG's (height, width)."""
        w, h = self.png_size
        return h, w

    @property
    def display_mm(self) -> tuple[float, float]:
        """(display_width, display_height) in mm, PrusaSlicer's names: nx·px, ny·py."""
        return self.nx * self.px, self.ny * self.py

    @property
    def bed_mm(self) -> tuple[float, float]:
        """(X, Y) extent of the printable bed in model axes, mm: the display's (width, height) in both orientations."""
        return self.display_mm

    def offset_for(self, bounds: Sequence[float] | None) -> tuple[float, float]:
        """(dx, dy) mm added to model XY to get bed XY: centres ``bounds`` = (xmin, ymin, xmax, ymax) on the bed."""
        if self.keep_xy or bounds is None:
            return 0.0, 0.0
        xmin, ymin, xmax, ymax = (float(b) for b in bounds)
        bx, by = self.bed_mm
        return bx / 2 - (xmin + xmax) / 2, by / 2 - (ymin + ymax) / 2

    def affine(self, bounds: Sequence[float] | None = None) -> np.ndarray:
        """(2, 3) float64 matrix A with (u, v) = A @ (x, y, 1): model mm → continuous pixel coordinates."""
        dx, dy = self.offset_for(bounds)
        w, h = self.display_mm
        if self.portrait:  # u = (h - Y)/py, v = (w - X)/px
            a = np.array([[0.0, -1.0 / self.py, (h - dy) / self.py], [-1.0 / self.px, 0.0, (w - dx) / self.px]])
        else:  # u = X/px, v = (h - Y)/py
            a = np.array([[1.0 / self.px, 0.0, dx / self.px], [0.0, -1.0 / self.py, (h - dy) / self.py]])
        cols, rows = self.png_size
        if self.mirror_x:
            a[0] = -a[0]
            a[0, 2] += cols
        if self.mirror_y:
            a[1] = -a[1]
            a[1, 2] += rows
        return a

    def to_pixels(self, xy: np.ndarray, bounds: Sequence[float] | None = None) -> np.ndarray:
        """(n, 2) float64 continuous pixel coordinates (u = column, v = row) of model points ``xy`` (mm)."""
        out = np.empty((xy.shape[0], 2), np.float64)
        out[:, 0], out[:, 1] = self.to_pixels_xy(xy[:, 0], xy[:, 1], bounds)
        return out

    def to_pixels_xy(self, x: np.ndarray, y: np.ndarray,
                     bounds: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`to_pixels` of coordinate arrays ``x``, ``y`` (mm): (u, v) float64 arrays, the same values."""
        a = self.affine(bounds)
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        # one of a[0, :2] is 0: exact as a matrix product
        return a[0, 0] * x + a[0, 1] * y + a[0, 2], a[1, 0] * x + a[1, 1] * y + a[1, 2]

    def pixel_centres(self, bounds: Sequence[float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Model (x, y) in mm of every pixel centre, two (ny, nx) arrays (inverse of :meth:`affine`)."""
        a = self.affine(bounds)
        inv = np.linalg.inv(np.vstack([a, [0, 0, 1]]))
        v, u = np.mgrid[0 : self.shape[0], 0 : self.shape[1]].astype(np.float64) + 0.5
        return inv[0, 0] * u + inv[0, 1] * v + inv[0, 2], inv[1, 0] * u + inv[1, 1] * v + inv[1, 2]


def gamma_lut(gamma: float) -> np.ndarray:
    """(256,) uint8: grey for ``k = min(255, floor(256·coverage))``, as agg's ``gamma_power``/``gamma_threshold``."""
    if not (is_real(gamma) and math.isfinite(gamma) and gamma >= 0):  # (RasterSpec's rule; -1 or NaN made numpy warn)
        raise ParameterError(f"gamma must be a number >= 0, got {gamma!r}", param="gamma")
    k = np.arange(256, dtype=np.float64) / 255.0
    if gamma == 0:
        return np.where(k >= 0.5, 255, 0).astype(np.uint8)
    return np.floor(255.0 * k**gamma + 0.5).astype(np.uint8)


def same_display(a: RasterSpec, b: RasterSpec) -> bool:
    """Whether two displays have the same pixels and pixel sizes (within 0.5 %): one printer's."""
    return tuple(a.resolution) == tuple(b.resolution) and all(
        abs(x - y) <= 0.005 * y for x, y in ((a.px, b.px), (a.py, b.py)))


def display_text(s: RasterSpec) -> str:
    """``"11520x5120 px of 0.019 x 0.024 mm"``."""
    return f"{s.resolution[0]}x{s.resolution[1]} px of {s.px:g} x {s.py:g} mm"


def orientation_text(s: RasterSpec) -> str:
    """``"landscape, mirror x"``: the display's orientation and mirrors (as ``gpuslice printers`` lists them)."""
    return ", ".join(["portrait" if s.portrait else "landscape"]
                     + [f"mirror {a}" for a in ("x", "y") if getattr(s, f"mirror_{a}")])


def with_printer(name: str, **overrides) -> RasterSpec:
    """A :class:`RasterSpec` of the preset ``name`` (:data:`PRINTERS`, or a preset file) with ``overrides``."""
    if not isinstance(name, str | os.PathLike):  # (5 was an AttributeError, an array "unhashable")
        raise ParameterError(f"printer must be a preset's name or a preset file, got {type(name).__name__}",
                             param="printer")
    return replace(RasterSpec(**find_printer(os.fspath(name)).display()), **overrides)


@dataclass(frozen=True)
class ResinOptions:
    """How a resin job is rasterised and encoded, besides the display (:class:`RasterSpec`); times in s."""

    printer: str | None = option(None, "Printer preset: a name `gpuslice printers` lists, or a .toml/.json preset "
                                 "file; options given override its values (raster: an archive naming the printer "
                                 "is written at its display only; a PNG stack takes display options too)")
    raster_backend: str = option("auto", "Rasteriser: auto is opencl (run-length runs); gl is the optional "
                                 "moderngl pass", choices=BACKENDS)
    supersample: int = option(8, "GL backend: samples per pixel side (1-16)")
    png_level: int = option(1, "Deflate level of each layer's non-blank rows (0-9); at 1 the OpenCL rasteriser "
                             "deflates straight from its runs (fastest, smaller files)")
    job_name: str | None = option(None, "SL1 jobDir and PNG prefix (default: the model's file name)")
    workers: int | None = option(None, "Layer encoding threads (and, with GPUSLICE_PNG_PROCESSES=1, processes "
                                       "for PNG layers made from runs) (default: the CPUs; 1: one thread)")
    z_samples: int = option(1, "Anti-aliasing in Z: each layer's greys averaged over this many planes inside its "
                            "slab (1: off; needs the OpenCL rasteriser)")
    #: the :class:`Printer` that ``printer`` names, read elsewhere (a batch's client read the preset file, which a
    #: Dask worker may not have): used instead of reading it again
    preset_read: Printer | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("printer", "job_name", "raster_backend"):
            v = getattr(self, name)
            if not (isinstance(v, str) or (v is None and name != "raster_backend")):
                raise ParameterError(f"{name} must be text, got {v!r}", param=name)
        for name in ("supersample", "png_level", "z_samples", "workers"):
            v = getattr(self, name)
            if not ((v is None and name == "workers") or (isinstance(v, numbers.Integral) and not isinstance(v, bool))):
                raise ParameterError(f"{name} must be a whole number, got {v!r}", param=name)
        if self.printer is not None and self.preset_read is None:
            find_printer(self.printer)
        if self.raster_backend not in BACKENDS:
            raise ParameterError(f"unknown raster backend '{self.raster_backend}' (use {', '.join(BACKENDS)})",
                                 param="raster_backend")
        if not 1 <= self.supersample <= 16:
            raise ParameterError(f"supersample must be from 1 to 16, got {self.supersample}", param="supersample")
        if not 0 <= self.png_level <= 9:
            raise ParameterError(f"png_level must be from 0 to 9, got {self.png_level}", param="png_level")
        if not 1 <= self.z_samples <= 64:
            raise ParameterError(f"z_samples must be from 1 to 64, got {self.z_samples}", param="z_samples")
        if self.z_samples > 1 and self.raster_backend not in ("auto", "opencl"):
            raise ParameterError(f"z_samples needs the OpenCL rasteriser (raster_backend opencl), not "
                                 f"{self.raster_backend}", param=("z_samples", "raster_backend"))
        if self.workers is not None and not 1 <= self.workers <= 256:
            raise ParameterError(f"workers must be from 1 to 256, got {self.workers}", param="workers")
        if self.job_name is not None and (not self.job_name or any(ch in self.job_name for ch in "/\\\0")):
            # a PNG stack's layers are <job name>NNNNN.png in its folder: '../x' would write them beside it
            raise ParameterError(f"job_name {self.job_name!r}: a job name is a file name prefix; it cannot hold '/' "
                                 "or '\\', nor be empty", param="job_name")

    def spec(self, **display) -> RasterSpec:
        """The :class:`RasterSpec`: the preset's values (if any) overridden by ``display`` values that are not None."""
        kw = self.preset.display() if self.preset is not None else {}
        kw.update({k: v for k, v in display.items() if v is not None})
        return RasterSpec(**kw)

    @property
    def preset(self) -> Printer | None:
        """The :class:`~gpuslice.raster.printers.Printer` that ``printer`` names, or None."""
        if self.preset_read is not None:
            return self.preset_read
        return find_printer(self.printer) if self.printer is not None else None

    def settings(self, **given) -> PrintSettings:
        """The :class:`~gpuslice.raster.settings.PrintSettings`: defaults, then the preset's, then ``given`` values
        that are not None."""
        preset = self.preset
        base = PrintSettings().with_values(preset.settings) if preset is not None else PrintSettings()
        return base.with_values(given)

    def check_format(self, fmt: str, spec: RasterSpec | None = None) -> None:
        """:class:`ParameterError` when the preset's printer cannot read the resin output ``fmt``, or when ``spec``'s
        display is not the display of the printer the archive names (:meth:`check_display`)."""
        preset = self.preset
        if preset is not None and not preset.reads(fmt):
            raise ParameterError(f"printer {preset.name} reads {', '.join(preset.formats)}, not {fmt}")
        if spec is not None:
            self.check_display(fmt, spec)

    def check_display(self, fmt: str, spec: RasterSpec) -> None:
        """:class:`ParameterError` when a printer archive ``fmt`` would carry the preset's machine name at a display
        ``spec`` that is not the preset's (``--printer`` with another ``--resolution`` or ``--pixel``, or another
        orientation or mirror): a firmware refuses such a file, or prints it at the wrong size or mirrored. A PNG
        stack names no printer. Pixel sizes compare within 0.5 % (:func:`same_display`). Without a preset, a format
        whose suffix names a machine checks the display itself (Photon Workshop:
        :func:`gpuslice.raster.photon_machines.refuse_settings`)."""
        from .printers import ANY_PRINTER_FORMATS

        preset = self.preset
        if fmt in ANY_PRINTER_FORMATS or preset is None:
            return
        want = RasterSpec(**preset.display())
        if not same_display(spec, want):
            raise ParameterError(f"printer {preset.name}'s display is {display_text(want)}, not the "
                                 f"{display_text(spec)} asked (leave --resolution/--pixel/--pixel-y out, or write a "
                                 "preset file of your printer)")
        if orientation_text(spec) != orientation_text(want):  # (a mirror left out prints the part mirrored)
            raise ParameterError(f"printer {preset.name}'s display is {orientation_text(want)}, not "
                                 f"{orientation_text(spec)} as asked (leave --portrait/--landscape/--mirror-x/"
                                 "--mirror-y out, or write a preset file of your printer)")
