"""Pre-print checks, a stage of the pipeline after slicing: islands and unsupported area (:mod:`.islands`), resin
traps and suction cups (:mod:`.cavities`), cross-section per layer, print time and resin (:mod:`.summary`), for
every layer in one pass, as columns (:class:`CheckReport`, ``to_json()``).

``run_checks(result)`` checks the contours (islands contour-exact, shapely/GEOS); ``run_checks(result, spec)`` the
pixels of a printer's display (islands pixel-exact on its grid). Traps and cups use a voxel grid of
:attr:`CheckOptions.trap_grid` mm cells (default 0.2 mm; 0: the display's pixels), see :mod:`.cavities` for its
resolution and error. ``gpuslice check``, ``raster --check`` and ``view --check`` run them through
:func:`gpuslice.pipeline.run_job`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..options import is_real, option
from ..raster.printers import MAX_PIXEL_MM, MIN_PIXEL_MM
from .cavities import DEFAULT_GRID_MM, KINDS, SUCTION_CUP, TRAP, Cavities, CavityFinder, enclosed_in_outlines
from .islands import Islands, PixelIslands, contour_islands
from .summary import CheckReport, peel_and_time

__all__ = ["CheckOptions", "CheckReport", "Islands", "Cavities", "run_checks", "contour_islands", "pixel_islands",
           "layer_intervals", "KINDS", "TRAP", "SUCTION_CUP", "DEFAULT_GRID_MM"]


#: the coarsest trap grid, mm (the grid is a display of such cells: a display's largest pixel)
MAX_TRAP_GRID_MM = MAX_PIXEL_MM


@dataclass(frozen=True)
class CheckOptions:
    """Options of the pre-print checks (lengths in mm)."""

    overhang_tolerance: float | None = option(
        None, "Grow the layer below by this much before measuring a layer's unsupported area; in contours also the "
        "pixel whose half area is the least contact that holds a region and whose half is the widest gap that joins "
        "two (default: one pixel of the printer's display, or of the default 0.05 mm display)", unit="mm")
    trap_grid: float = option(DEFAULT_GRID_MM, "Cell of the voxel grid for resin traps and suction cups (0: the "
                              "printer's pixels, with --printer)", unit="mm")

    def __post_init__(self) -> None:
        for name, value in (("overhang_tolerance", self.overhang_tolerance), ("trap_grid", self.trap_grid)):
            if value is None and name == "overhang_tolerance":
                continue
            if not is_real(value):
                raise ParameterError(f"{name} must be a number (mm), got {value!r}", param=name)
            if not (math.isfinite(value) and value >= 0):
                raise ParameterError(f"{name} must be >= 0 mm, got {value}", param=name)
            if name == "trap_grid" and value > MAX_TRAP_GRID_MM:  # (its cells are a display's pixels: their bound)
                raise ParameterError(f"trap_grid must be at most {MAX_TRAP_GRID_MM:g} mm, got {value:g}", param=name)
            # a pixel's bounds: a trap grid of 5e-324 mm made the grid's width infinite (an internal error); an
            # overhang tolerance of 1e308 an infinite least contact (refused as "support", a name of no flag)
            if name == "overhang_tolerance" and value > MAX_PIXEL_MM:
                raise ParameterError(f"overhang_tolerance must be at most {MAX_PIXEL_MM:g} mm, got {value:g}",
                                     param=name)
            if name == "trap_grid" and 0 < value < MIN_PIXEL_MM:
                raise ParameterError(f"trap_grid must be 0 or at least {MIN_PIXEL_MM:g} mm, got {value:g}", param=name)


def _check_arguments(result, spec, settings, options, bounds, backend: str, workers) -> None:
    """One-line :class:`ParameterError` for arguments of :func:`run_checks` of the wrong kind, before any work."""
    from ..raster.edges import check_raster_args
    from ..raster.settings import PrintSettings

    check_raster_args(result, spec, bounds=bounds)  # result, spec and bounds as the rasterisers take them
    for name, value, kind, hint in (
        ("settings", settings, PrintSettings, "gpuslice.raster.PrintSettings, or None"),
        ("options", options, CheckOptions, "gpuslice.checks.CheckOptions, or None"),
    ):
        if value is not None and not isinstance(value, kind):
            raise ParameterError(f"{name} must be a {kind.__name__} ({hint}), got {type(value).__name__}")
    if backend not in ("auto", "opencl", "numpy"):
        raise ParameterError(f"unknown checks backend {backend!r} (use auto, opencl or numpy)")
    if workers is not None and not (is_real(workers) and float(workers).is_integer() and workers >= 1):
        raise ParameterError(f"workers must be a whole number >= 1 (or None: the CPUs), got {workers!r}")


def _pixel_mm(spec) -> tuple[float, float]:
    """A pixel's size (mm) along the PNG's columns and along its rows."""
    return (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)


def _to_mm(spec, bounds) -> np.ndarray:
    return np.linalg.inv(np.vstack([spec.affine(bounds), [0.0, 0.0, 1.0]]))[:2]


def _coarse_spec(bounds, grid: float):
    """A display of ``grid`` mm cells over ``bounds`` plus two empty cells all round (the model centred on it)."""
    from ..raster.spec import RasterSpec

    xmin, ymin, xmax, ymax = bounds
    # (a span of a whole number of cells stays one: float32 bounds are a few ulps wide of a round size, and one cell
    # more would centre the model half a cell off the grid, every wall cell then half solid and counted so)
    nx = int(math.ceil((xmax - xmin) / grid - 1e-6)) + 4
    ny = int(math.ceil((ymax - ymin) / grid - 1e-6)) + 4
    if nx * ny > 2**31 - 1:
        raise ParameterError(f"trap_grid {grid:g} mm is too fine for a {xmax - xmin:.0f} x {ymax - ymin:.0f} mm model",
                             param="trap_grid")
    return RasterSpec(resolution=(nx, ny), pixel=grid, gamma=0.0)


def hole_layers(result) -> np.ndarray:
    """The layers next to empty space enclosed in a layer: those with a hole loop, and the layers just above and
    below them (sorted). Only there can a trap or a suction cup be: a layer without a hole has no enclosed empty
    space (every empty point of it reaches the outside within the layer)."""
    holes = np.asarray(result.loop_is_hole, bool) & np.asarray(result.loop_closed, bool)
    lay = np.unique(np.asarray(result.loop_layer)[holes])
    near = np.unique(np.concatenate([lay - 1, lay, lay + 1])) if lay.size else lay
    return near[(near >= 0) & (near < result.n_layers)].astype(np.int64)


def layer_intervals(result, spec, bounds=None, *, backend: str = "auto", device=None,
                    max_batch_pieces: int | None = None, layers=None):
    """Yield ``(first layer, layers, (layer, row, start, end))`` per batch of consecutive layers: the pixels of
    ``spec``'s display that ``result``'s polygons cover at least half (:func:`gpuslice.raster.runs.iter_runs` with a
    hard threshold), as merged row intervals. ``bounds``: what is centred (default: the result's points);
    ``max_batch_pieces``: the rasteriser's batch size (memory), default its own; ``layers``: these (sorted) only,
    a batch per run of consecutive ones."""
    from ..raster.edges import result_bounds
    from ..raster.runs import iter_runs
    from .intervals import solid_intervals

    backend, device = _backend(backend, device)
    extra = {} if max_batch_pieces is None else {"max_batch_pieces": int(max_batch_pieces)}
    bounds = bounds if bounds is not None else result_bounds(result)
    sel = None if layers is None else np.asarray(layers, np.int64)
    if sel is not None and sel.size == 0:
        return
    for runs in iter_runs(result, replace(spec, gamma=0.0), backend=backend, device=device, bounds=bounds,
                          layers=sel, **extra):
        lay = np.asarray(runs.layers, np.int64)
        if not lay.size:
            continue
        parts = solid_intervals(runs, 128)
        cut = np.flatnonzero(np.diff(lay) != 1) + 1  # runs of consecutive layers
        for a, b in zip(np.r_[0, cut], np.r_[cut, lay.size], strict=True):
            i, j = np.searchsorted(parts[0], [lay[a], lay[b - 1] + 1])
            yield int(lay[a]), int(b - a), tuple(p[i:j] for p in parts)


def pixel_islands(result, spec, *, tolerance: float | None = None, bounds=None, backend: str = "auto",
                  device=None) -> Islands:
    """Islands and unsupported area on ``spec``'s pixels alone (:class:`~gpuslice.checks.islands.PixelIslands`);
    ``tolerance`` mm (default: one pixel), other arguments as :func:`run_checks`."""
    from ..raster.edges import result_bounds

    bounds = bounds if bounds is not None else result_bounds(result)
    tol = float(max(spec.px, spec.py) if tolerance is None else tolerance)
    cw, rh = _pixel_mm(spec)
    pix = PixelIslands(result.n_layers, spec.shape[0], spec.shape[1], _to_mm(spec, bounds), cw, rh, tol)
    if bounds is not None:
        for layer0, k, parts in layer_intervals(result, spec, bounds, backend=backend, device=device):
            pix.feed(layer0, k, parts)
    return pix.result()


def _backend(backend: str, device) -> tuple[str, Any]:
    if backend == "numpy":
        return "numpy", None
    if device is not None:
        return "opencl", device
    try:
        from ..device import get_device

        return "opencl", get_device()
    except Exception:  # no OpenCL: the runs' numpy twin
        if backend == "opencl":
            raise
        return "numpy", None


def _cavities(result, finder, grid_spec, bounds, backend: str, device, spec, options):
    """The traps and suction cups: the layers with holes rasterised on the trap grid (unless they were fed with the
    printer's pixels already), then :meth:`CavityFinder.result`."""
    if not (spec is not None and options.trap_grid == 0):
        near = hole_layers(result)  # the other layers have no enclosed empty space: not rasterised
        for layer0, k, parts in layer_intervals(result, grid_spec, bounds, backend=backend, device=device,
                                                layers=near):
            finder.feed(layer0, k, parts)
    return finder.result(enclosed=lambda lay, x, y: enclosed_in_outlines(result, lay, x, y))


def run_checks(result, spec=None, settings=None, *, options: CheckOptions | None = None,
               bounds: tuple[float, float, float, float] | None = None, backend: str = "auto", device=None,
               workers: int | None = None, name: str = "model") -> CheckReport:
    """Check ``result`` (a :class:`~gpuslice.slicing.result.SliceResult`) before printing; see the package docstring.

    spec : a :class:`~gpuslice.raster.spec.RasterSpec` (a printer's display): islands and unsupported area on its
        pixels, placed as the archive places them (``bounds``, default the result's, centred unless ``keep_xy``);
        None: on the contours. settings : :class:`~gpuslice.raster.settings.PrintSettings` for the print time and
        the resin's mass (default: the defaults). options : :class:`CheckOptions`. backend : the rasteriser of the
        masks, ``"opencl"``, ``"numpy"`` or ``"auto"`` (OpenCL when there is a device); device : the OpenCL device.
        workers : threads for the contour checks (default: the CPUs). name : the file named in errors.
    """
    from ..raster.edges import check_fits, result_bounds
    from ..raster.settings import PrintSettings
    from ..raster.spec import RasterSpec

    _check_arguments(result, spec, settings, options, bounds, backend, workers)
    options = options or CheckOptions()
    settings = settings or PrintSettings()
    timings: dict[str, float] = {}
    n = result.n_layers
    if options.trap_grid == 0 and spec is None:
        raise ParameterError("trap_grid 0 (the printer's pixels) needs a printer's display", param="trap_grid")
    bounds = bounds if bounds is not None else result_bounds(result)
    if options.overhang_tolerance is not None:
        tol = float(options.overhang_tolerance)
    else:
        tol = float(max(spec.px, spec.py) if spec is not None else RasterSpec().pixel)
    backend, device = _backend(backend, device)
    empty = bounds is None or n == 0
    finder = None
    if not empty:
        grid_spec = spec if options.trap_grid == 0 else _coarse_spec(bounds, float(options.trap_grid))
        cw, rh = _pixel_mm(grid_spec)
        finder = CavityFinder(grid_spec.shape[0], grid_spec.shape[1], _to_mm(grid_spec, bounds), cw * rh,
                              result.thickness, result.z, cw if cw == rh else math.sqrt(cw * rh))
    t = time.perf_counter()
    if spec is None or empty:
        traps = None
        if finder is not None:  # the cavities' grid on the device while GEOS's threads take the contours
            from ..prefetch import beside

            traps = beside(_cavities, result, finder, grid_spec, bounds, backend, device, spec, options,
                           name="gpuslice-cavities")
        islands = contour_islands(result, tol, workers=workers) if not empty else Islands.concat([], n)
    else:
        check_fits(result, spec, bounds, name=name)
        cw, rh = _pixel_mm(spec)
        pix = PixelIslands(n, spec.shape[0], spec.shape[1], _to_mm(spec, bounds), cw, rh, tol)
        shared = options.trap_grid == 0
        for layer0, k, parts in layer_intervals(result, spec, bounds, backend=backend, device=device):
            pix.feed(layer0, k, parts)
            if shared:
                finder.feed(layer0, k, parts)
        islands = pix.result()
    timings["islands"] = time.perf_counter() - t
    t = time.perf_counter()
    if finder is None:
        cavities = CavityFinder(1, 1, np.eye(3)[:2], 1.0, np.zeros(0), np.zeros(0), float(options.trap_grid)).result()
    elif spec is None:
        cavities = traps.result()
    else:
        cavities = _cavities(result, finder, grid_spec, bounds, backend, device, spec, options)
    timings["cavities"] = time.perf_counter() - t
    peel = peel_and_time(result, settings)
    display = None
    if spec is not None:
        display = {"resolution": [spec.nx, spec.ny], "pixel": [spec.px, spec.py], "portrait": spec.portrait}
    open_ = ~np.asarray(result.loop_closed, bool)
    return CheckReport(islands, cavities, peel["area"], peel["max_area"], peel["max_area_layer"],
                       peel["print_time_s"], peel["resin_ml"], peel["resin_g"], peel["resin_density"],
                       "pixels" if spec is not None else "contours", tol, display, np.asarray(result.z), timings,
                       int(open_.sum()), int(np.unique(np.asarray(result.loop_layer)[open_]).size),
                       int(result.meta.get("repairs", {}).get("filled_holes", 0)))
