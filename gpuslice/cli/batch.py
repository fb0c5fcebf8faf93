"""``gpuslice batch``: slice many models with the same options, on local worker processes or a Dask cluster.

The engine is :mod:`gpuslice.batch`; this module only parses options, shows progress and prints the summary.
Exit status: 0 when every model is done or skipped, 1 when some model failed (the others are still done; the
failures are listed), 2 when the batch cannot start (no models, bad options, an unreachable scheduler), 130 on
Ctrl-C (workers stopped, no partial output left, the report written with the unfinished models as "not run").
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from ..batch.options import BatchOptions, check_path
from ..errors import flatten
from .options import (
    RESIN_DEFAULTS,
    build,
    check_output_file,
    check_output_place,
    check_resin_layers,
    check_writable,
    click_options,
    fail,
    slicing_options,
    slicing_values,
    warn,
    with_options,
)

__all__ = ["batch"]


def _raster_options(pairs: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    """``KEY=VALUE`` texts as (key, text) pairs: :class:`~gpuslice.batch.options.BatchOptions` types them by their
    option fields (and records the text in the output folder's manifest, as given)."""
    out = []
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            fail(f"--raster-opt {pair!r}: expected KEY=VALUE")
        out.append((key.strip().replace("-", "_"), value.strip()))
    return tuple(out)


def _batch_options(kw: dict, raster_opt: tuple[str, ...]):
    """The :class:`BatchOptions`; a resin option's error names it as ``--raster-opt KEY`` (batch has no such flag)."""
    from ..batch.options import raster_option_fields
    from ..errors import ParameterError

    overrides = None
    if kw["raster"] is not None and _default("thickness"):  # resin layers: `raster`'s own default thickness
        kw["thickness"], overrides = None, RESIN_DEFAULTS
    params, placement = slicing_values(kw, overrides)
    try:
        return build(BatchOptions, kw, params=params, placement=placement,
                     raster_options=_raster_options(raster_opt) if kw["raster"] is not None else ())
    except ParameterError as exc:
        resin = [p for p in exc.params if p in raster_option_fields()]
        if not resin:
            raise
        text = str(exc)
        for name in resin:
            text = text.replace(name, f"--raster-opt {name}", 1)
        raise ParameterError(text, param=tuple(p for p in exc.params if p not in resin)) from None


def _default(name: str) -> bool:
    """Whether the running command's option ``name`` was left at its default (False outside a command)."""
    from click.core import ParameterSource

    ctx = click.get_current_context(silent=True)
    return ctx is not None and ctx.get_parameter_source(name) == ParameterSource.DEFAULT


class _Progress:
    """A rich progress bar on stderr when it is a terminal; otherwise one line per failed model."""

    def __init__(self, total: int, quiet: bool) -> None:
        self.bar = None
        self.quiet = quiet
        if not quiet and sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(TextColumn("slicing"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(),
                                TextColumn("{task.description}"), console=Console(stderr=True), transient=True)
            self.task = self.bar.add_task("", total=total)

    def __enter__(self):
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.stop()

    def __call__(self, rec: dict) -> None:
        if rec["status"] == "failed":  # (-q hides the bar and the table, not a model's failure)
            line = f"gpuslice: failed: {flatten(rec['error'])}"  # (a file name's control characters: escaped)
            if self.bar is not None:
                self.bar.console.print(line, markup=False, highlight=False)
            else:
                click.echo(line, err=True)
        if self.bar is not None:
            self.bar.update(self.task, advance=1, description=flatten(rec["model"])[-40:])


@click.command()
@click.argument("inputs", nargs=-1, required=True, type=click.Path(path_type=str))
@click.option("-o", "--output", "out_dir", type=click.Path(path_type=str), required=True,
              help="Output folder; it mirrors the input tree, one result per model.")
@with_options(slicing_options())
@with_options(click_options(BatchOptions, only=("fmt",)))
@click.option("--glob", "pattern", default=None,
              help="In folders, the models to take, e.g. '**/*.stl' (case-insensitive; default: every .stl .3mf "
                   ".obj .ply .off).")
@with_options(click_options(BatchOptions, only=("raster",)))
@with_options(click_options(BatchOptions, only=("check",)))
@click.option("--raster-opt", "raster_opt", multiple=True, metavar="KEY=VALUE",
              help="A resin option (a `gpuslice raster` option's name), e.g. pixel=0.05, resolution=3840x2400, "
                   "printer=generic-4k (repeatable).")
@click.option("-j", "--workers", type=int, default=None,
              help="Local worker processes (0: in this process). Default: one per core, PoCL threads shared out.")
@click.option("--threads", type=int, default=None, help="PoCL threads per local worker (default: cores // workers).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run on an existing Dask cluster, e.g. tcp://HOST:8786 (needs gpuslice[batch] there and here).")
@click.option("--transfer", type=click.Choice(["bytes", "shared"]), default=None,
              help="With --scheduler: 'bytes' sends model bytes to the workers and writes their outputs here "
                   "(default); 'shared' lets workers read and write the paths (a shared file system).")
@click.option("--force", is_flag=True, help="Redo models whose output exists; allow other options in OUT.")
@click.option("--report", type=click.Path(path_type=str), default=None,
              help="Write the batch report (per model status, facets, layers, timings, error) as JSON.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar and no summary table (failures are still said).")
def batch(inputs, out_dir, pattern, raster_opt, workers, threads, scheduler, transfer, force, report, quiet,
          **kw) -> None:
    """Slice every model in INPUTS (folders, searched recursively; list files of paths, .txt/.list/.lst; model files)
    with the same options (those of `slice`, adaptive layers included) into OUT, on local workers or a Dask
    cluster. Models whose output exists are skipped. With --raster, layers are 0.05 mm unless -t is given (as
    `gpuslice raster`), and each model's resin file is the one `raster` writes with the same options."""
    from ..batch import BatchRunner, discover, format_summary
    from ..io.report import write_report

    if workers is not None and workers < 0:
        fail(f"--workers must be >= 0, got {workers}")
    if threads is not None and threads < 1:
        fail(f"--threads must be >= 1, got {threads}")
    if transfer is not None and scheduler is None:
        fail("--transfer only applies with --scheduler")
    if kw["raster"] is None and raster_opt:
        fail("--raster-opt needs --raster")
    if kw["raster"] is not None and click.get_current_context().get_parameter_source("fmt") in (
            click.core.ParameterSource.COMMANDLINE, click.core.ParameterSource.ENVIRONMENT):
        fail(f"--format and --raster: each model gets one output, its --raster {kw['raster']} archive (--format "
             "names a contour format)")
    check_output_file(report, creates=out_dir)  # refused now, not after every model is done
    check_output_place(out_dir)
    if Path(out_dir).is_dir():  # (its outputs are written inside it)
        check_writable(out_dir, out_dir)
    opts = _batch_options(kw, raster_opt)
    if opts.raster is not None:
        from ..raster.outputs import source_date

        source_date()  # a bad SOURCE_DATE_EPOCH is an error now, not in every model
        check_resin_layers(opts.params)
        opts.resin()  # the resin options checked now (a job name with '/', ...), not in every model
    models = discover(inputs, pattern, opts.suffix, out_dir)
    if report is not None:
        _check_report_clear(report, inputs, models, out_dir)
    client = None
    if scheduler is not None:
        from ..batch import connect

        client = connect(scheduler)
    runner = None
    try:
        with _Progress(len(models), quiet) as progress:
            runner = BatchRunner(models, opts, out_dir, force=force, progress=progress, inputs=inputs)
            result = runner.run(workers, threads=threads, client=client, transfer=transfer or "bytes")
    except KeyboardInterrupt as exc:
        if runner is not None and report is not None:
            write_report(runner.report(), report)
        if runner is not None:
            s = runner.report()["summary"]
            signum = getattr(exc, "signum", None)  # (SIGTERM, SIGHUP: cli.main.Terminated)
            why = "interrupted" if signum is None else str(exc)
            click.echo(f"gpuslice: {why}: {s['done']} done, {s['not_run']} not run", err=True)
            raise SystemExit(130 if signum is None else 128 + signum) from None  # said once, with the counts
        raise
    finally:
        if client is not None:
            client.close()
    if report is not None:
        write_report(result, report)
    for line in _resin_warnings(opts, out_dir) if result["summary"]["done"] else ():
        warn(line)  # (as `raster` says them, once for the batch, once its outputs are in place)
    if not quiet:
        click.echo(format_summary(result))
        if report is not None:
            click.echo(f"wrote {report}")
    if result["summary"]["failed"]:
        raise SystemExit(1)


def _resin_warnings(opts, out_dir: str) -> list[str]:
    """`raster`'s warnings about the batch's resin options (no printer named, a preset without exposures), which
    hold for every model's archive alike."""
    if opts.raster is None:
        return []
    from ..raster.outputs import RESIN_FORMATS
    from .raster import _generic_exposure, _no_printer

    spec, ropts, settings = opts.resin()
    fmt, what = RESIN_FORMATS[opts.raster], f"each {opts.raster} file in {out_dir}"
    found = (_no_printer(ropts, fmt, spec, settings, what),
             _generic_exposure(ropts, dict(opts.raster_options), fmt, what))
    return [w for w in found if w]


def _check_report_clear(report: str, inputs, models, out_dir: str) -> None:
    """A one-line error, before any model, when ``--report`` names an input (a model, a list file) or a model's
    output (or a path inside a PNG stack's folder): the report written at the end would replace it."""
    import os

    real = os.path.realpath
    rep, root = real(report), real(os.fspath(out_dir))
    if rep == root:
        fail(f"{report}: --report names the output folder; name a file")
    given = {real(os.fspath(x)) for x in inputs if os.path.isfile(os.fspath(x))}  # model and list files named
    if rep in given or any(rep == m.path for m in models):  # (a model's path is resolved by discover)
        fail(f"{report}: --report names an input of the batch; name another file")
    if os.path.dirname(rep) == root and os.path.basename(rep).startswith(".gpuslice-batch"):
        # (its manifest or journal: the next run then refused the folder)
        fail(f"{report}: --report names the batch's own record in {out_dir}; name another file")
    for m in models:
        out = os.path.join(root, m.out)
        if rep == out or rep.startswith(out + os.sep) or rep == os.fspath(check_path(out)):
            fail(f"{report}: --report names the output of {m.src}; name another file")
