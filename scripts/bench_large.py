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

``--large-scaling STEM`` also runs ``nefertiti_loop2`` at :data:`SCALING_THICKNESS` (0.1 M to 30 M segments: one mesh,
so only the segments change), without the ``--report`` run, and plots time against segment count
(``STEM.png``, ``STEM.svg``): the whole process and the stages that grow with the segments (crossings, chaining,
nesting, write; the others depend on the facets), log-log with a slope-1 line; those stages' nanoseconds per segment
(flat where the time is linear); and peak RSS. The other rows of the same run are drawn as points. It prints a
least-squares line ``whole = a + b * segments`` over the series, its largest relative residual, and the log-log
slope of the segment stages (1: linear).
"""

from __future__ import annotations

import itertools
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
#: the stages whose work grows with the segments (the others: with the facets, or fixed)
SEGMENT_STAGES = ("crossings", "chaining", "nesting", "write")
#: ``--large-scaling``: nefertiti_loop2 (120 mm) at these thicknesses (mm): about 0.1, 0.3, 1, 3, 10 and 30 M segments
SCALING_MESH = "nefertiti_loop2"
SCALING_THICKNESS = (2.0, 0.67, 0.2, 0.067, 0.02, 0.0067)


def add_arguments(ap) -> None:
    """The ``--large`` options of ``bench_contours.py``."""
    ap.add_argument("--large", action="store_true",
                    help="only the big-mesh benchmark (whole process, peak RSS, stages); see scripts/bench_large.py")
    ap.add_argument("--large-dir", type=Path, default=LARGE_DIR, help="the meshes of scripts/make_large.py")
    ap.add_argument("--large-meshes", default=DEFAULT_LARGE,
                    help=f"comma-separated subset of {', '.join(LARGE_MESHES)}")
    ap.add_argument("--large-thickness", default="0.02,0.05", help="layer thicknesses, mm, comma-separated")
    ap.add_argument("--large-repeat", type=int, default=1, help="timed runs per mesh and thickness (median)")
    ap.add_argument("--large-scaling", type=Path, default=None, metavar="STEM",
                    help=f"also {SCALING_MESH} from 0.1 M to 30 M segments; plot time against segments to "
                         "STEM.png and STEM.svg")


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
                log, report: bool = True) -> list[dict]:
    """One record per (mesh, thickness): wall times, peak RSS, stages and counts (``report``: and the timings of
    one more run with ``--report``)."""
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
                timings = {}
                if report:
                    run_measured([*cmd, "-q", "--report", str(rep)])
                    timings = json.loads(rep.read_text()).get("timings_s", {})
                rows.append({
                    **{k: runs[-1]["counts"].get(k) for k in ("facets", "layers", "segments", "loops", "points")},
                    "mesh": name, "thickness": t, "npz_bytes": npz.stat().st_size, "command": cmd,
                    "wall_s": walls, "median_s": statistics.median(walls), "peak_rss_bytes": rss,
                    "peak_rss_max_mib": max(rss) / 2**20,
                    "stages_s": {k: statistics.median(r["stages"].get(k, 0.0) for r in runs) for k in STAGES},
                    "report_timings_s": timings,
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
        cusp = r["report_timings_s"].get("cusp")
        cells.append(f"{1000 * cusp:.0f}" if cusp is not None else "–")
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
    series = []
    if args.large_scaling is not None:
        series = bench_large(exe, [SCALING_MESH], list(SCALING_THICKNESS), args.large_dir, args.large_repeat, log,
                             report=False)
    if not rows and not series:
        log("nothing was benchmarked")
        return 0
    if rows:
        print(report_large(rows, env, args.large_repeat))
    if series:
        fit = scaling_fit(series)
        print(f"\n{SCALING_MESH} from {series[0]['segments']:,} to {series[-1]['segments']:,} segments "
              f"(median of {args.large_repeat}): whole = {fit['a_s']:.3f} s + {fit['b_ns']:.1f} ns x segments "
              f"(largest residual {100 * fit['residual']:.1f} % of a run's time); the segment stages "
              f"({', '.join(SEGMENT_STAGES)}) grow as segments^{fit['slope']:.2f}, "
              f"{fit['ns_min']:.0f}-{fit['ns_max']:.0f} ns a segment")
        print(report_large(series, env, args.large_repeat))
        for path in plot_scaling(series, rows, args.large_scaling, env):
            log(f"wrote {path}")
    if args.json:
        args.json.write_text(json.dumps({"environment": env, "large": rows, "scaling": series}, indent=1))
        log(f"wrote {args.json}")
    return 0


def _segment_stages(row: dict) -> float:
    return sum(row["stages_s"].get(k, 0.0) for k in SEGMENT_STAGES)


def scaling_fit(series: list[dict]) -> dict:
    """The line ``whole = a + b * segments`` (least squares; ``b`` in ns a segment), its largest residual as a share
    of that run's time, the log-log slope of the segment stages' time, and their ns a segment (min, max)."""
    import numpy as np

    seg = np.array([r["segments"] for r in series], np.float64)
    wall = np.array([r["median_s"] for r in series])
    b, a = np.polyfit(seg, wall, 1)
    residual = float(np.max(np.abs(wall - (a + b * seg)) / wall))
    part = np.array([_segment_stages(r) for r in series])
    slope = float(np.polyfit(np.log(seg), np.log(np.maximum(part, 1e-9)), 1)[0])
    ns = part / seg * 1e9
    return {"a_s": float(a), "b_ns": float(b * 1e9), "residual": residual, "slope": slope,
            "ns_min": float(ns.min()), "ns_max": float(ns.max())}


def plot_scaling(series: list[dict], others: list[dict], stem: Path, env: dict) -> list[Path]:
    """Time, ns a segment and peak RSS against segments (module docstring); ``STEM.png`` and ``STEM.svg``."""
    import numpy as np

    from gpuslice.bench.plots import _mpl, _save

    plt = _mpl()
    fig, (ax_t, ax_ns, ax_m) = plt.subplots(1, 3, figsize=(13, 4))
    seg = np.array([r["segments"] for r in series], np.float64)
    wall = np.array([r["median_s"] for r in series])
    part = np.array([_segment_stages(r) for r in series])
    label = f"{SCALING_MESH} ({series[0]['facets']:,} facets)"
    ax_t.loglog(seg, wall, "o-", color="tab:blue", label=f"{label}: whole process")
    ax_t.loglog(seg, part, "s-", color="tab:orange", label=f"{label}: {' + '.join(SEGMENT_STAGES)}")
    ax_t.loglog(seg, part[-1] * seg / seg[-1], "--", color="grey", lw=1, label="slope 1 (linear)")
    ax_ns.semilogx(seg, part / seg * 1e9, "s-", color="tab:orange", label=label)
    ax_m.loglog(seg, [r["peak_rss_max_mib"] for r in series], "o-", color="tab:blue", label=label)
    extra = [r for r in others if not (r["mesh"] == SCALING_MESH and r["thickness"] in SCALING_THICKNESS)]
    for r, marker in zip(extra, itertools.cycle("^vD<>pP*"), strict=False):
        name = f"{r['mesh']} ({r['facets']:,} facets) -t {r['thickness']:g}"
        ax_t.loglog(r["segments"], r["median_s"], marker, color="tab:green", label=name)
        ax_ns.semilogx(r["segments"], _segment_stages(r) / r["segments"] * 1e9, marker, color="tab:green", label=name)
        ax_m.loglog(r["segments"], r["peak_rss_max_mib"], marker, color="tab:green", label=name)
    ax_t.set(xlabel="segments", ylabel="seconds", title="gpuslice slice … -o x.npz")
    ax_ns.set(xlabel="segments", ylabel="ns a segment", title=" + ".join(SEGMENT_STAGES))
    ax_ns.set_ylim(bottom=0)
    ax_m.set(xlabel="segments", ylabel="MiB", title="peak RSS")
    for ax in (ax_t, ax_ns, ax_m):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6, loc="upper left" if ax is not ax_ns else "upper right")
    fig.suptitle(f"time against segment count; {env.get('machine', '')}", fontsize=9)
    fig.tight_layout()
    return _save(fig, stem)
