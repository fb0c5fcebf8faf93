"""``gpuslice check``: slice a model and run the pre-print checks (islands, unsupported area, resin traps and suction
cups, peel area, print time and resin) as one pipeline job; print a table, optionally write the JSON report. The exit
status is 0 whatever the checks find (defects are findings, not errors)."""

from __future__ import annotations

import re
from pathlib import Path

import click
import numpy as np

from ..checks import CheckOptions
from ..checks.summary import hours_minutes
from ..errors import ParameterError
from ..options import flag_of
from ..raster.settings import PrintSettings
from ..raster.spec import ResinOptions
from .options import (
    RESIN_DEFAULTS,
    build,
    check_output_file,
    check_resin_layers,
    click_options,
    far_warning,
    refuse_model_as_output,
    slicing_options,
    slicing_values,
    values,
    warn,
    with_options,
)

__all__ = ["check", "print_report"]

#: rows of each list printed (the JSON report has them all)
MAX_ROWS = 10


def print_report(report, name: str, *, console=None, max_rows: int = MAX_ROWS) -> None:
    """Print ``report`` (:class:`gpuslice.checks.CheckReport`) as rich tables: the summary, then the first
    ``max_rows`` islands (layer order) and the ``max_rows`` largest traps and suction cups."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console()
    isl, cav, unsup = report.islands, report.cavities, report.islands.unsupported
    z = report.z if report.z is not None else np.zeros(report.area.size)
    where = f"pixels of {report.display['resolution'][0]}x{report.display['resolution'][1]}" \
        if report.display else "contours"
    t = Table(title=f"{name}: pre-print checks ({where})", show_header=False, title_justify="left")
    t.add_column("check", style="bold")
    t.add_column("result")
    n_isl = report.n_islands
    t.add_row("islands", f"[red]{n_isl} in {report.island_layers.size} layers[/red]" if n_isl else "none")
    ok = np.isfinite(unsup)  # NaN: a layer whose polygons GEOS could not process
    worst = int(np.argmax(np.where(ok, unsup, -1.0))) if unsup.size else -1
    failed = f"; not computed on {int((~ok).sum())} layers" if (~ok).any() else ""
    t.add_row("unsupported area", (f"largest {unsup[worst]:.3f} mm² at layer {worst}, total {np.nansum(unsup):.1f} "
              f"mm² (tolerance {report.overhang_tolerance:g} mm)" if worst >= 0 and ok[worst] and unsup[worst] > 0
              else "none") + failed)
    traps = cav.kind == 0
    t.add_row("resin traps", f"[red]{cav.n_traps}, {cav.volume[traps].sum():.1f} mm³[/red]" if cav.n_traps else "none")
    t.add_row("suction cups", f"[yellow]{cav.n_cups}, largest {cav.max_area[~traps].max():.1f} mm²[/yellow]"
              if cav.n_cups else "none")
    t.add_row("voxel grid (traps)", f"{cav.grid_mm:g} mm")
    if report.max_area_layer >= 0:
        t.add_row("largest cross-section", f"{report.max_area:.1f} mm² at layer {report.max_area_layer} "
                  f"(z {z[report.max_area_layer]:.3f} mm)")
    t.add_row("print time", hours_minutes(report.print_time_s))
    t.add_row("resin", f"{report.resin_ml:.2f} ml, {report.resin_g:.2f} g at {report.resin_density:g} g/ml")
    if report.filled_holes:  # an open mesh: what is checked is the filled one
        t.add_row("checked as filled", f"[yellow]{report.filled_holes} holes of the mesh closed before slicing "
                  "(--no-fill-holes: as stored)[/yellow]")
    if report.open_chains:  # a broken mesh: what bounds nothing is not checked (it read as a clean bill)
        t.add_row("not checked", f"[yellow]{report.open_chains} open chains in {report.open_chain_layers} layers: "
                  "they bound nothing (a broken mesh)[/yellow]")
    console.print(t)
    if n_isl:
        ti = Table(title="islands", title_justify="left")
        for col in ("layer", "z mm", "area mm²", "x mm", "y mm"):
            ti.add_column(col, justify="right")
        for k in range(min(n_isl, max_rows)):
            ti.add_row(str(isl.layer[k]), f"{z[isl.layer[k]]:.3f}", f"{isl.area[k]:.4f}", f"{isl.x[k]:.2f}",
                       f"{isl.y[k]:.2f}")
        console.print(ti)
        if n_isl > max_rows:
            console.print(f"… and {n_isl - max_rows} more islands (--json for all)")
    if cav.kind.size:
        tc = Table(title="resin traps and suction cups (largest first)", title_justify="left")
        for col in ("kind", "layers", "volume mm³", "largest section mm²", "a point x, y, z mm"):
            tc.add_column(col, justify="right")
        for k in np.argsort(-cav.volume, kind="stable")[:max_rows].tolist():
            tc.add_row("trap" if cav.kind[k] == 0 else "suction cup", f"{cav.layer_min[k]}–{cav.layer_max[k]}",
                       f"{cav.volume[k]:.1f}", f"{cav.max_area[k]:.2f}",
                       f"{cav.x[k]:.1f}, {cav.y[k]:.1f}, {cav.z[k]:.2f}")
        console.print(tc)
        if cav.kind.size > max_rows:
            console.print(f"… and {cav.kind.size - max_rows} more (--json for all)")


def _with_flags(exc: ParameterError) -> ParameterError:
    text = str(exc)
    for param in exc.params:
        flag = flag_of(param, CheckOptions)
        if flag:
            text = re.sub(rf"(?<![\w-]){re.escape(param)}(?![\w-])", flag, text)
    return ParameterError(text, param=tuple(p for p in exc.params if not flag_of(p, CheckOptions)))


@click.command()
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@with_options(slicing_options(overrides=RESIN_DEFAULTS))
@with_options(click_options(ResinOptions, only=("printer",)))
@with_options(click_options(CheckOptions))
@with_options(click_options(PrintSettings, defaults=False, preset=True))  # None unless given: they override the preset
@click.option("--json", "json_path", type=click.Path(path_type=str), default=None,
              help="Write the JSON report (every island, trap and cup; per-layer areas).")
@click.option("-q", "--quiet", is_flag=True, help="No table on stdout.")
def check(model: str, json_path: str | None, quiet: bool, **kw) -> None:
    """Slice MODEL and check it before printing: islands (contour-exact; pixel-exact on the printer's grid with
    --printer), unsupported area per layer, resin traps and suction cups, the largest cross-section, print time (with
    --printer: as the printer's own archive states it) and resin. Exits 0 even when it finds defects."""
    from ..pipeline import CheckOutput, Job, run_job

    refuse_model_as_output(model, json_path)
    check_output_file(json_path)
    params, placement = slicing_values(kw, RESIN_DEFAULTS)
    check_resin_layers(params)
    options = build(ResinOptions, kw)
    spec = options.spec() if options.printer is not None else None
    settings = options.settings(**values(PrintSettings, kw))
    try:
        checks = CheckOutput(spec, settings, build(CheckOptions, kw), json_path, printer=options.preset)
        done = run_job(Job(source=model, placement=placement, params=params, mesh_check=False, checks=checks))
    except ParameterError as exc:  # CheckOptions' fields as this command's flags (cli.options knows the others)
        raise _with_flags(exc) from None
    if (far := far_warning(model, done.mesh)) is not None:
        warn(far)
    if not quiet:
        print_report(done.stats["checks"], Path(model).name)
        if json_path is not None:
            click.echo(f"wrote {json_path}")
