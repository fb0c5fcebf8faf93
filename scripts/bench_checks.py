"""Benchmark of the pre-print checks (issue 13): ``gpuslice check`` on shared meshes, the checks' cost against the
slicing's, as the pipeline times them (one :func:`gpuslice.pipeline.run_job` per run after one warm-up run; the
median of ``--repeat`` runs, and the best).

    python scripts/bench_checks.py                       # nefertiti at 80 mm, benchy at 60 mm, 0.05 mm layers
    python scripts/bench_checks.py --printer generic-4k  # also the pixel-exact checks on that display
    python scripts/bench_checks.py --no-simplify         # the unsupported area on the true outlines (the reference)
    python scripts/bench_checks.py --json bench_checks.json

"slicing" is the pipeline's load + topology + schedule + crossings + chaining + nesting (the device's one-off
kernel build left out); "checks" is the ``checks`` stage, split into ``islands`` (islands and unsupported area) and
``cavities`` (the voxel grid's rasterisation, traps and suction cups). Timings are wall-clock seconds; the machine's
load average (1 min) is printed before and after each mesh, since other work on the machine slows both.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

SLICING = ("load", "topology", "schedule", "crossings", "chaining", "nesting")
MESHES = {"nefertiti": 80.0, "benchy": 60.0}


def run_once(path: Path, fit: float, thickness: float, printer: str | None, backend: str) -> dict:
    from gpuslice.checks import CheckOptions
    from gpuslice.mesh.mesh import Placement
    from gpuslice.pipeline import CheckOutput, Job, run_job
    from gpuslice.raster.spec import with_printer
    from gpuslice.slicing.params import SliceParams

    spec = with_printer(printer) if printer else None
    job = Job(source=str(path), placement=Placement(fit=fit), params=SliceParams(thickness=thickness, backend=backend),
              mesh_check=False, checks=CheckOutput(spec, None, CheckOptions()))
    t = time.perf_counter()
    done = run_job(job)
    total = time.perf_counter() - t
    report = done.stats["checks"]
    tm = done.timings
    return {"layers": done.result.n_layers, "points": int(done.result.points.shape[0]),
            "slicing_s": sum(tm.get(k, 0.0) for k in SLICING), "checks_s": tm["checks"],
            "islands_s": report.timings["islands"], "cavities_s": report.timings["cavities"], "total_s": total,
            "device_s": tm.get("device", 0.0), "counts": report.to_json()["counts"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--meshes", default=str(Path(__file__).resolve().parents[2] / "shared" / "meshes"))
    ap.add_argument("--thickness", type=float, default=0.05)
    ap.add_argument("--printer", default=None, help="also run the checks on this printer's pixels")
    ap.add_argument("--backend", default="opencl", choices=("opencl", "numpy"))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--no-simplify", action="store_true",
                    help="measure the unsupported area on the true outlines (gpuslice.checks.islands.SIMPLIFY = 0)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    if args.no_simplify:
        import gpuslice.checks.islands as islands

        islands.SIMPLIFY = 0.0
    rows = []
    for name, fit in MESHES.items():
        path = Path(args.meshes) / f"{name}.stl"
        if not path.is_file():
            print(f"{name}: {path} not found, skipped")
            continue
        for printer in (None, args.printer) if args.printer else (None,):
            load0 = os.getloadavg()[0]
            runs = [run_once(path, fit, args.thickness, printer, args.backend) for _ in range(args.repeat + 1)][1:]
            load1 = os.getloadavg()[0]
            keys = ("slicing_s", "checks_s", "islands_s", "cavities_s", "total_s")
            med = {k: float(statistics.median(r[k] for r in runs)) for k in keys}
            best = {k: min(r[k] for r in runs) for k in keys}
            row = {"mesh": name, "fit_mm": fit, "mode": f"pixels {printer}" if printer else "contours",
                   "layers": runs[0]["layers"], "points": runs[0]["points"], **med,
                   "best": best, "counts": runs[0]["counts"], "ratio": med["checks_s"] / med["slicing_s"],
                   "load_avg_1min": [load0, load1], "simplify": not args.no_simplify}
            rows.append(row)
            print(f"{name} ({fit:g} mm, {row['layers']} layers, {row['points']:,} points), {row['mode']}, median of "
                  f"{len(runs)} (best): slicing {med['slicing_s']:.3f} s ({best['slicing_s']:.3f}), checks "
                  f"{med['checks_s']:.3f} s ({best['checks_s']:.3f}; islands + unsupported {med['islands_s']:.3f}, "
                  f"traps/cups {med['cavities_s']:.3f}) = {row['ratio']:.2f}x slicing; load {load0:.1f} -> "
                  f"{load1:.1f}; {row['counts']}", flush=True)
    if args.json:
        from gpuslice.device import get_device

        dev = get_device().name if args.backend == "opencl" else "numpy"
        with open(args.json, "w") as f:
            json.dump({"machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(), "device": dev,
                       "thickness_mm": args.thickness, "repeat": args.repeat, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
