"""Compare two OpenCL devices on every shared mesh, in one process: the device weld, the contours and the runs.

    python scripts/gpu_compare.py --a nvidia --b pocl [--fit 60] [--thickness 0.1,0.05] [--json out.json]

For each mesh of ``<meshes>/catalog.csv`` (default ``<repo>/../shared/meshes``) that loads (a mesh the loader
refuses is counted as refused, with its message):

* ``weld``: ``load_mesh(path, fit=F, device=A)`` against the same on device B: vertices and faces equal;
* ``slice``: ``slice_mesh(mesh, thickness=T, device=…)`` for each thickness (the host-welded mesh, so both devices
  cut the same facets): every array of the :class:`~gpuslice.slicing.result.SliceResult` (points, offsets, nesting,
  z, areas, repairs) equal, else the largest point difference (mm) and which arrays differ;
* ``runs``: the runs of device A's result at the first thickness on a 3840x2400 display of 0.05 mm pixels, gamma 1
  and gamma 0, made by each device's runs kernel: every run equal.

Exit status 1 when anything differs. Used by ``scripts/gpu_check.sh`` (a GPU against PoCL on the same machine).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
import traceback
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
FIELDS = ("points", "loop_offsets", "layer_offsets", "loop_layer", "loop_is_hole", "loop_parent", "loop_closed",
          "z", "thickness", "area")


def diff_results(ra, rb) -> dict:
    """Which arrays of two slice results differ, and by how much where their shapes agree (mm for points)."""
    out: dict = {"differ": []}
    for f in FIELDS:
        a, b = getattr(ra, f), getattr(rb, f)
        if a.shape != b.shape or not np.array_equal(a, b):
            out["differ"].append(f)
            if a.shape == b.shape and a.dtype.kind == "f":
                out[f"{f}_max_abs"] = float(np.max(np.abs(a.astype(np.float64) - b.astype(np.float64))))
            elif a.shape != b.shape:
                out[f"{f}_shapes"] = [list(a.shape), list(b.shape)]
    keys = sorted(set(ra.repairs) | set(rb.repairs))
    for k in keys:
        a, b = ra.repairs.get(k), rb.repairs.get(k)
        if a is None or b is None or not np.array_equal(np.asarray(a), np.asarray(b)):
            out["differ"].append(f"repairs.{k}")
    return out


def runs_equal(ra, rb) -> bool:
    return all(np.array_equal(getattr(ra, f), getattr(rb, f))
               for f in ("layers", "layer_offsets", "row", "x", "length", "grey"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--a", default="nvidia", help="device A (GPUSLICE_DEVICE syntax)")
    ap.add_argument("--b", default="pocl", help="device B")
    ap.add_argument("--meshes", type=Path, default=ROOT.parent / "shared" / "meshes")
    ap.add_argument("--fit", type=float, default=60.0)
    ap.add_argument("--thickness", default="0.1,0.05")
    ap.add_argument("--only", action="append", default=[])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    from gpuslice import load_mesh, slice_mesh
    from gpuslice.device import get_device
    from gpuslice.raster import RasterSpec
    from gpuslice.raster.runs import layer_runs

    da, db = get_device(args.a), get_device(args.b)
    print(f"A = {da.name}\nB = {db.name}", flush=True)
    ts = [float(x) for x in args.thickness.split(",")]
    with open(args.meshes / "catalog.csv", newline="") as f:
        names = [(r["name"], r["file"]) for r in csv.DictReader(f)]
    if args.only:
        names = [n for n in names if n[0] in args.only]
    rows, bad = [], 0
    t_start = time.perf_counter()
    for name, file in names:
        row: dict = {"mesh": name}
        try:
            path = args.meshes / file
            try:
                mesh = load_mesh(path, fit=args.fit)
            except Exception as exc:  # refused: the loader's one-line error
                row["refused"] = str(exc).splitlines()[0][:120]
                rows.append(row)
                print(f"{name:28s} refused: {row['refused']}", flush=True)
                continue
            ma, mb = load_mesh(path, fit=args.fit, device=da), load_mesh(path, fit=args.fit, device=db)
            row["weld"] = bool(np.array_equal(ma.vertices, mb.vertices) and np.array_equal(ma.faces, mb.faces))
            first = None
            for t in ts:
                ra, rb = slice_mesh(mesh, thickness=t, device=da), slice_mesh(mesh, thickness=t, device=db)
                d = diff_results(ra, rb)
                row[f"slice_{t:g}"] = d
                row[f"points_{t:g}"] = int(ra.points.shape[0])
                first = ra if first is None else first
            spec_kw = dict(resolution=(3840, 2400), pixel=0.05)
            for g in (1.0, 0.0):
                spec = RasterSpec(gamma=g, **spec_kw)
                a = layer_runs(first, spec, device=da, clip=True)
                b = layer_runs(first, spec, device=db, clip=True)
                row[f"runs_g{g:g}"] = runs_equal(a, b)
                row[f"n_runs_g{g:g}"] = int(a.n_runs)
        except Exception as exc:  # report and go on: one broken case must not hide the others
            row["error"] = f"{type(exc).__name__}: {exc}"[:300]
            traceback.print_exc()
        ok = "error" not in row and row["weld"] and all(not row[f"slice_{t:g}"]["differ"] for t in ts) and \
            row["runs_g1"] and row["runs_g0"]
        bad += not ok
        rows.append(row)
        desc = "same" if ok else json.dumps({k: v for k, v in row.items() if k != "mesh"})[:400]
        print(f"{name:28s} {desc}", flush=True)
    summary = {"a": da.name, "b": db.name, "meshes": len(rows), "refused": sum("refused" in r for r in rows),
               "differ": bad, "seconds": round(time.perf_counter() - t_start, 1)}
    print(json.dumps(summary), flush=True)
    if args.json:
        args.json.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
