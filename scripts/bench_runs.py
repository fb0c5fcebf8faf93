"""Micro-benchmark of resin layers as runs (gpuslice.raster.runs) on the armadillo job, against the bitmap raster path.

The job (docs: ../shared/PERFORMANCE-NOTES.md): ``../shared/meshes/armadillo.stl`` after one
``trimesh.remesh.subdivide_loop`` (345,928 facets), stood upright, scaled to 95 mm tall, 0.05 mm layers (1,900),
an 11520x5120 display of 0.019 mm pixels, gamma 0 and gamma 1. The file's tallest axis is Y (extents 0.84 x 1.00 x
0.76), so it is rotated +90 degrees about X, (x, y, z) -> (x, -z, y), to make Y the height; then ``fit=95``.

In-process, warm (one warm-up run first), median of ``--repeat`` (wall and process CPU seconds: the CPU time of
PoCL's threads counts, so it tells what a loaded machine hides): ``layer_edges`` (float32, as the runs take them);
runs with OpenCL (given those edges; in ``LANES`` lanes and in one; the stages split out in one more run, one lane,
that drains the queue after each; long rows finished on the host); both as the writers call them (``iter_runs``
making the edges chunk by chunk, the next chunk's on a thread while this one's runs are made: issue 18's in-process
target, <= 0.3 s at gamma 0) and
with the numpy twin (``--skip-numpy``); once, for reference, the old bitmap path
``iter_tiles(backend="opencl-bitmap")`` with every tile consumed, its own ``layer_edges`` included (``--skip-old``,
it takes ~20 s). Prints layers/s, the run count and the process's peak RSS after each stage, and the load average.

``--stage-repeat N``: the stage-split run N times, each stage's minimum and median (the kernels' own cost on a noisy
machine: the minimum moves little from run to run, the whole-process medians move 10-15 %). ``--z-samples K``: the
runs of the first 512 layers averaged over K sub-planes each (their K*512 planes sliced, each layer's sub-planes'
edges merged: what ``raster --z-samples K`` rasterises) instead of the plain layers.

Usage: ``python scripts/bench_runs.py [--repeat 3] [--gammas 0,1] [--skip-numpy] [--skip-old] [--stage-repeat N]
[--z-samples K]``
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MESH = REPO.parent / "shared" / "meshes" / "armadillo.stl"


def peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timed(fn, repeat: int) -> tuple[float, float, object]:
    """(median wall s, median process CPU s, last result) of ``repeat`` runs after a warm-up (repeat 0: one run)."""
    out = fn() if repeat else None  # warm-up
    walls, cpus = [], []
    for _ in range(max(repeat, 1)):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus), out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--gammas", default="0,1")
    ap.add_argument("--skip-numpy", action="store_true")
    ap.add_argument("--skip-old", "--skip-raster", action="store_true", help="skip the old bitmap path (~20 s)")
    ap.add_argument("--stage-repeat", type=int, default=1, help="stage-split runs (min and median of each stage)")
    ap.add_argument("--z-samples", type=int, default=1, help="K sub-planes per layer, the first 512 layers")
    args = ap.parse_args(argv)
    if not MESH.is_file():
        print(f"{MESH} not found", file=sys.stderr)
        return 2
    import trimesh

    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.device import get_device
    from gpuslice.raster import RasterSpec, iter_tiles, layer_edges
    from gpuslice.raster.runs import LANES, RunsKernel, iter_runs

    dev = get_device()
    m = trimesh.load(MESH, force="mesh")
    v, f = trimesh.remesh.subdivide_loop(m.vertices, m.faces, iterations=1)
    v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)  # Y up -> Z up (a rotation, det +1)
    mesh = mesh_from_triangles(v[f], fit=95.0, device=dev, name="armadillo")
    t = time.perf_counter()
    res = slice_mesh(mesh, thickness=0.05, backend="opencl")
    t_slice = time.perf_counter() - t
    ext = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    print(f"armadillo Loop x1: {mesh.n_faces} facets, {ext[0]:.1f} x {ext[1]:.1f} x {ext[2]:.1f} mm, "
          f"{res.n_layers} layers, {res.points.shape[0]} points; slice {t_slice:.2f} s (cold); device {dev.name}")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} on {os.cpu_count()} CPUs")
    src, k = res, args.z_samples
    if k > 1:  # the first 512 layers' K sub-planes, sliced (the polygon path of --z-samples)
        from gpuslice.raster.edges import result_bounds, z_sample_planes

        bounds = result_bounds(res)
        z, th = z_sample_planes(res, k)
        src = slice_mesh(mesh, backend="opencl", z=z[: 512 * k], layer_thickness=th[: 512 * k])
        print(f"--z-samples {k}: the first 512 layers, {src.n_layers} sub-planes")
    n = src.n_layers // k
    kern = RunsKernel.of(dev)

    def row(name, wall, cpu, extra=""):
        print(f"| {name} | {wall * 1000:.0f} ms | {cpu * 1000:.0f} ms | {n / wall:.0f} layers/s | "
              f"{peak_mb():.0f} MB | {extra} |")

    for gamma in (float(g) for g in args.gammas.split(",")):
        spec = RasterSpec(resolution=(11520, 5120), pixel=0.019, gamma=gamma)
        print(f"\n### gamma {gamma:g}, 11520x5120 @ 0.019 mm")
        print("| stage | wall (median) | CPU (median) | rate | peak RSS | notes |\n|---|---|---|---|---|---|")
        if k > 1:
            from gpuslice.raster.edges import merge_layer_groups

            wall, cpu, le = timed(lambda spec=spec: merge_layer_groups(
                layer_edges(src, spec, bounds, dtype=np.float32), k), args.repeat)
        else:
            wall, cpu, le = timed(lambda spec=spec: layer_edges(res, spec, dtype=np.float32), args.repeat)
        row("layer_edges (float32)", wall, cpu, f"{le.edges.shape[0]} edges")

        def runs(backend, le=le, spec=spec, lanes=None):
            count = 0
            given = dict(merged=le, z_samples=k) if k > 1 else {} if le is None else dict(edges=le)
            for r in iter_runs(None if k > 1 else res, spec, backend=backend, device=dev, lanes=lanes, **given):
                count += r.n_runs
            return count

        wall, cpu, count = timed(lambda: runs("opencl"), args.repeat)
        row(f"runs, OpenCL (given the edges), {LANES} lanes", wall, cpu, f"{count} runs")
        wall, cpu, count = timed(lambda: runs("opencl", lanes=1), args.repeat)
        row("runs, OpenCL (given the edges), one lane (before lanes)", wall, cpu, f"{count} runs")
        if k == 1:
            wall, cpu, count = timed(lambda: runs("opencl", None), args.repeat)
            row(f"layer_edges + runs, OpenCL, as the writers call them, {LANES} lanes", wall, cpu, f"{count} runs")
            wall, cpu, count = timed(lambda: runs("opencl", None, lanes=1), args.repeat)
            row("layer_edges + runs, OpenCL, as the writers call them, one lane", wall, cpu, f"{count} runs")
        long0, fb0, stages = kern.long_rows, kern.fallbacks, {}
        for _ in range(max(args.stage_repeat, 1)):
            kern.timings = {}
            runs("opencl", lanes=1)  # (one lane: the stages of every batch on kern's queue, drained after each)
            for name, v in kern.timings.items():
                stages.setdefault(name, []).append(v)
        kern.timings = None
        med = {name: statistics.median(v) for name, v in stages.items()}
        split = ", ".join(f"{name} {v * 1000:.0f} ms" for name, v in med.items())
        if args.stage_repeat > 1:
            split += "; minima: " + ", ".join(f"{name} {min(v) * 1000:.1f}" for name, v in stages.items())
        print(f"| stages (queue drained after each; median of {max(args.stage_repeat, 1)}) | "
              f"{sum(med.values()) * 1000:.0f} ms | | | | {split}; {kern.long_rows - long0} long rows on the host, "
              f"{kern.fallbacks - fb0} batches redone |")
        if not args.skip_numpy:
            wall, cpu, count = timed(lambda: runs("numpy"), args.repeat)
            row("runs, numpy twin (given the edges)", wall, cpu, f"{count} runs")
        if not args.skip_old and k == 1:
            def raster(spec=spec):
                px = 0
                for tile in iter_tiles(res, spec, backend="opencl-bitmap", device=dev):
                    px += tile.data.size
                return px

            wall, cpu, px = timed(raster, 0)
            row("old bitmap path, once: iter_tiles opencl-bitmap (+ its layer_edges)", wall, cpu,
                f"{px / 1e9:.2f} G tile pixels")
    print(f"\npeak RSS of the process: {peak_mb():.0f} MB; load average after: "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
