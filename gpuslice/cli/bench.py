"""``gpuslice bench`` (timings and quality of uniform and adaptive settings side by side) and ``gpuslice plot``
(the paper's figures), imported only when one of them runs. The model is loaded by the pipeline's own stages
(:func:`gpuslice.pipeline.prepare_device`, :func:`~gpuslice.pipeline.load_job_mesh`); each setting is then sliced
by :func:`gpuslice.slicing.slicer.slice_mesh`, the slicing stages the bench times."""

from __future__ import annotations

import contextlib
import json
import math
from pathlib import Path

import click

from ..mesh.mesh import Placement
from ..schedule.validate import MIN_LAYER_MM
from ..slicing.params import SliceParams
from .options import build, click_options, fail, values, with_options

#: the most runs per setting `bench --repeat` takes
MAX_REPEAT = 1000

__all__ = ["bench", "plot"]

#: the SliceParams fields bench and plot take as they are (thicknesses and adaptive modes are lists here)
_SHARED = ("backend", "device", "max_cusp", "max_area", "min_height", "max_height", "smooth", "roi_ladder",
           "roi_threshold", "roi_quantile", "roi_windows")

_common = [
    click.option("-t", "--thickness", "thicknesses", default=None, help="Uniform thicknesses, mm: 0.1,0.2,0.3."),
    click.option("--adaptive", "modes", default=None, help="Adaptive modes to add: roi,cusp,area."),
    *click_options(Placement),
    *click_options(SliceParams, only=_SHARED),
]


def _refuse_unused(settings) -> None:
    """A one-line error for an adaptive option given on the command line that no setting of the run uses
    (``--max-cusp`` without ``--adaptive cusp``), as ``slice`` refuses it: its value would only sit in the output."""
    from click.core import ParameterSource

    ctx = click.get_current_context()
    modes = {s.overrides.get("adaptive") for s in settings}
    for name, for_modes in SliceParams.FOR_MODES.items():
        if name in _SHARED and ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT) and \
                not modes & set(for_modes):
            need = " or ".join(f"--adaptive {m}" for m in for_modes)
            fail(f"--{name.replace('_', '-')} shapes {' or '.join(for_modes)} layers, which no setting of this run "
                 f"makes: add {need}, or leave it out")


def _setup(model, thicknesses, modes, kw):
    from ..bench.runner import parse_settings
    from ..pipeline import Job, load_job_mesh, prepare_device

    settings = parse_settings(thicknesses, modes)
    _refuse_unused(settings)
    params = SliceParams(**values(SliceParams, kw))
    job = Job(source=model, placement=build(Placement, kw), params=params)
    load_times: dict[str, float] = {}
    dev = prepare_device(params, timings=load_times)
    mesh = load_job_mesh(job, dev, load_times)
    _refuse_no_layers(model, mesh, [s.overrides.get("thickness") for s in settings])
    return settings, params, mesh, load_times


def _refuse_no_layers(model: str, mesh, thicknesses, flag: str = "-t") -> None:
    """A one-line error naming ``model`` and ``flag`` when it is flat, or when one of the uniform ``thicknesses``
    (mm; None entries skipped) cuts it nowhere: its first plane, at half a layer, lies above the top."""
    from ..schedule.uniform import uniform

    if mesh.height <= 0:
        fail(f"{model}: the model is flat (0 mm tall): no layers to slice")
    for t in thicknesses:
        if t is not None and len(uniform(mesh.height, t)) == 0:
            fail(f"{model}: {flag} {t:g} mm gives no layers: the model is only {mesh.height:g} mm tall")


def _fmt(v, digits=4):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def _table(res) -> None:
    from rich.console import Console
    from rich.table import Table

    ctx = res.context
    t = Table(title=f"{Path(ctx['model']).name}: {ctx['facets']} facets, {ctx['height_mm']:.4g} mm tall, "
                    f"median of {ctx['repeat']} runs (load {_fmt(ctx['load_s'])} s + weld {_fmt(ctx['topology_s'])} s"
                    f" not included)")
    cols = [("setting", "setting"), ("layers", "layers"), ("total_s", "total s"), ("schedule_s", "schedule"),
            ("crossings_s", "crossings"), ("chaining_s", "chaining"), ("nesting_s", "nesting"), ("points", "points"),
            ("max_cusp_mm", "max cusp mm"), ("mean_cusp_mm", "mean cusp mm"),
            ("volume_deviation_pct", "vol dev %")]
    for _, head in cols:
        t.add_column(head, justify="left" if head == "setting" else "right")
    for r in res.rows:
        t.add_row(*[_fmt(r.get(k)) for k, _ in cols])
    Console(width=max(Console().width, 160)).print(t)
    ref = ctx.get("reference_thickness_mm")
    click.echo(f"device: {ctx['device']}; volume deviation against a uniform {_fmt(ref)} mm reference"
               if ref else f"device: {ctx['device']}")
    finer = [r["setting"] for r in res.rows if ref and r.get("thickness_min_mm") is not None
             and r["thickness_min_mm"] < ref - 1e-12]
    if finer:  # (the default reference is at most 20,000 layers: a tall part's is coarser than fine settings)
        click.echo(f"note: the {_fmt(ref)} mm reference is coarser than the thinnest layers of "
                   f"{'setting' if len(finer) == 1 else 'settings'} {', '.join(finer)}, whose vol dev it cannot "
                   "judge (give a finer --ref-thickness)")
    for r in res.rows:
        for lv in r.get("roi_windows", []):
            wins = ", ".join(f"z {a:.4g}..{b:.4g} mm" for a, b in lv["windows_mm"]) or "none"
            click.echo(f"{r['setting']}: level {lv['level']} ({lv['thickness_mm']:g} mm) window {wins}")



@contextlib.contextmanager
def _plots_into(path: str):
    """Make the plot directory (:func:`_make_dir`) and write the plots in the block as one set: renamed into place
    together at its end, or none of them (a full disk halfway left part of a set, old and new plots mixed); a
    directory this command made is removed again when the block fails."""
    from ..io.atomic import committed_together

    made = not Path(path).exists()
    _make_dir(path)
    try:
        with committed_together():
            yield
    except BaseException:
        if made:
            with contextlib.suppress(OSError):
                Path(path).rmdir()  # (only when empty)
        raise


def _make_dir(path: str, create: bool = True) -> None:
    """Create the plot directory (as ``mkdir -p`` of one level); its parent must exist. ``create=False`` only checks
    (before the work, so that a failed run leaves no empty directory)."""
    d = Path(path)
    if d.exists() and not d.is_dir():
        fail(f"{d}: exists and is not a directory")
    if not d.parent.is_dir():
        fail(f"{d}: directory {d.parent} does not exist")
    if create:
        d.mkdir(exist_ok=True)

@click.command()
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@with_options(_common)
@click.option("--repeat", type=int, default=3, show_default=True, help="Runs per setting; the table shows medians.")
@click.option("--no-quality", is_flag=True, help="Skip the volume deviation (cusp heights are always given).")
@click.option("--ref-thickness", type=float, default=None,
              help="Reference thickness for the volume deviation, mm (default: the thinnest layer / 5, at least "
                   "the model's height / 20000).")
@click.option("--json", "as_json", is_flag=True, help="Print the table as JSON.")
@click.option("--csv", "as_csv", is_flag=True, help="Print the table as CSV.")
@click.option("--plots", "plots_dir", type=click.Path(path_type=str), default=None,
              help="Also write the plots (PNG and SVG) into this directory.")
def bench(model, thicknesses, modes, repeat, no_quality, ref_thickness, as_json, as_csv, plots_dir, **kw) -> None:
    """Time and compare layer settings on MODEL: the paper's Tables 2-3 as one table (medians of --repeat runs)."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from ..bench.runner import run_bench

    if as_json and as_csv:
        fail("--json and --csv exclude each other")
    if not 1 <= repeat <= MAX_REPEAT:  # (99999999999 ran until it was killed)
        fail(f"--repeat must be from 1 to {MAX_REPEAT}, got {repeat}")
    if ref_thickness is not None and not (math.isfinite(ref_thickness) and ref_thickness >= MIN_LAYER_MM):
        fail(f"--ref-thickness must be a positive number of mm (at least {MIN_LAYER_MM:g}), got {ref_thickness}")
    if ref_thickness is not None and no_quality:
        fail("--ref-thickness is the volume deviation's reference, which --no-quality skips: leave one out")
    if plots_dir is not None:
        _make_dir(plots_dir, create=False)
    settings, params, mesh, load_times = _setup(model, thicknesses, modes, kw)
    if not no_quality:
        _refuse_no_layers(model, mesh, [ref_thickness], "--ref-thickness")
    console = Console(stderr=True)
    steps = 1 + len(settings) * repeat + (0 if no_quality else len(settings))
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), console=console, transient=True, disable=not console.is_terminal) as bar:
        task = bar.add_task("bench", total=steps)
        res = run_bench(mesh, settings, params, repeat=repeat, quality=not no_quality, ref_thickness=ref_thickness,
                        load_times=load_times,
                        progress=lambda desc, adv=1: bar.update(task, advance=adv, description=desc))
    if as_json:
        click.echo(json.dumps(res.to_json(), indent=1))
    elif as_csv:
        click.echo(res.to_csv(), nl=False)
    else:
        _table(res)
    if plots_dir is not None:
        from ..bench.plots import plot_all

        with _plots_into(plots_dir):
            paths = plot_all(res.results, plots_dir, Path(model).stem)
        click.echo(f"wrote {len(paths)} plot files to {plots_dir}", err=as_json or as_csv)


@click.command()
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@with_options(_common)
@click.option("-o", "--out", "out_dir", type=click.Path(path_type=str), required=True,
              help="Directory for the PNG and SVG files.")
@click.option("--layers", default=None, help="Layer indices to draw (of the first setting), e.g. 39,159.")
def plot(model, thicknesses, modes, out_dir, layers, **kw) -> None:
    """Plot MODEL's slices: points per layer (Fig. 6/11), layer contours and points (Fig. 5/10), 3D stacks (Fig. 8)."""
    from dataclasses import replace

    from ..bench.plots import default_layers, plot_all, plot_layers
    from ..slicing.slicer import slice_mesh

    _make_dir(out_dir, create=False)
    try:  # (checked before any work, the range once the first setting is sliced: before any file is written)
        idx = [int(x) for x in (layers or "").split(",") if x.strip()]
    except ValueError:
        fail(f"--layers: expected comma-separated layer indices, got '{layers}'")
    settings, params, mesh, _ = _setup(model, thicknesses, modes, kw)
    results = {s.label: slice_mesh(mesh, replace(params, **s.overrides)) for s in settings}
    first = next(iter(results.values()))
    bad = [i for i in idx if not 0 <= i < first.n_layers]
    if bad:
        fail(f"--layers: {bad} out of range (0..{first.n_layers - 1})")
    name = Path(model).stem
    with _plots_into(out_dir):
        paths = plot_all(results, out_dir, name)
        if layers:
            paths += plot_layers(first, idx or default_layers(first), Path(out_dir) / f"{name}_layers_chosen")
    for lv in (r.meta.get("adaptive") or {} for r in results.values()):
        for x in lv.get("levels", []):
            wins = ", ".join(f"z {w['z_mm'][0]:.4g}..{w['z_mm'][1]:.4g} mm" for w in x["windows"]) or "none"
            click.echo(f"roi level {x['level']} ({x['thickness_mm']:g} mm): window {wins}")
    click.echo(f"wrote {len(paths)} files to {out_dir}")
