"""Benchmark of issue 6: ``gpuslice batch`` serial, on local workers and on a local Dask cluster, with peers.

Usage::

    python scripts/bench_batch.py [--repeat 5] [--peer-repeat 3] [--thickness 0.1,0.05] [--fit 60]
                                  [--skip-peers] [--json out.json]

Models: every mesh of ``../shared/meshes/catalog.csv`` outside the ``problem`` category (26 meshes, 28 to 225k
facets), each written once as a binary STL scaled so its longest side is ``--fit`` mm (``peers.write_scaled_stl``),
so that every contender slices the same files in mm with no scaling option.

Measured side by side in the same run, as whole commands (``subprocess`` wall time, so Python start-up, imports,
OpenCL set-up and kernel build count, as a user sees them), median of ``--repeat`` runs, each into a fresh output
folder, the contenders interleaved (one run of each in turn) so that outside load hits them alike:

* ``gpuslice batch DIR -o OUT -t H -j 0``: serial, every model in the one process;
* ``gpuslice batch DIR -o OUT -t H``: local workers, the default count (one per core, PoCL threads shared out);
* ``gpuslice batch DIR -o OUT -t H -j 1 --threads C``: one worker process with every core (the pool's cost);
* ``gpuslice batch DIR -o OUT -t H --scheduler ADDR --transfer bytes|shared``: a Dask ``LocalCluster`` of two
  worker processes (one thread each, ``POCL_MAX_PTHREAD_COUNT=1``) started once by this script (its start-up is
  reported apart); the first batch on fresh workers (kernel build in each) is reported apart from the medians;
* peers: ``gpuslice slice`` once per model from a shell-like loop (what one would do without ``batch``), and
  Slic3r 1.3's own multi-file mode, ``slic3r --export-svg --layer-height H --first-layer-height H *.stl``
  (one process, models one after another; Slic3r is the contour slicer of ``scripts/bench_contours.py``).

Where the time goes comes from the batch reports (``--report``): start-up (process, imports, pool), per-worker
device and kernel set-up, the sum of the per-model stages (read, weld, slicing, write) and the rest (dispatch and,
for Dask, transfer). A Markdown table goes to stdout, progress to stderr; ``--json FILE`` keeps every sample.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402  (scripts/peers.py)

REPO = Path(__file__).resolve().parents[1]
MESHES = REPO.parent / "shared" / "meshes"


def log(*args) -> None:
    print(*args, file=sys.stderr, flush=True)


def prepare(folder: Path, fit: float) -> list[Path]:
    rows = list(csv.DictReader(open(MESHES / "catalog.csv")))
    out = []
    for row in rows:
        if row["category"] == "problem":
            continue
        dst = folder / f"{row['name']}.stl"
        peers.write_scaled_stl(MESHES / row["file"], dst, fit=fit)
        out.append(dst)
    return out


def timed(cmd: list[str], env: dict | None = None, cwd: Path | None = None):
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    return time.perf_counter() - t, proc


def gpuslice_batch(models: Path, work: Path, h: float, extra: list[str]) -> tuple[float, dict]:
    out = work / "out"
    shutil.rmtree(out, ignore_errors=True)
    rep = work / "report.json"
    wall, proc = timed(["gpuslice", "batch", str(models), "-o", str(out), "-t", f"{h:g}", "-q", "--report",
                        str(rep), *extra])
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"gpuslice batch {' '.join(extra)} failed: {proc.stderr}")
    return wall, json.loads(rep.read_text())


def breakdown(report: dict) -> dict:
    """Seconds summed over the models' records, per stage, plus the per-worker set-up."""
    done = [r for r in report["models"] if r["status"] == "done"]
    stages: dict[str, float] = {}
    for r in done:
        for k, v in r["timings_s"].items():
            stages[k] = stages.get(k, 0.0) + v
    s = report["summary"]
    return {"stages": stages, "worker_init_s": s["worker_init_s"], "wall_in_batch_s": s["wall_s"],
            "done": s["done"], "failed": s["failed"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--peer-repeat", type=int, default=3, help="repeats of the (slow) peers")
    ap.add_argument("--thickness", default="0.1,0.05")
    ap.add_argument("--fit", type=float, default=60.0)
    ap.add_argument("--skip-peers", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    if not (MESHES / "catalog.csv").is_file():
        log(f"{MESHES} not found: the benchmark needs the shared meshes")
        return 2
    from distributed import Client, LocalCluster

    from gpuslice.batch.task import _cores

    cores = _cores()
    thicknesses = [float(x) for x in args.thickness.split(",")]
    samples: dict = {"machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                                 "cpu": platform.processor() or platform.machine(), "cores": cores},
                     "fit_mm": args.fit, "runs": {}}
    with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
        tmp = Path(tmp)
        models = tmp / "models"
        models.mkdir()
        files = prepare(models, args.fit)
        rows = csv.DictReader(open(MESHES / "catalog.csv"))
        facets = sum(int(r["facets"]) for r in rows if r["category"] != "problem")
        samples["models"] = len(files)
        samples["facets"] = facets
        log(f"{len(files)} models, {facets} facets, fit {args.fit} mm, {cores} cores")
        start, _ = timed([sys.executable, "-c", "import gpuslice.batch.runner, gpuslice.cli"])
        samples["python_import_s"] = start
        t = time.perf_counter()
        cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                               host="127.0.0.1", env={"POCL_MAX_PTHREAD_COUNT": "1", "POCL_CPU_MAX_CU_COUNT": "1"})
        client = Client(cluster)
        samples["dask_cluster_start_s"] = time.perf_counter() - t
        samples["load_average_start"] = os.getloadavg()
        addr = cluster.scheduler_address
        contenders = {
            "serial (-j 0)": ["-j", "0"],
            "local workers (default)": [],
            f"1 worker, {cores} threads": ["-j", "1", "--threads", str(cores)],
            "Dask 2 workers, bytes": ["--scheduler", addr, "--transfer", "bytes"],
            "Dask 2 workers, shared": ["--scheduler", addr, "--transfer", "shared"],
        }
        try:
            for h in thicknesses:
                runs: dict = {name: {"wall_s": [], "reports": []} for name in contenders}
                work = tmp / "work"
                work.mkdir(exist_ok=True)
                if "dask_first" not in samples:  # fresh Dask workers: device and kernels made in each
                    first, rep = gpuslice_batch(models, work, h, contenders["Dask 2 workers, shared"])
                    samples["dask_first"] = {"wall_s": first, **breakdown(rep)}
                for k in range(args.repeat):  # interleaved, so that load from elsewhere hits every contender
                    for name, extra in contenders.items():
                        wall, rep = gpuslice_batch(models, work, h, extra)
                        runs[name]["wall_s"].append(wall)
                        runs[name]["reports"].append(breakdown(rep))
                        runs[name]["workers"] = rep["summary"].get("workers")
                        log(f"h={h:g} #{k} {name}: {wall:.2f} s")
                for r in runs.values():
                    r["median_s"] = statistics.median(r["wall_s"])
                if not args.skip_peers:
                    walls = []
                    for _ in range(args.peer_repeat):
                        out = tmp / "loop"
                        shutil.rmtree(out, ignore_errors=True)
                        out.mkdir()
                        t = time.perf_counter()
                        for f in files:
                            subprocess.run(["gpuslice", "slice", str(f), "-t", f"{h:g}", "-q", "-o",
                                            str(out / f"{f.stem}.npz")], capture_output=True)
                        walls.append(time.perf_counter() - t)
                    runs["peer: gpuslice slice loop"] = {"wall_s": walls, "median_s": statistics.median(walls)}
                    log(f"h={h:g} gpuslice slice loop: {statistics.median(walls):.2f} s")
                    exe = peers.find_peer("slic3r")
                    if exe:
                        walls = []
                        for _ in range(args.peer_repeat):
                            out = tmp / "slic3r"
                            shutil.rmtree(out, ignore_errors=True)
                            out.mkdir()
                            for f in files:
                                shutil.copy(f, out / f.name)
                            cmd = [exe, "--no-gui", "--export-svg", "--layer-height", f"{h:g}",
                                   "--first-layer-height", f"{h:g}", *sorted(p.name for p in out.glob("*.stl"))]
                            wall, proc = timed(cmd, cwd=out)
                            n_svg = len(list(out.glob("*.svg")))
                            walls.append(wall)
                        runs["peer: slic3r --export-svg (all files)"] = {
                            "wall_s": walls, "median_s": statistics.median(walls), "svgs": n_svg,
                            "rc": proc.returncode}
                        log(f"h={h:g} slic3r: {statistics.median(walls):.2f} s ({n_svg} svgs, rc {proc.returncode})")
                samples["runs"][f"{h:g}"] = runs
        finally:
            samples["load_average_end"] = os.getloadavg()
            client.close()
            cluster.close()

    n = samples["models"]
    print(f"\n{n} models ({samples['facets']} facets), fit {args.fit:g} mm; {cores} cores; "
          f"median of {args.repeat} ({args.peer_repeat} for peers); "
          f"Dask cluster start {samples['dask_cluster_start_s']:.2f} s (not included); first batch on fresh Dask "
          f"workers {samples['dask_first']['wall_s']:.2f} s; load average (1, 5, 15 min) at start "
          f"{samples['load_average_start']}, at end {samples['load_average_end']}\n")
    for h, runs in samples["runs"].items():
        base = runs["serial (-j 0)"]["median_s"]
        print(f"| h = {h} mm | wall s (median) | models/s | vs serial |")
        print("|---|---:|---:|---:|")
        for name, r in runs.items():
            print(f"| {name} | {r['median_s']:.2f} | {n / r['median_s']:.1f} | {base / r['median_s']:.2f}x |")
        print()
        for name, r in runs.items():
            if "reports" not in r:
                continue
            rep = sorted(r["reports"], key=lambda x: x["wall_in_batch_s"])[len(r["reports"]) // 2]
            st = rep["stages"]
            init = rep["worker_init_s"]
            print(f"- {name}: in-batch {rep['wall_in_batch_s']:.2f} s of {r['median_s']:.2f} s; worker set-up "
                  f"{', '.join(f'{x:.2f}' for x in init) or '-'} s; model stages summed: "
                  + ", ".join(f"{k} {v:.2f}" for k, v in st.items() if k != "total")
                  + f"; total {st.get('total', 0):.2f} s")
        print()
    if args.json:
        Path(args.json).write_text(json.dumps(samples, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
