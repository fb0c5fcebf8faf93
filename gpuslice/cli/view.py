"""``gpuslice view``: slice a mesh (or load a saved ``.npz`` result) and write the self-contained layer viewer page
(one pipeline job)."""

from __future__ import annotations

import time
from pathlib import Path

import click

from ..mesh.mesh import Placement
from ..options import options_of
from ..slicing.params import SliceParams
from .options import (
    RESIN_DEFAULTS,
    check_output_file,
    check_resin_layers,
    fail,
    far_warning,
    refuse_model_as_output,
    slicing_options,
    slicing_values,
    warn,
    with_options,
)

__all__ = ["view"]


def _checks(check: bool, ropts):
    """The page's pre-print checks: none, the contours' (no --printer: ``ropts`` None) or the printer's pixels with
    its settings (``ropts``: :class:`~gpuslice.raster.spec.ResinOptions` naming it)."""
    from ..pipeline import CheckOutput

    if not check:
        return None
    if ropts is None:
        return CheckOutput()
    return CheckOutput(ropts.spec(), ropts.settings(), printer=ropts.preset)


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"


@click.command()
@click.argument("source", type=click.Path(dir_okay=True, path_type=str))
@click.option("-o", "--output", type=click.Path(path_type=str), default=None,
              help="The page to write (.html; default: SOURCE's name with .html, in the current folder).")
@with_options(slicing_options(defaults=False))  # None unless given: they are refused with a saved .npz
@click.option("--raster", is_flag=True, help="Add each layer's resin mask (gpuslice.raster), drawn under the contours "
              "(layers 0.05 mm unless -t is given, as `gpuslice raster`).")
@click.option("--printer", default=None,
              help="The printer preset (a name `gpuslice printers` lists, or a .toml/.json file): --raster draws its "
              "display's masks (default generic-4k); --check checks its pixels with its print settings, as `gpuslice "
              "check --printer` (default: the contours, default settings).")
@click.option("--mask-every", type=int, default=1, show_default=True,
              help="--raster: a mask for every N-th layer only (smaller page).")
@click.option("--title", default=None, help="Page title (default, or empty: the model's file name).")
@click.option("--check", is_flag=True, help="Run the pre-print checks (as `gpuslice check`: layers 0.05 mm unless -t "
              "is given) and mark islands, resin traps and suction cups on their layers, with a list to jump to them.")
@click.option("-q", "--quiet", is_flag=True, help="Print nothing but errors.")
def view(source: str, output: str | None, raster: bool, printer: str, mask_every: int, title: str | None,
         check: bool, quiet: bool, **kw) -> None:
    """Write a self-contained HTML layer viewer for SOURCE (a mesh, sliced with the `slice` options, or a saved
    .npz result). Open it in any browser, offline: slider and arrow keys step through the layers."""
    from ..pipeline import Job, ViewOutput, run_job

    src = Path(source)
    if output is None:
        output = src.with_suffix(".html").name
    if Path(output).suffix.lower() not in (".html", ".htm"):
        fail(f"{output}: the viewer is an HTML page (use a .html name)")
    refuse_model_as_output(source, output)
    check_output_file(output)
    if mask_every < 1:
        fail(f"--mask-every must be >= 1, got {mask_every}")
    if src.suffix.lower() == ".npz":
        flags = {i.name: i.flags[0] for cls in (SliceParams, Placement) for i in options_of(cls) if i.flags}
        given = [flags[k] for k, v in kw.items() if v is not None and v is not False and k in flags]  # (flags: True)
        if given:
            fail(f"{source}: a saved result is already sliced; {', '.join(given)} only "
                 f"{'applies' if len(given) == 1 else 'apply'} to meshes")
    from ..raster.spec import ResinOptions

    masks = ropts = None
    if printer is not None:
        ropts = ResinOptions(printer=printer)  # an unknown name or a bad file: refused here, with or without flags
        if not (raster or check):
            fail("--printer applies with --raster or --check")
    if raster:
        try:
            import PIL  # noqa: F401
        except ImportError:
            fail("--raster needs pillow (pip install 'gpuslice[raster]')")
        masks = (ropts or ResinOptions(printer="generic-4k")).spec()  # a preset name or a .toml/.json preset file
    # resin masks or pre-print checks: sliced as `raster` and `check` slice (0.05 mm) unless -t is given
    params, placement = slicing_values(kw, RESIN_DEFAULTS if raster or check else None)
    if raster or check:
        check_resin_layers(params)
    t0 = time.perf_counter()
    done = run_job(Job(source=source, placement=placement, params=params, mesh_check=False, saved_result=True,
                       view=ViewOutput(output, title or None, masks, mask_every), checks=_checks(check, ropts)))
    if (far := far_warning(source, done.mesh)) is not None:
        warn(far)
    t1 = done.timings.get("view", 0.0)
    if not quiet:
        m = done.stats.get("masks")
        extra = f", {len(m.png):,} masks ({m.label})" if m is not None else ""
        size = done.stats["view_bytes"]
        click.echo(f"wrote {output}: {_size(size)} ({size:,} bytes), {done.result.n_layers:,} layers, "
                   f"{int(done.result.points.shape[0]):,} points{extra}; slicing/loading/masks "
                   f"{time.perf_counter() - t0 - t1:.2f} s, page {t1:.2f} s")
        for line in done.stats["checks"].lines() if check else ():
            click.echo(line)
