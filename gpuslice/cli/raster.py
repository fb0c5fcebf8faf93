"""``gpuslice raster``: slice a model and write its layers as resin-printer bitmaps (one pipeline job; the output
format comes from the resin-output registry, :mod:`gpuslice.raster.outputs`)."""

from __future__ import annotations

import sys
import time
from contextlib import nullcontext
from pathlib import Path

import click

from ..raster.outputs import resin_format_names
from ..raster.settings import PrintSettings, format_duration, resin_ml
from ..raster.spec import RasterSpec, ResinOptions
from .options import (
    RESIN_DEFAULTS,
    build,
    check_distinct_outputs,
    check_output_file,
    check_output_place,
    check_resin_layers,
    click_options,
    fail,
    open_chains_warning,
    refuse_model_as_output,
    slicing_options,
    slicing_values,
    values,
    warn,
    with_options,
)

__all__ = ["raster"]


def _print_checks(model: str):
    from .check import print_report

    return lambda report: print_report(report, Path(model).name)


def _outputs_help() -> str:
    from ..raster.outputs import resin_usage

    return resin_usage()


class _Bar:
    """A rich progress bar on stderr, made at the first layer (when the layer count is known)."""

    def __init__(self, label: str, show: bool | None) -> None:
        self.label, self.show, self.bar = label, show, None

    def __call__(self, k: int, n: int) -> None:
        if self.bar is None:
            if not (self.show if self.show is not None else (sys.stderr.isatty() or n >= 1000)):
                self.show = False
                return
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

            self.bar = Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                                TimeRemainingColumn(), console=Console(stderr=True), transient=False)
            self.task = self.bar.add_task(self.label, total=n)
            self.bar.start()
        if k % 16 == 0 or k == n:
            self.bar.update(self.task, completed=k)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()


#: the archives written without a preset for no machine in particular, which a printer's firmware may refuse (the
#: Photon Workshop suffixes name their machine; .cxdlp, .cxdlpv4, .jxs and .sl1s need a preset)
MACHINE_FORMATS = ("goo", "prz", "ctb", "sl1")


def _turned(options: ResinOptions, fmt, spec: RasterSpec, output: str) -> str | None:
    """Without ``--printer``, a file whose suffix names its machine (Photon Workshop's, the M7 zip's) is checked for
    that machine's display size only: the warning when its orientation or mirror is not the one of the preset
    natively writing that suffix (the Photon Mono X mirrors x: an unmirrored file prints mirrored), else None."""
    from ..raster.printers import PRINTERS
    from ..raster.spec import orientation_text

    if options.preset is not None or fmt.folder or fmt.name in MACHINE_FORMATS:
        return None
    match = next((p for p in PRINTERS.values() if p.native_format == fmt.name), None)
    if match is None or match.orientation == orientation_text(spec):
        return None
    return (f"{output} is written {orientation_text(spec)}, but the {match.title}'s display, which its suffix "
            f"names, is {match.orientation}: it prints mirrored or turned; give --printer {match.name}")


def _no_printer(options: ResinOptions, fmt, spec: RasterSpec, settings: PrintSettings, output: str) -> str | None:
    """The warning for a GOO, PRZ, CTB or SL1 written without ``--printer`` (:data:`MACHINE_FORMATS`): it names no
    machine and holds a generic display, which a printer's firmware may refuse; else None."""
    if options.preset is not None or fmt.name not in MACHINE_FORMATS:
        return None
    return (f"{output} names no printer (no --printer) and holds a generic {spec.png_size[0]}x{spec.png_size[1]} "
            f"display of {spec.px:g} mm pixels, bottom layers ({settings.bottom_layers}) at "
            f"{settings.bottom_exposure:g} s and {settings.exposure:g} s layers; a printer checks its machine and "
            "display: give its --printer (gpuslice printers)")


def _generic_exposure(options: ResinOptions, kw: dict, fmt, output: str) -> str | None:
    """The warning for an archive of a printer preset without the maker's exposures and no ``--exposure``, or None:
    the generic default (PrusaSlicer's SL1 material, made for its RGB display) is several times what a mono LCD
    needs; said rather than let a print overcure. A PNG stack stores no exposures: not warned."""
    preset = options.preset
    if preset is None or fmt.folder or "exposure" in preset.settings or kw.get("exposure") is not None:
        return None
    return (f"{output}: printer {preset.name}'s preset holds no exposures, so its layers get the generic "
            f"{PrintSettings().exposure:g} s (PrusaSlicer's SL1), far more than a mono LCD needs; give your resin's "
            "--exposure (and --bottom-exposure, --bottom-layers)")


@click.command()
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help=f"Where to write: {_outputs_help()}.")
@click.option("--format", "fmt_name", type=click.Choice(resin_format_names()), default=None,
              help="The output format, for an -o whose suffix names none (default: -o's suffix picks it; `png`: a PNG "
                   "stack; a suffix another format owns is refused).")
@with_options(slicing_options(overrides=RESIN_DEFAULTS))
@with_options(click_options(ResinOptions, only=("printer",)))
@with_options(click_options(RasterSpec, defaults=False, preset=True))  # None unless given: they override the preset
@with_options(click_options(ResinOptions, exclude=("printer",)))
@with_options(click_options(PrintSettings, defaults=False, preset=True))  # None unless given: they override the preset
@click.option("--progress/--no-progress", default=None, help="Progress bar on stderr [TTY or long runs].")
@click.option("--report", type=click.Path(path_type=str), default=None, help="Write timings and counts as JSON.")
@click.option("--check", is_flag=True, help="Run the pre-print checks on the printer's pixels (as `gpuslice check "
              "--printer`) and print them before writing.")
@click.option("-q", "--quiet", is_flag=True, help="No summary on stdout.")
def raster(model: str, output: str, fmt_name: str | None, progress: bool | None, report: str | None, check: bool,
           quiet: bool, **kw) -> None:
    """Slice MODEL and write its layers for a resin printer: the output's suffix picks the format (-o part.goo,
    part.ctb, part.pwmx, part.cxdlp, part.sl1, … -o's help below lists every suffix; a PNG stack: -o dir/;
    --format overrides it; `gpuslice printers` lists the presets, --printer NAME sets the display, print settings
    and the formats it reads).

    The model is centred on the display (--keep-xy keeps its XY); column j has its centre at x = (j + 0.5)*pixel
    and row 0 is the +y edge (landscape). Greys are pixel coverage with PrusaSlicer's gamma.
    """
    from ..io.atomic import committed_together
    from ..io.report import write_report
    from ..pipeline import CheckOutput, Job, ResinOutput, run_job
    from ..raster.outputs import resin_format_for

    t_start = time.perf_counter()
    fmt = resin_format_for(output, fmt_name)
    refuse_model_as_output(model, output, report)
    check_output_place(output)
    check_output_file(report, creates=output)  # (a PNG stack's folder is made by the command)
    check_distinct_outputs(output, report)
    if report is not None and fmt.folder and Path(report).resolve().is_relative_to(Path(output).resolve()):
        # (a report named as a layer replaced that layer; any other made the next run refuse the folder)
        fail(f"{report}: lies inside {output.rstrip('/')}/, which holds only the {fmt.title}'s layers: write the "
             "report beside it")
    params, placement = slicing_values(kw, RESIN_DEFAULTS)
    check_resin_layers(params)
    options = build(ResinOptions, kw)
    spec = options.spec(**values(RasterSpec, kw))
    generic = _generic_exposure(options, kw, fmt, output)  # (before values() takes the flags out of kw)
    settings = options.settings(**values(PrintSettings, kw))
    job = Job(source=model, placement=placement, params=params, mesh_check=False,
              resin=ResinOutput(output, fmt.name, spec, options, settings),
              checks=CheckOutput(spec, settings, on_report=None if quiet else _print_checks(model)) if check else None)
    procs = nullcontext()
    if fmt.png:  # PNG layers on every core: this command's entry points are safe to import in a worker process
        from ..raster.png_procs import enabled

        procs = enabled()
    bar = _Bar(f"raster {Path(output).name}", progress)
    # the archive and the report renamed into place together, or neither
    with committed_together():
        try:
            with procs:
                done = run_job(job, progress=bar)
        finally:
            bar.stop()
        timings = {**done.timings, "total": time.perf_counter() - t_start}
        stats, n = done.stats, done.result.n_layers
        # (said once the output is in place: a refused or failed job keeps its one line)
        notes = [note for note in (open_chains_warning(model, done.result, output), generic,
                                   _turned(options, fmt, spec, output),
                                   _no_printer(options, fmt, spec, settings, output)) if note]
        ml = resin_ml(done.result.area, done.result.thickness)
        # the format's own estimate where it keeps one (SL1: exposures and tilts), else the settings' (lifts, waits):
        # the one the checks state too (ResinFormat.print_time_s)
        stats.pop("print_time_s", None)
        t_print = fmt.print_time_s(settings, n)
        estimate = {"print_time_s": round(t_print, 3), "resin_ml": round(ml, 4),
                    "resin_g": round(ml * settings.resin_density, 4)}
        # the layer images' bytes whatever the format (its stats name them png_bytes, svg_bytes ... as they are)
        size = stats.get("png_bytes", stats.get("svg_bytes", 0.0))
        if report is not None:
            write_report({"layers": n, "raster_backend": stats["raster_backend"], "output": output,
                          "timings_s": timings,
                          **{k: v.to_json() if k == "checks" else v  # (--check: the check's JSON report)
                             for k, v in stats.items() if k != "raster_backend"},
                          "display": {"resolution": list(spec.resolution), "pixel": [spec.px, spec.py],
                                      "portrait": spec.portrait, "mirror_x": spec.mirror_x, "mirror_y": spec.mirror_y},
                          "repairs": done.result.meta["repairs"], "open_chains": done.result.meta["open_chains"],
                          "image_bytes": size,
                          **estimate},
                         report)
    for note in notes:
        warn(note)
    if not quiet:
        pitch = f"{spec.px:g}" if spec.py == spec.px else f"{spec.px:g} x {spec.py:g}"
        drawn = f"raster {stats['raster_backend']}" + (f" ({stats['gl_renderer']})" if "gl_renderer" in stats else "")
        click.echo(f"{Path(model).name}: {n} layers of {spec.png_size[0]}x{spec.png_size[1]} px ({pitch} mm), "
                   f"{drawn}, {size / 1e6:.1f} MB of layer images, "
                   f"{timings['total']:.2f} s; print about {format_duration(estimate['print_time_s'])} (h:mm), "
                   f"{ml:.1f} ml of resin; wrote {output}")
