"""The ``gpuslice`` command line: ``info``, ``slice``, ``devices``, ``shape`` here; ``raster``, ``bench``, ``plot``,
``batch`` and ``view`` in their own ``cli_*.py`` modules, imported only when that command runs (start-up stays short).

Results go to stdout (or files), progress and errors to stderr. A user error (bad file, bad option) prints one line
``gpuslice: error: <file>: <problem>`` and exits with status 2; Ctrl-C exits with 130. Outputs are written under a
temporary name and renamed when complete, so an interrupted run leaves no partial file. ``--debug`` shows
tracebacks.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import click

from .. import __version__
from ..errors import GpusliceError

__all__ = ["main", "cli"]

EXIT_USAGE = 2


def _fail(message: str, code: int = EXIT_USAGE) -> None:
    click.echo(f"gpuslice: error: {message}", err=True)
    raise SystemExit(code)


def _load(path: str, scale: float | None, fit: float | None, device=None):
    from ..io.meshfile import read_mesh_file
    from ..mesh.mesh import mesh_from_triangles

    t0 = time.perf_counter()
    raw = read_mesh_file(path)
    t1 = time.perf_counter()
    mesh = mesh_from_triangles(
        raw.triangles, raw.normals, scale=scale, fit=fit, name=str(path), source_format=raw.source_format,
        solids=raw.solids, device=device,
    )
    t2 = time.perf_counter()
    return mesh, {"load": t1 - t0, "topology": t2 - t1}


# command name -> "module:attribute", imported on first use
LAZY_COMMANDS = {
    "raster": "gpuslice.cli.raster:raster",
    "bench": "gpuslice.cli.bench:bench",
    "plot": "gpuslice.cli.bench:plot",
    "batch": "gpuslice.cli.batch:batch",
    "view": "gpuslice.cli.view:view",
}


class LazyGroup(click.Group):
    """A click group whose heavier commands live in their own modules and are imported when used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(LAZY_COMMANDS))


    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in LAZY_COMMANDS and cmd_name not in self.commands:
            import importlib

            module, attr = LAZY_COMMANDS[cmd_name].split(":")
            try:
                mod = importlib.import_module(module)
            except ModuleNotFoundError as exc:
                if exc.name != module:  # a missing dependency inside the module: say so
                    raise
                return None
            self.add_command(getattr(mod, attr), cmd_name)
        return super().get_command(ctx, cmd_name)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, message=f"gpuslice %(version)s (Python {sys.version.split()[0]})")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """Slice triangle meshes (STL) into closed, nested layer contours on any OpenCL device."""
    ctx.obj = {"debug": debug}


_mesh_options = [
    click.option("--scale", type=float, default=None, help="Multiply coordinates by this factor (to mm)."),
    click.option("--fit", type=float, default=None, help="Scale so the longest side is this many mm."),
]


def fail(message: str, code: int = EXIT_USAGE) -> None:
    """Print ``gpuslice: error: <message>`` on stderr and exit with ``code`` (2: user error)."""
    _fail(message, code)


def load_model(path: str, scale: float | None, fit: float | None, backend: str = "opencl", device: str | None = None):
    """The device, then the mesh: for ``backend="opencl"`` the OpenCL device ``device`` is chosen and its kernels
    built first (the mesh is welded on it too); then ``path`` is read and welded (scaled, on the bed).

    Returns ``(Mesh, Device or None, {"device": s, "load": s, "topology": s})``.
    """
    dev, t_dev = None, 0.0
    if backend == "opencl":
        from ..device import get_device

        t = time.perf_counter()
        dev = get_device(device)
        dev.program("crossings.cl")  # builds every kernels/*.cl (one program)
        t_dev = time.perf_counter() - t
    mesh, times = _load(path, scale, fit, dev)
    return mesh, dev, {"device": t_dev, **times}


mesh_options = _mesh_options


def _with(options):
    def deco(f):
        for opt in reversed(options):
            f = opt(f)
        return f

    return deco


with_options = _with


def slicing_options(thickness: float = 0.1, *, defaults: bool = True) -> list:
    """The slicing options shared by ``slice``, ``raster``, ``view`` and ``batch`` (decorators, for ``with_options``):
    ``-t/--thickness`` (mm, default ``thickness``), ``--first-layer``, ``--z-mode``, ``--scale``/``--fit``,
    ``--fill-rule``, ``--max-gap``, ``--backend``, ``--device``. ``defaults=False`` leaves every value None unless
    given (for a command that must tell whether the user gave one), the defaults being named in the help instead."""

    def opt(*names, default, help, **kw):
        if defaults:
            return click.option(*names, default=default, show_default=default is not None, help=help, **kw)
        shown = f" (default {default})" if default is not None else ""
        return click.option(*names, default=None, help=help + shown, **kw)

    return [
        opt("-t", "--thickness", type=float, default=thickness, help="Layer thickness, mm."),
        opt("--first-layer", type=float, default=None, help="First layer thickness, mm (default: -t)."),
        opt("--z-mode", type=click.Choice(["mid", "paper"]), default="mid",
            help="mid: cut at the middle of each layer, z=(i+0.5)h; paper: Z_i = i*h."),
        *_mesh_options,
        opt("--fill-rule", type=click.Choice(["nonzero", "evenodd", "positive"]), default="nonzero",
            help="Which loops bound material."),
        opt("--max-gap", type=float, default=2.0,
            help="Join open chain ends closer than this, mm (0: never); chains left open are not filled."),
        opt("--backend", type=click.Choice(["opencl", "numpy"]), default="opencl",
            help="The OpenCL kernels, or their numpy reference twins."),
        opt("--device", default=None, help="OpenCL device: 'P:D' index or a name piece (env GPUSLICE_DEVICE)."),
    ]

# ---- adaptive schedules (issue 4; gpuslice/adaptive.py): options shared by `slice`, `bench` and `plot` ----------
adaptive_options = [
    click.option("--adaptive", type=click.Choice(["roi", "cusp", "area"]), default=None,
                 help="Adaptive layers: roi (the paper's ladder), cusp (t*|n_z| <= --max-cusp), area (error area)."),
    click.option("--max-cusp", type=float, default=0.05, show_default=True, help="cusp: largest cusp height, mm."),
    click.option("--max-area", type=float, default=0.0025, show_default=True,
                 help="area: largest staircase error area per mm of surface, mm^2."),
    click.option("--min-height", type=float, default=0.05, show_default=True, help="cusp/area: thinnest layer, mm."),
    click.option("--max-height", type=float, default=0.3, show_default=True, help="cusp/area: thickest layer, mm."),
    click.option("--smooth", type=float, default=0.0, show_default=True,
                 help="cusp/area: thickness may change by at most this many mm per mm of height (0: off)."),
    click.option("--roi-ladder", default="1,0.5,0.1", show_default=True, help="roi: thicknesses, coarse to fine, mm."),
    click.option("--roi-threshold", default=None,
                 help="roi: points per layer marking the region of interest (one value, or one per step)."),
    click.option("--roi-quantile", type=float, default=0.75, show_default=True,
                 help="roi: without --roi-threshold, this quantile of each level's points per layer."),
    click.option("--roi-windows", type=int, default=1, show_default=True, help="roi: windows kept per level (0: all)."),
]


def _floats(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        _fail(f"{option}: expected comma-separated numbers, got '{text}'")
        raise  # unreachable


def adaptive_params(kw: dict) -> dict:
    """SliceParams fields from the ``adaptive_options`` values."""
    return {
        "adaptive": kw["adaptive"], "max_cusp": kw["max_cusp"], "max_area": kw["max_area"],
        "min_height": kw["min_height"], "max_height": kw["max_height"], "smooth": kw["smooth"],
        "roi_ladder": _floats(kw["roi_ladder"], "--roi-ladder"),
        "roi_threshold": _floats(kw["roi_threshold"], "--roi-threshold") if kw["roi_threshold"] else None,
        "roi_quantile": kw["roi_quantile"], "roi_windows": kw["roi_windows"],
    }


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


@cli.command()
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@_with(_mesh_options)
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def info(model: str, scale: float | None, fit: float | None, as_json: bool) -> None:
    """Facets, unique vertices, distinct normals, bbox, watertight, bodies and volume of MODEL (after scaling)."""
    mesh, _ = _load(model, scale, fit)
    data = mesh.info()
    if as_json:
        click.echo(json.dumps(data, indent=1))
        return
    for key, value in data.items():
        if isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, list):
            value = " ".join(f"{v:.6g}" for v in value)
        click.echo(f"{key:24s} {value}")


@cli.command(name="slice")
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@_with(slicing_options())
@click.option("-o", "--output", type=click.Path(path_type=str), default=None,
              help="Write the layers: .npz, .svg or .cli.")
@click.option("--report", type=click.Path(path_type=str), default=None, help="Write the run report as JSON.")
@click.option("-q", "--quiet", is_flag=True, help="No summary on stdout.")
@_with(adaptive_options)
def slice_cmd(model, thickness, first_layer, z_mode, scale, fit, fill_rule, max_gap, backend, device, output,
              report, quiet, **adaptive) -> None:
    """Slice MODEL into layers of closed, nested contours."""
    from ..formats import export
    from ..io.report import write_report
    from ..mesh.defects import mesh_repairs
    from ..slicing.slicer import SliceParams, slice_mesh

    if output is not None and Path(output).suffix.lower() not in (".npz", ".svg", ".cli"):
        _fail(f"{output}: unknown output format '{Path(output).suffix}' (use .npz, .svg or .cli)")
    params = SliceParams(thickness=thickness, first_layer=first_layer, z_mode=z_mode, fill_rule=fill_rule,
                         max_gap=max_gap, backend=backend, device=device, **adaptive_params(adaptive))
    mesh, dev, load_times = load_model(model, scale, fit, backend, device)
    t_dev = load_times.pop("device")
    result = slice_mesh(mesh, params)
    t = time.perf_counter()  # what the mesh needed: flipped facets, non-manifold edges, ... (defects.py), first
    result.meta["repairs"] = {**mesh_repairs(mesh), **result.meta["repairs"]}
    load_times["mesh_check"] = time.perf_counter() - t
    timings = {**load_times, **result.meta["timings_s"]}
    timings["device"] = timings.get("device", 0.0) + t_dev
    if output is not None:
        t = time.perf_counter()
        export(result, output)
        timings["export"] = time.perf_counter() - t
    result.meta["timings_s"] = timings
    meta = result.meta
    if report is not None:  # the schedule's cusp heights (quality.py), in every report
        from ..bench.quality import cusp_summary

        t = time.perf_counter()
        result.meta.update(cusp_summary(mesh, result, dev))
        timings["cusp"] = time.perf_counter() - t
        write_report(build_report(result), report)
    if not quiet:
        for line in adaptive_lines(meta):
            click.echo(line)
        click.echo(
            f"{Path(model).name}: {meta['facets']} facets, {meta['layers']} layers, {meta['segments']} segments, "
            f"{meta['loops']} loops, {meta['points']} points, {meta['open_chains']} open chains"
        )
        repairs = {k: v for k, v in meta["repairs"].items() if v}
        click.echo("repairs: " + (", ".join(f"{k} {v}" for k, v in repairs.items()) if repairs else "none"))
        click.echo("times (ms): " + ", ".join(f"{k} {1000 * v:.1f}" for k, v in timings.items()))
        click.echo(f"device: {meta['device']}")
        if output:
            click.echo(f"wrote {output}")


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


@cli.command()
@click.argument("name", type=click.Choice(sorted(__import__("gpuslice.mesh.shapes").mesh.shapes.SHAPES)))
@click.option("-o", "--output", type=click.Path(path_type=str), required=True, help="Binary STL to write.")
def shape(name: str, output: str) -> None:
    """Write a built-in test solid NAME (mm, closed, outward-wound) as a binary STL, e.g. for a first run."""
    from ..mesh.shapes import SHAPES, write_stl

    tri = SHAPES[name]()
    write_stl(tri, output, header=f"gpuslice shape {name}".encode())
    click.echo(f"wrote {output}: {name}, {len(tri)} facets")


@cli.command()
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
@click.option("--device", default=None, help="Show which device this spec selects.")
def devices(as_json: bool, device: str | None) -> None:
    """List OpenCL platforms and devices, and which one gpuslice uses."""
    from ..device import list_devices, resolve

    found = list_devices()
    chosen = resolve(device)["id"] if found else None
    if as_json:
        click.echo(json.dumps({"devices": found, "selected": chosen}, indent=1))
        return
    for d in found:
        mark = "*" if d["id"] == chosen else " "
        click.echo(f"{mark} {d['id']}  {d['platform']} | {d['device']} | {d['type']} | {d['compute_units']} CU | "
                   f"{d['global_mem_mib']} MiB | {d['platform_version']}")
    if not found:
        _fail("no OpenCL device found (pip install pocl-binary-distribution)")
    click.echo("(* = used by default; override with --device or GPUSLICE_DEVICE)")


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 ok, 2 user error, 130 interrupted)."""
    args = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in args
    try:
        cli.main(args=args, prog_name="gpuslice", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("gpuslice: interrupted", err=True)
        return 130
    except click.ClickException as exc:
        click.echo(f"gpuslice: error: {exc.format_message()}", err=True)
        return EXIT_USAGE
    except GpusliceError as exc:
        if debug:
            raise
        click.echo(f"gpuslice: error: {exc}", err=True)
        return EXIT_USAGE
    except KeyboardInterrupt:
        click.echo("gpuslice: interrupted", err=True)
        return 130
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else 1
    except MemoryError:
        click.echo("gpuslice: error: out of memory", err=True)
        return 1
    except OSError as exc:  # an output that cannot be written (disk full, permission denied): the user's to fix
        if debug:
            raise
        reason = exc.strerror or " ".join(str(exc).split()) or type(exc).__name__
        click.echo(f"gpuslice: error: {exc.filename}: {reason}" if exc.filename else f"gpuslice: error: {reason}",
                   err=True)
        return EXIT_USAGE
    except Exception as exc:  # never a traceback for users; --debug shows it
        if debug:
            raise
        message = " ".join(str(exc).split())  # one line
        click.echo(f"gpuslice: internal error: {type(exc).__name__}: {message} (run with --debug)", err=True)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
