"""Click options generated from the option dataclasses (:mod:`gpuslice.options`), and the way back: click's values
into those dataclasses, library errors into flags.

``click_options(SliceParams)`` makes one click option per declared field: its flags, type, choices, default and help
come from the field, never from here. ``build(SliceParams, kwargs)`` takes those fields back out of a command's
keyword arguments (parsing ``1,0.5,0.1`` or ``3840x2400``) into the dataclass, which validates them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import click

from ..errors import ParameterError
from ..options import OptionInfo, options_of

__all__ = ["click_options", "with_options", "build", "values", "flag_for", "cli_message", "fail", "EXIT_USAGE",
           "option_classes", "slicing_options", "slicing_values", "refuse_model_as_output", "RESIN_DEFAULTS",
           "check_output_file", "check_distinct_outputs", "check_resin_layers", "MIN_RESIN_LAYER", "warn",
           "open_chains_warning"]

EXIT_USAGE = 2

#: the slicing defaults of the resin commands (`raster`, `check`, and `batch --raster`, `view --raster/--check`):
#: resin printers print thinner layers than `slice`'s default
RESIN_DEFAULTS = {"thickness": 0.05}

#: the thinnest layer the resin commands take, mm: no resin printer's Z axis steps finer than about 1 µm (the finest
#: makers quote 1.25 µm); thinner layers only make millions of layers to rasterise (-t 5e-6: 4 million on a 20 mm part)
MIN_RESIN_LAYER = 0.001


def fail(message: str, code: int = EXIT_USAGE) -> None:
    """Print ``gpuslice: error: <message>`` on stderr and exit with ``code`` (2: user error)."""
    click.echo(f"gpuslice: error: {message}", err=True)
    raise SystemExit(code)


def warn(message: str) -> None:
    """Print ``gpuslice: warning: <message>`` on stderr (the command goes on; ``-q`` does not hide it)."""
    click.echo(f"gpuslice: warning: {message}", err=True)


def far_warning(model: str, mesh) -> str | None:
    """The warning (for :func:`warn`) when ``mesh`` reaches beyond :data:`gpuslice.mesh.mesh.FAR_XY_MM` in X or Y
    and was not centred: its float32 coordinates, and so its layers, are coarser there than the model may be."""
    import numpy as np

    from ..mesh.mesh import FAR_XY_MM, extreme_xy

    if mesh is None or mesh.n_faces == 0 or mesh.offset[0] or mesh.offset[1]:
        return None
    reach = extreme_xy(mesh.vertices.min(axis=0), mesh.vertices.max(axis=0))
    if reach <= FAR_XY_MM:
        return None
    step = float(np.spacing(np.float32(reach)))
    return (f"{model}: its X/Y reach {reach:.6g} mm from the origin, where float32 coordinates lie {step:.2g} mm "
            "apart, and its layers carry that error (--center moves the model to the origin first, in float64)")


def open_chains_warning(model: str, result, output: str) -> str | None:
    """The warning (for :func:`warn`) when ``result`` has open chains (a mesh not closed where they are), else None:
    an archive or mask leaves what they outline unfilled, so those layers print blank or partly blank, which nothing
    else would say (``slice`` reports them in its summary; ``check`` lists them as not checked)."""
    import numpy as np

    per_layer = result.open_chains_per_layer
    layers = np.flatnonzero(per_layer)
    if not layers.size:
        return None
    span = f"layer {layers[0]}" if layers.size == 1 else f"layers {layers[0]}-{layers[-1]}"
    return (f"{model}: {int(per_layer.sum())} open chains in {layers.size} layers ({span}): the mesh is not closed "
            f"there, and {output} leaves what they outline unfilled (repair the mesh; `gpuslice check` lists them)")


def refuse_model_as_output(model: str, *outputs: str | None) -> None:
    """A one-line error when an output path is the model file itself (``-o part.stl --format goo`` would replace the
    model it reads); None outputs are skipped."""
    import os

    for out in outputs:
        if out is None:
            continue
        refuse_dash(out)
        try:
            same = os.path.samefile(model, out.rstrip("/\\") or ".")
        except OSError:  # either does not exist (yet): not the same file
            same = False
        if same:
            fail(f"{out}: is the model {model} itself; name another output")


def refuse_dash(out: str) -> None:
    """A one-line error for the output ``-``: gpuslice writes its outputs as files (whole, or not at all: renamed
    into place when complete), never to standard output, and a file named ``-`` is not what the convention asks."""
    if out == "-":
        fail("-: gpuslice writes files, not standard output; name the file to write (./- for a file named '-')")


def check_output_file(*paths: str | None, creates: str | None = None) -> None:
    """A one-line error, before any work, for an output file that could not be written at the end: its folder does
    not exist or is a file, or the path is an existing folder. None paths are skipped; ``creates``: a folder the
    command makes itself (batch's output folder, a PNG stack), where a file may go although it does not exist yet."""
    from pathlib import Path

    from ..io.atomic import refuse_special

    made = Path(creates.rstrip("/\\") or ".").resolve() if creates is not None else None
    for out in paths:
        if out is None:
            continue
        refuse_dash(out)
        path = Path(out)
        if path.is_dir() or out.endswith(("/", "\\")):  # (`--report newdir/` wrote a file named newdir)
            fail(f"{out}: is a folder; name the file to write")
        refuse_special(path)  # (a device, FIFO or socket: the atomic rename would replace it)
        parent = path.parent
        if made is not None and parent.resolve() == made and not made.exists():
            continue  # (made by the command before the file is written)
        if parent.exists() and not parent.is_dir():
            fail(f"{out}: {parent} is a file, not a directory")
        if not parent.is_dir():
            fail(f"{out}: directory {parent} does not exist")
        check_writable(out, parent)


def check_output_place(out: str) -> None:
    """A one-line error, before any work, when the folder ``out`` is made or replaced in (a PNG stack, a batch's
    output folder) does not exist or cannot be written: one level is made, as every command makes its output (a
    typo's whole tree was made)."""
    from pathlib import Path

    refuse_dash(out)
    parent = Path(out.rstrip("/\\") or ".").resolve().parent
    if not parent.is_dir():
        fail(f"{out}: directory {parent} does not exist")
    check_writable(out, parent)


def check_writable(out: str, folder) -> None:
    """A one-line error, before any work, when ``folder`` (where ``out`` goes) cannot be written: a read-only file
    system or no permission (it failed only when the writing started, after the slicing)."""
    import os

    if not os.access(folder, os.W_OK | os.X_OK):
        fail(f"{out}: directory {folder} is not writable (read-only, or no permission)")


def check_distinct_outputs(output: str | None, report: str | None) -> None:
    """A one-line error when ``--report`` names the output itself (it would silently replace the file just written);
    None paths are skipped."""
    import os

    if output is None or report is None:
        return
    # (real paths: a folder reached through a symbolic link is the same folder)
    a, b = (os.path.normcase(os.path.realpath(x.rstrip("/\\") or ".")) for x in (output, report))
    if a == b:
        fail(f"{report}: --report names the output itself; name another file")


def check_resin_layers(params) -> None:
    """A one-line error when a resin command's finest layer (``-t``, ``--first-layer``; ``--min-height`` for
    cusp/area, the last ``--roi-ladder`` step for roi) is thinner than :data:`MIN_RESIN_LAYER` mm."""
    if params.adaptive in ("cusp", "area"):
        finest = {"min_height": params.min_height}
    elif params.adaptive == "roi":
        finest = {"roi_ladder": min(params.roi_ladder)}
    else:
        finest = {"thickness": params.thickness, "first_layer": params.first_layer}
    for name, value in finest.items():
        if value is not None and value < MIN_RESIN_LAYER:
            fail(f"{flag_for(name)} {value:g} mm: resin layers thinner than {MIN_RESIN_LAYER:g} mm are refused "
                 "(no resin printer moves in finer steps)")


def _click_option(info: OptionInfo, defaults: bool, default: Any, preset: bool = False) -> Callable:
    help_text = info.describe()
    also = ", or the --printer preset's" if preset else ""  # (the value a preset gives comes first)
    kw: dict[str, Any] = {"help": help_text}
    if info.metavar:
        kw["metavar"] = info.metavar
    names = list(info.flags)
    if info.type is bool:
        if info.negatable:
            if "/" not in names[-1]:
                names[-1] = f"{names[-1]}/--no-{names[-1][2:]}"
            kw["default"] = default if defaults else None
            if defaults:
                kw["show_default"] = True
            else:
                on, off = names[-1].split("/")
                kw["help"] = f"{help_text} [default: {on if default else off}{also}]"
        else:
            kw["is_flag"] = True
            kw["default"] = False
        return click.option(*names, info.name, **kw)
    if info.choices is not None:
        kw["type"] = click.Choice([str(c) for c in info.choices])
    elif info.parse is not None or info.type not in (int, float):
        kw["type"] = str
    else:
        kw["type"] = info.type
    shown = None if default is None else info.text(default)
    if defaults and info.parse is None:
        kw["default"] = default
        kw["show_default"] = shown is not None
    else:  # None unless given: the dataclass default applies (shown in the help)
        kw["default"] = None
        if shown is not None:
            kw["help"] = f"{help_text} [default: {shown}{also}]"
        elif preset:
            kw["help"] = f"{help_text} [default: the --printer preset's]"
    return click.option(*names, info.name, **kw)


def click_options(cls: type, *, only: Iterable[str] | None = None, exclude: Iterable[str] = (), defaults: bool = True,
                  overrides: dict[str, Any] | None = None, preset: bool = False) -> list[Callable]:
    """Click option decorators for the declared fields of ``cls`` (those with flags), in declaration order.

    only / exclude : field names to keep / leave out. defaults : show each field's default as the option's
    default (False: every value is None unless given, so a command can tell what the user gave; defaults named in
    the help). overrides : a command's own defaults for some fields (e.g. ``raster``'s 0.05 mm layers).
    preset : (with ``defaults=False``) a ``--printer`` preset's values come before the defaults: the help says so.
    """
    keep = set(only) if only is not None else None
    out = []
    for info in options_of(cls):
        if not info.flags or info.name in exclude or (keep is not None and info.name not in keep):
            continue
        default = (overrides or {}).get(info.name, info.default)
        out.append(_click_option(info, defaults, default, preset and not defaults))
    return out


def with_options(options: list[Callable]) -> Callable:
    """Apply a list of click option decorators (the first listed comes first in ``--help``)."""

    def deco(f):
        for opt in reversed(options):
            f = opt(f)
        return f

    return deco


def values(cls: type, kwargs: dict[str, Any], *, pop: bool = True) -> dict[str, Any]:
    """The values given for ``cls``'s fields among a command's ``kwargs`` (removed from them when ``pop``), parsed;
    None values (not given) are left out."""
    out = {}
    for info in options_of(cls):
        if info.name not in kwargs:
            continue
        value = kwargs.pop(info.name) if pop else kwargs[info.name]
        if value is None:
            continue
        if isinstance(value, str) and info.parse is not None:
            try:
                value = info.parse(value)
            except ParameterError as exc:
                raise ParameterError(f"{info.name}: {exc}", param=info.name) from None
        out[info.name] = value
    return out


def build(cls: type, kwargs: dict[str, Any], **extra: Any):
    """``cls(**values(cls, kwargs), **extra)``: the dataclass from a command's arguments (taken out of them)."""
    return cls(**{**values(cls, kwargs), **extra})


def option_classes() -> list[type]:
    """Every dataclass whose fields are command-line options (for mapping error messages to flags)."""
    from ..batch.options import BatchOptions
    from ..mesh.mesh import Placement
    from ..raster.settings import PrintSettings
    from ..raster.spec import RasterSpec, ResinOptions
    from ..slicing.params import SliceParams

    return [SliceParams, Placement, RasterSpec, ResinOptions, PrintSettings, BatchOptions]


def flag_for(param: str) -> str | None:
    """The command-line flag of option field ``param`` (``max_gap`` → ``--max-gap``)."""
    for cls in option_classes():
        for info in options_of(cls):
            if info.name == param and info.flags:
                return info.flag.split("/")[0]
    return None


def cli_message(exc: ParameterError) -> str:
    """``exc``'s message with the option fields it names written as the command line's flags."""
    import re

    text = str(exc)
    for param in getattr(exc, "params", ()):
        flag = flag_for(param)
        if flag:
            text = re.sub(rf"(?<![\w-]){re.escape(param)}(?![\w-])", flag, text)
    return text


def slicing_options(*, defaults: bool = True, overrides: dict[str, Any] | None = None) -> list[Callable]:
    """The options every slicing command shares: :class:`SliceParams`' fields, then :class:`Placement`'s."""
    from ..mesh.mesh import Placement
    from ..slicing.params import SliceParams

    return [*click_options(SliceParams, defaults=defaults, overrides=overrides),
            *click_options(Placement, defaults=defaults)]


def _given() -> list[str]:
    """The current command's parameters the user gave (on the command line or through the environment), not
    left at their defaults."""
    from click.core import ParameterSource

    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return []
    return [name for name in ctx.params
            if ctx.get_parameter_source(name) not in (None, ParameterSource.DEFAULT, ParameterSource.DEFAULT_MAP)]


def slicing_values(kwargs: dict[str, Any], overrides: dict[str, Any] | None = None):
    """(:class:`SliceParams`, :class:`Placement`) from a command's arguments (taken out of them); ``overrides``:
    the command's own defaults (as given to :func:`slicing_options`)."""
    from ..mesh.mesh import Placement
    from ..slicing.params import SliceParams

    params = SliceParams(**{**(overrides or {}), **values(SliceParams, kwargs)})
    for name, modes in params.not_for_mode(_given()):  # (uniform layers or another mode would ignore it, silently)
        kind = "uniform" if modes == (None,) else f"--adaptive {' or '.join(modes)}"
        fail(f"{flag_for(name)} shapes {kind} layers"
             + (f", not {params.adaptive} ones" if params.adaptive else "; add --adaptive " + modes[0]))
    return params, build(Placement, kwargs)
