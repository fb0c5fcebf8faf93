"""``gpuslice raster``: slice a model and write its layers as resin-printer bitmaps (SL1 archive or PNG stack)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

from .main import fail, load_model, slicing_options, with_options

__all__ = ["raster"]


def _resolution(text: str) -> tuple[int, int]:
    try:
        nx, ny = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected NXxNY pixels, e.g. 3840x2400, got '{text}'") from None
    return nx, ny


@click.command()
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="FILE.sl1 (archive) or DIR/ (a PNG stack).")
@with_options(slicing_options(thickness=0.05))
@click.option("--printer", default=None, help="Display preset (see gpuslice.raster.PRINTERS); options below override.")
@click.option("--resolution", default=None,
              help="Display pixels NXxNY along X and Y [3840x2400]; PNGs are NXxNY (landscape) or NYxNX (portrait).")
@click.option("--pixel", type=float, default=None, help="Pixel size along X (the display's width), mm [0.05].")
@click.option("--pixel-y", type=float, default=None, help="Pixel size along Y, mm (default: square).")
@click.option("--mirror-x/--no-mirror-x", default=None, help="Mirror the columns.")
@click.option("--mirror-y/--no-mirror-y", default=None, help="Mirror the rows.")
@click.option("--portrait/--landscape", default=None, help="Display orientation [landscape].")
@click.option("--keep-xy", is_flag=True, help="Keep the model's own XY instead of centring it on the display.")
@click.option("--gamma", type=float, default=1.0, show_default=True,
              help="Antialiasing gamma (PrusaSlicer's): 1 linear coverage, 0 hard threshold at 50 %.")
@click.option("--raster-backend", type=click.Choice(["auto", "gl", "opencl", "numpy"]), default="auto",
              show_default=True, help="auto: GL on a hardware GPU, else OpenCL.")
@click.option("--supersample", type=click.IntRange(1, 16), default=8, show_default=True,
              help="GL backend: samples per pixel side.")
@click.option("--png-level", type=click.IntRange(0, 9), default=1, show_default=True,
              help="Deflate level of each layer's non-blank rows.")
@click.option("--exposure", type=float, default=10.0, show_default=True, help="Exposure time, s (config.ini).")
@click.option("--exposure-first", type=float, default=15.0, show_default=True, help="First layers' exposure, s.")
@click.option("--job-name", default=None, help="SL1 jobDir and PNG prefix (default: the model's file name).")
@click.option("--workers", type=click.IntRange(1, 256), default=None, help="PNG encoding threads [CPUs].")
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr [TTY or long runs].")
@click.option("--report", type=click.Path(path_type=str), default=None, help="Write timings and counts as JSON.")
@click.option("-q", "--quiet", is_flag=True, help="No summary on stdout.")
def raster(model, output, thickness, first_layer, z_mode, scale, fit, fill_rule, max_gap, backend, device, printer,
           resolution, pixel, pixel_y, mirror_x, mirror_y, portrait, keep_xy, gamma, raster_backend, supersample,
           png_level, exposure, exposure_first, job_name, workers, progress, report, quiet) -> None:
    """Slice MODEL and write one 8-bit bitmap per layer: an SL1 archive (-o part.sl1) or a PNG stack (-o dir/).

    The model is centred on the display (--keep-xy keeps its XY); column j has its centre at x = (j + 0.5)*pixel
    and row 0 is the +y edge (landscape). Greys are pixel coverage with PrusaSlicer's gamma.
    """
    from ..io.report import write_report
    from ..raster.coverage import PRINTERS, RasterSpec, check_fits, choose_backend, iter_tiles
    from ..raster.sl1 import info_from, write_png_stack, write_sl1
    from ..slicing.slicer import SliceParams, slice_mesh

    t_start = time.perf_counter()
    out_is_dir = output.endswith(("/", "\\")) or Path(output).is_dir()
    if not out_is_dir and Path(output).suffix.lower() != ".sl1":
        fail(f"{output}: unknown output format '{Path(output).suffix}' (use FILE.sl1, or DIR/ for a PNG stack)")
    parent = Path(output.rstrip("/\\") or ".").resolve().parent
    if not parent.is_dir():
        fail(f"{output}: directory {parent} does not exist")
    kw: dict = {}
    if printer is not None:
        if printer not in PRINTERS:
            fail(f"unknown printer '{printer}' (use {', '.join(sorted(PRINTERS))})")
        kw.update(PRINTERS[printer])
    if resolution is not None:
        kw["resolution"] = _resolution(resolution)
    for key, value in (("pixel", pixel), ("pixel_y", pixel_y), ("mirror_x", mirror_x), ("mirror_y", mirror_y),
                       ("portrait", portrait)):
        if value is not None:
            kw[key] = value
    spec = RasterSpec(**kw, keep_xy=keep_xy, gamma=gamma)
    rb = choose_backend(raster_backend)
    params = SliceParams(thickness=thickness, first_layer=first_layer, z_mode=z_mode, fill_rule=fill_rule,
                         max_gap=max_gap, backend=backend, device=device)
    mesh, dev, timings = load_model(model, scale, fit, backend, device)
    timings.pop("device")
    if dev is None and rb == "opencl":  # numpy slicing, OpenCL rasterising
        from ..device import get_device

        dev = get_device(device)
    result = slice_mesh(mesh, params)
    timings.update({f"slice_{k}": v for k, v in result.meta["timings_s"].items()})
    b = mesh.bounds
    bounds = (b[0, 0], b[0, 1], b[1, 0], b[1, 1])
    check_fits(result, spec, bounds, name=model)
    name = job_name or Path(model).stem
    n = result.n_layers
    tiles = iter_tiles(result, spec, backend=rb, device=dev, bounds=bounds, supersample=supersample)

    show = progress if progress is not None else (sys.stderr.isatty() or n >= 1000)
    t_out = time.perf_counter()
    bar = None
    if show:
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

        bar = Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                       TimeRemainingColumn(), console=Console(stderr=True), transient=False)
        task = bar.add_task(f"raster {Path(output).name}", total=n)
        bar.start()

        def tick(k: int) -> None:
            if k % 16 == 0 or k == n:
                bar.update(task, completed=k)
    else:
        tick = None
    try:
        if out_is_dir:
            stats = write_png_stack(tiles, spec, output.rstrip("/\\") or ".", prefix=name, level=png_level,
                                    workers=workers, progress=tick)
        else:
            info = info_from(result, name, {"exposure_time": exposure, "initial_exposure_time": exposure_first})
            stats = write_sl1(tiles, spec, output, info, n, level=png_level, workers=workers, progress=tick)
    finally:
        if bar is not None:
            bar.stop()
    timings["raster_and_write"] = time.perf_counter() - t_out
    timings["total"] = time.perf_counter() - t_start
    if report is not None:
        write_report({"layers": n, "raster_backend": rb, "output": output, "timings_s": timings, **stats,
                      "display": {"resolution": list(spec.resolution), "pixel": [spec.px, spec.py],
                                  "portrait": spec.portrait, "mirror_x": spec.mirror_x, "mirror_y": spec.mirror_y}},
                     report)
    if not quiet:
        click.echo(f"{Path(model).name}: {n} layers of {spec.png_size[0]}x{spec.png_size[1]} px ({spec.px:g} mm), "
                   f"raster {rb}, {stats['png_bytes'] / 1e6:.1f} MB of PNG, "
                   f"{timings['total']:.2f} s; wrote {output}")
