"""How a resin printer prints each layer: exposures, the bottom and transition layers, the lift and retract moves,
the waits and the light's PWM (:class:`PrintSettings`, each option declared once), as per-layer columns
(:func:`layer_table`) that every archive writer stores and that the print-time and resin estimates read.

Conventions (those of Chitubox, UVtools and the archive formats): times in s, heights in mm, speeds in mm/min.

* **Bottom layers**: layer i (0-based) is a bottom layer for ``i < bottom_layers``; it is exposed for
  ``bottom_exposure`` and moves with the ``bottom_*`` values (each None: the normal value).
* **Transition layers**: the next ``transition_layers`` layers (T of them) step their exposure down linearly from
  ``bottom_exposure`` to ``exposure``: transition layer t (0-based) gets ``bottom_exposure - (t + 1)·step`` with
  ``step = (bottom_exposure - exposure) / (T + 1)`` rounded to 0.01 s, kept within [exposure, bottom_exposure]
  (UVtools' ``GetTransitionStepTime``). So bottom 30 s, normal 2.5 s and T = 4 give 24.5, 19, 13.5 and 8 s. There is
  no ramp when ``bottom_exposure <= exposure`` or the step rounds to 0 (the transition layers get ``exposure``).
  Transition layers move and wait as normal layers; only their exposure ramps.
* **Lift** (after the exposure, peeling the layer off the vat's film): ``lift_height`` at ``lift_speed`` (the slow
  peel), then, where ``lift_height2 > 0``, ``lift_height2`` at ``lift_speed2`` (the fast stage): Chitubox's
  two-stage motion control (TSMC).
* **Retract** (back down for the next layer): the plate comes back by as much as it was lifted (the firmware adds
  the layer height), so the retract is not a free length: it is the lift's total, ``lift_height + lift_height2``,
  made of a fast stage at ``retract_speed`` then, where ``retract_height2 > 0``, a slow final stage of
  ``retract_height2`` at ``retract_speed2`` near the film. The fast stage's length is the read-only
  :attr:`PrintSettings.retract_height` (``lift_height + lift_height2 - retract_height2``), as UVtools defines it.
* **Waits**: ``wait_before_cure`` (rest after the retract, before the light), ``wait_after_cure`` (before the lift),
  ``wait_after_lift`` (at the top of the lift).
* **PWM**: the light's intensity 1-255 (``light_pwm``, ``bottom_light_pwm``).

A layer's time (:func:`layer_times`) is ``wait_before_cure + exposure + wait_after_cure + lift + wait_after_lift +
retract``, each move ``height / speed · 60`` (UVtools' estimate with no light-off delay; printers add acceleration
and, for tilting vats, their own tilt time). The whole print is their sum (:func:`print_time_s`). The resin volume is
the sum of layer area × thickness (:func:`resin_ml`), its mass that times ``resin_density``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..options import check_flag, option, shown

__all__ = ["PrintSettings", "layer_table", "layer_times", "print_time_s", "resin_ml", "header_layer_height",
           "per_layer_mode", "changed_settings", "MOTION_REST_LIGHT", "transition_step", "ramp_layers",
           "format_duration", "LAYER_COLUMNS"]

#: settings with a bottom-layer twin ``bottom_<name>`` (None: the normal value)
BOTTOM_TWINS = ("lift_height", "lift_speed", "lift_height2", "lift_speed2", "retract_speed", "retract_height2",
                "retract_speed2", "wait_before_cure", "wait_after_cure", "wait_after_lift")


#: upper bounds of the settings (an hour of exposure or rest a layer, a metre of lift, 1 m/s: beyond any resin
#: printer; the archives hold times in 32-bit fields)
MAX_SECONDS = 3600.0
MAX_HEIGHT_MM = 1000.0
MAX_SPEED = 60000.0
#: the slowest a stage may move, mm/min: every estimate stays finite (a denormal speed, 5e-324, made the moves'
#: times infinite: a numpy warning, and an internal error in `check`); slower ones are refused by the print time
MIN_SPEED = 1e-6
#: the densest resin, g/ml (osmium is 22.6; 1e308 overflowed the archives' float32 mass fields: an internal error)
MAX_DENSITY = 100.0
#: the shortest exposure, s (a millisecond: 5e-324 s passed '> 0' and was written as 0.0 into the archives'
#: float32 fields: a layer lit for no time, without a word)
MIN_EXPOSURE_S = 1e-3
#: the longest print time an archive's 32-bit field holds, s (136 years)
MAX_PRINT_TIME_S = 2**32 - 1


@dataclass(frozen=True)
class PrintSettings:
    """The print settings of a resin job (times s, heights mm, speeds mm/min); see the module docstring."""

    bottom_layers: int = option(1, "Layers exposed with --bottom-exposure (the first layers, on the plate)")
    bottom_exposure: float = option(15.0, "Exposure of the bottom layers", unit="s",
                                    flags=("--bottom-exposure", "--exposure-first"))
    exposure: float = option(10.0, "Exposure of the normal layers", unit="s")
    transition_layers: int = option(10, "Layers after the bottom ones whose exposure steps down linearly from "
                                    "--bottom-exposure to --exposure")
    lift_height: float = option(5.0, "Lift after each layer (first, slow stage: the peel)", unit="mm")
    lift_speed: float = option(65.0, "Lift speed (first stage)", unit="mm/min")
    lift_height2: float = option(0.0, "Second, fast lift stage after the first (0: one stage)", unit="mm")
    lift_speed2: float = option(0.0, "Second lift stage's speed", unit="mm/min")
    retract_speed: float = option(150.0, "Retract speed (the fast stage; the retract returns the whole lift)",
                                  unit="mm/min")
    retract_height2: float = option(0.0, "Last, slow retract stage near the vat film, part of the lift's height "
                                    "(0: one stage)", unit="mm")
    retract_speed2: float = option(0.0, "Slow retract stage's speed", unit="mm/min")
    bottom_lift_height: float | None = option(None, "Bottom layers' lift (default: --lift-height)", unit="mm")
    bottom_lift_speed: float | None = option(None, "Bottom layers' lift speed (default: --lift-speed)",
                                             unit="mm/min")
    bottom_lift_height2: float | None = option(None, "Bottom layers' second lift stage (default: --lift-height2)",
                                               unit="mm")
    bottom_lift_speed2: float | None = option(None, "Bottom layers' second lift speed (default: --lift-speed2)",
                                              unit="mm/min")
    bottom_retract_speed: float | None = option(None, "Bottom layers' retract speed (default: --retract-speed)",
                                                unit="mm/min")
    bottom_retract_height2: float | None = option(None, "Bottom layers' slow retract stage (default: "
                                                  "--retract-height2)", unit="mm")
    bottom_retract_speed2: float | None = option(None, "Bottom layers' slow retract speed (default: "
                                                 "--retract-speed2)", unit="mm/min")
    wait_before_cure: float = option(0.0, "Rest before each exposure (after the retract)", unit="s")
    wait_after_cure: float = option(0.0, "Rest after each exposure, before the lift", unit="s")
    wait_after_lift: float = option(0.0, "Rest at the top of the lift", unit="s")
    bottom_wait_before_cure: float | None = option(None, "Bottom layers' rest before exposure (default: "
                                                   "--wait-before-cure)", unit="s")
    bottom_wait_after_cure: float | None = option(None, "Bottom layers' rest after exposure (default: "
                                                  "--wait-after-cure)", unit="s")
    bottom_wait_after_lift: float | None = option(None, "Bottom layers' rest after the lift (default: "
                                                  "--wait-after-lift)", unit="s")
    light_pwm: int = option(255, "Light intensity of the normal layers (PWM, 1-255)")
    bottom_light_pwm: int = option(255, "Light intensity of the bottom layers (PWM, 1-255)")
    per_layer_settings: bool = option(False, "Let the printer read each layer's own settings from the archive "
                                      "(off by default: some firmware freezes on it; on by itself when the layers' "
                                      "thicknesses vary, as the printer must then read each layer's height)",
                                      negatable=True)
    resin_density: float = option(1.1, "Resin density, for the mass estimate", unit="g/ml")

    def __post_init__(self) -> None:
        for name in ("bottom_layers", "transition_layers"):
            v = getattr(self, name)
            if not (_is_int(v) and 0 <= v <= 100000):
                raise ParameterError(f"{name} must be a whole number of layers from 0 to 100000, got {shown(v)}",
                                     param=name)
        for name in ("bottom_exposure", "exposure", "resin_density"):
            v = getattr(self, name)
            if not (_is_number(v) and v > 0):
                raise ParameterError(f"{name} must be > 0, got {shown(v)}", param=name)
        for name in ("bottom_exposure", "exposure"):
            if getattr(self, name) < MIN_EXPOSURE_S:
                raise ParameterError(f"{name} must be at least {MIN_EXPOSURE_S:g} s, got {shown(getattr(self, name))}",
                                     param=name)
        if self.resin_density > MAX_DENSITY:
            raise ParameterError(f"resin_density must be at most {MAX_DENSITY:g} g/ml, got {shown(self.resin_density)}",
                                 param="resin_density")
        for name in ("lift_height", "lift_height2", "retract_height2", "wait_before_cure", "wait_after_cure",
                     "wait_after_lift", "lift_speed2", "retract_speed2"):
            for n in (name, f"bottom_{name}"):
                v = getattr(self, n)
                if (v is None and n == name) or (v is not None and not (_is_number(v) and v >= 0)):
                    raise ParameterError(f"{n} must be >= 0, got {shown(v)}", param=n)  # (None: only bottom_ ones)
        for name in ("lift_speed", "retract_speed"):
            for n in (name, f"bottom_{name}"):
                v = getattr(self, n)
                if (v is None and n == name) or (v is not None and not (_is_number(v) and v > 0)):
                    raise ParameterError(f"{n} must be > 0 mm/min, got {shown(v)}", param=n)
        for names, top, unit in ((("bottom_exposure", "exposure", "wait_before_cure", "wait_after_cure",
                                   "wait_after_lift"), MAX_SECONDS, "s"),
                                 (("lift_height", "lift_height2", "retract_height2"), MAX_HEIGHT_MM, "mm"),
                                 (("lift_speed", "lift_speed2", "retract_speed", "retract_speed2"), MAX_SPEED,
                                  "mm/min")):
            for name in names:
                for n in (name, f"bottom_{name}"):
                    v = getattr(self, n, None)
                    if v is not None and v > top:
                        raise ParameterError(f"{n} must be at most {top:g} {unit}, got {shown(v)}", param=n)
                    if unit == "mm/min" and v is not None and 0 < v < MIN_SPEED:  # (0: a second stage not used)
                        raise ParameterError(f"{n} must be at least {MIN_SPEED:g} mm/min, got {shown(v)}", param=n)
        for name in ("light_pwm", "bottom_light_pwm"):
            v = getattr(self, name)
            if not (_is_int(v) and 1 <= v <= 255):
                raise ParameterError(f"{name} must be a whole number from 1 to 255, got {shown(v)}", param=name)
        check_flag(self.per_layer_settings, "per_layer_settings")
        for prefix in ("", "bottom_"):  # contradictions, for the normal and for the bottom layers
            g = self.group(prefix == "bottom_")
            for height, speed in (("lift_height2", "lift_speed2"), ("retract_height2", "retract_speed2")):
                if g[height] > 0 and g[speed] <= 0:
                    raise ParameterError(f"{prefix}{speed} must be > 0 mm/min when {prefix}{height} is set",
                                         param=(prefix + speed, prefix + height))
                # (a speed given for a stage that moves nothing: dropped unsaid; a bottom speed inherited is not given,
                # and a normal one the bottom layers' own second stage inherits is used)
                given = getattr(self, prefix + speed) is not None
                if not prefix and getattr(self, "bottom_" + speed) is None and self.group(True)[height] > 0:
                    given = False
                if given and g[speed] > 0 and g[height] <= 0:
                    raise ParameterError(f"{prefix}{speed} {g[speed]:g} mm/min is the speed of a second stage, which "
                                         f"moves nothing without {prefix}{height}", param=(prefix + speed,
                                                                                           prefix + height))
            lift = g["lift_height"] + g["lift_height2"]
            if g["retract_height2"] > lift + 1e-9:
                raise ParameterError(
                    f"{prefix}retract_height2 ({g['retract_height2']:g} mm) is longer than the lift it returns "
                    f"({prefix}lift_height + {prefix}lift_height2 = {lift:g} mm)",
                    param=(prefix + "retract_height2", prefix + "lift_height2", prefix + "lift_height"))

    def group(self, bottom: bool) -> dict[str, float]:
        """The motion and wait values of a bottom (``bottom=True``) or normal layer: :data:`BOTTOM_TWINS` names →
        value (the bottom twin where given), plus the derived ``retract_height``."""
        g = {}
        for name in BOTTOM_TWINS:
            twin = getattr(self, f"bottom_{name}") if bottom else None
            g[name] = float(getattr(self, name) if twin is None else twin)
        g["retract_height"] = max(g["lift_height"] + g["lift_height2"] - g["retract_height2"], 0.0)
        return g

    def two_stages_lost(self) -> str | None:
        """The flag of a second lift or retract stage that one stage at one speed cannot hold (``--lift-height2`` at a
        speed other than ``--lift-speed``, or the slow ``--retract-height2`` at a speed other than
        ``--retract-speed``), for the bottom or the normal layers; None when one stage each holds the motion exactly
        (the formats with one stage: CTB v2/v3, Photon Workshop before 516)."""
        for bottom in (False, True):
            g = self.group(bottom)
            twin = "--bottom-" if bottom else "--"
            if g["lift_height2"] > 0 and g["lift_speed2"] not in (0.0, g["lift_speed"]):
                return f"{twin}lift-height2 {g['lift_height2']:g} at {twin}lift-speed2 {g['lift_speed2']:g}"
            if g["retract_height2"] > 0 and g["retract_speed2"] not in (0.0, g["retract_speed"]):
                return (f"{twin}retract-height2 {g['retract_height2']:g} at {twin}retract-speed2 "
                        f"{g['retract_speed2']:g}")
        return None

    @property
    def retract_height(self) -> float:
        """The fast retract stage of a normal layer, mm: ``lift_height + lift_height2 - retract_height2``."""
        return self.group(False)["retract_height"]

    @property
    def bottom_retract_height(self) -> float:
        """The fast retract stage of a bottom layer, mm (from the bottom lift)."""
        return self.group(True)["retract_height"]

    def with_values(self, values: dict[str, Any]) -> PrintSettings:
        """A copy with ``values`` (field → value; None values ignored) replaced, validated together."""
        known = {f.name for f in fields(self)}
        unknown = sorted(set(values) - known)
        if unknown:
            if unknown[0] in ("retract_height", "bottom_retract_height"):
                raise ParameterError(f"{unknown[0]} is not a setting: the retract returns the whole lift (set the "
                                     "lift heights, and retract_height2 for a slow last stage)")
            raise ParameterError(f"unknown print setting '{unknown[0]}' (use {', '.join(sorted(known))})")
        return replace(self, **{k: v for k, v in values.items() if v is not None})


def _is_number(v: Any) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v: Any) -> bool:
    return isinstance(v, int | np.integer) and not isinstance(v, bool)


#: the columns of :func:`layer_table`, all (n,) arrays
LAYER_COLUMNS = ("exposure", "lift_height", "lift_speed", "lift_height2", "lift_speed2", "retract_height",
                 "retract_speed", "retract_height2", "retract_speed2", "wait_before_cure", "wait_after_cure",
                 "wait_after_lift", "light_pwm", "bottom")


def transition_step(settings: PrintSettings) -> float:
    """The exposure step of the transition layers, s (>= 0; 0 when there is no ramp): module docstring."""
    s = settings
    if s.transition_layers == 0 or s.bottom_exposure <= s.exposure:
        return 0.0
    step = (s.bottom_exposure - s.exposure) / (s.transition_layers + 1)
    return math.floor(step * 100.0 + 0.5) / 100.0  # to 0.01 s, halves away from zero (as UVtools)


def ramp_layers(settings: PrintSettings) -> int:
    """The transition layers an archive's header states: ``transition_layers`` where they ramp the exposure down
    (:func:`transition_step` > 0), else 0, as the per-layer table has no ramp then (a bottom exposure at or below
    the normal one: the header said 10 transition layers that no layer had)."""
    return int(settings.transition_layers) if transition_step(settings) > 0 else 0


def layer_table(settings: PrintSettings, n_layers: int) -> dict[str, np.ndarray]:
    """Per-layer print settings of ``n_layers`` layers: float64 columns of :data:`LAYER_COLUMNS` (``light_pwm``
    int64, ``bottom`` bool), following the module docstring's bottom, transition and retract rules."""
    s = settings
    i = np.arange(n_layers)
    bottom = i < s.bottom_layers
    t = i - s.bottom_layers  # 0 .. T-1 inside the transition
    trans = (t >= 0) & (t < s.transition_layers)
    step = transition_step(s)
    ramp = np.clip(s.bottom_exposure - (t + 1) * step, s.exposure, s.bottom_exposure) if step > 0 else s.exposure
    exposure = np.where(bottom, float(s.bottom_exposure), np.where(trans, ramp, float(s.exposure)))
    b, n = s.group(True), s.group(False)
    out = {"exposure": exposure.astype(np.float64)}
    for name in LAYER_COLUMNS:
        if name in n:
            out[name] = np.where(bottom, b[name], n[name]).astype(np.float64)
    out["light_pwm"] = np.where(bottom, s.bottom_light_pwm, s.light_pwm).astype(np.int64)
    out["bottom"] = bottom
    return {name: out[name] for name in LAYER_COLUMNS}


def _move(height: np.ndarray, speed: np.ndarray) -> np.ndarray:
    """Seconds of moves of ``height`` mm at ``speed`` mm/min (0 where the height is 0)."""
    safe = np.where(speed > 0, speed, 1.0)
    return np.where(height > 0, height / safe * 60.0, 0.0)


def layer_times(settings: PrintSettings, n_layers: int) -> np.ndarray:
    """(n,) float64 seconds each layer takes: waits, exposure, lift and retract (module docstring)."""
    c = layer_table(settings, n_layers)
    return (c["wait_before_cure"] + c["exposure"] + c["wait_after_cure"] + c["wait_after_lift"]
            + _move(c["lift_height"], c["lift_speed"]) + _move(c["lift_height2"], c["lift_speed2"])
            + _move(c["retract_height"], c["retract_speed"]) + _move(c["retract_height2"], c["retract_speed2"]))


def print_time_s(settings: PrintSettings, n_layers: int) -> float:
    """Estimated print time of ``n_layers`` layers in s: the sum of :func:`layer_times`."""
    return float(layer_times(settings, n_layers).sum())


#: the settings of the lift and retract moves, the rests and the light intensity (each with its bottom twin)
MOTION_REST_LIGHT = ("lift_height", "lift_speed", "lift_height2", "lift_speed2", "retract_speed", "retract_height2",
                     "retract_speed2", "wait_before_cure", "wait_after_cure", "wait_after_lift", "light_pwm")


def changed_settings(settings: PrintSettings, names: tuple[str, ...], base: PrintSettings | None = None) -> list[str]:
    """The settings among ``names`` (and their ``bottom_`` twins) that differ from ``base`` (default: the
    defaults; a format passes the preset's, so that only what the user gave counts), as flags with their values
    (``"--lift-height 3"``): for a format to refuse what it cannot store rather than drop it."""
    default = base if base is not None else PrintSettings()
    out = []
    for name in names:
        for key in (name, f"bottom_{name}"):
            if not hasattr(settings, key):
                continue
            v = getattr(settings, key)
            if v is not None and v != getattr(default, key):
                flag = f"--{key.replace('_', '-')}"
                out.append(flag if v is True else f"{flag} {shown(v)}")  # (a switch: its flag alone)
    return out


def per_layer_mode(settings: PrintSettings, thickness_mm: np.ndarray) -> bool:
    """Whether an archive turns its per-layer-settings switch on: when asked (``per_layer_settings``), and always
    when the layers' thicknesses vary (adaptive layers, a thicker first layer): the printer then follows each
    layer's own height from the layer table, where the header holds one height for all."""
    th = np.asarray(thickness_mm, np.float64)
    return bool(settings.per_layer_settings) or (th.size > 1 and float(np.ptp(th)) > 1e-9)


def median(values: np.ndarray) -> float:
    """``np.median`` of a non-empty float64 array without NaNs, by a sort (numpy's imports ``numpy.ma``: ~15 ms)."""
    s = np.sort(np.ravel(np.asarray(values, np.float64)))
    k = s.size // 2
    return float(s[k]) if s.size % 2 else float((s[k - 1] + s[k]) / 2.0)


def header_layer_height(thickness_mm: np.ndarray, empty: float = 0.0) -> float:
    """The one layer height (mm) an archive header states for layers of these thicknesses: the median of the layers
    after the first (which may be thicker), the first's when it is alone, ``empty`` when there are none."""
    th = np.asarray(thickness_mm, np.float64)
    if th.size == 0:
        return float(empty)
    return median(th[1:]) if th.size > 1 else float(th[0])


def resin_ml(area_mm2: np.ndarray, thickness_mm: np.ndarray) -> float:
    """Resin volume in ml (= cm³) of layers with these cross-section areas (mm²) and thicknesses (mm)."""
    v = float(np.dot(np.asarray(area_mm2, np.float64), np.asarray(thickness_mm, np.float64))) / 1000.0
    return v if math.isfinite(v) else 0.0


def format_duration(seconds: float) -> str:
    """``seconds`` as ``h:mm`` (rounded to the minute), e.g. 5430 s → ``"1:31"``."""
    minutes = int(math.floor(max(float(seconds), 0.0) / 60.0 + 0.5))
    return f"{minutes // 60}:{minutes % 60:02d}"
