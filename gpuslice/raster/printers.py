"""Resin printer presets (:class:`Printer`, the table :data:`PRINTERS`) and users' own presets from a TOML or JSON
file (:func:`find_printer`).

A preset holds what the printer's display is (pixels, pixel pitch in x and y, orientation, mirror), its build height,
the archive formats its firmware reads (the first is its native one, with that format's version and the machine name
the archive's header carries) and, optionally, default print settings
(:class:`~gpuslice.raster.settings.PrintSettings` field → value) that the command line's own values override. Every
row cites where its numbers come from (``source``). The built-in rows live in ``printers.toml`` beside this module,
read on first use.

A user's preset file has the same keys (``name`` defaults to the file's stem), or ``inherits`` a built-in preset and
changes some of its keys, e.g. ``my-saturn.toml``::

    inherits = "elegoo-saturn-3-ultra"
    [settings]
    exposure = 2.2
    bottom_exposure = 25

or a printer of its own::

    resolution = [11520, 5120]
    pixel = 0.019
    pixel_y = 0.024
    build_height = 250
    formats = ["goo"]
"""

from __future__ import annotations

import difflib
import functools
import json
import math
import os
import re
import stat
from collections.abc import Iterator, Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from ..errors import ParameterError

__all__ = ["Printer", "PRINTERS", "find_printer", "printer_names", "load_printer_file", "printer_from_dict",
           "ANY_PRINTER_FORMATS"]

#: the largest pixel a display may have, mm (a resin display's are 0.01-0.1 mm; larger ones only overflow the
#: formats' float32 header fields)
MAX_PIXEL_MM = 1000.0
#: the smallest, mm (1 nm: a denormal pitch such as 5e-324 made the placement's 1 / pixel infinite, and a model
#: 'fitted' a display of no width)
MIN_PIXEL_MM = 1e-6
#: the largest Z travel a printer preset may give, mm (1e308 overflowed the archives' float32 fields)
MAX_BUILD_MM = 10_000.0

#: formats every preset may write: they are not printer archives (a folder of PNGs to look at)
ANY_PRINTER_FORMATS = ("png",)


@dataclass(frozen=True)
class Printer:
    """One resin printer (lengths mm).

    name : the ``--printer`` value; title : maker and model as sold.
    resolution : display pixels (nx, ny) along its width and height; pixel, pixel_y : pitch along x and y (pixel_y
        None: square).
    build_height : Z travel (mm); mirror_x, mirror_y, portrait : display orientation as :class:`RasterSpec` has it.
    formats : the archive formats its firmware reads, the native one first
        (:data:`gpuslice.raster.outputs.RESIN_FORMATS` names where gpuslice writes them; an empty tuple: any);
        format_version : the native format's version number its firmware expects (None: the writer's default);
        machine : the machine name archives carry in their header.
    settings : default print settings (:class:`~gpuslice.raster.settings.PrintSettings` fields).
    source : where the numbers come from (a maker's page or a profile's file name); notes : what a user should know.
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
    notes: str = ""

    def __post_init__(self) -> None:
        res = self.resolution
        if not (isinstance(res, tuple) and len(res) == 2 and all(_is_int(v) and v > 0 for v in res)):
            raise ParameterError(f"printer {self.name}: resolution must be two positive whole numbers, got {res}")
        for k in ("pixel", "pixel_y", "build_height"):
            v = getattr(self, k)
            if v is None and k == "pixel_y":
                continue
            ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
            lo, hi = (MIN_PIXEL_MM, MAX_PIXEL_MM) if k != "build_height" else (0.0, MAX_BUILD_MM)
            if not (ok and lo <= v <= hi):
                what = "a positive number of mm" if k != "build_height" else "a number of mm (0: not given)"
                raise ParameterError(f"printer {self.name}: {k} must be {what} from {lo:g} up to {hi:g}, got {v}")
        for k in ("mirror_x", "mirror_y", "portrait"):
            if not isinstance(getattr(self, k), bool):
                raise ParameterError(f"printer {self.name}: {k} must be true or false, got {getattr(self, k)}")
        if not (isinstance(self.formats, tuple) and all(isinstance(f, str) and f for f in self.formats)):
            raise ParameterError(f"printer {self.name}: formats must be a list of format names, got {self.formats}")
        if self.format_version is not None and not (_is_int(self.format_version) and self.format_version >= 0):
            raise ParameterError(f"printer {self.name}: format_version must be a whole number, got "
                                 f"{self.format_version}")
        for k in ("name", "title", "machine", "source", "notes"):
            if not isinstance(getattr(self, k), str):
                raise ParameterError(f"printer {self.name}: {k} must be text, got {getattr(self, k)!r}")
        if not isinstance(self.settings, dict):
            raise ParameterError(f"printer {self.name}: settings must be a table of print settings")

    @property
    def py(self) -> float:
        """Pixel pitch along y, mm."""
        return float(self.pixel if self.pixel_y is None else self.pixel_y)

    @property
    def display_mm(self) -> tuple[float, float]:
        """(width, height) of the display in mm: nx·pixel, ny·pixel_y."""
        return self.resolution[0] * float(self.pixel), self.resolution[1] * self.py

    @property
    def build_mm(self) -> tuple[float, float, float]:
        """(X, Y, Z) build size in mm: the display's width and height, and the build height."""
        return (*self.display_mm, float(self.build_height))

    @property
    def native_format(self) -> str | None:
        return self.formats[0] if self.formats else None

    @property
    def orientation(self) -> str:
        """``"landscape"`` or ``"portrait"``, then the mirrors: ``"landscape, mirror x"``."""
        parts = ["portrait" if self.portrait else "landscape"]
        parts += [f"mirror {a}" for a in ("x", "y") if getattr(self, f"mirror_{a}")]
        return ", ".join(parts)

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

    def to_dict(self) -> dict[str, Any]:
        """The preset as JSON-ready values (the keys of a preset file, plus ``display_mm`` and ``build_mm``)."""
        d = asdict(self)
        d["resolution"], d["formats"] = list(self.resolution), list(self.formats)
        d["display_mm"] = [round(v, 6) for v in self.display_mm]
        d["build_mm"] = [round(v, 6) for v in self.build_mm]
        return d


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


_KEYS = {f.name for f in fields(Printer)}


def printer_from_dict(data: Mapping[str, Any], where: str, *, name: str | None = None) -> Printer:
    """A :class:`Printer` from a preset's keys (``inherits``: a built-in preset whose keys the others replace;
    ``settings`` are merged); :class:`ParameterError` naming ``where`` (the file) and the problem."""
    data = dict(data)
    parent_name = data.pop("inherits", None)
    unknown = sorted(set(data) - _KEYS)
    if unknown:
        raise ParameterError(f"{where}: unknown printer preset key '{unknown[0]}' (use "
                             f"{', '.join(sorted(_KEYS | {'inherits'}))})")
    if parent_name is not None:
        if not isinstance(parent_name, str) or _canonical(parent_name) not in PRINTERS:
            raise ParameterError(f"{where}: inherits unknown printer '{parent_name}' (see `gpuslice printers`)")
        parent = PRINTERS[_canonical(parent_name)]
        base = {f.name: getattr(parent, f.name) for f in fields(Printer)}
        base["settings"] = {**parent.settings, **(data.pop("settings", None) or {})}
        base["name"] = name or parent.name
        data = {**base, **data}
    if name is not None:
        data.setdefault("name", name)
    data.setdefault("title", data.get("name", ""))
    for k in ("name", "resolution", "pixel"):
        if k not in data:
            raise ParameterError(f"{where}: printer preset needs '{k}'")
    try:
        if isinstance(data["resolution"], list | tuple):
            data["resolution"] = tuple(data["resolution"])
        if isinstance(data.get("formats"), list | tuple):
            data["formats"] = tuple(data["formats"])
        printer = Printer(**data)
        from .settings import PrintSettings

        PrintSettings().with_values(printer.settings)  # validates the settings now, not when a job starts
    except (ParameterError, TypeError, ValueError) as exc:
        text = str(exc).removeprefix(f"printer {data['name']}: ")
        raise ParameterError(f"{where}: {text}") from None
    return printer


def _parse_toml(text: str) -> dict[str, Any]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10: the tomli backport (a dependency there)
        import tomli as tomllib
    return tomllib.loads(text)


class _Presets(Mapping[str, Printer]):
    """The built-in presets, read from ``printers.toml`` on first use (name → :class:`Printer`)."""

    def __init__(self) -> None:
        self._rows: dict[str, Printer] | None = None

    def _table(self) -> dict[str, Printer]:
        if self._rows is None:
            from importlib.resources import files

            text = files(__package__).joinpath("printers.toml").read_text(encoding="utf-8")
            rows = {name: printer_from_dict(row, f"printers.toml [{name}]", name=name)
                    for name, row in _parse_toml(text).items()}
            self._rows = dict(sorted(rows.items()))
        return self._rows

    def __getitem__(self, name: str) -> Printer:
        return self._table()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._table())

    def __len__(self) -> int:
        return len(self._table())

    def __repr__(self) -> str:
        return f"PRINTERS({', '.join(self)})"


#: the built-in presets by name, sorted (rows and sources: ``printers.toml``)
PRINTERS: Mapping[str, Printer] = _Presets()


def printer_names() -> list[str]:
    return sorted(PRINTERS)


#: a printer preset file larger than this is refused (the built-in table, every preset in it, is ~20 KB)
PRESET_MAX_BYTES = 1 << 20


def load_printer_file(path: str | os.PathLike) -> Printer:
    """A :class:`Printer` from a TOML (``.toml``) or JSON (``.json``) file with :class:`Printer`'s keys
    (``name`` defaults to the file's stem; ``inherits`` names a built-in preset to start from);
    :class:`ParameterError` naming the file otherwise."""
    p = Path(path)
    try:
        st = p.stat()
        if not stat.S_ISREG(st.st_mode):  # (a FIFO waits forever, /dev/zero never ends: read only regular files)
            what = "is a folder" if stat.S_ISDIR(st.st_mode) else "not a regular file"
            raise ParameterError(f"{p}: cannot read printer preset ({what})")
        if st.st_size > PRESET_MAX_BYTES:
            raise ParameterError(f"{p}: a printer preset of {st.st_size} bytes is not one (at most "
                                 f"{PRESET_MAX_BYTES})")
        text = p.read_bytes()
    except OSError as exc:
        raise ParameterError(f"{p}: cannot read printer preset ({exc.strerror or exc})") from None
    return _printer_from_bytes(str(p), text)


@functools.lru_cache(maxsize=32)
def _printer_from_bytes(path: str, text: bytes) -> Printer:
    """The preset file ``path`` of contents ``text``, parsed once per (path, contents): a job asks for its preset
    many times (display, settings, format); by contents, not modification time and size (a rewrite within the clock's
    step with as many bytes was missed)."""
    p = Path(path)
    try:
        source = text.decode("utf-8")
        data = _parse_toml(source) if p.suffix.lower() == ".toml" else json.loads(source)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ParameterError(f"{p}: not a valid {p.suffix.lstrip('.').upper() or 'JSON'} printer preset "
                             f"({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise ParameterError(f"{p}: a printer preset must be a table of keys")
    return printer_from_dict(data, str(p), name=data.get("name") or p.stem)


def _canonical(name: str) -> str:
    """``"Elegoo Saturn 3 Ultra"`` → ``"elegoo-saturn-3-ultra"``."""
    return re.sub(r"[\s_]+", "-", name.strip().lower())


def find_printer(name: str) -> Printer:
    """The preset ``name`` (:data:`PRINTERS`; case, spaces and underscores do not matter), or a user's preset when
    ``name`` is a path to a ``.toml`` or ``.json`` file; :class:`ParameterError` otherwise."""
    if name in PRINTERS:
        return PRINTERS[name]
    if name.lower().endswith((".toml", ".json")):
        return load_printer_file(os.path.abspath(name))
    key = _canonical(name)
    if key in PRINTERS:
        return PRINTERS[key]
    close = difflib.get_close_matches(key, list(PRINTERS), n=3, cutoff=0.6)
    hint = f"did you mean {' or '.join(close)}? " if close else ""
    raise ParameterError(f"unknown printer '{name}' ({hint}`gpuslice printers` lists them; or give a .toml/.json "
                         "preset file)")
