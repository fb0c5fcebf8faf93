"""Benchmark ``SliceResult.to_shapely()`` (all layers to shapely MultiPolygons) against trimesh's
``section_multiplane`` on the same planes, in one process (docs/BENCHMARKS.md, "Python geometry ecosystem").

    python scripts/bench_shapely.py [--mesh ../shared/meshes/nefertiti.stl] [--height 80] [-t 0.05] [--repeat 5]

The mesh is scaled so it stands ``--height`` mm tall and sliced at ``-t`` mm (uniform, cut mid-slab); then, each
``--repeat`` times (median reported): ``to_shapely()``; trimesh ``section_multiplane`` on the placed mesh with the
result's z planes (it returns ``Path2D`` outlines, not polygons); and once, trimesh's ``polygons_closed`` of every
section (shapely Polygons of its closed outlines, holes not nested: ``polygons_full`` would need rtree).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def median_time(fn, repeat: int) -> tuple[float, object]:
    """Median wall time of ``repeat`` calls (s), and the last call's value."""
    times, value = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        value = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=str(REPO.parent / "shared" / "meshes" / "nefertiti.stl"))
    ap.add_argument("--height", type=float, default=80.0, help="scale the mesh to this height, mm")
    ap.add_argument("-t", "--thickness", type=float, default=0.05, help="layer thickness, mm")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--no-peer-polygons", action="store_true", help="skip trimesh's polygons_closed (slow)")
    args = ap.parse_args()

    import shapely
    import trimesh

    import gpuslice

    raw = gpuslice.load_mesh(args.mesh)
    mesh = gpuslice.load_mesh(raw, scale=args.height / raw.height)
    t = time.perf_counter()
    res = gpuslice.slice_mesh(mesh, thickness=args.thickness)
    t_slice = time.perf_counter() - t
    print(f"mesh {args.mesh}: {mesh.n_faces} facets, {mesh.height:.3f} mm tall; {res.n_layers} layers, "
          f"{res.n_loops} loops, {res.points.shape[0]} points (slice_mesh {t_slice:.2f} s, {res.meta['device']})")

    res.to_shapely()  # warm-up: imports
    t_ours, polys = median_time(res.to_shapely, args.repeat)
    areas = shapely.area(polys)
    rel = float(np.max(np.abs(areas - res.area) / np.maximum(res.area, 1e-12)))
    print(f"gpuslice to_shapely(): median {t_ours:.3f} s of {args.repeat} "
          f"({res.points.shape[0] / t_ours / 1e6:.1f} M points/s); max relative area error {rel:.1e}")

    tm = trimesh.Trimesh(mesh.vertices.astype(np.float64), mesh.faces, process=False)
    heights = np.asarray(res.z, dtype=np.float64)

    def peer():
        return tm.section_multiplane(plane_origin=[0, 0, 0], plane_normal=[0, 0, 1], heights=heights)

    t_peer, sections = median_time(peer, args.repeat)
    print(f"trimesh section_multiplane (Path2D outlines): median {t_peer:.3f} s of {args.repeat}")
    if not args.no_peer_polygons:
        # polygons_full (holes nested) needs rtree; polygons_closed (every closed outline as a shapely Polygon, no
        # nesting) is the nearest to to_shapely that plain trimesh gives
        t = time.perf_counter()
        n_closed = sum(len(s.polygons_closed) for s in sections if s is not None)
        t_closed = time.perf_counter() - t
        print(f"trimesh polygons_closed of every section (once, {n_closed} polygons, holes not nested): "
              f"{t_closed:.3f} s")
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((line.split(":", 1)[1].strip() for line in fh if line.startswith("model name")), cpu)
    except OSError:
        pass
    print(f"machine: {platform.platform()}, {os.cpu_count()} CPUs, {cpu}; "
          f"python {platform.python_version()}, shapely {shapely.__version__} (GEOS {shapely.geos_version_string}), "
          f"trimesh {trimesh.__version__}, numpy {np.__version__}")
    if hasattr(os, "getloadavg"):
        print("load average: {:.2f} {:.2f} {:.2f}".format(*os.getloadavg()))


if __name__ == "__main__":
    main()
