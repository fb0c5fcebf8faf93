"""In-process stages of ``slice_mesh`` on one OpenCL device against another (a GPU against PoCL), with manifold3d.

    python scripts/gpu_stages.py [--devices nvidia,pocl] [--repeat 7] [--large /tmp/gpuslice-large] [--json F]

Meshes: the contour benchmark's three at 0.05 mm (nefertiti 80 mm, benchy 60 mm, the icosphere s7 of radius 20 mm;
``scripts/bench_contours.py``), and with ``--large`` its ``nefertiti_loop2.stl`` (``scripts/make_large.py``) at 0.05
and 0.02 mm. Each mesh is loaded once (host weld); per device: one warm-up, then the median wall time of
``--repeat`` slices and the median of each stage of ``result.meta["timings_s"]``. manifold3d: its ``slice(z).area()``
loop over the same planes (median of 3). ``--profile``: a cProfile of one slice of the last mesh on the first
device, all batches on the calling thread (``max_segments_per_batch`` unbounded), top 25 by total time.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))
STAGES = ("device", "topology", "schedule", "crossings", "chaining", "nesting")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", default="nvidia,pocl")
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--meshes-dir", type=Path, default=ROOT.parent / "shared" / "meshes")
    ap.add_argument("--large", type=Path, default=None, help="folder holding nefertiti_loop2.stl")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    import peers
    import trimesh

    from gpuslice import load_mesh, slice_mesh
    from gpuslice.device import get_device

    devs = [get_device(d) for d in args.devices.split(",")]
    tmp = Path(tempfile.mkdtemp())
    ico = tmp / "icosphere7_r20.stl"
    trimesh.creation.icosphere(subdivisions=7, radius=20).export(ico, file_type="stl")
    cases = [("nefertiti", args.meshes_dir / "nefertiti.stl", 80.0, 0.05),
             ("benchy", args.meshes_dir / "benchy.stl", 60.0, 0.05), ("icosphere", ico, None, 0.05)]
    if args.large:
        cases += [("nefertiti_loop2", args.large / "nefertiti_loop2.stl", None, t) for t in (0.05, 0.02)]
    rows = []
    for name, path, fit, t in cases:
        mesh = load_mesh(path, fit=fit)
        row = {"mesh": name, "t": t, "facets": mesh.n_faces}
        for d in devs:
            r = slice_mesh(mesh, thickness=t, device=d)  # warm-up (kernels built, buffers sized)
            walls, st = [], {k: [] for k in STAGES}
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                r = slice_mesh(mesh, thickness=t, device=d)
                walls.append(time.perf_counter() - t0)
                for k in STAGES:
                    st[k].append(r.meta["timings_s"].get(k, 0.0))
            row[d.name] = {"wall_ms": 1e3 * statistics.median(walls),
                           **{k: 1e3 * statistics.median(v) for k, v in st.items()}}
            row["segments"] = r.meta["segments"]
            row["layers"] = r.meta["layers"]
        row["manifold3d_ms"] = "not timed above 500k facets (slow)"
        if mesh.n_faces <= 500_000:
            try:
                m = peers.manifold_from_arrays(mesh.vertices, mesh.faces, weld=False)
                ws = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    for z in r.z.tolist():
                        m.slice(z).area()
                    ws.append(time.perf_counter() - t0)
                row["manifold3d_ms"] = 1e3 * statistics.median(ws)
            except Exception as exc:  # a peer that cannot take the mesh
                row["manifold3d_ms"] = f"{type(exc).__name__}: {exc}"[:100]
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("| mesh | T | segments | device | wall ms | " + " | ".join(STAGES) + " | manifold3d ms |")
    print("|---|---|---|---|---|" + "---|" * len(STAGES) + "---|")
    for row in rows:
        for d in devs:
            s = row[d.name]
            m = row["manifold3d_ms"]
            print(f"| {row['mesh']} | {row['t']} | {row['segments']:,} | {d.name[:40]} | {s['wall_ms']:.1f} | "
                  + " | ".join(f"{s[k]:.1f}" for k in STAGES) + f" | {m if isinstance(m, str) else f'{m:.0f}'} |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    if args.profile:
        name, path, fit, t = cases[-1]
        mesh = load_mesh(path, fit=fit)
        slice_mesh(mesh, thickness=t, device=devs[0], max_segments_per_batch=1 << 30)
        prof = cProfile.Profile()
        prof.enable()
        r = slice_mesh(mesh, thickness=t, device=devs[0], max_segments_per_batch=1 << 30)
        prof.disable()
        print(f"profile: {name} at {t} mm on {devs[0].name}, one batch: {r.meta['timings_s']}")
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    return 0


if __name__ == "__main__":
    sys.exit(main())
