"""Contour output formats, behind one registry: ``suffix → writer``.

Each format is one module here with a writer ``write(result, path, **options)`` (atomic, bytes a pure function of
the result and options) and one :class:`ContourFormat` entry in :data:`CONTOUR_FORMATS` below. The command line's
choices and messages (``slice -o``, ``batch --format``), the suffix dispatch of :func:`export` and the docs read
this registry. Writer modules are imported only when a file of theirs is written.

Adding a format (say GeoJSON): write ``gpuslice/formats/geojson.py`` with ``write_geojson(result, path, ...)``, then
add ``ContourFormat("geojson", (".geojson",), "geojson:write_geojson", "…")`` to ``CONTOUR_FORMATS``.
"""

from __future__ import annotations

import importlib
import inspect
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ParameterError

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

__all__ = ["CONTOUR_FORMATS", "ContourFormat", "export", "format_for", "format_names", "open_stream", "suffixes"]


@dataclass(frozen=True)
class ContourFormat:
    """One contour output format: ``name`` (``--format`` value), ``suffixes`` (lower case, the first is the one
    batch gives its outputs), ``writer`` as ``"module:function"`` inside :mod:`gpuslice.formats`, ``help``;
    ``stream``: optionally a ``"module:Class"`` that writes the file while the layers are sliced (made with the
    path before slicing, the slicer's ``points_sink``, then ``commit(result)`` or ``abort()``: the bytes the writer
    gives), used by :func:`open_stream`."""

    name: str
    suffixes: tuple[str, ...]
    writer: str
    help: str
    stream: str | None = None

    @property
    def suffix(self) -> str:
        return self.suffixes[0]

    def load(self) -> Callable[..., None]:
        """The writer function (its module imported now)."""
        module, func = self.writer.split(":")
        return getattr(importlib.import_module(f"{__name__}.{module}"), func)

    def options(self) -> tuple[str, ...]:
        """The keyword options the writer takes (after ``result`` and ``path``)."""
        params = list(inspect.signature(self.load()).parameters.values())[2:]
        return tuple(p.name for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY)


#: the registry, in the order the help lists them
CONTOUR_FORMATS: dict[str, ContourFormat] = {
    f.name: f
    for f in (
        ContourFormat("npz", (".npz",), "npz:write_npz", "every array of the result (numpy .npz)", "npz:NpzStream"),
        ContourFormat("svg", (".svg",), "svg:write_svg", "all layers in one SVG, a <g> per layer, 1 unit = 1 mm"),
        ContourFormat("cli", (".cli",), "commonlayer:write_cli", "Common Layer Interface 2.0, ASCII"),
        ContourFormat("dxf", (".dxf",), "dxf:write_dxf", "a DXF layer per slice, closed LWPOLYLINEs, mm (ezdxf)"),
        ContourFormat("geojson", (".geojson",), "geojson:write_geojson",
                      "a FeatureCollection, one MultiPolygon Feature per layer (z, thickness, area), mm"),
        ContourFormat("3mf", (".3mf",), "threemf:write_3mf_slices", "3MF Slice Extension slice stack, mm"),
    )
}


def format_names() -> list[str]:
    """The registered format names (``npz``, ``svg``, ``cli``, …)."""
    return list(CONTOUR_FORMATS)


def suffixes() -> list[str]:
    """Every registered suffix, e.g. ``[".npz", ".svg", ".cli"]``."""
    return [s for f in CONTOUR_FORMATS.values() for s in f.suffixes]


def _choices() -> str:
    s = suffixes()
    return ", ".join(s[:-1]) + " or " + s[-1] if len(s) > 1 else s[0]


def format_for(path: str | os.PathLike, name: str | None = None) -> ContourFormat:
    """The format of ``path`` by its suffix (any case), or the one named ``name`` (``slice --format``: for a suffix
    no other format owns, as ``raster --format`` does: ``--format cli -o x.svg`` would write CLI text in an .svg);
    :class:`ParameterError` naming ``path`` otherwise."""
    p = Path(os.fspath(path))
    if name is not None:
        if name not in CONTOUR_FORMATS:
            raise ParameterError(f"{p}: unknown output format '{name}' (use {', '.join(CONTOUR_FORMATS)})")
        fmt, kind = CONTOUR_FORMATS[name], p.suffix.lower()
        owner = next((f for f in CONTOUR_FORMATS.values() if kind and kind in f.suffixes), None)
        if owner is not None and owner is not fmt:
            raise ParameterError(f"{p}: a {kind} file is {owner.name.upper()}, and --format {name} writes "
                                 f"{name.upper()} (name it part{fmt.suffixes[0]}, or leave --format out)")
        return fmt
    kind = p.suffix.lower()
    for f in CONTOUR_FORMATS.values():
        if kind in f.suffixes:
            return f
    if not kind:  # (-o o: "unknown output format ''" said nothing)
        raise ParameterError(f"{p}: no suffix to say the output format (use {_choices()}, or --format)")
    raise ParameterError(f"{p}: unknown output format '{p.suffix}' (use {_choices()})")


def _format_of_file(p: Path, name: str | None) -> ContourFormat:
    """:func:`format_for` of an output file: a folder's suffix (usually none) says nothing, so it is named as the
    real problem."""
    if name is None and p.is_dir():
        raise ParameterError(f"{p}: is a directory")
    return format_for(p, name)


def open_stream(path: str | os.PathLike, fmt: str | None = None) -> Any:
    """The format's stream (:attr:`ContourFormat.stream`) opened on ``path``, or None when the format has none
    (it is then written at the end by :func:`export`); :class:`ParameterError` as :func:`export` gives."""
    p = Path(os.fspath(path))
    f = _format_of_file(p, fmt)
    if f.stream is None:
        return None
    module, cls = f.stream.split(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), cls)(p)


def export(result: SliceResult, path: str | os.PathLike, fmt: str | None = None, **options: Any) -> None:
    """Write ``result`` in the format named by the suffix of ``path`` (case-insensitive), or by ``fmt`` (a
    :data:`CONTOUR_FORMATS` name, whatever the suffix), atomically.

    ``options`` are passed on to the writer (e.g. ``decimals`` for ``.svg``/``.cli``; ``.npz`` takes none).

    Raises
    ------
    ParameterError
        Unknown suffix, options the writer does not take, a path that is a directory, a ``result`` that is not a
        :class:`~gpuslice.slicing.result.SliceResult`.
    """
    from ..slicing.result import SliceResult

    if not isinstance(path, str | os.PathLike):
        raise ParameterError(f"path must be a file path, got {type(path).__name__}")
    p = Path(os.fspath(path))
    if not isinstance(result, SliceResult):
        raise ParameterError(f"{p}: result must be a SliceResult (gpuslice.slice_mesh's), got {type(result).__name__}")
    fmt = _format_of_file(p, fmt)
    unknown = sorted(set(options) - set(fmt.options()))
    if unknown:
        if not fmt.options():
            raise ParameterError(f"{p}: {fmt.suffix} output takes no options, got {', '.join(unknown)}")
        raise ParameterError(f"{p}: {fmt.suffix} output takes no option {', '.join(unknown)} "
                             f"(it takes {', '.join(fmt.options())})")
    try:
        fmt.load()(result, p, **options)
    except ParameterError as exc:  # a writer's own refusal (coordinates too large, ...): named by its file
        text = str(exc)
        raise (exc if text.startswith(str(p)) else ParameterError(f"{p}: {text}")) from None
