"""Benchmark of issue 7: the layer viewer page (``gpuslice view``) at scale, in headless Chromium.

Usage::

    python scripts/bench_view.py [--mesh nefertiti] [--fit 120] [-t 0.05] [--repeat 5] [--json out.json]

The mesh (``../shared/meshes/<mesh>.stl`` scaled so its longest side is ``--fit`` mm; nefertiti at 120 mm and
0.05 mm gives 2,400 layers and about a million points) is sliced once; then, side by side in the same run:

* the viewer page: written with :func:`gpuslice.view.page.write_view` (Python time and page size), opened ``--repeat``
  times in a fresh tab of Debian's ``/usr/bin/chromium`` (playwright, 1280×800): ``load``: the page's
  ``loadEventEnd`` (navigation start to the end of the load event: reading and parsing the file, decoding the
  arrays, the first layer drawn); ``ready``: ``performance.now()`` when the viewer's set-up ended; then one scrub
  through every layer (``gpusliceViewer.stepTimes``: one ``setLayer`` + a pixel read-back that waits for both
  canvases to be rasterised, each layer's Path2D built on first visit): median, 95th percentile and max ms per step.
* the baseline a user has without the viewer: the same result exported as SVG by ``gpuslice slice -o x.svg``
  (``gpuslice.formats.svg.write_svg``, every layer a ``<g>``), opened the same way (size and ``loadEventEnd``). No peer
  slicer (PrusaSlicer, Cura) has a layer preview that can be timed headless, so none is measured here.

Other engineers share this 2-core VM: timings are noisy; medians of ``--repeat`` runs are quoted. A Markdown table
goes to stdout, progress to stderr.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import gpuslice
from gpuslice.formats.svg import write_svg
from gpuslice.view.page import write_view

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT.parent / "shared" / "meshes"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]


def _open(browser, path: Path, viewer: bool) -> dict:
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    t = time.perf_counter()
    page.goto(path.as_uri(), wait_until="load", timeout=300_000)
    wall = time.perf_counter() - t
    nav = page.evaluate("JSON.stringify(performance.getEntriesByType('navigation')[0])")
    out = {"load_ms": json.loads(nav)["loadEventEnd"], "goto_s": wall}
    if viewer:
        page.wait_for_function("window.gpusliceViewer && window.gpusliceViewer.ready")
        out.update(page.evaluate("gpusliceViewer.timings"))
        n = page.evaluate("gpusliceViewer.nLayers")
        steps = page.evaluate(f"gpusliceViewer.stepTimes(0, {n})")
        steps.sort()
        out["step_median_ms"] = statistics.median(steps)
        out["step_p95_ms"] = steps[int(0.95 * (len(steps) - 1))]
        out["step_max_ms"] = steps[-1]
    page.close()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", default="nefertiti")
    ap.add_argument("--fit", type=float, default=120.0)
    ap.add_argument("-t", "--thickness", type=float, default=0.05)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    mesh = gpuslice.load_mesh(MESHES / f"{args.mesh}.stl", fit=args.fit)
    res = gpuslice.slice_mesh(mesh, thickness=args.thickness)
    n_points = int(res.points.shape[0])
    print(f"{args.mesh} fit {args.fit} mm, t {args.thickness} mm: {res.n_layers} layers, {n_points} points",
          file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        html, svg = Path(tmp) / "view.html", Path(tmp) / "layers.svg"
        write_times, svg_times = [], []
        for _ in range(args.repeat):
            t = time.perf_counter()
            write_view(res, html)
            write_times.append(time.perf_counter() - t)
            t = time.perf_counter()
            write_svg(res, svg)
            svg_times.append(time.perf_counter() - t)
        runs: dict[str, list[dict]] = {"view": [], "svg": []}
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
            print(f"chromium {browser.version}", file=sys.stderr)
            for k in range(args.repeat):
                runs["view"].append(_open(browser, html, True))
                runs["svg"].append(_open(browser, svg, False))
                print(f"run {k}: view {runs['view'][-1]['load_ms']:.0f} ms, svg {runs['svg'][-1]['load_ms']:.0f} ms",
                      file=sys.stderr)
            version = browser.version
            browser.close()
        sizes = {"view": html.stat().st_size, "svg": svg.stat().st_size}

    def med(kind: str, key: str) -> float:
        return statistics.median(r[key] for r in runs[kind])

    print(f"\n{args.mesh}, longest side {args.fit:g} mm, {args.thickness} mm layers: {res.n_layers:,} layers, "
          f"{n_points:,} points; Chromium {version} headless, median of {args.repeat}\n")
    print("| page | size | written (Python) | load (loadEventEnd) | viewer ready | step median / p95 / max |")
    print("|---|---|---|---|---|---|")
    print(f"| `gpuslice view` HTML | {sizes['view'] / 1e6:.1f} MB | {statistics.median(write_times):.2f} s | "
          f"{med('view', 'load_ms'):.0f} ms | {med('view', 'ready_ms'):.0f} ms | "
          f"{med('view', 'step_median_ms'):.2f} / {med('view', 'step_p95_ms'):.2f} / "
          f"{med('view', 'step_max_ms'):.1f} ms |")
    print(f"| SVG export (baseline) | {sizes['svg'] / 1e6:.1f} MB | {statistics.median(svg_times):.2f} s | "
          f"{med('svg', 'load_ms'):.0f} ms | – | – |")
    print(f"\nload ratio view/svg: {med('view', 'load_ms') / med('svg', 'load_ms'):.2f}; "
          f"size ratio: {sizes['view'] / sizes['svg']:.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"args": vars(args), "layers": res.n_layers, "points": n_points,
                                               "sizes": sizes, "write_s": write_times, "svg_write_s": svg_times,
                                               "runs": runs, "chromium": version}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
