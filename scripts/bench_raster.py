"""Benchmark resin rasterisation (issue 3): ``gpuslice raster`` against PrusaSlicer's SL1 export, side by side.

For each mesh (nefertiti 80 mm, benchy 60 mm by default), scaled once with ``peers.write_scaled_stl`` so both
programs read the same file:

* whole process, wall time, median of ``--repeat`` runs, alternating the two programs:
  ``gpuslice raster SCALED.stl -t 0.05 --pixel 0.05 --resolution 3840x2400 -o OUT.sl1`` and
  :func:`prusa_command` (the issue's command plus ``--dont-arrange``, see :data:`PRUSA_EXTRA`);
* in-process stages: slicing; rasterising (layers/s) with the OpenCL pass (all layers) and the GL pass (a sample);
  PNG encoding (layers/s) with ISA-L and zlib at levels 1 and 6, one thread and the thread pool;
* equal work: layer counts, PNG size, per-layer IoU (thresholded at 128) and mean grey difference over covered
  pixels between the two archives on every ``--every``-th layer.

Usage: ``python scripts/bench_raster.py [--meshes nefertiti,benchy] [--repeat 3] [--json out.json]``.
Markdown goes to stdout, progress to stderr.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MESHES = {"nefertiti": ("nefertiti.stl", 80.0), "benchy": ("benchy.stl", 60.0), "cow": ("cow.stl", 80.0)}

#: Added to the issue's PrusaSlicer command: its CLI arranges objects (libnest2d) unless told not to, which moves a
#: single object ~0.02 mm off the --center point (0.39 px in x on cow); with --dont-arrange --center is exact.
#: Its SLA elephant-foot compensation is already 0 with these options (prusaslicer.ini says so), so no flag for it.
PRUSA_EXTRA = ["--dont-arrange"]


def prusa_command(stl: str | os.PathLike, out: str | os.PathLike, h: float = 0.05, nx: int = 3840, ny: int = 2400,
                  pixel: float = 0.05) -> list[str]:
    """The issue's ``prusa-slicer --export-sla`` command for a W x D mm display of nx x ny pixels."""
    exe = peers.find_peer("prusa-slicer") or "prusa-slicer"
    w, d = nx * pixel, ny * pixel
    f = lambda v: f"{v:g}"  # noqa: E731
    return [
        exe, "--export-sla", "--printer-technology", "SLA", "--layer-height", f(h), "--initial-layer-height", f(h),
        "--no-supports-enable", "--no-pad-enable", "--display-width", f(w), "--display-height", f(d),
        "--display-pixels-x", str(nx), "--display-pixels-y", str(ny), "--display-orientation", "landscape",
        "--no-display-mirror-x", "--no-display-mirror-y", "--bed-shape", f"0x0,{f(w)}x0,{f(w)}x{f(d)},0x{f(d)}",
        "--center", f"{f(w / 2)},{f(d / 2)}", "--slice-closing-radius", "0", "--gamma-correction", "1",
        *PRUSA_EXTRA, str(stl), "-o", str(out),
    ]


def gpuslice_command(stl, out, h: float = 0.05, nx: int = 3840, ny: int = 2400, pixel: float = 0.05) -> list[str]:
    exe = Path(sys.executable).parent / "gpuslice"
    return [str(exe if exe.exists() else "gpuslice"), "raster", str(stl), "-t", f"{h:g}", "--pixel", f"{pixel:g}",
            "--resolution", f"{nx}x{ny}", "-o", str(out), "-q", "--no-progress"]


def sl1_layers(path) -> tuple[zipfile.ZipFile, list[str]]:
    z = zipfile.ZipFile(path)
    return z, sorted(n for n in z.namelist() if n.endswith(".png") and "/" not in n)


def compare_sl1(ours, theirs, every: int = 1) -> dict:
    """Per-layer agreement of two SL1 archives (layer i with layer i): IoU of the masks thresholded at 128 and
    mean |grey difference| over covered pixels (grey > 0 in either), on every ``every``-th common layer."""
    from PIL import Image

    za, na = sl1_layers(ours)
    zb, nb = sl1_layers(theirs)
    ious, diffs, sizes = [], [], set()
    for i in range(0, min(len(na), len(nb)), every):
        a = np.asarray(Image.open(io.BytesIO(za.read(na[i]))))
        b = np.asarray(Image.open(io.BytesIO(zb.read(nb[i]))))
        sizes.add((a.shape, b.shape))
        if a.shape != b.shape:
            continue
        ta, tb = a >= 128, b >= 128
        union = np.count_nonzero(ta | tb)
        ious.append(np.count_nonzero(ta & tb) / union if union else 1.0)
        cov = (a > 0) | (b > 0)
        diffs.append(float(np.abs(a.astype(np.int16) - b)[cov].mean()) if cov.any() else 0.0)
    return {"layers_ours": len(na), "layers_theirs": len(nb), "sizes": sorted(sizes), "iou": ious,
            "grey_diff": diffs, "compared": len(ious)}


def _timed(cmd: list[str]) -> float:
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def in_process(stl: Path, gl_sample: int = 24) -> dict:
    """Stage timings (s) and rates (layers/s) inside one process, after a warm-up."""
    from gpuslice import load_mesh, slice_mesh
    from gpuslice.device import get_device
    from gpuslice.raster import RasterSpec, iter_tiles
    from gpuslice.raster.png import PngEncoder, encode_all

    dev = get_device()
    mesh = load_mesh(stl, device=dev)
    slice_mesh(mesh, thickness=0.05)
    t = time.perf_counter()
    res = slice_mesh(mesh, thickness=0.05)
    out = {"slice_s": time.perf_counter() - t, "layers": res.n_layers}
    spec = RasterSpec()
    b = mesh.bounds
    bounds = (b[0, 0], b[0, 1], b[1, 0], b[1, 1])
    list(iter_tiles(res, spec, backend="opencl", device=dev, bounds=bounds, layers=[0]))
    samples = []
    for _ in range(3):
        t = time.perf_counter()
        tiles = list(iter_tiles(res, spec, backend="opencl", device=dev, bounds=bounds))
        samples.append(time.perf_counter() - t)
    out["raster_opencl_layers_per_s"] = res.n_layers / statistics.median(samples)
    out["tile_mpixels_per_layer"] = float(np.mean([t.data.size for t in tiles]) / 1e6)
    try:
        from gpuslice.raster.gl import gl_info

        info = gl_info()
        if info is not None:
            sel = np.linspace(0, res.n_layers - 1, gl_sample).astype(int)
            list(iter_tiles(res, spec, backend="gl", bounds=bounds, layers=sel[:1]))
            t = time.perf_counter()
            list(iter_tiles(res, spec, backend="gl", bounds=bounds, layers=sel))
            out["raster_gl_layers_per_s"] = len(sel) / (time.perf_counter() - t)
            out["gl_renderer"] = info["renderer"]
    except Exception as exc:  # pragma: no cover
        out["gl_error"] = str(exc)
    for deflater, level in (("isal", 1), ("zlib", 1), ("zlib", 6)):
        try:
            enc = PngEncoder(spec.nx, spec.ny, level, deflater)
        except Exception:
            continue
        sub = tiles[:: max(1, len(tiles) // 200)]
        t = time.perf_counter()
        nbytes = sum(len(enc.encode(x)) for x in sub)
        one = len(sub) / (time.perf_counter() - t)
        t = time.perf_counter()
        encode_all(sub, enc, lambda k, d: None, None)
        pool = len(sub) / (time.perf_counter() - t)
        out[f"encode_{deflater}{level}"] = {"layers_per_s_1thread": one, "layers_per_s_pool": pool,
                                            "kb_per_layer": nbytes / len(sub) / 1e3}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", default="nefertiti,benchy")
    ap.add_argument("--meshes-dir", default=str(REPO.parent / "shared" / "meshes"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--every", type=int, default=10, help="compare every N-th layer with PrusaSlicer's")
    ap.add_argument("--skip-peers", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    ps = None if args.skip_peers else peers.find_peer("prusa-slicer")
    if ps is None and not args.skip_peers:
        print("prusa-slicer not found: gpuslice only", file=sys.stderr)
    results = {"machine": {"nproc": os.cpu_count(), "cpu": platform.processor() or platform.machine(),
                           "python": platform.python_version(), "load_before": os.getloadavg()}}
    tmp = Path(tempfile.mkdtemp(prefix="bench_raster_"))
    try:
        for name in args.meshes.split(","):
            file, fit = MESHES[name]
            src = Path(args.meshes_dir) / file
            if not src.is_file():
                print(f"{src}: not found, skipped", file=sys.stderr)
                continue
            stl = tmp / f"{name}.stl"
            peers.write_scaled_stl(src, stl, fit=fit)
            ours, theirs = tmp / f"{name}_gpuslice.sl1", tmp / f"{name}_prusa.sl1"
            r: dict = {"fit_mm": fit}
            _timed(gpuslice_command(stl, ours))  # warm-up (kernel cache)
            g, p = [], []
            for k in range(args.repeat):
                print(f"{name}: run {k + 1}/{args.repeat}", file=sys.stderr)
                g.append(_timed(gpuslice_command(stl, ours)))
                if ps:
                    p.append(_timed(prusa_command(stl, theirs)))
            r["gpuslice_s"], r["prusa_s"] = g, p
            r["stages"] = in_process(stl)
            if ps:
                r["compare"] = compare_sl1(ours, theirs, args.every)
            results[name] = r
    finally:
        results["machine"]["load_after"] = os.getloadavg()
        shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))
    print(_markdown(results))
    return 0


def _markdown(res: dict) -> str:
    names = [k for k in res if k != "machine"]
    med = statistics.median
    rows = ["| | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)]

    def row(label, fn):
        vals = []
        for n in names:
            try:
                vals.append(fn(res[n]))
            except (KeyError, ValueError, ZeroDivisionError, statistics.StatisticsError):
                vals.append("–")
        rows.append(f"| {label} | " + " | ".join(vals) + " |")

    row("layers (gpuslice / PrusaSlicer)", lambda r: f"{r['stages']['layers']} / {r['compare']['layers_theirs']}")
    row("**gpuslice raster, wall s (median)**", lambda r: f"**{med(r['gpuslice_s']):.2f}**")
    row("PrusaSlicer --export-sla, wall s (median)", lambda r: f"{med(r['prusa_s']):.2f}")
    row("**ratio gpuslice / PrusaSlicer**", lambda r: f"**{med(r['gpuslice_s']) / med(r['prusa_s']):.2f}**")
    row("runs gpuslice (s)", lambda r: " ".join(f"{v:.2f}" for v in r["gpuslice_s"]))
    row("runs PrusaSlicer (s)", lambda r: " ".join(f"{v:.2f}" for v in r["prusa_s"]))
    row("slice_mesh in-process (s)", lambda r: f"{r['stages']['slice_s']:.3f}")
    row("bbox tile per layer (Mpx)", lambda r: f"{r['stages']['tile_mpixels_per_layer']:.2f}")
    row("rasterise, OpenCL (layers/s)", lambda r: f"{r['stages']['raster_opencl_layers_per_s']:.0f}")
    row("rasterise, GL llvmpipe (layers/s)", lambda r: f"{r['stages']['raster_gl_layers_per_s']:.1f}")
    for key in ("isal1", "zlib1", "zlib6"):
        row(f"encode {key}, 1 thread / pool (layers/s)",
            lambda r, key=key: f"{r['stages']['encode_' + key]['layers_per_s_1thread']:.0f} / "
            f"{r['stages']['encode_' + key]['layers_per_s_pool']:.0f}")
        row(f"encode {key}, kB per layer", lambda r, key=key: f"{r['stages']['encode_' + key]['kb_per_layer']:.1f}")
    row("IoU ≥128 min / median", lambda r: f"{min(r['compare']['iou']):.4f} / {med(r['compare']['iou']):.4f}")
    row("grey diff over covered px, max / median",
        lambda r: f"{max(r['compare']['grey_diff']):.2f} / {med(r['compare']['grey_diff']):.2f}")
    row("PNG sizes", lambda r: " ".join(f"{a[1]}x{a[0]}" for a, _ in r["compare"]["sizes"]))
    m = res["machine"]
    return "\n".join(rows) + f"\n\nmachine: {m['nproc']} CPUs, Python {m['python']}, load average before " \
        f"{m['load_before'][0]:.1f}, after {m['load_after'][0]:.1f}"


if __name__ == "__main__":
    sys.exit(main())
