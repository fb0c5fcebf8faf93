"""How a resin printer prints each layer: exposures, the bottom and transition layers, the lift and retract moves,
the waits and the light's PWM (:class:`PrintSettings`, each option declared once), as per-layer columns
(:func:`layer_table`) that every archive writer stores and that the print-time and resin estimates read.

Conventions (what resin firmware and its archive formats use): times in s, heights in mm, speeds in mm/min.
Layer i (0-based) is a **bottom** layer for ``i < bottom_layers``; the next ``transition_layers`` layers step their
exposure linearly from ``bottom_exposure`` towards ``exposure`` (Chitubox's and UVtools' ramp: transition layer t of
T gets ``bottom_exposure - (t + 1)·(bottom_exposure - exposure)/(T + 1)``); later layers get ``exposure``. The lift is
two-stage where ``lift_height2 > 0`` (first ``lift_height`` at ``lift_speed``, then ``lift_height2`` at
``lift_speed2``); the retract likewise (``retract_height2`` at ``retract_speed2`` first, the slow stage near the
vat film, then ``retract_height`` at ``retract_speed``); both are one stage by default. Bottom layers use the
``bottom_*`` lift values where given (None: the normal ones).

A layer's time (:func:`layer_times`) is ``wait_before_cure + exposure + wait_after_cure + lift + wait_after_lift +
retract``, each move ``height / speed · 60``; the whole print is their sum (:func:`print_time_s`). Resin volume is the
sum of layer area × thickness (:func:`resin_ml`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..options import option

__all__ = ["PrintSettings", "layer_table", "layer_times", "print_time_s", "resin_ml", "LAYER_COLUMNS"]


@dataclass(frozen=True)
class PrintSettings:
    """The print settings of a resin job (times s, heights mm, speeds mm/min); see the module docstring."""

    bottom_layers: int = option(1, "Layers exposed with --bottom-exposure (the first layers, on the plate)")
    bottom_exposure: float = option(15.0, "Exposure of the bottom layers", unit="s",
                                    flags=("--bottom-exposure", "--exposure-first"))
    exposure: float = option(10.0, "Exposure of the normal layers", unit="s")
    transition_layers: int = option(10, "Layers after the bottom ones whose exposure steps linearly from "
                                    "--bottom-exposure to --exposure")
    lift_height: float = option(5.0, "Lift after each layer (first stage)", unit="mm")
    lift_speed: float = option(65.0, "Lift speed (first stage)", unit="mm/min")
    lift_height2: float = option(0.0, "Second lift stage, after the first (0: one stage)", unit="mm")
    lift_speed2: float = option(0.0, "Second lift stage's speed", unit="mm/min")
    retract_height: float = option(5.0, "Retract towards the vat (last stage; the whole retract when one stage)",
                                   unit="mm")
    retract_speed: float = option(150.0, "Retract speed", unit="mm/min")
    retract_height2: float = option(0.0, "First retract stage, the slow approach to the film (0: one stage)",
                                    unit="mm")
    retract_speed2: float = option(0.0, "First retract stage's speed", unit="mm/min")
    bottom_lift_height: float | None = option(None, "Bottom layers' lift (default: --lift-height)", unit="mm")
    bottom_lift_speed: float | None = option(None, "Bottom layers' lift speed (default: --lift-speed)",
                                             unit="mm/min")
    wait_before_cure: float = option(0.0, "Rest before each exposure (after the retract)", unit="s")
    wait_after_cure: float = option(0.0, "Rest after each exposure, before the lift", unit="s")
    wait_after_lift: float = option(0.0, "Rest at the top of the lift", unit="s")
    light_pwm: int = option(255, "Light intensity of the normal layers (PWM, 1-255)")
    bottom_light_pwm: int = option(255, "Light intensity of the bottom layers (PWM, 1-255)")
    per_layer_settings: bool = option(False, "Let the printer read each layer's own settings from the archive "
                                      "(off by default: some firmware freezes on it)", negatable=True)
    resin_density: float = option(1.1, "Resin density, for the mass estimate", unit="g/ml")

    def __post_init__(self) -> None:
        for name in ("bottom_layers", "transition_layers"):
            v = getattr(self, name)
            if not (isinstance(v, int | np.integer) and not isinstance(v, bool) and 0 <= v <= 100000):
                raise ParameterError(f"{name} must be a whole number of layers >= 0, got {v}", param=name)
        for name in ("bottom_exposure", "exposure", "resin_density"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be > 0, got {v}", param=name)
        for name in ("lift_height", "lift_height2", "retract_height", "retract_height2", "bottom_lift_height",
                     "wait_before_cure", "wait_after_cure", "wait_after_lift", "lift_speed2", "retract_speed2"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ParameterError(f"{name} must be >= 0, got {v}", param=name)
        for name in ("lift_speed", "retract_speed", "bottom_lift_speed"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be > 0 mm/min, got {v}", param=name)
        for height, speed in (("lift_height2", "lift_speed2"), ("retract_height2", "retract_speed2")):
            if getattr(self, height) > 0 and getattr(self, speed) <= 0:
                raise ParameterError(f"{speed} must be > 0 mm/min when {height} is set", param=(speed, height))
        for name in ("light_pwm", "bottom_light_pwm"):
            v = getattr(self, name)
            if not (isinstance(v, int | np.integer) and 1 <= v <= 255):
                raise ParameterError(f"{name} must be from 1 to 255, got {v}", param=name)

    def with_values(self, values: dict[str, Any]) -> PrintSettings:
        """A copy with ``values`` (field → value; None values ignored) replaced."""
        known = {f.name for f in fields(self)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ParameterError(f"unknown print setting '{unknown[0]}' (use {', '.join(sorted(known))})")
        return replace(self, **{k: v for k, v in values.items() if v is not None})


#: the columns of :func:`layer_table`, all (n,) arrays
LAYER_COLUMNS = ("exposure", "lift_height", "lift_speed", "lift_height2", "lift_speed2", "retract_height",
                 "retract_speed", "retract_height2", "retract_speed2", "wait_before_cure", "wait_after_cure",
                 "wait_after_lift", "light_pwm", "bottom")


def layer_table(settings: PrintSettings, n_layers: int) -> dict[str, np.ndarray]:
    """Per-layer print settings of ``n_layers`` layers: float64 columns of :data:`LAYER_COLUMNS` (``light_pwm``
    int64, ``bottom`` bool), following the module docstring's bottom/transition rule."""
    s = settings
    i = np.arange(n_layers)
    bottom = i < s.bottom_layers
    t = i - s.bottom_layers  # 0 .. T-1 inside the transition
    trans = (t >= 0) & (t < s.transition_layers)
    step = (s.bottom_exposure - s.exposure) / (s.transition_layers + 1)
    exposure = np.where(bottom, s.bottom_exposure, np.where(trans, s.bottom_exposure - (t + 1) * step, s.exposure))

    def col(normal: float, bottom_value: float | None = None) -> np.ndarray:
        b = normal if bottom_value is None else bottom_value
        return np.where(bottom, float(b), float(normal))

    return {
        "exposure": exposure.astype(np.float64),
        "lift_height": col(s.lift_height, s.bottom_lift_height),
        "lift_speed": col(s.lift_speed, s.bottom_lift_speed),
        "lift_height2": col(s.lift_height2),
        "lift_speed2": col(s.lift_speed2),
        "retract_height": col(s.retract_height),
        "retract_speed": col(s.retract_speed),
        "retract_height2": col(s.retract_height2),
        "retract_speed2": col(s.retract_speed2),
        "wait_before_cure": col(s.wait_before_cure),
        "wait_after_cure": col(s.wait_after_cure),
        "wait_after_lift": col(s.wait_after_lift),
        "light_pwm": np.where(bottom, s.bottom_light_pwm, s.light_pwm).astype(np.int64),
        "bottom": bottom,
    }


def _move(height: np.ndarray, speed: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(height > 0, height / np.where(speed > 0, speed, 1.0) * 60.0, 0.0)


def layer_times(settings: PrintSettings, n_layers: int) -> np.ndarray:
    """(n,) float64 seconds each layer takes: waits, exposure, lift and retract (module docstring)."""
    c = layer_table(settings, n_layers)
    return (c["wait_before_cure"] + c["exposure"] + c["wait_after_cure"] + c["wait_after_lift"]
            + _move(c["lift_height"], c["lift_speed"]) + _move(c["lift_height2"], c["lift_speed2"])
            + _move(c["retract_height"], c["retract_speed"]) + _move(c["retract_height2"], c["retract_speed2"]))


def print_time_s(settings: PrintSettings, n_layers: int) -> float:
    """Estimated print time of ``n_layers`` layers in s: the sum of :func:`layer_times`."""
    return float(layer_times(settings, n_layers).sum())


def resin_ml(area_mm2: np.ndarray, thickness_mm: np.ndarray) -> float:
    """Resin volume in ml (= cm³) of layers with these cross-section areas (mm²) and thicknesses (mm)."""
    v = float(np.dot(np.asarray(area_mm2, np.float64), np.asarray(thickness_mm, np.float64))) / 1000.0
    return v if math.isfinite(v) else 0.0
