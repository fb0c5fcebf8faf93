"""``gpuslice bench``: the paper's Tables 2–3 as one table, uniform thicknesses and adaptive schedules side by side.

For every setting (a uniform thickness, or an adaptive mode) the whole in-process pipeline, ``slice_mesh`` from a
loaded mesh to nested polygons (schedule, crossings, chaining, nesting; for ``roi`` the schedule stage includes its
level slices), runs ``repeat`` times after one untimed warm-up run of the first setting (OpenCL program build,
buffers); the table gives the median total and the median of each stage (``result.meta["timings_s"]``). Loading the
file (read + weld) is timed once and reported apart, not in the totals. Quality figures (:mod:`gpuslice.quality`)
are computed once per setting, outside the timings: max and mean cusp height and the volume deviation against one
fine uniform reference shared by all rows.
"""

from __future__ import annotations

import csv
import io
import statistics
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from ..errors import ParameterError
from ..mesh.mesh import Mesh
from ..slicing.slicer import SliceParams, slice_mesh

__all__ = ["Setting", "parse_settings", "run_bench", "BenchResult", "STAGES"]

STAGES = ("schedule", "crossings", "chaining", "nesting")


@dataclass
class Setting:
    """One row of the table: a label and the :class:`SliceParams` fields it sets."""

    label: str
    overrides: dict


@dataclass
class BenchResult:
    """The table (``rows``: one dict per setting) and the run's context; ``results`` keeps each setting's last
    :class:`~gpuslice.result.SliceResult` (for plots)."""

    rows: list[dict]
    context: dict
    results: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {**self.context, "rows": self.rows}

    def to_csv(self) -> str:
        buf = io.StringIO()
        keys = [k for k in self.rows[0] if k != "times_s"] if self.rows else []
        w = csv.DictWriter(buf, fieldnames=keys, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        for r in self.rows:
            w.writerow(r)
        return buf.getvalue()


def parse_settings(thicknesses: str | None, adaptive: str | None) -> list[Setting]:
    """Settings from ``-t 0.1,0.2,0.3`` and ``--adaptive roi,cusp`` (either may be empty, not both)."""
    from ..schedule.validate import MIN_LAYER_MM

    out = []
    for part in (thicknesses or "").split(","):
        if not part.strip():
            if thicknesses and thicknesses.strip():  # ("1,,2": an item left out, not dropped without a word)
                raise ParameterError(f"-t: an empty item in '{thicknesses}'")
            continue
        try:
            t = float(part)
        except ValueError:
            raise ParameterError(f"-t: '{part}' is not a thickness in mm") from None
        if not (np.isfinite(t) and t >= MIN_LAYER_MM):
            raise ParameterError(f"-t: layer thickness must be a positive number of mm (at least {MIN_LAYER_MM:g}), "
                                 f"got {part}")
        out.append(Setting(f"{t:g} mm", {"thickness": t, "adaptive": None}))
    for part in (adaptive or "").split(","):
        mode = part.strip()
        if not mode:
            continue
        if mode not in ("roi", "cusp", "area"):
            raise ParameterError(f"unknown adaptive mode '{mode}' (use roi, cusp, area)")
        out.append(Setting(f"adaptive {mode}", {"adaptive": mode}))
    if not out:
        raise ParameterError("bench: give thicknesses and/or adaptive modes", param=("thickness", "adaptive"))
    return out


def run_bench(
    mesh: Mesh,
    settings: list[Setting],
    params: SliceParams | None = None,
    *,
    repeat: int = 3,
    quality: bool = True,
    ref_thickness: float | None = None,
    load_times: dict | None = None,
    progress=None,
) -> BenchResult:
    """Time every setting ``repeat`` times (medians) and measure its quality; see the module docstring.

    ``progress``: an optional callable ``progress(description, advance)`` called after each run.
    """
    from .quality import cusp_summary, layer_geometries, reference_thickness, volume_deviation

    if repeat < 1:
        raise ParameterError(f"repeat must be >= 1, got {repeat}")
    params = params or SliceParams()
    device = None
    if params.backend == "opencl":
        from ..device import get_device

        device = get_device(params.device)
    tick = progress or (lambda desc, adv=1: None)
    slice_mesh(mesh, replace(params, **settings[0].overrides))  # warm-up: program build, buffers
    tick("warm-up", 1)
    rows, results = [], {}
    for s in settings:
        p = replace(params, **s.overrides)
        totals, stages = [], {k: [] for k in STAGES}
        res = None
        for _ in range(repeat):
            t0 = time.perf_counter()
            res = slice_mesh(mesh, p)
            totals.append(time.perf_counter() - t0)
            for k in STAGES:
                stages[k].append(res.meta["timings_s"].get(k, 0.0))
            tick(s.label, 1)
        results[s.label] = res
        th = res.thickness
        row = {
            "setting": s.label,
            "layers": res.n_layers,
            "total_s": statistics.median(totals),
            **{f"{k}_s": statistics.median(v) for k, v in stages.items()},
            "points": int(res.points.shape[0]),
            "thickness_min_mm": float(th.min()) if th.size else None,
            "thickness_max_mm": float(th.max()) if th.size else None,
            "device": res.meta["device"],
            "times_s": totals,
        }
        c = cusp_summary(mesh, res, device)
        row["max_cusp_mm"], row["mean_cusp_mm"] = c["max_cusp_mm"], c["mean_cusp_mm"]
        if s.overrides.get("adaptive") == "roi":
            row["roi_windows"] = [
                {"level": lv["level"], "thickness_mm": lv["thickness_mm"], "windows_mm": [w["z_mm"] for w in
                                                                                          lv["windows"]]}
                for lv in res.meta.get("adaptive", {}).get("levels", [])
            ]
        rows.append(row)
    context = {
        "model": mesh.name, "facets": mesh.n_faces, "height_mm": mesh.height, "repeat": repeat,
        "backend": params.backend, "device": rows[0]["device"] if rows else None,
        "load_s": (load_times or {}).get("load"), "topology_s": (load_times or {}).get("topology"),
        "reference_thickness_mm": None,
    }
    if quality and rows:
        # the thinnest typical layer (1st percentile: the last layer of a schedule may be a sliver under the top)
        typical = min(float(np.percentile(results[r["setting"]].thickness, 1)) for r in rows)
        h_ref = ref_thickness or reference_thickness(mesh.height, typical)
        tick("reference", 0)
        try:
            ref = slice_mesh(mesh, params, thickness=h_ref, adaptive=None, first_layer=None, z_mode="mid")  # (plain)
        except ParameterError as exc:  # (said of the reference: alone, "thickness must be ..." named -t's field)
            if ref_thickness is None:
                raise
            raise ParameterError(f"ref_thickness {h_ref:g} mm: {exc}", param="ref_thickness") from None
        ref_geoms = layer_geometries(ref)
        context["reference_thickness_mm"] = h_ref
        context["reference_layers"] = ref.n_layers
        for r in rows:
            vd = volume_deviation(results[r["setting"]], ref, ref_geoms=ref_geoms)
            r["volume_deviation_mm3"] = vd["volume_deviation_mm3"]
            r["volume_deviation_pct"] = vd["volume_deviation_pct"]
            tick("quality", 1)
    context["params"] = {k: v for k, v in asdict(params).items() if k not in ("thickness", "adaptive")}
    return BenchResult(rows, context, results)
