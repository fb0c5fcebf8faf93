"""Benchmark the resin jobs of issues 18 and 19: a model to a 12K/16K printer archive, every format, whole process.

Jobs (``--jobs``):

* ``armadillo``: the shared ``armadillo.stl`` after one ``trimesh.remesh.subdivide_loop`` (345,928 facets), stood
  upright ((x, y, z) -> (x, -z, y)), ``--fit 95`` (1,900 layers at 0.05 mm): mslicer's published job, on our mesh;
* ``nefertiti``: the shared ``nefertiti.stl`` at ``--fit 80``, 0.05 mm (1,600 layers).

Displays (``--displays``): ``12k`` = 11520x5120 at 0.019 mm (the issue's job; a Saturn 3 Ultra's panel) and ``16k``
= 15120x6230 at 0.014 x 0.019 mm. Outputs (``--formats``): goo, ctb, pwmx, pwsz, cxdlp, cxdlpv4, sl1, png (a PNG
stack), at gamma 0 and 1 (``--gammas``), plus ``--z-samples 4`` at gamma 1 for the first format (``--z4``).

Every command is ``gpuslice raster STL --fit F -t 0.05 --resolution R --pixel P [--pixel-y Q] --gamma G -o OUT
--report R.json -q --no-progress`` (for ``pwmx``, ``pwsz``, ``cxdlp`` and ``cxdlpv4``: ``--printer P.json``, a preset
file of that display reading that format, as gpuslice refuses a Photon Mono X file of another display and a .cxdlp
without a Halot model code) under ``/usr/bin/time -v`` (wall time and peak RSS of the whole process), run ``--repeat``
times, the commands interleaved; the medians are printed with the stages of the median run's report (load, topology,
crossings, chaining, nesting, raster) and layers/s of the whole job. ``--prusa`` adds PrusaSlicer's SL1 export of
the same STL at the same display (once: it takes minutes) as the reference of the same run.

Usage: ``python scripts/bench_resin.py [--jobs armadillo,nefertiti] [--displays 12k,16k]
[--formats goo,ctb,pwmx,sl1,png] [--gammas 0,1] [--repeat 3] [--prusa] [--json out.json] [--out-dir DIR]``.
Markdown on stdout, progress on stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MESHES = REPO.parent / "shared" / "meshes"
DISPLAYS = {"12k": ((11520, 5120), 0.019, None), "16k": ((15120, 6230), 0.014, 0.019)}
SUFFIX = {"goo": ".goo", "ctb": ".ctb", "pwmx": ".pwmx", "sl1": ".sl1", "png": "/", "nanodlp": ".nanodlp",
          "pwsz": ".pwsz", "cxdlp": ".cxdlp", "cxdlpv4": ".cxdlpv4"}
#: a preset's settings for the formats whose units the defaults do not fit (.cxdlp: whole mm/s, no transition ramp)
PRESET_SETTINGS = {"cxdlp": {"transition_layers": 0, "wait_before_cure": 1.0, "lift_height": 6.0, "lift_speed": 60.0,
                             "bottom_lift_height": 6.0, "bottom_lift_speed": 60.0, "retract_speed": 60.0}}
FIT = {"armadillo": 95.0, "nefertiti": 80.0}
STAGES = ("device", "load", "topology", "crossings", "chaining", "nesting", "z_samples", "raster")


def job_stl(name: str, cache: Path) -> Path:
    """The job's STL (made once, deterministically, into ``cache``)."""
    if name == "nefertiti":
        return MESHES / "nefertiti.stl"
    out = cache / "armadillo_loop1_upright.stl"
    if not out.exists():
        import numpy as np
        import trimesh

        m = trimesh.load(MESHES / "armadillo.stl", force="mesh")
        v, f = trimesh.remesh.subdivide_loop(m.vertices, m.faces, iterations=1)
        v = np.column_stack([v[:, 0], -v[:, 2], v[:, 1]])
        tmp = out.with_suffix(".tmp.stl")
        trimesh.Trimesh(v, f, process=False).export(tmp)
        os.replace(tmp, out)
    return out


def command(stl: Path, fit: float, display: str, gamma: float, out: str, report: Path, z: int = 1) -> list[str]:
    """The gpuslice command of one run. A Photon Workshop suffix names a machine whose display the file must be
    (gpuslice refuses another), and none has these displays: such an output gets a preset file of its own, a
    printer with this display reading that format (as a user's own preset would), beside ``report``."""
    (nx, ny), px, py = DISPLAYS[display]
    suffix = Path(out).suffix.lstrip(".")
    cmd = [sys.executable, "-m", "gpuslice.cli", "raster", str(stl), "--fit", f"{fit:g}", "-t", "0.05",
           "--gamma", f"{gamma:g}", "-o", out, "--report", str(report), "-q", "--no-progress"]
    if suffix not in ("", "goo", "ctb", "sl1", "nanodlp", "png"):  # a Photon Workshop machine's suffix
        preset = report.with_name(f"bench-{display}-{suffix}.json")
        preset.write_text(json.dumps({"name": f"bench-{display}", "resolution": [nx, ny], "pixel": px,
                                      **({"pixel_y": py} if py is not None else {}), "build_height": 200,
                                      "formats": [suffix], "settings": PRESET_SETTINGS.get(suffix, {}),
                                      # (a .cxdlp or .cxdlpv4 carries a Halot model code, CL-…)
                                      "machine": f"CL-{display}" if "cxdlp" in suffix else f"bench {display}"}))
        return [*cmd, "--printer", str(preset), *(["--z-samples", str(z)] if z > 1 else [])]
    cmd += ["--resolution", f"{nx}x{ny}", "--pixel", f"{px:g}"]
    if py is not None:
        cmd += ["--pixel-y", f"{py:g}"]
    if z > 1:
        cmd += ["--z-samples", str(z)]
    return cmd


def timed(cmd: list[str], timeout: float | None = None) -> tuple[float, float]:
    """(wall s, peak RSS MB) of ``cmd`` as ``/usr/bin/time -v`` measures the whole process."""
    p = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, timeout=timeout)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {p.stderr.strip().splitlines()[-1:]}")
    wall = re.search(r"Elapsed \(wall clock\) time .*: (?:(\d+):)?(\d+):([\d.]+)", p.stderr)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
    h, m, s = (float(g) if g else 0.0 for g in wall.groups())
    return h * 3600 + m * 60 + s, int(rss.group(1)) / 1024


def prusa_command(stl: Path, out: Path, display: str) -> list[str]:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_raster

    (nx, ny), px, py = DISPLAYS[display]
    cmd = bench_raster.prusa_command(stl, out, 0.05, nx, ny, px)
    if py is not None:  # PrusaSlicer's display is width x height mm over nx x ny pixels
        i = cmd.index("--display-height")
        cmd[i + 1] = f"{ny * py:g}"
    return cmd


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", default="armadillo,nefertiti")
    ap.add_argument("--displays", default="12k,16k")
    ap.add_argument("--formats", default="goo,ctb,pwmx,sl1,png")
    ap.add_argument("--gammas", default="0,1")
    ap.add_argument("--z4", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--prusa", action="store_true")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "gpuslice-bench"))
    ap.add_argument("--json", default=None)
    ap.add_argument("--out-dir", default=None, help="where the outputs are written (default: the temp directory); "
                    "/dev/shm keeps the file system's own cost out (BENCHMARKS: a PNG stack on ext4 without a journal)")
    a = ap.parse_args(argv)
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    runs = []  # (job, display, fmt, gamma, z)
    formats = a.formats.split(",")
    for job in a.jobs.split(","):
        for display in a.displays.split(","):
            for fmt in formats:
                for g in a.gammas.split(","):
                    runs.append((job, display, fmt, float(g), 1))
            if a.z4:
                runs.append((job, display, formats[0], 1.0, 4))
    work = Path(tempfile.mkdtemp(prefix="bench-resin-", dir=a.out_dir))
    results: dict[tuple, list] = {r: [] for r in runs}
    try:
        for rep in range(a.repeat):
            for r in runs:
                job, display, fmt, g, z = r
                out = work / f"out{SUFFIX[fmt]}" if fmt != "png" else work / "out"
                report = work / "r.json"
                cmd = command(job_stl(job, cache), FIT[job], display, g, str(out) + ("/" if fmt == "png" else ""),
                              report, z)
                wall, rss = timed(cmd)
                rep_json = json.loads(report.read_text())
                size = out.stat().st_size if out.is_file() else sum(p.stat().st_size for p in out.iterdir())
                results[r].append({"wall": wall, "rss": rss, "layers": rep_json["layers"], "bytes": size,
                                   "stages": {k: rep_json["timings_s"].get(k, 0.0) for k in STAGES}})
                shutil.rmtree(out) if out.is_dir() else out.unlink()
                print(f"[{rep + 1}/{a.repeat}] {job} {display} {fmt} gamma {g:g} z{z}: {wall:.2f} s, {rss:.0f} MB",
                      file=sys.stderr)
        prusa = {}
        if a.prusa:
            for job in a.jobs.split(","):
                for display in a.displays.split(","):
                    stl = job_stl(job, cache)
                    scaled = cache / f"{job}_{FIT[job]:g}mm.stl"
                    if not scaled.exists():  # PrusaSlicer reads the same placed mesh: scale it as --fit does
                        sys.path.insert(0, str(Path(__file__).resolve().parent))
                        import peers

                        peers.write_scaled_stl(stl, scaled, fit=FIT[job])
                    wall, rss = timed(prusa_command(scaled, work / "prusa.sl1", display), timeout=3600)
                    prusa[(job, display)] = {"wall": wall, "rss": rss}
                    print(f"PrusaSlicer {job} {display}: {wall:.1f} s, {rss:.0f} MB", file=sys.stderr)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    load = os.getloadavg()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, load {load[0]:.2f}; "
          f"repeat {a.repeat}, medians\n")
    print("| job | display | output | gamma | z | whole s | peak MB | layers/s | load | topo | cross | chain | nest "
          "| raster | MB |")
    print("|" + "---|" * 15)
    table = []
    for r, rows in results.items():
        job, display, fmt, g, z = r
        mid = sorted(rows, key=lambda x: x["wall"])[len(rows) // 2]
        wall = statistics.median(x["wall"] for x in rows)
        rss = statistics.median(x["rss"] for x in rows)
        st = mid["stages"]
        print(f"| {job} | {display} | {fmt} | {g:g} | {z} | {wall:.2f} | {rss:.0f} | {mid['layers'] / wall:.0f} | "
              f"{st['load']:.2f} | {st['topology']:.2f} | {st['crossings']:.2f} | {st['chaining']:.2f} | "
              f"{st['nesting']:.2f} | {st['raster'] + st['z_samples']:.2f} | {mid['bytes'] / 1e6:.1f} |")
        table.append({"job": job, "display": display, "format": fmt, "gamma": g, "z_samples": z, "wall_s": wall,
                      "peak_mb": rss, "runs": rows})
    for (job, display), p in prusa.items():
        print(f"| {job} | {display} | PrusaSlicer sl1 | 1 | 1 | {p['wall']:.1f} | {p['rss']:.0f} | | | | | | | | |")
    if a.json:
        Path(a.json).write_text(json.dumps({"results": table, "prusa": [
            {"job": j, "display": d, **p} for (j, d), p in prusa.items()], "load": load}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
