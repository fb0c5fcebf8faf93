"""``gpuslice slice``: slice a model into layers of closed, nested contours (one pipeline job)."""

from __future__ import annotations

from pathlib import Path

import click

from ..formats import format_names
from .options import (
    check_distinct_outputs,
    check_output_file,
    fail,
    far_warning,
    refuse_model_as_output,
    slicing_options,
    slicing_values,
    warn,
    with_options,
)

__all__ = ["slice_cmd", "build_report", "adaptive_lines"]


def _formats_help() -> str:
    from ..formats import suffixes

    return ", ".join(suffixes())


def adaptive_lines(meta: dict) -> list[str]:
    """Human-readable lines about an adaptive schedule (the roi windows chosen at each level)."""
    info = meta.get("adaptive") or {}
    out = []
    for lv in info.get("levels", []):
        wins = "; ".join(f"layers [{w['layers'][0]}, {w['layers'][1]}] = z {w['z_mm'][0]:.6g}..{w['z_mm'][1]:.6g} mm"
                         for w in lv["windows"]) or "none"
        out.append(f"roi level {lv['level']}: {lv['thickness_mm']:g} mm over z {lv['region_mm'][0]:.6g}.."
                   f"{lv['region_mm'][1]:.6g} mm, {lv['layers']} layers, threshold {lv['threshold_points']:.6g} "
                   f"points/layer -> window {wins}")
    if info.get("mode") in ("cusp", "area"):
        out.append(f"adaptive {info['mode']}: resolution {info['resolution_mm']:g} mm, "
                   f"{info['bound_violations']} layers above the bound (min height)")
    return out


def build_report(result) -> dict:
    """The ``--report`` JSON: per-layer arrays and the run's figures (see README for the keys)."""
    meta = result.meta
    return {
        **{k: v for k, v in meta.items() if k not in ("params",)},
        "params": meta.get("params", {}),
        "z": result.z.tolist(),
        "thickness": result.thickness.tolist(),
        "area_mm2": result.area.tolist(),
        "points": result.points_per_layer.tolist(),
        "loops_per_layer": result.loops_per_layer.tolist(),
        "open_chains_per_layer": result.open_chains_per_layer.tolist(),
        "repairs_per_layer": {k: v.tolist() for k, v in result.repairs.items()},
        "volume_mm3": result.volume,
    }


@click.command(name="slice")
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@with_options(slicing_options())
@click.option("-o", "--output", type=click.Path(path_type=str), default=None,
              help=f"Write the layers; the suffix picks the format ({_formats_help()}).")
@click.option("--format", "fmt_name", type=click.Choice(format_names()), default=None,
              help="The output format (default: -o's suffix picks it); with -o, for a suffix that no format "
                   "owns (--format svg -o part.txt; -o part.npz stays NPZ).")
@click.option("--report", type=click.Path(path_type=str), default=None, help="Write the run report as JSON.")
@click.option("-q", "--quiet", is_flag=True, help="No summary on stdout.")
def slice_cmd(model: str, output: str | None, fmt_name: str | None, report: str | None, quiet: bool, **kw) -> None:
    """Slice MODEL into layers of closed, nested contours."""
    from ..formats import format_for
    from ..io.atomic import committed_together
    from ..io.report import write_report
    from ..pipeline import Job, run_job

    refuse_model_as_output(model, output, report)  # (first: a write-protected model is the model, not a permission)
    check_output_file(output, report)  # a folder that is missing: refused now, not after the slicing ("out/": a folder)
    if output is not None:
        format_for(output, fmt_name)  # an unknown suffix fails before any work
    elif fmt_name is not None:
        fail(f"--format {fmt_name} needs -o, the file to write")
    check_distinct_outputs(output, report)
    params, placement = slicing_values(kw)
    with committed_together():  # the layers and the report renamed into place together, or neither
        done = run_job(Job(source=model, placement=placement, params=params, contours=output,
                           contours_format=fmt_name, cusp=report is not None))
        if report is not None:
            write_report(build_report(done.result), report)
    if (far := far_warning(model, done.mesh)) is not None:
        warn(far)
    meta = done.result.meta
    if not quiet:
        for line in adaptive_lines(meta):
            click.echo(line)
        click.echo(
            f"{Path(model).name}: {meta['facets']} facets, {meta['layers']} layers, {meta['segments']} segments, "
            f"{meta['loops']} loops, {meta['points']} points, {meta['open_chains']} open chains"
        )
        repairs = {k: v for k, v in meta["repairs"].items() if v}
        click.echo("repairs: " + (", ".join(f"{k} {v}" for k, v in repairs.items()) if repairs else "none"))
        click.echo("times (ms): " + ", ".join(f"{k} {1000 * v:.1f}" for k, v in done.timings.items()))
        click.echo(f"device: {meta['device']}")
        if output:
            click.echo(f"wrote {output}")
