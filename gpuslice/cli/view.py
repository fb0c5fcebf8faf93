"""``gpuslice view``: slice a mesh (or load a saved ``.npz`` result) and write the self-contained layer viewer page."""

from __future__ import annotations

import time
from pathlib import Path

import click

from .main import fail, load_model, slicing_options, with_options

__all__ = ["view"]


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"


@click.command()
@click.argument("source", type=click.Path(dir_okay=True, path_type=str))
@click.option("-o", "--output", type=click.Path(path_type=str), default=None,
              help="The page to write (.html; default: SOURCE's name with .html, in the current folder).")
@with_options(slicing_options(defaults=False))  # None unless given: they are refused with a saved .npz
@click.option("--raster", is_flag=True, help="Add each layer's resin mask (gpuslice.raster), drawn under the contours.")
@click.option("--printer", default="generic-4k", show_default=True,
              help="--raster: the display preset (gpuslice.raster.PRINTERS).")
@click.option("--mask-every", type=int, default=1, show_default=True,
              help="--raster: a mask for every N-th layer only (smaller page).")
@click.option("--title", default=None, help="Page title (default: the model's file name).")
@click.option("-q", "--quiet", is_flag=True, help="Print nothing but errors.")
def view(source, output, thickness, first_layer, z_mode, scale, fit, fill_rule, max_gap, backend, device, raster,
         printer, mask_every, title, quiet) -> None:
    """Write a self-contained HTML layer viewer for SOURCE (a mesh, sliced with the `slice` options, or a saved
    .npz result). Open it in any browser, offline: slider and arrow keys step through the layers."""
    from ..slicing.result import SliceResult
    from ..view.page import write_view

    src = Path(source)
    if output is None:
        output = src.with_suffix(".html").name
    if Path(output).suffix.lower() not in (".html", ".htm"):
        fail(f"{output}: the viewer is an HTML page (use a .html name)")
    slicing = {"-t": thickness, "--first-layer": first_layer, "--z-mode": z_mode, "--scale": scale, "--fit": fit,
               "--fill-rule": fill_rule, "--max-gap": max_gap, "--backend": backend, "--device": device}
    t0 = time.perf_counter()
    dev, bounds = None, None
    if src.suffix.lower() == ".npz":
        given = [k for k, v in slicing.items() if v is not None]
        if given:
            fail(f"{source}: a saved result is already sliced; {', '.join(given)} only apply to meshes")
        result = SliceResult.load(src)
        sliced = result.meta.get("file")
        default_title = f"{Path(str(sliced)).name} ({src.name})" if sliced else src.name
    else:
        from ..slicing.slicer import SliceParams, slice_mesh

        given = {"thickness": thickness, "first_layer": first_layer, "z_mode": z_mode, "fill_rule": fill_rule,
                 "max_gap": max_gap, "backend": backend, "device": device}
        params = SliceParams(**{k: v for k, v in given.items() if v is not None})  # the rest: SliceParams' defaults
        mesh, dev, _ = load_model(source, scale, fit, params.backend, device)
        result = slice_mesh(mesh, params)
        default_title = src.name
        lo, hi = mesh.vertices[:, :2].min(axis=0), mesh.vertices[:, :2].max(axis=0)
        bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))  # the mesh is centred, as `raster` does
    masks = None
    if raster:
        masks = _masks(source, result, printer, mask_every, bounds, backend, dev)
    t1 = time.perf_counter()
    size = write_view(result, output, title=title or default_title, masks=masks)
    t2 = time.perf_counter()
    if not quiet:
        extra = f", {len(masks.png):,} masks ({masks.label})" if masks is not None else ""
        click.echo(f"wrote {output}: {_size(size)} ({size:,} bytes), {result.n_layers:,} layers, "
                   f"{int(result.points.shape[0]):,} points{extra}; slicing/loading/masks {t1 - t0:.2f} s, "
                   f"page {t2 - t1:.2f} s")


def _masks(source: str, result, printer: str, every: int, bounds, backend: str | None, device):
    """The resin masks for ``--raster``, or a one-line error when gpuslice.raster or pillow is missing."""
    try:
        from ..raster.coverage import with_printer
    except ImportError as exc:
        fail(f"--raster needs gpuslice.raster ({exc})")
    try:
        import PIL  # noqa: F401
    except ImportError:
        fail("--raster needs pillow (pip install 'gpuslice[raster]')")
    from ..view.page import raster_masks

    if every < 1:
        fail(f"--mask-every must be >= 1, got {every}")
    return raster_masks(result, with_printer(printer), every=every, bounds=bounds,
                        backend="numpy" if backend == "numpy" else "auto", device=device, name=source)
