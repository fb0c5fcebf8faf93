"""Resin printer presets (:class:`Printer`, the table :data:`PRINTERS`) and users' own presets from a TOML or JSON
file (:func:`find_printer`).

A preset holds what the printer's display is (pixels, pixel pitch in x and y, orientation, mirror), its build height,
the archive formats its firmware reads (the first is its native one, with that format's version and the machine name
the archive's header carries) and, optionally, default print settings
(:class:`~gpuslice.raster.settings.PrintSettings` field → value) that the command line's own values override. Every
row cites where its numbers come from (``source``).

A user's preset file has the same keys, e.g. ``my-printer.toml``::

    name = "my-printer"
    resolution = [11520, 5120]
    pixel = 0.019
    pixel_y = 0.024
    build_height = 250
    formats = ["goo"]
    [settings]
    exposure = 2.2
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from ..errors import ParameterError

__all__ = ["Printer", "PRINTERS", "find_printer", "printer_names", "load_printer_file"]

#: formats every preset may write: they are not printer archives (a folder of PNGs to look at)
ANY_PRINTER_FORMATS = ("png",)


@dataclass(frozen=True)
class Printer:
    """One resin printer (lengths mm).

    name : the ``--printer`` value; title : maker and model as sold.
    resolution : display pixels (nx, ny) along its width and height; pixel, pixel_y : pitch along x and y (pixel_y
        None: square).
    build_height : Z travel (mm); mirror_x, mirror_y, portrait : display orientation as :class:`RasterSpec` has it.
    formats : the archive formats (:data:`gpuslice.raster.outputs.RESIN_FORMATS` names) its firmware reads, the
        native one first; format_version : the native format's version number its firmware expects (None: the
        writer's default); machine : the machine name archives carry in their header.
    settings : default print settings (:class:`~gpuslice.raster.settings.PrintSettings` fields).
    source : where the numbers come from (a maker's page or a profile's file name).
    """

    name: str
    title: str
    resolution: tuple[int, int]
    pixel: float
    pixel_y: float | None = None
    build_height: float = 0.0
    mirror_x: bool = False
    mirror_y: bool = False
    portrait: bool = False
    formats: tuple[str, ...] = ()
    format_version: int | None = None
    machine: str = ""
    settings: dict[str, Any] = field(default_factory=dict, hash=False, compare=False)
    source: str = ""

    def __post_init__(self) -> None:
        nx, ny = self.resolution
        if not (isinstance(nx, int) and isinstance(ny, int) and nx > 0 and ny > 0):
            raise ParameterError(f"printer {self.name}: resolution must be two positive integers, got "
                                 f"{self.resolution}")
        for k in ("pixel", "pixel_y"):
            v = getattr(self, k)
            if v is not None and not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ParameterError(f"printer {self.name}: {k} must be a positive number of mm, got {v}")

    @property
    def py(self) -> float:
        return float(self.pixel if self.pixel_y is None else self.pixel_y)

    @property
    def build_mm(self) -> tuple[float, float, float]:
        """(width, depth, height) of the build volume in mm: the display's extent and the Z travel."""
        return self.resolution[0] * self.pixel, self.resolution[1] * self.py, float(self.build_height)

    @property
    def native_format(self) -> str | None:
        return self.formats[0] if self.formats else None

    def display(self) -> dict[str, Any]:
        """:class:`~gpuslice.raster.spec.RasterSpec` keyword arguments of this display."""
        d: dict[str, Any] = {"resolution": tuple(self.resolution), "pixel": self.pixel}
        if self.pixel_y is not None:
            d["pixel_y"] = self.pixel_y
        for k in ("mirror_x", "mirror_y", "portrait"):
            if getattr(self, k):
                d[k] = True
        return d

    def reads(self, fmt: str) -> bool:
        """Whether the firmware reads the resin output ``fmt`` (any format when the preset lists none)."""
        return not self.formats or fmt in self.formats or fmt in ANY_PRINTER_FORMATS


def _p(name: str, title: str, resolution: tuple[int, int], pixel: float, **kw: Any) -> Printer:
    return Printer(name, title, resolution, pixel, **kw)


_PRUSA = "PrusaSlicer 2.5 resources/profiles/PrusaResearch.ini (display_pixels, display_width/height)"

#: the presets, by name (see each row's ``source``)
PRINTERS: dict[str, Printer] = {
    p.name: p
    for p in (
        _p("generic-4k", "Generic 8.9-inch 4K monochrome LCD", (3840, 2400), 0.05, build_height=250),
        _p("generic-2k", "Generic 5.5-inch 2K LCD", (2560, 1440), 0.04725, build_height=150),
        _p("prusa-sl1", "Original Prusa SL1", (1440, 2560), 0.04725, build_height=150, portrait=True,
           mirror_x=True, formats=("sl1",), machine="SL1", source=_PRUSA),
        _p("prusa-sl1s", "Original Prusa SL1S Speed", (1620, 2560), 0.05, build_height=150, portrait=True,
           mirror_x=True, formats=("sl1s", "sl1"), machine="SL1S", settings={"exposure": 2.0, "bottom_exposure": 30.0},
           source=_PRUSA),
        _p("elegoo-mars", "Elegoo Mars", (1440, 2560), 0.04725, build_height=150),
        _p("elegoo-saturn", "Elegoo Saturn", (3840, 2400), 0.05, build_height=200),
        _p("anycubic-photon-mono-x", "Anycubic Photon Mono X", (3840, 2400), 0.05, build_height=245),
        _p("elegoo-saturn-3-ultra", "Elegoo Saturn 3 Ultra", (11520, 5120), 0.019, pixel_y=0.024,
           build_height=260, formats=("goo", "ctb"), machine="Saturn 3 Ultra",
           settings={"bottom_layers": 5, "bottom_exposure": 30.0, "exposure": 2.5, "transition_layers": 0},
           source="https://www.elegoo.com/products/elegoo-saturn-3-ultra-resin-3d-printer (10-inch 12K, "
                  "11520x5120, 19x24 um, 218.88x122.88x260 mm)"),
    )
}


def printer_names() -> list[str]:
    return sorted(PRINTERS)


def load_printer_file(path: str | os.PathLike) -> Printer:
    """A :class:`Printer` from a TOML (``.toml``) or JSON (``.json``) file with :class:`Printer`'s keys
    (``name`` defaults to the file's stem); :class:`ParameterError` naming the file otherwise."""
    p = Path(path)
    try:
        text = p.read_bytes()
    except OSError as exc:
        raise ParameterError(f"{p}: cannot read printer preset ({exc.strerror or exc})") from None
    try:
        if p.suffix.lower() == ".toml":
            import tomllib

            data = tomllib.loads(text.decode("utf-8"))
        else:
            data = json.loads(text)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ParameterError(f"{p}: not a valid {p.suffix.lstrip('.').upper() or 'JSON'} printer preset "
                             f"({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ParameterError(f"{p}: a printer preset must be a table of keys")
    known = {f.name for f in fields(Printer)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ParameterError(f"{p}: unknown printer preset key '{unknown[0]}' (use {', '.join(sorted(known))})")
    data.setdefault("name", p.stem)
    data.setdefault("title", data["name"])
    for k in ("resolution", "pixel"):
        if k not in data:
            raise ParameterError(f"{p}: printer preset needs '{k}'")
    try:
        data["resolution"] = tuple(data["resolution"])
        data["formats"] = tuple(data.get("formats", ()))
        if not isinstance(data.get("settings", {}), dict):
            raise ParameterError("settings must be a table")
        printer = Printer(**data)
        from .settings import PrintSettings

        PrintSettings().with_values(printer.settings)  # validates the settings now
    except (ParameterError, TypeError, ValueError) as exc:
        raise ParameterError(f"{p}: {exc}") from None
    return printer


def find_printer(name: str) -> Printer:
    """The preset ``name`` (:data:`PRINTERS`), or a user's preset when ``name`` is a path to a ``.toml`` or ``.json``
    file; :class:`ParameterError` otherwise."""
    if name in PRINTERS:
        return PRINTERS[name]
    if name.lower().endswith((".toml", ".json")):
        return load_printer_file(name)
    raise ParameterError(f"unknown printer '{name}' (use one of `gpuslice printers` or a .toml/.json preset file)")
