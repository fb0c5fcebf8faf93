"""Benchmark of the pre-print checks (issue 13): ``gpuslice check`` on shared meshes, the checks' cost against the
slicing's, as the pipeline times them (one :func:`gpuslice.pipeline.run_job` per run after one warm-up run; the
median of ``--repeat`` runs, and the best).

    python scripts/bench_checks.py                       # nefertiti at 80 mm, benchy at 60 mm, 0.05 mm layers
    python scripts/bench_checks.py --printer generic-4k  # also the pixel-exact checks on that display
    python scripts/bench_checks.py --no-simplify         # the unsupported area on the true outlines (the reference)
    python scripts/bench_checks.py --json bench_checks.json
    python scripts/bench_checks.py --screen              # the mesh screen of the unsupported area (tried, dropped)

"slicing" is the pipeline's load + topology + schedule + crossings + chaining + nesting (the device's one-off
kernel build left out); "checks" is the ``checks`` stage, split into ``islands`` (islands and unsupported area) and
``cavities`` (the voxel grid's rasterisation, traps and suction cups; in contour mode they run alongside the islands,
so their share is only the wait left after them). Timings are wall-clock seconds; the machine's
load average (1 min) is printed before and after each mesh, since other work on the machine slows both.

``--screen`` measures an exact screen of the contour-mode unsupported area that was tried and dropped (BENCHMARKS,
"Pre-print checks"). On a closed mesh, a point of layer i outside layer i - 1 lies under a piece of the surface
between the two planes; going down the surface from it to plane i - 1 moves it sideways by at most
h · (the largest rate met), where a facet's rate is |n_z| / |n_xy| (its steepest descent), an edge's |dxy| / |dz|
(followed only in a valley, where both facets descend onto it) and a vertex's the smallest rate of its downward
edges (a local minimum: infinite). So within tol·cos(pi/8) (GEOS's 2-segment arcs) of layer i - 1 unless a
"bad" facet, valley edge or vertex is met: the exact overlay is only needed in windows around those, grown by the
tolerance. Printed: slabs with nothing bad (whole layers skipped), the windows (cells of ``--cell`` mm merged along
x), the share of layer i's points in them, the screen's and the windowed GEOS's time against the whole-layer
reference (one thread), and the largest difference.
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


def _screen(mesh, zs, tol: float, cell: float):
    """The windows of the screen (module docstring): ``(slabs with nothing bad, window layer, (K, 4) rects mm)``."""
    import numpy as np

    h = float(np.max(np.diff(zs.astype(np.float64)))) if zs.size > 1 else 0.0
    lim = tol * np.cos(np.pi / 8) * 0.999 / max(h, 1e-300)  # the largest rate that keeps a slab within the buffer
    v = mesh.vertices.astype(np.float64)
    f, ev = mesh.faces, mesh.edge_vertices
    vl = np.searchsorted(zs, mesh.vertices[:, 2], side="right")  # the slab of each vertex (half-open planes)
    with np.errstate(divide="ignore", invalid="ignore"):
        nrm = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        bad_f = ~(np.abs(nrm[:, 2]) <= lim * np.hypot(nrm[:, 0], nrm[:, 1]))
        d = v[ev[:, 1]] - v[ev[:, 0]]
        rate = np.hypot(d[:, 0], d[:, 1]) / np.abs(d[:, 2])
        descent = (nrm[:, 2] / (nrm * nrm).sum(1))[:, None] * nrm - np.array([0.0, 0.0, 1.0])
        onto = np.zeros(f.shape, bool)  # does the facet's steepest descent run onto side k?
        for k in range(3):
            a, b, c = v[f[:, k]], v[f[:, (k + 1) % 3]], v[f[:, (k + 2) % 3]]
            m = np.cross(b - a, nrm)
            onto[:, k] = (descent * m).sum(1) * ((a - c) * m).sum(1) > 0
    valley = np.bincount(mesh.face_edges.reshape(-1), onto.reshape(-1), minlength=ev.shape[0]) >= 2
    bad_e = valley & ~(rate <= lim)
    upper = np.where(v[ev[:, 0], 2] > v[ev[:, 1], 2], ev[:, 0], ev[:, 1])
    v_rate = np.full(v.shape[0], np.inf)
    np.minimum.at(v_rate, upper, np.nan_to_num(rate, nan=np.inf))
    bad_v = np.flatnonzero(~(v_rate <= lim))
    fb, eb = np.flatnonzero(bad_f), np.flatnonzero(bad_e)
    fx, ex = v[f[fb]][:, :, :2], v[ev[eb]][:, :, :2]
    lo = np.concatenate([vl[f[fb]].min(1), vl[ev[eb]].min(1), vl[bad_v]])  # slabs met, in part or whole
    hi = np.concatenate([vl[f[fb]].max(1), vl[ev[eb]].max(1), vl[bad_v]])
    bmin = np.concatenate([fx.min(1), ex.min(1), v[bad_v, :2]]) - tol
    bmax = np.concatenate([fx.max(1), ex.max(1), v[bad_v, :2]]) + tol
    n = zs.size
    lo, hi = np.maximum(lo, 1), np.minimum(hi, n - 1)
    cnt = np.maximum(hi - lo + 1, 0)
    item = np.repeat(np.arange(cnt.size), cnt)
    slab = lo[item] + np.arange(item.size) - (np.cumsum(cnt) - cnt)[item]
    ok = np.ones(n, bool)
    ok[slab] = False
    ok[0] = False
    # cells of `cell` mm touched by each grown box, per slab; runs of cells along x become rectangles
    x0, y0 = v[:, 0].min() - 2 * tol, v[:, 1].min() - 2 * tol
    nx = int((v[:, 0].max() - x0) / cell) + 3
    ny = int((v[:, 1].max() - y0) / cell) + 3
    c0 = np.floor((bmin[item] - (x0, y0)) / cell).astype(np.int64)
    span = np.floor((bmax[item] - (x0, y0)) / cell).astype(np.int64) - c0 + 1  # cells along x and y
    per = span[:, 0] * span[:, 1]
    k = np.repeat(np.arange(item.size), per)
    off = np.arange(k.size) - np.repeat(np.cumsum(per) - per, per)
    key = np.unique((slab[k] * ny + c0[k, 1] + off // span[k, 0]) * nx + c0[k, 0] + off % span[k, 0])
    cut = np.flatnonzero(np.diff(key) != 1) + 1
    first, last = key[np.r_[0, cut]] if key.size else key, key[np.r_[cut - 1, key.size - 1]] if key.size else key
    row = first // nx
    rects = np.stack([x0 + first % nx * cell, y0 + row % ny * cell, x0 + (last % nx + 1) * cell,
                      y0 + (row % ny + 1) * cell], axis=1)
    return ok, row // ny, rects


def screen(path: Path, fit: float, thickness: float, cell: float) -> None:
    """Print the screen's figures for one mesh (module docstring)."""
    import numpy as np
    import shapely

    from gpuslice import load_mesh, slice_mesh
    from gpuslice.checks import contour_islands
    from gpuslice.slicing.geometry import polygons_shapely

    mesh = load_mesh(path, fit=fit)
    res = slice_mesh(mesh, thickness=thickness)
    tol = 0.05
    t = time.perf_counter()
    ref = contour_islands(res, tol, workers=1, simplify=0).unsupported
    t_ref = time.perf_counter() - t
    t = time.perf_counter()
    ok, lay_w, rects = _screen(mesh, np.asarray(res.z, np.float32), tol, cell)
    t_screen = time.perf_counter() - t
    t = time.perf_counter()
    lay = polygons_shapely(res)
    g = 1.5 * tol
    cur = np.array([shapely.clip_by_rect(lay[i], *r) for i, r in zip(lay_w, rects, strict=True)], dtype=object)
    prev = np.array([shapely.clip_by_rect(lay[i - 1], r[0] - g, r[1] - g, r[2] + g, r[3] + g)
                     for i, r in zip(lay_w, rects, strict=True)], dtype=object)
    area = shapely.area(shapely.difference(cur, shapely.buffer(prev, tol, quad_segs=2)))
    unsup = np.bincount(lay_w, area, minlength=res.n_layers)
    t_win = time.perf_counter() - t
    share = shapely.get_num_coordinates(cur).sum() / max(res.points.shape[0], 1)
    print(f"{path.stem}: {int(ok.sum())} of {res.n_layers - 1} slabs with nothing bad; {lay_w.size} windows of "
          f"{cell:g} mm cells hold {share:.0%} of the points; whole layers {t_ref:.3f} s, screen {t_screen:.3f} s + "
          f"windows {t_win:.3f} s; largest difference {np.abs(unsup - ref).max():.1e} mm2 (unsupported in "
          f"{int((ref > 0).sum())} layers, none in a skipped one: {not np.any(ref[ok] > 0)})", flush=True)


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
    ap.add_argument("--screen", action="store_true", help="measure the mesh screen instead (module docstring)")
    ap.add_argument("--cell", type=float, default=4.0, help="--screen: window cell, mm")
    args = ap.parse_args()
    if args.screen:
        for name, fit in MESHES.items():
            screen(Path(args.meshes) / f"{name}.stl", fit, args.thickness, args.cell)
        return
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
