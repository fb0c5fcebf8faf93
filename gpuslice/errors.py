"""The project's own exception classes.

Every error a user can cause (a bad path, a broken file, an option out of range) is raised as a
:class:`GpusliceError` subclass whose message is one line naming the file and the problem; the command line
prints that line on stderr and exits with status 2.
"""

from __future__ import annotations

import re

__all__ = [
    "GpusliceError",
    "MeshFileError",
    "EmptyMeshError",
    "InvalidGeometryError",
    "ParameterError",
    "DeviceError",
    "BatchError",
    "flatten",
    "one_line",
]


class GpusliceError(Exception):
    """Base class of every error gpuslice raises on purpose."""


class MeshFileError(GpusliceError):
    """A mesh file cannot be read: missing, a directory, truncated, not an STL, garbage text."""


class EmptyMeshError(MeshFileError):
    """The file is well formed but holds no facets."""


class InvalidGeometryError(MeshFileError):
    """Coordinates that cannot be sliced: NaN, infinite, or so large that float32 arithmetic overflows."""


class ParameterError(GpusliceError):
    """An option out of range: a non-positive thickness, unsorted z values, an unknown fill rule.

    ``param``: the option field(s) the message names by their field names (``"max_gap must be >= 0 mm"``; a name or
    a tuple), as declared in the options' dataclasses (:mod:`gpuslice.options`); the command line writes those
    names as its flags (``--max-gap must be >= 0 mm``). Messages that use a plain word instead ("unknown printer")
    name no ``param``.
    """

    def __init__(self, message: str, *, param: str | tuple[str, ...] | None = None) -> None:
        super().__init__(message)
        self.params: tuple[str, ...] = (param,) if isinstance(param, str) else tuple(param or ())


class DeviceError(GpusliceError):
    """No usable OpenCL device, or the one asked for does not exist."""


class BatchError(GpusliceError):
    """A batch cannot start: no models found, clashing outputs, options differing from the output folder's."""


#: control characters other than whitespace (a file's bytes in a message: a terminal would act on ESC sequences)
_CONTROL = re.compile("[\x00-\x08\x0e-\x1f\x7f-\x9f]")


def flatten(text: str, limit: int | None = None) -> str:
    """``text`` on one line (every run of whitespace, newlines included, becomes one space; other control characters
    written ``\\xNN``), cut to ``limit`` characters with ``...`` when longer."""
    out = _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", " ".join(str(text).split()))
    if limit is not None and len(out) > limit:
        out = out[: limit - 3] + "..."
    return out


def one_line(exc: BaseException) -> str:
    """The one-line message of ``exc`` for a user: a :class:`GpusliceError`'s own message (it names the file and the
    problem), an :class:`OSError` naming a file as ``file: reason`` (as the command line says it), any other
    exception's as ``Type: message``; the type name alone when the message is empty."""
    text = flatten(str(exc))
    if isinstance(exc, GpusliceError):
        return text or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {flatten(exc.strerror)}"
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
