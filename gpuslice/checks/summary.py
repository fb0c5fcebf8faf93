"""The checks' report (:class:`CheckReport`): islands, unsupported area, traps and suction cups as columns, the
cross-section per layer (the peel-force proxy), the print time and the resin; ``to_json()`` gives the JSON report
(keys in :meth:`CheckReport.to_json`), ``lines()`` a short text summary, ``view_data()`` what the viewer marks."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..raster.settings import format_duration
from .cavities import KINDS, SUCTION_CUP, TRAP, Cavities
from .islands import Islands

__all__ = ["CheckReport", "peel_and_time"]


def peel_and_time(result, settings) -> dict[str, Any]:
    """Cross-section per layer and its largest value with its layer (the peel-force proxy), the print time from
    ``settings``' per-layer table (:func:`gpuslice.raster.settings.print_time_s`: exposures, lifts, retracts,
    waits), the resin volume (ml) and mass (g, at ``settings.resin_density`` g/ml)."""
    from ..raster.settings import print_time_s, resin_ml

    area = np.asarray(result.area, np.float64)
    n = int(area.size)
    k = int(np.argmax(area)) if n else -1
    ml = resin_ml(area, result.thickness) if n else 0.0
    return {"area": area, "max_area": float(area[k]) if n else 0.0, "max_area_layer": k,
            "print_time_s": print_time_s(settings, n) if n else 0.0, "resin_ml": ml,
            "resin_g": ml * float(settings.resin_density), "resin_density": float(settings.resin_density)}


def hours_minutes(seconds: float) -> str:
    """A print time as ``"H h MM min"``, rounded to the minute as ``raster`` prints it (``format_duration``)."""
    h, m = format_duration(seconds).split(":")
    return f"{h} h {m} min"


@dataclass
class CheckReport:
    """What :func:`gpuslice.checks.run_checks` found (lengths mm, areas mm², volumes mm³, times s).

    islands : :class:`~gpuslice.checks.islands.Islands` (with the per-layer ``unsupported`` area).
    cavities : :class:`~gpuslice.checks.cavities.Cavities` (traps and suction cups).
    area : (L,) cross-section per layer; max_area, max_area_layer : its largest value and that layer (-1: none).
    print_time_s, resin_ml, resin_g, resin_density : the estimates and the density used (g/ml).
    mode : ``"contours"`` (islands contour-exact) or ``"pixels"`` (on ``display``'s grid); display : the printer's
    display (resolution, pixel) or None; overhang_tolerance : mm. timings : seconds per part of the checks
    (``islands``, then ``cavities``: on the contours the cavities run alongside the islands, on a thread of their
    own, and their time is what is left to wait for once the islands are done).
    open_chains, open_chain_layers : the result's chains left open and the layers they are in (a broken mesh: they
    bound no area, so no island, overhang, trap or cup is found along them). filled_holes : the mesh's holes closed by
    fans of facets before slicing (:mod:`gpuslice.mesh.holes`): the checks are of the filled mesh.
    """

    islands: Islands
    cavities: Cavities
    area: np.ndarray
    max_area: float
    max_area_layer: int
    print_time_s: float
    resin_ml: float
    resin_g: float
    resin_density: float
    mode: str
    overhang_tolerance: float
    display: dict[str, Any] | None = None
    z: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    #: chains left open (a broken mesh): they bound nothing, so nothing is checked along them
    open_chains: int = 0
    open_chain_layers: int = 0
    #: holes filled before slicing (an open mesh): what is checked is the filled one
    filled_holes: int = 0

    @property
    def n_islands(self) -> int:
        return int(self.islands.layer.size)

    @property
    def island_layers(self) -> np.ndarray:
        """The layers with at least one island."""
        return np.unique(self.islands.layer)

    def to_json(self) -> dict[str, Any]:
        """The JSON report: ``islands`` (rows ``layer``, ``area_mm2``, ``x``, ``y``, ``bbox``), ``unsupported_area_mm2``
        (per layer), ``traps`` (rows ``volume_mm3``, ``layer_min``, ``layer_max``, ``x``, ``y``, ``z``, ``kind`` =
        ``trap`` | ``suction_cup``, ``max_area_mm2``, ``bbox``), ``area_mm2`` (per layer), ``max_area_mm2``,
        ``max_area_layer``, ``print_time_s``, ``resin_ml``, ``resin_g``, ``resin_density_g_ml``, ``counts``,
        ``mode``, ``display``, ``overhang_tolerance_mm``, ``trap_grid_mm``, ``timings_s``."""
        isl, cav = self.islands, self.cavities
        islands = [{"layer": int(isl.layer[k]), "area_mm2": float(isl.area[k]), "x": float(isl.x[k]),
                    "y": float(isl.y[k]), "bbox": [float(v) for v in isl.bbox[k]]} for k in range(isl.layer.size)]
        traps = [{"kind": KINDS[int(cav.kind[k])], "volume_mm3": float(cav.volume[k]),
                  "layer_min": int(cav.layer_min[k]), "layer_max": int(cav.layer_max[k]), "x": float(cav.x[k]),
                  "y": float(cav.y[k]), "z": float(cav.z[k]), "max_area_mm2": float(cav.max_area[k]),
                  "bbox": [float(v) for v in cav.bbox[k]]} for k in range(cav.kind.size)]
        return {
            "mode": self.mode,
            "display": self.display,
            "layers": int(self.area.size),
            "overhang_tolerance_mm": self.overhang_tolerance,
            "trap_grid_mm": cav.grid_mm,
            "counts": {"islands": self.n_islands, "island_layers": int(self.island_layers.size),
                       "traps": cav.n_traps, "suction_cups": cav.n_cups, "open_chains": self.open_chains,
                       "filled_holes": self.filled_holes},
            "islands": islands,
            "unsupported_area_mm2": [float(v) if np.isfinite(v) else None for v in isl.unsupported],  # None: failed
            "traps": traps,
            "area_mm2": [float(v) for v in self.area],
            "max_area_mm2": self.max_area,
            "max_area_layer": self.max_area_layer,
            "print_time_s": self.print_time_s,
            "resin_ml": self.resin_ml,
            "resin_g": self.resin_g,
            "resin_density_g_ml": self.resin_density,
            "timings_s": dict(self.timings),
        }

    def lines(self) -> list[str]:
        """A few lines of text: the counts and the estimates (for logs and one-line summaries)."""
        cav, unsup = self.cavities, self.islands.unsupported
        worst = int(np.argmax(np.where(np.isfinite(unsup), unsup, -1.0))) if unsup.size else -1  # NaN: not computed
        return [
            f"islands: {self.n_islands} in {self.island_layers.size} layers"
            + (f" (first at layer {int(self.islands.layer[0])})" if self.n_islands else ""),
            f"unsupported area: largest {unsup[worst] if worst >= 0 else 0.0:.3f} mm2 at layer {worst}, "
            f"total {float(np.nansum(unsup)):.1f} mm2 (tolerance {self.overhang_tolerance:g} mm)",
            f"resin traps: {cav.n_traps} ({float(cav.volume[cav.kind == TRAP].sum()):.1f} mm3), suction cups: "
            f"{cav.n_cups} (grid {cav.grid_mm:g} mm)",
            f"largest cross-section: {self.max_area:.1f} mm2 at layer {self.max_area_layer}",
            f"print time: {hours_minutes(self.print_time_s)}, resin: {self.resin_ml:.2f} ml, {self.resin_g:.2f} g",
        ] + ([f"not checked: {self.open_chains} open chains in {self.open_chain_layers} layers (a broken mesh: "
              "they bound nothing)"] if self.open_chains else []) + (
            [f"checked as filled: {self.filled_holes} holes of the mesh closed before slicing (--no-fill-holes: as "
             "stored)"] if self.filled_holes else [])

    def view_data(self) -> dict[str, list]:
        """What the viewer marks: ``islands`` rows [layer, x, y, area, xmin, ymin, xmax, ymax] and ``cavities`` rows
        [kind, layer_min, layer_max, x, y, z, volume, max_area, xmin, ymin, xmax, ymax] (kind: 0 trap, 1 suction
        cup), numbers rounded to 1e-4 (a value that rounds to zero is 0, never -0)."""
        isl, cav = self.islands, self.cavities
        r = lambda v: round(float(v), 4) + 0.0  # noqa: E731  (-0.0 + 0.0 is 0.0)
        islands = [[int(isl.layer[k]), r(isl.x[k]), r(isl.y[k]), r(isl.area[k]), *map(r, isl.bbox[k])]
                   for k in range(isl.layer.size)]
        cavities = [[int(cav.kind[k]), int(cav.layer_min[k]), int(cav.layer_max[k]), r(cav.x[k]), r(cav.y[k]),
                     r(cav.z[k]), r(cav.volume[k]), r(cav.max_area[k]), *map(r, cav.bbox[k])]
                    for k in range(cav.kind.size)]
        return {"islands": islands, "cavities": cavities, "kinds": list(KINDS),
                "summary": self.lines(), "suction_cup": SUCTION_CUP}
