"""Build the big benchmark meshes of issue 14 deterministically from the public ones in ``../shared/meshes``.

Usage::

    python scripts/make_large.py [OUT_DIR] [--meshes-dir DIR] [--only nefertiti_loop2,benchy_plate12]
                                 [--size 120] [--spacing 70,40]

Writes binary STLs into ``OUT_DIR`` (default ``/tmp/gpuslice-large/``):

* ``nefertiti_loop2.stl``: ``nefertiti.stl`` welded by gpuslice's loader, scaled so its longest side is ``--size``
  mm (120: 6,000 layers at 0.02 mm), lowest point at z = 0, then 2 Loop subdivisions
  (``trimesh.remesh.subdivide_loop``): 99,938 -> 1,599,008 facets;
* ``nefertiti_loop3.stl``: the same after 3 subdivisions: 6,396,032 facets;
* ``benchy_plate12.stl``: 12 copies of ``benchy.stl`` (mm, as shipped: 60 x 31 x 48 mm; 225,146 facets once its 8
  degenerate ones are dropped) on a 4 x 3 grid whose copies are ``--spacing`` X,Y mm apart (70,40: gaps of about 10
  and 9 mm): 2,701,752 facets.

Each file is written atomically. ``OUT_DIR/make_large.json`` records, per file, its recipe (the source file's
SHA-256, the parameters, the trimesh and numpy versions) and the SHA-256 of the bytes written; a file whose
recipe is unchanged and whose bytes still hash to the recorded value is skipped without rebuilding. Prints one
line per file: name, facets, size, SHA-256 prefix, seconds, and whether it was built or skipped.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_MESHES_DIR = REPO.parent / "shared" / "meshes"
DEFAULT_OUT = Path("/tmp/gpuslice-large")
MANIFEST = "make_large.json"
RECIPE_VERSION = 1  # bump when the construction below changes


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file's bytes (read in 16 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 24), b""):
            h.update(block)
    return h.hexdigest()


def _welded(src: Path, fit: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64 mm, faces (F, 3) int64) of ``src`` as gpuslice loads it (welded, on the bed)."""
    from gpuslice import load_mesh

    mesh = load_mesh(src, fit=fit)
    return mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)


def nefertiti_loop(src: Path, size: float, iterations: int) -> np.ndarray:
    """(F, 3, 3) triangles: ``src`` scaled to ``size`` mm, then ``iterations`` Loop subdivisions."""
    import trimesh.remesh

    v, f = _welded(src, size)
    v, f = trimesh.remesh.subdivide_loop(v, f, iterations=iterations)
    v = v - [0.0, 0.0, v[:, 2].min()]  # smoothing pulls the lowest point up a little: back on the bed
    return v[f]


def benchy_plate(src: Path, spacing: tuple[float, float], nx: int = 4, ny: int = 3) -> np.ndarray:
    """(F, 3, 3) triangles: ``nx`` x ``ny`` copies of ``src`` whose origins are ``spacing`` (x, y) mm apart."""
    v, f = _welded(src, None)
    tri = v[f]
    ox, oy = np.meshgrid(np.arange(nx) * spacing[0], np.arange(ny) * spacing[1], indexing="xy")
    offsets = np.stack([ox.ravel(), oy.ravel(), np.zeros(nx * ny)], axis=1)
    return (tri[None, :, :, :] + offsets[:, None, None, :]).reshape(-1, 3, 3)


def targets(args) -> dict[str, tuple[str, dict, object]]:
    """name -> (source file name, recipe parameters, builder of the triangles)."""
    d = args.meshes_dir
    return {
        "nefertiti_loop2": ("nefertiti.stl", {"size_mm": args.size, "loop_iterations": 2},
                            lambda: nefertiti_loop(d / "nefertiti.stl", args.size, 2)),
        "nefertiti_loop3": ("nefertiti.stl", {"size_mm": args.size, "loop_iterations": 3},
                            lambda: nefertiti_loop(d / "nefertiti.stl", args.size, 3)),
        "benchy_plate12": ("benchy.stl", {"grid": [4, 3], "spacing_mm": list(args.spacing)},
                           lambda: benchy_plate(d / "benchy.stl", args.spacing)),
    }


def _spacing(text: str) -> tuple[float, float]:
    try:
        x, y = (float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--spacing: expected X,Y in mm, got '{text}'") from None
    if x <= 0 or y <= 0:
        raise argparse.ArgumentTypeError("--spacing: both values must be > 0 mm")
    return x, y


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", nargs="?", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    ap.add_argument("--meshes-dir", type=Path, default=DEFAULT_MESHES_DIR, help="holds nefertiti.stl, benchy.stl")
    ap.add_argument("--only", default="", help="comma-separated subset of the files (names without .stl)")
    ap.add_argument("--size", type=float, default=120.0, help="nefertiti's longest side, mm (default 120)")
    ap.add_argument("--spacing", type=_spacing, default=(70.0, 40.0), help="benchy plate: X,Y mm (default 70,40)")
    args = ap.parse_args(argv)
    if args.size <= 0:
        ap.error("--size must be > 0 mm")
    import trimesh

    todo = targets(args)
    wanted = [n.strip() for n in args.only.split(",") if n.strip()] or list(todo)
    unknown = [n for n in wanted if n not in todo]
    if unknown:
        ap.error(f"unknown file(s) {', '.join(unknown)} (choose from {', '.join(todo)})")
    args.out.mkdir(parents=True, exist_ok=True)
    manifest_path = args.out / MANIFEST
    manifest = json.loads(manifest_path.read_text()) if manifest_path.is_file() else {}
    from gpuslice.io.atomic import atomic_path
    from gpuslice.mesh.shapes import write_stl

    for name in wanted:
        source, params, build = todo[name]
        src = args.meshes_dir / source
        if not src.is_file():
            print(f"{name}: SKIP, {src} not found", file=sys.stderr)
            continue
        recipe = {"version": RECIPE_VERSION, "source": source, "source_sha256": sha256_file(src), **params,
                  "trimesh": trimesh.__version__, "numpy": np.__version__}
        path = args.out / f"{name}.stl"
        old = manifest.get(name, {})
        t = time.perf_counter()
        if path.is_file() and old.get("recipe") == recipe and sha256_file(path) == old.get("sha256"):
            state, facets = "skipped (same recipe, same content hash)", old["facets"]
        else:
            tri = build()
            facets = int(tri.shape[0])
            write_stl(tri, path, header=f"gpuslice make_large {name}".encode())
            del tri
            state = "built"
            manifest[name] = {"recipe": recipe, "sha256": sha256_file(path), "facets": facets,
                              "bytes": path.stat().st_size}
            with atomic_path(manifest_path) as tmp:
                tmp.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
        print(f"{name}.stl: {facets:,} facets, {path.stat().st_size / 2**20:.0f} MiB, "
              f"sha256 {manifest[name]['sha256'][:16]}, {time.perf_counter() - t:.1f} s, {state}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
