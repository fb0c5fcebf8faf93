"""Fuzz the layer-image encoding kernels (kernels/goo.cl, ctb.cl, photon.cl, png.cl) against their numpy twins.

Random groups of small random layers (few greys, blank, full and sparse layers, rows full to both ends, any first
and last entry), typed as the runs kernel types its runs, are encoded by each format's kernels and by its twin; any
difference is printed with the case and counted. The kernels may hand a group to the twin (``fallbacks``: runs
touching across a row end for GOO, long merges for CTB and PW0): that is counted, not a difference.

Usage: ``python scripts/fuzz_encoders.py [--cases 400] [--seed 0]``; exit status 1 when anything differs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "raster"))
from run_images import runs_of  # noqa: E402  (the tests' helper: layers as the runs kernel lays them out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    from gpuslice.device import get_device
    from gpuslice.raster import ctb, goo, photon
    from gpuslice.raster.deflate_runs import encode_png_from_runs
    from gpuslice.raster.png_runs import PngRunsEncoder

    dev = get_device()
    rng = np.random.default_rng(args.seed)
    bad = 0
    for case in range(args.cases):
        h, w, n = int(rng.integers(1, 40)), int(rng.integers(1, 90)), int(rng.integers(1, 12))
        palette = rng.choice(np.arange(256, dtype=np.uint8), size=int(rng.integers(1, 8)))
        images = []
        for _ in range(n):
            img = rng.choice(palette, size=(h, w)).astype(np.uint8)
            img[rng.random((h, w)) < rng.random()] = 0
            if rng.random() < 0.2:
                img[:] = 0
            elif rng.random() < 0.1:
                img[:] = palette[0]
            images.append(img)
        runs = runs_of(images)
        a = int(rng.integers(0, n))
        b = int(rng.integers(a + 1, n + 1))
        px = h * w
        same = {
            "goo": goo.encode_batch(runs, a, b, w, px, device=dev) == goo.encode_batch(runs, a, b, w, px),
            "ctb": ctb.rle7_runs(runs, a, b, w, px, device=dev) == ctb.rle7_runs(runs, a, b, w, px),
        }
        got, want = photon.encode_pw0_runs(runs, a, b, w, px, device=dev), photon.encode_pw0_runs(runs, a, b, w, px)
        same["pw0"] = got[0] == want[0] and all(np.array_equal(x, y) for x, y in zip(got[1:], want[1:], strict=True))
        pngs = PngRunsEncoder.of(dev).encode(runs, a, b, w, h)
        same["png"] = pngs is None or pngs == [encode_png_from_runs(runs, k, w, h, "static") for k in range(a, b)]
        if not all(same.values()):
            bad += 1
            print(f"case {case}: {h}x{w}, {n} layers, entries {a}..{b - 1}: differ in "
                  f"{', '.join(k for k, v in same.items() if not v)}")
    fallbacks = {name: enc.of(dev).fallbacks for name, enc in (("goo", goo.GooEncoder), ("ctb", ctb.CtbEncoder),
                                                                ("pw0", photon.PhotonEncoder), ("png", PngRunsEncoder))}
    print(f"{args.cases} cases, {bad} differ; groups left to the twins: {fallbacks}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
