"""Micro-benchmark: a resin layer's PNG from its runs, by the bitmap path and by the runs deflater.

The job: ``../shared/meshes/nefertiti.stl`` (99,938 facets; its tallest side is Z) scaled to 80 mm tall
(``fit=80``), 0.05 mm layers (1,600), runs from ``gpuslice.raster.runs`` (OpenCL) of ``--layers`` layers spread
evenly over the height (blank layers skipped), on an 11520x5120 display of 0.019 mm pixels and a 3840x2400 one of
0.05 mm, gamma 0 and gamma 1. Per layer, in this thread (one core), median over layers of the best of ``--repeat``:

* (a) **bitmap**: runs -> the layer's bounding-box bitmap (a :class:`~gpuslice.raster.Tile`, timed too) ->
  :meth:`PngEncoder.encode` with ISA-L (or zlib with ``--deflater zlib``) at level 1, the current path;
* (b) **runs**: :func:`~gpuslice.raster.deflate_runs.encode_png_from_runs`, dynamic and fixed Huffman codes.

Every PNG is decoded once (zlib) and checked against ``runs.to_mask(k)``. Prints ms/layer, layers/s and PNG sizes.

Usage: ``python scripts/bench_png_runs.py [--layers 40] [--repeat 3] [--gammas 0,1] [--deflater isal]``
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import zlib
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MESH = REPO.parent / "shared" / "meshes" / "nefertiti.stl"
DISPLAYS = (((11520, 5120), 0.019), ((3840, 2400), 0.05))


def best(fn, repeat: int) -> tuple[float, object]:
    out, times = None, []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def tile_from_runs(runs, k: int):
    """The bounding-box bitmap of entry ``k`` as a Tile (what a bitmap encoder needs), by the package's own
    :func:`gpuslice.raster.coverage.tile_from_runs` over the runs' bounding box."""
    from gpuslice.raster import Tile
    from gpuslice.raster.coverage import tile_from_runs as fill

    a, b = int(runs.layer_offsets[k]), int(runs.layer_offsets[k + 1])
    if a == b:
        return Tile(int(runs.layers[k]), 0, 0, np.zeros((0, 0), np.uint8))
    row, x, n = runs.row[a:b], runs.x[a:b], runs.length[a:b]
    r0, c0 = int(row[0]), int(x.min())
    h, w = int(row[-1]) - r0 + 1, int((x + n).max()) - c0
    return Tile(int(runs.layers[k]), r0, c0, fill(runs, k, r0, c0, h, w))


def decoded(png: bytes, shape: tuple[int, int]) -> np.ndarray:
    """The pixels of one of our PNGs (one IDAT right after IHDR), via zlib (checks the Adler-32 too)."""
    n = int.from_bytes(png[33:37], "big")
    raw = np.frombuffer(zlib.decompress(png[41 : 41 + n]), np.uint8).reshape(shape[0], shape[1] + 1)
    assert not raw[:, 0].any()
    return raw[:, 1:]


def measure(runs, k: int, enc, repeat: int) -> dict[str, tuple[float, bytes | None]]:
    """Seconds (best of ``repeat``) and PNG of each way of encoding entry ``k``: ``tile`` (runs -> Tile),
    ``enc`` (PngEncoder.encode of that tile), ``dyn`` and ``fix`` (encode_png_from_runs)."""
    from gpuslice.raster.deflate_runs import encode_png_from_runs

    ny, nx = runs.shape
    sec_tile, tile = best(lambda: tile_from_runs(runs, k), repeat)
    out = {"tile": (sec_tile, None), "enc": best(lambda: enc.encode(tile), repeat)}
    for key, huffman in (("dyn", "dynamic"), ("fix", "fixed")):
        out[key] = best(lambda huffman=huffman: encode_png_from_runs(runs, k, nx, ny, huffman), repeat)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=40)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--gammas", default="0,1")
    ap.add_argument("--deflater", default="isal")
    args = ap.parse_args(argv)
    if not MESH.is_file():
        print(f"{MESH} not found", file=sys.stderr)
        return 2
    import trimesh

    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.device import get_device
    from gpuslice.raster import RasterSpec
    from gpuslice.raster.png import PngEncoder
    from gpuslice.raster.runs import layer_runs

    dev = get_device()
    m = trimesh.load(MESH, force="mesh")
    mesh = mesh_from_triangles(m.vertices[m.faces], fit=80.0, device=dev, name="nefertiti")
    res = slice_mesh(mesh, thickness=0.05, backend="opencl")
    sel = sorted({int(i) for i in np.linspace(0, res.n_layers - 1, args.layers + 2)[1:-1]})
    print(f"nefertiti 80 mm: {mesh.n_faces} facets, {res.n_layers} layers; {len(sel)} layers timed; "
          f"device {dev.name}; deflater {args.deflater} level 1")
    print("\n| display | gamma | runs/layer | (a) runs->tile | (a) encode | **(a) total** | (b) runs dynamic | "
          "(b) runs fixed | speed-up (a)/(b dyn) | PNG kB: (a) / (b dyn) / (b fixed) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for (nx, ny), px in DISPLAYS:
        enc = PngEncoder(nx, ny, level=1, deflater=args.deflater)
        for gamma in (float(g) for g in args.gammas.split(",")):
            spec = RasterSpec(resolution=(nx, ny), pixel=px, gamma=gamma)
            runs = layer_runs(res, spec, backend="opencl", device=dev, layers=sel)
            t = {key: [] for key in ("tile", "enc", "dyn", "fix")}
            size = {key: [] for key in ("enc", "dyn", "fix")}
            n_runs = []
            for k in range(len(sel)):
                if runs.layer_offsets[k + 1] == runs.layer_offsets[k]:
                    continue
                n_runs.append(int(runs.layer_offsets[k + 1] - runs.layer_offsets[k]))
                for key, (sec, png) in measure(runs, k, enc, args.repeat).items():
                    t[key].append(sec)
                    if png is not None:
                        assert np.array_equal(decoded(png, (ny, nx)), runs.to_mask(k)), (key, sel[k])
                        size[key].append(len(png))
            med = {key: statistics.median(v) * 1e3 for key, v in t.items()}
            tot = statistics.median(a + b for a, b in zip(t["tile"], t["enc"], strict=True)) * 1e3
            kb = {key: statistics.median(v) / 1e3 for key, v in size.items()}
            print(f"| {nx}x{ny} | {gamma:g} | {statistics.median(n_runs):.0f} | {med['tile']:.2f} ms | "
                  f"{med['enc']:.2f} ms | **{tot:.2f} ms ({1e3 / tot:.0f}/s)** | "
                  f"{med['dyn']:.2f} ms ({1e3 / med['dyn']:.0f}/s) | {med['fix']:.2f} ms ({1e3 / med['fix']:.0f}/s) | "
                  f"{tot / med['dyn']:.1f}x | {kb['enc']:.1f} / {kb['dyn']:.1f} / {kb['fix']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
