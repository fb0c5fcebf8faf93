"""The schedule options checked without a mesh: what :func:`~gpuslice.schedule.adaptive.cusp_schedule`,
:func:`~gpuslice.schedule.adaptive.roi_schedule` and :func:`~gpuslice.schedule.uniform.uniform` refuse before they
look at the mesh, and :func:`check_schedule_params`, all of it for a :class:`~gpuslice.slicing.params.SliceParams`:
a batch refuses bad layer settings before its first model (``gpuslice batch -t 0``), not once per model."""

from __future__ import annotations

import numpy as np

from ..errors import ParameterError
from ..options import is_finite, is_real, shown

__all__ = ["check_error_bounded", "check_heights", "check_roi", "check_schedule_params", "check_uniform",
           "MIN_LAYER_MM"]

#: the thinnest uniform layer, mm (1 nm: a first layer of 1e-300 mm had its plane at z = 0 in float32, a layer of
#: no area without a word)
MIN_LAYER_MM = 1e-6


def check_uniform(thickness, first_layer, z_mode: str) -> None:
    """The options of a uniform schedule (see :func:`~gpuslice.schedule.uniform.uniform`): a positive thickness and
    first layer, mm, and a known ``z_mode`` (``paper`` without a first layer of its own)."""
    if not (is_finite(thickness) and float(thickness) > 0):
        raise ParameterError(f"thickness must be a positive number of mm (the layers'), got {shown(thickness)}",
                             param="thickness")
    if not (first_layer is None or (is_finite(first_layer) and float(first_layer) > 0)):
        raise ParameterError(f"first_layer must be a positive number of mm (its thickness), got {shown(first_layer)}",
                             param="first_layer")
    for name, v in (("thickness", thickness), ("first_layer", first_layer)):  # (a first layer of 5e-324 mm was cut
        if v is not None and float(v) < MIN_LAYER_MM:  # on the bed in float32: a layer of no area, without a word)
            raise ParameterError(f"{name} must be at least {MIN_LAYER_MM:g} mm, got {shown(v)}", param=name)
    if z_mode not in ("mid", "paper"):
        raise ParameterError(f"unknown z mode '{z_mode}' (use 'mid' or 'paper')")
    if z_mode == "paper" and first_layer is not None:
        raise ParameterError("first_layer applies to z_mode 'mid' only", param=("first_layer", "z_mode"))


def check_heights(min_height: float, max_height: float) -> None:
    """``min_height`` > 0 and ``max_height`` >= it, mm (the error-bounded modes' thickness clamp)."""
    if not (is_finite(min_height) and float(min_height) > 0):
        raise ParameterError(f"min_height must be a positive number of mm, got {shown(min_height)}",
                             param="min_height")
    if not (is_finite(max_height) and float(max_height) >= float(min_height)):
        raise ParameterError(f"max_height must be >= min_height ({shown(min_height)} mm), got {shown(max_height)}",
                             param=("max_height", "min_height"))


def check_error_bounded(mode: str, max_cusp, max_area, min_height, max_height, smooth, resolution=None) -> None:
    """The options of an error-bounded schedule (``mode`` "cusp" or "area"; see
    :func:`~gpuslice.schedule.adaptive.cusp_schedule`), each named by its field in the error."""
    if mode not in ("cusp", "area"):
        raise ParameterError(f"unknown error-bounded mode '{mode}' (use cusp or area)")
    for name, v in (("max_cusp", max_cusp), ("max_area", max_area), ("min_height", min_height),
                    ("max_height", max_height), ("smooth", smooth)):
        if not is_real(v):  # (text or a bool: named here, not a numpy TypeError below)
            raise ParameterError(f"{name} must be a number, got {v!r}", param=name)
    if resolution is not None and not (is_real(resolution) and resolution > 0):
        raise ParameterError(f"resolution must be a positive number of mm, got {resolution!r}", param="resolution")
    if mode == "cusp" and not (is_finite(max_cusp) and float(max_cusp) > 0):
        raise ParameterError(f"max_cusp must be a positive number of mm, got {max_cusp}", param="max_cusp")
    if mode == "area" and not (is_finite(max_area) and float(max_area) > 0):
        raise ParameterError(f"max_area must be a positive number of mm², got {max_area}", param="max_area")
    check_heights(min_height, max_height)
    if not (is_finite(smooth) and float(smooth) >= 0):
        raise ParameterError(f"smooth must be >= 0 (mm per mm), got {smooth}", param="smooth")


def check_roi(ladder, threshold, quantile, min_layers, max_windows) -> tuple[tuple[float, ...], tuple | None]:
    """The options of the paper's adaptive schedule (see :func:`~gpuslice.schedule.adaptive.roi_schedule`):
    ``(ladder, thresholds)`` as floats, the thresholds one per refinement step (None: the quantile decides)."""
    if not (isinstance(ladder, tuple | list | np.ndarray) and all(is_real(t) for t in ladder)):
        raise ParameterError(f"roi_ladder must be positive thicknesses in mm, got {ladder!r}", param="roi_ladder")
    ladder = tuple(float(t) for t in ladder)
    if not ladder or not all(np.isfinite(t) and t > 0 for t in ladder):
        raise ParameterError(f"roi_ladder must be positive thicknesses in mm, got {ladder}", param="roi_ladder")
    for name, v, whole, least in (("roi_quantile", quantile, False, None), ("roi_min_layers", min_layers, True, 1),
                                  ("roi_windows", max_windows, True, 0)):
        if not is_real(v) or (whole and float(v) != int(v)) or (least is not None and v < least):
            kind = f"a whole number >= {least}" if whole else "a number"
            raise ParameterError(f"{name} must be {kind}, got {v!r}", param=name)
    if any(b >= a for a, b in zip(ladder[:-1], ladder[1:], strict=True)):
        raise ParameterError(f"roi_ladder must go from coarse to fine (decreasing), got {ladder}", param="roi_ladder")
    if threshold is None:
        if not (0.0 <= quantile <= 1.0):
            raise ParameterError(f"roi_quantile must be in [0, 1], got {quantile}", param="roi_quantile")
        return ladder, None
    thr = (threshold,) if np.isscalar(threshold) else tuple(threshold) if isinstance(
        threshold, tuple | list | np.ndarray) else (threshold,)
    if not all(is_real(v) for v in thr):
        raise ParameterError(f"roi_threshold must be points per layer >= 0, got {threshold!r}", param="roi_threshold")
    if len(thr) == 1:
        thr = thr * max(len(ladder) - 1, 1)
    if len(thr) != max(len(ladder) - 1, 1):
        raise ParameterError(f"roi_threshold needs 1 or {len(ladder) - 1} values, got {len(thr)}",
                             param="roi_threshold")
    if not all(np.isfinite(v) and v >= 0 for v in thr):
        raise ParameterError(f"roi_threshold must be points per layer >= 0, got {threshold}", param="roi_threshold")
    return ladder, thr


def check_schedule_params(params) -> None:
    """Everything the schedule of ``params`` (a :class:`~gpuslice.slicing.params.SliceParams`) would refuse whatever
    the mesh: the thickness, first layer and z mode of uniform layers, the options of an adaptive mode. (What
    depends on the model, such as more than 5e7 layers for its height, is left to the slicing.)"""
    if params.adaptive is None:
        check_uniform(params.thickness, params.first_layer, params.z_mode)
    elif params.adaptive == "roi":
        check_roi(params.roi_ladder, params.roi_threshold, params.roi_quantile, 2, params.roi_windows)
    else:
        check_error_bounded(params.adaptive, params.max_cusp, params.max_area, params.min_height, params.max_height,
                            params.smooth)
