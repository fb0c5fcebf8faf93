"""Options declared once: a dataclass field per option, carrying its name, default, unit, choices and help.

Every option of gpuslice lives in one frozen dataclass field made by :func:`option` (:class:`~gpuslice.slicing.
params.SliceParams`, :class:`~gpuslice.mesh.mesh.Placement`, :class:`~gpuslice.raster.spec.RasterSpec`,
:class:`~gpuslice.raster.spec.ResinOptions`, …). The command line is generated from these fields
(:mod:`gpuslice.cli.options`), batch's ``--raster-opt KEY=VALUE`` is typed by them (:func:`parse_value`), and the
library's :class:`~gpuslice.errors.ParameterError` names the field, which the command line maps to its flag
(:func:`flag_of`). No default, choice list or help text is written twice.

Metadata of a field (all optional but ``help``):

* ``help``: one sentence, no unit; ``unit``: ``"mm"``, ``"s"``, … (appended to the help on the command line);
* ``flags``: the command-line names, e.g. ``("-t", "--thickness")``; default ``--field-name``; ``()`` keeps the
  field off the command line;
* ``choices``: a tuple of allowed values, or a callable giving them (a registry's names, read when needed);
* ``parse``: text → value for fields whose command-line text is not a plain number or string (``3840x2400``,
  ``1,0.5,0.1``) and ``show`` its inverse; ``negatable``: a bool shown as ``--x/--no-x`` (default: a plain ``--x``
  flag).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import types
import typing
from collections.abc import Callable, Iterator
from dataclasses import MISSING, Field, dataclass
from typing import Any

from .errors import ParameterError

__all__ = ["OptionInfo", "option", "options_of", "parse_value", "flag_of", "parse_floats", "parse_resolution",
           "is_real", "python_number", "shown"]


def is_real(v: object) -> bool:
    """A real number: a Python or numpy integer or float, not a bool (``True`` is no thickness)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def is_finite(v: object) -> bool:
    """``v`` is a real number (:func:`is_real`) whose float is finite: False for NaN, ±inf and integers beyond a
    float's range (``np.isfinite(2**1000)`` is a TypeError)."""
    if not is_real(v):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


def check_flag(v: object, name: str) -> bool:
    """``v`` as a bool when it is True or False (a Python or numpy bool), else a one-line :class:`ParameterError`
    naming ``name`` (``"no"`` or 1 would otherwise read as a choice)."""
    if not (isinstance(v, bool) or (type(v).__module__ == "numpy" and type(v).__name__ in ("bool", "bool_"))):
        raise ParameterError(f"{name} must be True or False, got {v!r}", param=name)
    return bool(v)


def python_number(v: object) -> object:
    """``v``, a numpy number as the same Python number (reports' JSON and archive headers take those), else as is."""
    return v.item() if is_real(v) and hasattr(v, "item") else v


def shown(v: object) -> str:
    """``v`` as an error message shows it: a number as itself (a whole number of more than 20 digits by its first
    and its length: 2**1000 is 302 digits), anything else by its repr (a string: ``'2'``)."""
    if not is_real(v):
        return repr(v)
    text = str(v)
    if isinstance(v, numbers.Integral) and len(text) > 20:
        return f"{text[:8]}… ({len(text.lstrip('-'))} digits)"
    return text


def option(
    default: Any,
    help: str,
    *,
    unit: str | None = None,
    flags: tuple[str, ...] | None = None,
    choices: tuple | Callable[[], tuple] | None = None,
    parse: Callable[[str], Any] | None = None,
    negatable: bool = False,
    metavar: str | None = None,
    show: Callable[[Any], str] | None = None,
) -> Any:
    """A dataclass field holding one option's default and its description (see the module docstring)."""
    meta = {"help": help, "unit": unit, "flags": flags, "choices": choices, "parse": parse, "negatable": negatable,
            "metavar": metavar, "show": show}
    return dataclasses.field(default=default, metadata={"gpuslice": meta})


@dataclass(frozen=True)
class OptionInfo:
    """What :func:`options_of` tells about one option field."""

    name: str
    default: Any
    type: type
    optional: bool  # None is allowed
    help: str
    unit: str | None
    flags: tuple[str, ...]
    choices: tuple | None
    parse: Callable[[str], Any] | None
    negatable: bool
    metavar: str | None
    show: Callable[[Any], str] | None

    @property
    def flag(self) -> str | None:
        """The long command-line flag (``--max-gap``), or None for a field kept off the command line."""
        longs = [f for f in self.flags if f.startswith("--")]
        return longs[0] if longs else (self.flags[0] if self.flags else None)

    def describe(self) -> str:
        """The help sentence with its unit: ``"Layer thickness, mm."``; the unit goes before a first parenthesis
        (``"Join open chain ends closer than this, mm (0: never)."``)."""
        text = self.help.rstrip(".")
        if not self.unit:
            return f"{text}."
        head, paren, tail = text.partition(" (")
        return f"{head}, {self.unit}{paren}{tail}."

    def text(self, value: Any) -> str:
        """``value`` as the command line writes it (``3840x2400``, ``1,0.5,0.1``)."""
        if self.show is not None:
            return self.show(value)
        if isinstance(value, tuple):
            return ",".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
        return str(value)


def _base_type(annotation: Any) -> tuple[type, bool]:
    """(the non-None type, whether None is allowed) of a field annotation such as ``float | None``."""
    args = typing.get_args(annotation)
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        rest = [a for a in args if a is not type(None)]
        return _base_type(rest[0])[0], True
    origin = typing.get_origin(annotation)
    return (origin or annotation), False


def _info(f: Field, annotation: Any) -> OptionInfo | None:
    meta = f.metadata.get("gpuslice")
    if meta is None:
        return None
    kind, optional = _base_type(annotation)
    choices = meta["choices"]
    if callable(choices):
        choices = tuple(choices())
    default = f.default if f.default is not MISSING else None
    flags = meta["flags"] if meta["flags"] is not None else ("--" + f.name.replace("_", "-"),)
    return OptionInfo(f.name, default, kind, optional or default is None, meta["help"], meta["unit"], tuple(flags),
                      choices, meta["parse"], meta["negatable"], meta["metavar"], meta["show"])


def options_of(cls: type) -> Iterator[OptionInfo]:
    """The option fields of dataclass ``cls`` in declaration order."""
    hints = typing.get_type_hints(cls)  # the annotations as types (they are strings under postponed evaluation)
    for f in dataclasses.fields(cls):
        info = _info(f, hints[f.name])
        if info is not None:
            yield info


def flag_of(param: str, *classes: type) -> str | None:
    """The command-line flag of option ``param`` in the first of ``classes`` declaring it."""
    for cls in classes:
        for info in options_of(cls):
            if info.name == param:
                return info.flag
    return None


def parse_value(info: OptionInfo, text: Any) -> Any:
    """``text`` (a command-line or ``KEY=VALUE`` string; other values pass through) as the value of ``info``'s
    field: parsed by its ``parse``, or converted to its type (``true``/``false``/``yes``/``no``/``1``/``0`` for bools);
    ``none`` for optional fields. Raises :class:`ParameterError` naming the field."""
    if not isinstance(text, str):
        return text
    if info.optional and text.strip().lower() in ("none", ""):
        return None
    if info.parse is not None:
        return info.parse(text)
    try:
        if info.type is bool:
            low = text.strip().lower()
            if low not in ("true", "false", "yes", "no", "1", "0", "on", "off"):
                raise ValueError(text)
            return low in ("true", "yes", "1", "on")
        if info.type in (int, float):
            return info.type(text)
    except ValueError:
        raise ParameterError(f"{info.name}: expected {info.type.__name__}, got '{text}'", param=info.name) from None
    return text


def parse_floats(text: str) -> tuple[float, ...]:
    """``"1,0.5,0.1"`` → ``(1.0, 0.5, 0.1)``."""
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ParameterError(f"expected comma-separated numbers, got '{text}'") from None


def parse_resolution(text: str) -> tuple[int, int]:
    """``"3840x2400"`` → ``(3840, 2400)``."""
    try:
        nx, ny = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ParameterError(f"expected NXxNY pixels, e.g. 3840x2400, got '{text}'") from None
    return nx, ny
