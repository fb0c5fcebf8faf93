"""``bench_contours.py --large``: whole-process time, peak memory and stages of ``gpuslice slice`` on big meshes.

The meshes are those of ``scripts/make_large.py`` (``nefertiti_loop2`` 1.6 M facets, ``benchy_plate12`` 2.7 M,
``nefertiti_loop3`` 6.4 M), read from ``--large-dir`` (default ``/tmp/gpuslice-large``; built first with
``python scripts/make_large.py``). For each mesh and layer thickness (``--large-thickness``, default 0.02 and
0.05 mm) it runs ``gpuslice slice FILE -t T -o OUT.npz`` as a child process and records:

* the whole process: wall time around the child (start-up, imports, OpenCL context, read, slice, write);
* its peak RSS: ``ru_maxrss`` of that child alone (``os.wait4``; Linux reports KiB);
* the stages it prints (``times (ms): ...``: the run report's ``timings_s``, i.e. device, load, topology,
  schedule, crossings, chaining, nesting, mesh_check, write) and its counts (facets, layers, segments, points).

Then one more run with ``--report OUT.json``: a report adds the schedule's cusp heights, whose ``cusp`` stage is
shown apart (it is not part of the plain command's time).

One untimed warm-up run per mesh (at the coarsest thickness: kernels in PyOpenCL's cache, the STL in the page
cache), then ``--large-repeat`` timed runs (median). A Markdown table goes to stdout.
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LARGE_DIR = Path("/tmp/gpuslice-large")
LARGE_MESHES = ("nefertiti_loop2", "benchy_plate12", "nefertiti_loop3")
DEFAULT_LARGE = "nefertiti_loop2,benchy_plate12"  # the 6.4 M mesh only when asked (about 2 GB, minutes)
STAGES = ("device", "load", "topology", "schedule", "crossings", "chaining", "nesting", "mesh_check", "write")


def add_arguments(ap) -> None:
    """The ``--large`` options of ``bench_contours.py``."""
    ap.add_argument("--large", action="store_true",
                    help="only the big-mesh benchmark (whole process, peak RSS, stages); see scripts/bench_large.py")
    ap.add_argument("--large-dir", type=Path, default=LARGE_DIR, help="the meshes of scripts/make_large.py")
    ap.add_argument("--large-meshes", default=DEFAULT_LARGE,
                    help=f"comma-separated subset of {', '.join(LARGE_MESHES)}")
    ap.add_argument("--large-thickness", default="0.02,0.05", help="layer thicknesses, mm, comma-separated")
    ap.add_argument("--large-repeat", type=int, default=1, help="timed runs per mesh and thickness (median)")


def run_measured(cmd: list[str], timeout: float = 1800.0) -> tuple[float, int, str]:
    """Run ``cmd``: (wall seconds, peak RSS bytes of that child, stdout). RuntimeError on a non-zero status."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=err)
        deadline = t + timeout
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() > deadline:
                proc.kill()
                raise RuntimeError(f"timed out after {timeout:.0f} s: {' '.join(cmd)}")
            time.sleep(0.005)
        wall = time.perf_counter() - t
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read().decode(errors="replace"), err.read().decode(errors="replace")
    if proc.returncode != 0:
        tail = (stdout + stderr).strip().splitlines()[-5:]
        raise RuntimeError(f"rc={proc.returncode}: {' '.join(cmd)}\n" + "\n".join(tail))
    return wall, int(usage.ru_maxrss) * 1024, stdout


def parse_summary(stdout: str) -> dict:
    """``gpuslice slice``'s summary: counts (``NAME: 225146 facets, 480 layers, ...``) and stage seconds."""
    counts = {key: int(val) for val, key in re.findall(r"(\d+) (facets|layers|segments|loops|points)\b", stdout)}
    stages: dict[str, float] = {}
    m = re.search(r"^times \(ms\): (.*)$", stdout, re.M)
    for part in m.group(1).split(",") if m else []:
        key, _, val = part.strip().rpartition(" ")
        stages[key] = float(val) / 1000.0
    return {"counts": counts, "stages": stages}


def bench_large(exe: list[str], names: list[str], thicknesses: list[float], large_dir: Path, repeat: int,
                log) -> list[dict]:
    """One record per (mesh, thickness): wall times, peak RSS, stages and counts."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-large-") as tmpdir:
        tmp = Path(tmpdir)
        for name in names:
            src = large_dir / f"{name}.stl"
            if not src.is_file():
                log(f"SKIP {name}: {src} not found (python scripts/make_large.py {large_dir})")
                continue
            npz, rep = tmp / f"{name}.npz", tmp / f"{name}.json"
            log(f"{name}: warm-up at {max(thicknesses):g} mm")
            run_measured([*exe, "slice", str(src), "-t", f"{max(thicknesses):g}", "-o", str(npz), "-q"])
            for t in thicknesses:
                walls, rss, runs = [], [], []
                cmd = [*exe, "slice", str(src), "-t", f"{t:g}", "-o", str(npz)]
                for _ in range(repeat):
                    wall, peak, out = run_measured(cmd)
                    walls.append(wall)
                    rss.append(peak)
                    runs.append(parse_summary(out))
                    log(f"{name} -t {t:g}: {wall:.2f} s, peak RSS {peak / 2**20:.0f} MiB")
                run_measured([*cmd, "-q", "--report", str(rep)])
                report = json.loads(rep.read_text())
                rows.append({
                    **{k: runs[-1]["counts"].get(k) for k in ("facets", "layers", "segments", "loops", "points")},
                    "mesh": name, "thickness": t, "npz_bytes": npz.stat().st_size, "command": cmd,
                    "wall_s": walls, "median_s": statistics.median(walls), "peak_rss_bytes": rss,
                    "peak_rss_max_mib": max(rss) / 2**20,
                    "stages_s": {k: statistics.median(r["stages"].get(k, 0.0) for r in runs) for k in STAGES},
                    "report_timings_s": report.get("timings_s", {}),
                })
    return rows


def report_large(rows: list[dict], env: dict, repeat: int) -> str:
    """A Markdown table of :func:`bench_large`'s records."""
    lines = [f"`gpuslice slice FILE -t T -o x.npz`, whole process (median of {repeat}, after one warm-up), peak RSS "
             f"of the process; stages as printed (ms); cusp: the stage a `--report` adds. {env.get('machine', '')}", ""]
    head = ["mesh", "facets", "T mm", "layers", "segments", "whole s", "peak RSS MiB", *STAGES, "cusp (--report)"]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    for r in rows:
        cells = [r["mesh"], f"{r['facets']:,}", f"{r['thickness']:g}", f"{r['layers']:,}", f"{r['segments']:,}",
                 f"{r['median_s']:.2f}", f"{r['peak_rss_max_mib']:,.0f}"]
        cells += [f"{1000 * r['stages_s'][k]:.0f}" for k in STAGES]
        cells.append(f"{1000 * r['report_timings_s'].get('cusp', 0.0):.0f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main_large(args, env: dict, log, exe: list[str] | None = None) -> int:
    """``bench_contours.py --large``: run, print the table, keep every sample in ``--json``. ``exe``: the
    ``gpuslice`` command (default ``python -m gpuslice.cli``)."""
    names = [n.strip() for n in args.large_meshes.split(",") if n.strip()]
    unknown = [n for n in names if n not in LARGE_MESHES]
    if unknown:
        raise SystemExit(f"--large-meshes: unknown {', '.join(unknown)} (choose from {', '.join(LARGE_MESHES)})")
    thicknesses = sorted({float(x) for x in args.large_thickness.split(",") if x.strip()})
    if not thicknesses or min(thicknesses) <= 0 or args.large_repeat < 1:
        raise SystemExit("--large-thickness needs values > 0 mm and --large-repeat >= 1")
    exe = exe or [sys.executable, "-m", "gpuslice.cli"]
    rows = bench_large(exe, names, thicknesses, args.large_dir, args.large_repeat, log)
    if not rows:
        log("nothing was benchmarked")
        return 0
    print(report_large(rows, env, args.large_repeat))
    if args.json:
        args.json.write_text(json.dumps({"environment": env, "large": rows}, indent=1))
        log(f"wrote {args.json}")
    return 0
