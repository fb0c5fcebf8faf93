"""Adaptive layers against a peer: gpuslice's cusp/area schedules and CuraEngine's adaptive layers, side by side.

Both slice the same scaled STL (``peers.write_scaled_stl``, nefertiti at 80 mm by default). CuraEngine 4.13 runs with
``adaptive_layer_height_enabled`` and a base height and variation that give the same thickness range [A, B]
(0.05–0.3 mm: layer_height 0.175, variation 0.125, step 0.01); its layer tops (gcode Z) become a schedule whose
quality gpuslice measures with the same code as its own (``gpuslice.bench.quality``: max and mean cusp height). Uniform
0.05 mm runs of both are the baseline. Times: CuraEngine is a whole process (it writes gcode, too: its times include
much more than slicing), so gpuslice is timed both in-process (``slice_mesh``, schedule included) and as a whole
``gpuslice slice`` process. Medians of ``--repeat`` runs; the machine is shared, so timings are noisy.

    python scripts/bench_adaptive.py [--mesh ../shared/meshes/nefertiti.stl] [--fit 80] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import peers  # noqa: E402

from gpuslice import load_mesh, slice_mesh  # noqa: E402
from gpuslice.bench.quality import cusp_summary  # noqa: E402
from gpuslice.device import get_device  # noqa: E402
from gpuslice.schedule.adaptive import schedule_from_edges  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _median_time(fn, repeat: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=str(REPO.parent / "shared" / "meshes" / "nefertiti.stl"))
    ap.add_argument("--fit", type=float, default=80.0)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    dev = get_device()
    with tempfile.TemporaryDirectory(prefix="bench-adaptive-") as tmp:
        stl = Path(tmp) / "model.stl"
        peers.write_scaled_stl(args.mesh, stl, fit=args.fit)
        mesh = load_mesh(stl, device=dev)
        print(f"model: {Path(args.mesh).name} at {args.fit:g} mm ({mesh.n_faces} facets, {mesh.height:.4g} mm tall); "
              f"device: {dev.name}; medians of {args.repeat}")
        rows = []
        slice_mesh(mesh, thickness=0.05)  # warm-up
        for label, kw, cli in (
            ("uniform 0.05", {"thickness": 0.05}, ["-t", "0.05"]),
            ("cusp C=0.05", {"adaptive": "cusp"}, ["--adaptive", "cusp"]),
            ("area A=0.0025", {"adaptive": "area"}, ["--adaptive", "area"]),
        ):
            t_in, res = _median_time(lambda kw=kw: slice_mesh(mesh, **kw), args.repeat)
            t_cli, _ = _median_time(
                lambda cli=cli: subprocess.run([sys.executable, "-m", "gpuslice.cli", "slice", str(stl), *cli, "-q"],
                                               check=True), args.repeat)
            q = cusp_summary(mesh, res, dev)
            rows.append((f"gpuslice {label}", res.n_layers, t_in, t_cli, q["max_cusp_mm"], q["mean_cusp_mm"]))
        cura_settings = {"adaptive_layer_height_enabled": "true", "adaptive_layer_height_variation": 0.125,
                         "adaptive_layer_height_variation_step": 0.01}
        for label, h, settings in (("uniform 0.05", 0.05, {}), ("adaptive 0.175±0.125", 0.175, cura_settings)):
            try:
                t_cli, out = _median_time(lambda h=h, s=settings: peers.cura_slice(stl, h, settings=s), args.repeat)
            except RuntimeError as exc:
                print(f"CuraEngine skipped: {exc}".splitlines()[0])
                break
            tops = np.asarray(out["z_top"], dtype=np.float64)
            edges = np.concatenate(([0.0], tops[tops > 0]))
            sched = schedule_from_edges(edges[np.concatenate(([True], np.diff(edges) > 0))])
            q = cusp_summary(mesh, sched, dev)
            rows.append((f"CuraEngine {label}", len(sched), None, t_cli, q["max_cusp_mm"], q["mean_cusp_mm"]))
    print()
    print("| setting | layers | in-process s | whole process s | max cusp mm | mean cusp mm |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, n, t_in, t_cli, mx, mean in rows:
        t_in_s = f"{t_in:.3f}" if t_in is not None else "-"
        print(f"| {name} | {n} | {t_in_s} | {t_cli:.3f} | {mx:.4f} | {mean:.4f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
