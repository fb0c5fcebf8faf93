"""Open meshes against Slic3r: gpuslice with its holes filled (the default), and without (``--no-fill-holes``), per
layer against Slic3r 1.3, whose loader fills holes (admesh's ``stl_fill_holes``).

Usage::

    python scripts/bench_holes.py                                   # the shared open meshes at 40 mm, 0.05 mm layers
    python scripts/bench_holes.py --meshes stanford_bunny --fit 60 -t 0.1 --repeat 5

For each mesh of ``--meshes`` (names in ``../shared/meshes/catalog.csv``): ``gpuslice.load_mesh(file, fit=--fit)``,
written as a binary STL moved by (100, 100, 0) mm (Slic3r wants positive coordinates) to a temporary folder; then

* per layer (the mid-layer planes, as Slic3r cuts): the area of ``slice_mesh(mesh, thickness=T)`` with and without
  ``fill_holes``, against Slic3r's (``slic3r --export-svg``, ``scripts/peers.py``): median and largest relative
  difference over the layers where Slic3r's area exceeds 1 mm², the layers more than 1 % apart, and gpuslice's empty
  layers;
* whole-process wall time (median of ``--repeat``) of ``python -m gpuslice.cli slice FILE -t T -o x.npz -q`` with
  and without ``--no-fill-holes``, and of Slic3r's export.

A Markdown table goes to stdout, progress to stderr.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402

MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"


def timed(cmd: list[str]) -> float:
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def compare(ours: np.ndarray, theirs: np.ndarray) -> str:
    n = min(ours.size, theirs.size)
    big = theirs[:n] > 1.0
    rel = np.abs(ours[:n] - theirs[:n])[big] / theirs[:n][big]
    return (f"{np.median(rel):.1e} / {rel.max():.1e} / {int((rel > 0.01).sum())} of {int(big.sum())} / "
            f"{int((ours < 1e-9).sum())}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", default="stanford_bunny,p_conveyor_holes,p_block_hole,prusa_frog_legs",
                    help="names in ../shared/meshes (comma-separated)")
    ap.add_argument("--fit", type=float, default=40.0, help="longest side, mm")
    ap.add_argument("-t", "--thickness", type=float, default=0.05, help="layer thickness, mm")
    ap.add_argument("--repeat", type=int, default=3, help="timed runs (median)")
    a = ap.parse_args()

    import csv

    from bench_soup import write_stl

    import gpuslice

    catalog = {r["name"]: r for r in csv.DictReader(open(MESHES / "catalog.csv"))}
    tmp = Path(tempfile.mkdtemp(prefix="gpuslice-holes-"))
    rows = []
    try:
        for name in [m.strip() for m in a.meshes.split(",") if m.strip()]:
            mesh = gpuslice.load_mesh(MESHES / catalog[name]["file"], fit=a.fit)
            stl = tmp / f"{name}.stl"
            write_stl(stl, (np.asarray(mesh.vertices)[np.asarray(mesh.faces)] + [100.0, 100.0, 0.0]).astype(np.float32))
            print(f"{name}: {mesh.n_faces} facets", file=sys.stderr, flush=True)
            filled = gpuslice.slice_mesh(mesh, thickness=a.thickness)
            left = gpuslice.slice_mesh(mesh, thickness=a.thickness, fill_holes=False)
            t0 = time.perf_counter()
            theirs = np.array([layer.area for layer in peers.slic3r_layers(stl, a.thickness)])
            t_slic3r = time.perf_counter() - t0
            g = [sys.executable, "-m", "gpuslice.cli", "slice", str(stl), "-t", str(a.thickness), "-o",
                 str(tmp / "x.npz"), "-q"]
            timed(g)  # (kernels built and cached)
            t_fill = statistics.median(timed(g) for _ in range(a.repeat))
            t_left = statistics.median(timed([*g, "--no-fill-holes"]) for _ in range(a.repeat))
            holes = filled.meta["repairs"].get("filled_holes", 0)
            rows.append([name, str(mesh.n_faces), str(filled.n_layers), str(holes),
                         compare(np.asarray(filled.area), theirs), compare(np.asarray(left.area), theirs),
                         f"{t_fill:.2f}", f"{t_left:.2f}", f"{t_slic3r:.2f}"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    head = ["mesh", "facets", "layers", "holes filled",
            "filled vs Slic3r: median / max rel. / layers > 1 % / empty layers", "--no-fill-holes: the same",
            "gpuslice s", "--no-fill-holes s", "Slic3r s"]
    print(f"fit {a.fit} mm, layers {a.thickness} mm; wall s, median of {a.repeat} (Slic3r: one run)\n")
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    main()
