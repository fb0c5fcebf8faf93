"""Benchmark of slicing triangle soups: meshes whose facets share no vertex, as an exporter that writes each facet's
corners with its own rounding produces.  gpuslice, PrusaSlicer and trimesh on the same soup, against gpuslice on the
clean (welded) mesh.

Usage::

    python scripts/bench_soup.py                                  # benchy, stanford_bunny at 40 mm, 0.05 mm layers
    python scripts/bench_soup.py --repeat 5 --jitter 1e-3 --json bench_soup.json
    python scripts/bench_soup.py --meshes benchy --fit 60 --thickness 0.1 --out-dir /tmp/soups   # keep the STLs

Soups (deterministic; written under ``--out-dir``, default a temporary folder removed at the end): each mesh of
``--meshes`` is read from ``../shared/meshes/<name>.stl`` (missing ones are skipped) with
``gpuslice.load_mesh(path, fit=--fit)``; every corner of every facet gets its own uniform jitter in
[-J, J] mm (``--jitter``, ``numpy.random.default_rng(1)`` per mesh), then all is shifted so the soup's lowest corner
is at (1, 1, 1) mm (PrusaSlicer wants positive coordinates) and written as a float32 binary STL.  The clean mesh,
with the same shift and no jitter, is the reference.

Measured (wall seconds, ``time.perf_counter``; median of ``--repeat`` runs):

* ``python -m gpuslice.cli slice FILE -t T -o x.npz -q``, whole process, on the soup and on the clean mesh (one
  untimed run first, so that the OpenCL kernels are built and cached), and on the soup with ``--join-edges 0``
  (its open edges not joined on the mesh: chaining's gap closing alone, as before the twenty-sixth session);
* ``prusa-slicer --export-sla ...`` (if on PATH), whole process, soup and clean; its time includes rasterising and
  zipping the SL1 layers, so it is an upper bound of its slicing; past ``--peer-timeout`` s: "> timeout";
* trimesh, in process (``--skip-trimesh`` leaves it out): ``trimesh.load(soup, process=False)``,
  ``section_multiplane`` and the areas of ``polygons_full`` (trimesh builds polygons lazily; without them it has not
  sliced to polygons).

Planes: z = z0 + (k + 0.5) T, k = 0 .. floor(height / T) - 1, z0 the soup's lowest z.  Correctness, per layer:
gpuslice's Python API (``slice_mesh(load_mesh(path), z=...)``) on the clean mesh at the same planes is the
reference; for the soup through gpuslice and through trimesh (sum of ``polygons_full`` areas, 0 where None), the
median and 99th percentile of |area - clean| / clean over layers with clean area > 1 mm², and the layers off by
more than 1 %.  A Markdown table goes to stdout, progress to stderr; ``--json FILE`` keeps every sample.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MESHES_DIR = REPO.parent / "shared" / "meshes"
STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (9,)), ("attr", "<u2")])  # 50 bytes per facet
PRUSA_FLAGS = ["--export-sla", "--printer-technology", "SLA", "--no-supports-enable", "--no-pad-enable",
               "--display-width", "120", "--display-height", "68", "--display-pixels-x", "2560",
               "--display-pixels-y", "1440", "--display-orientation", "landscape", "--no-display-mirror-x",
               "--no-display-mirror-y", "--bed-shape", "0x0,120x0,120x68,0x68", "--center", "60,34",
               "--slice-closing-radius", "0"]


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def write_stl(path: Path, tri: np.ndarray) -> None:
    """Binary STL of (n, 3, 3) triangles: zero header, zero normals, zero attributes."""
    rec = np.zeros(len(tri), STL_DTYPE)
    rec["v"] = tri.reshape(-1, 9).astype("<f4")
    with open(path, "wb") as f:
        f.write(bytes(80))
        f.write(np.uint32(len(tri)).tobytes())
        f.write(rec.tobytes())


def build(src: Path, fit: float, jitter: float, out: Path) -> tuple[Path, Path, np.ndarray]:
    """Write ``<name>_soup.stl`` and ``<name>_clean.stl``; return their paths and the soup's float32 triangles."""
    import gpuslice

    mesh = gpuslice.load_mesh(src, fit=fit)
    tri = np.asarray(mesh.vertices, np.float32)[np.asarray(mesh.faces)].astype(np.float64)
    soup = tri + np.random.default_rng(1).uniform(-jitter, jitter, size=tri.shape)
    shift = 1.0 - soup.reshape(-1, 3).min(axis=0)
    soup32, clean32 = (soup + shift).astype(np.float32), (tri + shift).astype(np.float32)
    paths = out / f"{src.stem}_soup.stl", out / f"{src.stem}_clean.stl"
    write_stl(paths[0], soup32)
    write_stl(paths[1], clean32)
    return paths[0], paths[1], soup32


def timed(cmd: list[str], timeout: float | None = None) -> float | None:
    """Whole-process wall seconds of ``cmd`` (None past ``timeout``); a failure is an error."""
    t = time.perf_counter()
    try:
        subprocess.run(cmd, check=True, timeout=timeout, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    except subprocess.TimeoutExpired:
        return None
    except subprocess.CalledProcessError as e:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{e.stderr.decode(errors='replace')[-2000:]}") from e
    return time.perf_counter() - t


def polygons(section: object) -> list:
    """A section's ``polygons_full``; without the optional ``rtree`` (which trimesh needs to nest two or more
    loops) the even-odd nesting of its closed loops' exteriors, with shapely (the same polygons)."""
    import shapely

    if section is None:
        return []
    try:
        return list(section.polygons_full)  # type: ignore[attr-defined]
    except ImportError:
        loops = [shapely.Polygon(p.exterior) for p in section.polygons_closed if p is not None]  # type: ignore
        region = loops[0] if loops else shapely.Polygon()
        for q in loops[1:]:
            region = shapely.symmetric_difference(region, q)
        return list(getattr(region, "geoms", [region])) if not region.is_empty else []


def trimesh_areas(path: Path, z0: float, heights: np.ndarray) -> tuple[float, np.ndarray, int]:
    """trimesh's load + section_multiplane + polygon areas: (seconds, per-layer area mm², layers None or empty)."""
    import trimesh

    t = time.perf_counter()
    mesh = trimesh.load(str(path), process=False)
    paths = mesh.section_multiplane(plane_origin=[0.0, 0.0, z0], plane_normal=[0.0, 0.0, 1.0], heights=heights)
    polys = [polygons(s) for s in paths]
    areas = np.array([sum(q.area for q in ps) for ps in polys], dtype=np.float64)
    return time.perf_counter() - t, areas, sum(1 for ps in polys if not ps)


def errors(areas: np.ndarray, ref: np.ndarray, z: np.ndarray) -> dict:
    """Relative area error over the layers whose reference area is > 1 mm², and the worst three layers."""
    keep = ref > 1.0
    rel = np.abs(areas[keep] - ref[keep]) / ref[keep]
    worst = np.argsort(rel)[::-1][:3]
    zk, ak, rk = z[keep], areas[keep], ref[keep]
    return {"median": float(np.median(rel)), "p99": float(np.percentile(rel, 99)), "over_1pct": int((rel > 0.01).sum()),
            "layers": int(keep.sum()),
            "worst": [{"z": float(zk[i]), "area": float(ak[i]), "clean": float(rk[i]), "rel": float(rel[i])}
                      for i in worst]}


def med(xs: list[float | None]) -> float | None:
    return None if not xs or any(x is None for x in xs) else statistics.median(xs)  # type: ignore[type-var]


def bench(name: str, src: Path, a: argparse.Namespace, out: Path) -> dict:
    import gpuslice

    soup, clean, tri = build(src, a.fit, a.jitter, out)
    z0, top = float(tri[..., 2].min()), float(tri[..., 2].max())
    n = math.floor((top - z0) / a.thickness)
    heights = (np.arange(n) + 0.5) * a.thickness
    clean_z0 = float(np.fromfile(clean, STL_DTYPE, offset=84)["v"][:, 2::3].min())
    r = {"mesh": name, "facets": len(tri), "layers": n, "soup": str(soup), "clean": str(clean)}
    log(f"{name}: {len(tri)} facets, {n} layers of {a.thickness} mm, height {top - z0:.2f} mm")

    g = [sys.executable, "-m", "gpuslice.cli", "slice"]
    for kind, path, extra in (("clean", clean, []), ("soup", soup, []), ("soup_unjoined", soup, ["--join-edges", "0"])):
        npz = out / f"{name}_{kind}.npz"
        r[f"gpuslice_{kind}_s"] = [timed([*g, str(path), "-t", str(a.thickness), "-o", str(npz), "-q", *extra])
                                   for _ in range(a.repeat)]
        log(f"  gpuslice {kind}: {r[f'gpuslice_{kind}_s']}")
    prusa = shutil.which("prusa-slicer")
    for kind, path in (("soup", soup), ("clean", clean)):
        runs: list[float | None] = []
        for _ in range(a.repeat if prusa else 0):
            cmd = [prusa, *PRUSA_FLAGS, "--layer-height", str(a.thickness), "--initial-layer-height",
                   str(a.thickness), "-o", str(out / f"{name}_{kind}.sl1"), str(path)]
            runs.append(timed(cmd, a.peer_timeout))
            if runs[-1] is None:
                break  # timed out: once is enough
        r[f"prusa_{kind}_s"] = runs
        log(f"  PrusaSlicer {kind}: {runs if prusa else 'not on PATH'}")

    tm = [trimesh_areas(soup, z0, heights) for _ in range(0 if a.skip_trimesh else a.repeat)]
    r["trimesh_soup_s"], r["trimesh_empty_layers"] = [t[0] for t in tm], tm[0][2] if tm else None
    log(f"  trimesh soup: {r['trimesh_soup_s']}, {r['trimesh_empty_layers']} layers None or without polygons")

    ref = gpuslice.slice_mesh(gpuslice.load_mesh(clean), z=heights + (z0 - clean_z0))
    got = gpuslice.slice_mesh(gpuslice.load_mesh(soup), z=heights)
    unjoined = gpuslice.slice_mesh(gpuslice.load_mesh(soup), z=heights, join_edges=0)
    assert ref.n_layers == got.n_layers == unjoined.n_layers == n, (ref.n_layers, got.n_layers, n)
    r["joined_edges"] = got.meta["repairs"].get("joined_edges", 0)
    r["err_gpuslice"] = errors(np.asarray(got.area), np.asarray(ref.area), z0 + heights)
    r["err_gpuslice_unjoined"] = errors(np.asarray(unjoined.area), np.asarray(ref.area), z0 + heights)
    r["err_trimesh"] = errors(tm[0][1], np.asarray(ref.area), z0 + heights) if tm else None
    return r


def table(rows: list[dict], prusa: bool) -> str:
    def s(xs: list[float | None]) -> str:
        if not xs:
            return "n/a"
        m = med(xs)
        return "> timeout" if m is None else f"{m:.2f}"

    def e(d: dict | None) -> str:
        return "n/a" if d is None else f"{d['median']:.2e} / {d['p99']:.2e} / {d['over_1pct']}"

    head = ["mesh", "facets", "layers", "gpuslice clean s", "gpuslice soup s", "gpuslice soup, --join-edges 0 s",
            "PrusaSlicer soup s", "PrusaSlicer clean s", "trimesh soup s", "trimesh empty layers", "edges joined",
            "gpuslice soup err med / p99 / >1%", "the same, --join-edges 0", "trimesh soup err med / p99 / >1%"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["mesh"], str(r["facets"]), str(r["layers"]), s(r["gpuslice_clean_s"]), s(r["gpuslice_soup_s"]),
                 s(r["gpuslice_soup_unjoined_s"]), s(r["prusa_soup_s"]) if prusa else "n/a",
                 s(r["prusa_clean_s"]) if prusa else "n/a", s(r["trimesh_soup_s"]), str(r["trimesh_empty_layers"]),
                 str(r["joined_edges"]), e(r["err_gpuslice"]), e(r["err_gpuslice_unjoined"]), e(r["err_trimesh"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--meshes", default="benchy,stanford_bunny", help="names in ../shared/meshes (comma-separated)")
    ap.add_argument("--fit", type=float, default=40.0, help="longest side of each mesh, mm")
    ap.add_argument("--jitter", type=float, default=1e-4, help="largest move of each corner per axis, mm")
    ap.add_argument("--thickness", "-t", type=float, default=0.05, help="layer thickness, mm")
    ap.add_argument("--repeat", type=int, default=3, help="runs per timing (median reported)")
    ap.add_argument("--peer-timeout", type=float, default=120.0, help="PrusaSlicer's limit per run, s")
    ap.add_argument("--out-dir", type=Path, help="keep the STLs and outputs here (default: a temporary folder)")
    ap.add_argument("--json", type=Path, help="write every sample here")
    ap.add_argument("--skip-trimesh", action="store_true", help="leave trimesh out (it takes minutes on a soup)")
    a = ap.parse_args()

    load0 = os.getloadavg()
    tmp = None if a.out_dir else tempfile.mkdtemp(prefix="gpuslice-soup-")
    out = a.out_dir or Path(tmp)  # type: ignore[arg-type]
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        first = True
        for name in [m.strip() for m in a.meshes.split(",") if m.strip()]:
            src = MESHES_DIR / f"{name}.stl"
            if not src.exists():
                log(f"{name}: {src} not found, skipped")
                continue
            if first:  # build and cache the OpenCL kernels outside the timings
                timed([sys.executable, "-m", "gpuslice.cli", "slice", str(src), "--fit", str(a.fit), "-t", "1",
                       "-o", str(out / "warmup.npz"), "-q"])
                first = False
            rows.append(bench(name, src, a, out))
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    load1 = os.getloadavg()
    prusa = shutil.which("prusa-slicer") is not None

    print(f"Soups: fit {a.fit} mm, jitter ±{a.jitter} mm per corner and axis, layers {a.thickness} mm; wall s, "
          f"median of {a.repeat}; area error = |area - clean| / clean over layers with clean area > 1 mm².\n")
    print(table(rows, prusa))
    print("\nPrusaSlicer's time includes rasterising and zipping the SL1 layers: an upper bound of its slicing."
          if prusa else "\nprusa-slicer not on PATH.")
    for r in rows:
        for k in ("err_gpuslice", "err_gpuslice_unjoined", "err_trimesh"):
            if r[k] is None:
                continue
            w = "; ".join(f"z={x['z']:.3f}: {x['area']:.2f} vs {x['clean']:.2f} mm² ({x['rel']:.1%})"
                          for x in r[k]["worst"])
            print(f"- {r['mesh']}, worst layers {k[4:]}: {w}")
    print(f"\nLoad average (1/5/15 min) before: {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}; "
          f"after: {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    if a.json:
        a.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(a).items()}, "rows": rows,
                                      "loadavg": [load0, load1]}, indent=1))


if __name__ == "__main__":
    main()
