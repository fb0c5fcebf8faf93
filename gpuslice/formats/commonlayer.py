"""``.cli``: the Common Layer Interface 2.0, ASCII (:func:`write_cli`, read back by :func:`read_cli`); each layer
is labelled with the height of its *top* (``bottom + thickness``). Output bytes are a pure function of the result."""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MeshFileError, ParameterError

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

from ..io.atomic import atomic_path
from .numbers import (
    MAX_ABS,
    check_decimals,
    format_fixed,
    format_numbers,
    layer_chunks,
    point_bounds,
    result_arrays,
    stacked_slabs,
)

PathLike = str | os.PathLike

__all__ = ["write_cli", "read_cli", "CLI_CLOCKWISE", "CLI_COUNTER_CLOCKWISE", "CLI_OPEN"]

#: CLI polyline direction codes (CLI 2.0): 0 clockwise = internal (hole), 1 counter-clockwise = external
#: (outer contour), 2 open line.
CLI_CLOCKWISE = 0
CLI_COUNTER_CLOCKWISE = 1
CLI_OPEN = 2

def _cli_decimals(units_mm: float) -> int:
    # enough decimals for 0.1 µm resolution in the file's units
    return max(0, min(9, math.ceil(math.log10(units_mm / 1e-4) - 1e-9)))


def _height_decimals(top: np.ndarray, decimals: int, chosen: bool) -> int:
    """Decimals for the layer tops ``top`` (file units): ``decimals``, or more (up to 9) where that many would
    write two layers at one height (layers thinner than 0.1 µm); a :class:`ParameterError` for ``decimals`` the
    caller ``chosen`` that does."""
    def distinct(d: int) -> bool:
        return bool(np.all(np.diff(np.rint(top * 10.0**d)) > 0))

    if top.size < 2 or distinct(decimals):
        return decimals
    if chosen:
        raise ParameterError(f"decimals={decimals} writes two layers at one height (the thinnest layer is "
                             f"{float(np.diff(top).min()):.3g} file units): give more decimals, or None")
    return next((d for d in range(decimals + 1, 10) if distinct(d)), 9)


def write_cli(
    result: SliceResult,
    path: PathLike,
    *,
    units_mm: float = 1.0,
    decimals: int | None = None,
    label: str = "part1",
) -> None:
    """Write ``result`` as a Common Layer Interface (CLI 2.0) ASCII file, atomically.

    The file::

        $$HEADERSTART
        $$ASCII
        $$UNITS/00000001.000000          mm per file unit (units_mm, %015.6f)
        $$VERSION/200
        $$LABEL/1,part1
        $$DIMENSION/x1,y1,z1,x2,y2,z2    bounding box in file units (omitted for a result with no points)
        $$LAYERS/000003                  number of layers
        $$HEADEREND
        $$GEOMETRYSTART
        $$LAYER/0.2000                   the layer's TOP height in file units
        $$POLYLINE/1,dir,n,p1x,p1y,...,pnx,pny
        ...
        $$GEOMETRYEND

    Conventions:

    * **Layer height**: ``$$LAYER/h`` is the top of the layer's slab, ``h = bottom + thickness`` (with
      ``bottom`` from :attr:`SliceResult.bottom`), the convention of CLI files from Materialise and EOS
      (a layer is built up *to* its height); not the cutting plane ``z``. Every layer is written, empty ones
      as a bare ``$$LAYER`` line, so layer i of the file is layer i of the result.
    * **Polylines**: one per non-empty loop, part id 1, ``dir`` 1 (counter-clockwise, external) for outer
      loops, 0 (clockwise, internal) for holes, 2 for open chains, taken from ``loop_is_hole`` /
      ``loop_closed``. A closed polyline repeats its first point at the end and ``n`` counts it.
    * **Numbers**: coordinates and heights are ``mm / units`` in fixed-point decimal with ``decimals``
      digits (default: enough for 0.1 µm, i.e. 4 with the default ``units_mm=1``, 1 with ``0.001``, 0 with
      ``0.0001``; the layer heights get more where layers thinner than that would share a height), rounded
      half-to-even. No date or other varying header, so output is deterministic.

    Parameters
    ----------
    result
        The slicing result.
    path
        Output file, conventionally ``*.cli``.
    units_mm
        Length of one file unit in mm, 1e-6 to 1000; written with 6 decimals, and that written value is the
        one used to scale the coordinates.
    decimals
        Digits after the decimal point, 0 to 9; ``None`` chooses from ``units_mm`` as above. Use 0 for
        readers that want integer coordinates.
    label
        Text of the ``$$LABEL`` of part 1 (no commas, slashes or line breaks).

    Raises
    ------
    ParameterError
        A parameter out of range or a malformed result (see :func:`write_svg`).
    """
    if (
        isinstance(units_mm, bool)
        or not isinstance(units_mm, int | float | np.number)
        or not 1e-6 <= round(float(units_mm), 6) <= 1000  # False for NaN
    ):
        raise ParameterError(f"units_mm must be a number from 0.000001 to 1000, got {units_mm!r}")
    units_text = f"{float(units_mm):015.6f}"
    units = float(units_text)
    chosen = decimals is not None
    decimals = _cli_decimals(units) if decimals is None else check_decimals(decimals)
    if not isinstance(label, str) or re.search(r"[,/\r\n$]", label):
        raise ParameterError(f"label must be text without commas, slashes, '$' or line breaks, got {label!r}")
    points, loop_offsets, layer_offsets = result_arrays(result)
    thickness = np.asarray(result.thickness, dtype=np.float64)
    bottom, top = stacked_slabs(result, "a CLI file")
    top = top / units
    if (points.size and np.abs(points).max() / units > MAX_ABS) or np.abs(top).max(initial=0) > MAX_ABS:
        raise ParameterError("result coordinates are too large to write in these units")
    is_hole = np.asarray(result.loop_is_hole, dtype=bool)
    closed = np.asarray(result.loop_closed, dtype=bool)
    direction = np.where(~closed, CLI_OPEN, np.where(is_hole, CLI_CLOCKWISE, CLI_COUNTER_CLOCKWISE))
    n_layers = int(thickness.size)

    def fnum(x: Sequence[float] | np.ndarray, digits: int = decimals) -> list[str]:
        text, _ = format_numbers(np.asarray(x, dtype=np.float64), digits, ord("\n"))
        return text.tobytes().decode().split("\n")[:-1]

    lines = ["$$HEADERSTART", "$$ASCII", f"$$UNITS/{units_text}", "$$VERSION/200", f"$$LABEL/1,{label}"]
    if points.size and n_layers:
        lo, hi = point_bounds(points)
        lo, hi = lo / units, hi / units
        box = (lo[0], lo[1], bottom[0] / units, hi[0], hi[1], top[-1])
        lines.append("$$DIMENSION/" + ",".join(fnum(box)))
    lines += [f"$$LAYERS/{n_layers:06d}", "$$HEADEREND", "$$GEOMETRYSTART", ""]
    top_text = fnum(top, _height_decimals(top, decimals, chosen))

    cum = loop_offsets[layer_offsets]
    with atomic_path(path) as tmp, open(tmp, "wb", buffering=1 << 20) as fh:
        fh.write("\n".join(lines).encode())
        for l0, l1 in layer_chunks(cum):
            r0, r1 = int(layer_offsets[l0]), int(layer_offsets[l1])
            p0, p1 = int(loop_offsets[r0]), int(loop_offsets[r1])
            offsets = loop_offsets[r0 : r1 + 1] - p0
            buf, loop_bytes = _cli_chunk(points[p0:p1], offsets, closed[r0:r1], direction[r0:r1], units, decimals)
            mv = memoryview(buf)
            for i in range(l0, l1):
                fh.write(f"$$LAYER/{top_text[i]}\n".encode())
                a, b = int(layer_offsets[i]) - r0, int(layer_offsets[i + 1]) - r0
                fh.write(mv[loop_bytes[a] : loop_bytes[b]])
        fh.write(b"$$GEOMETRYEND\n")


def _cli_chunk(
    pts: np.ndarray,
    offsets: np.ndarray,
    closed: np.ndarray,
    direction: np.ndarray,
    units: float,
    decimals: int,
) -> tuple[np.ndarray, np.ndarray]:
    """``$$POLYLINE`` lines of a chunk's loops; returns the text and each loop's byte offset (R + 1,)."""
    first = offsets[:-1]
    lengths = offsets[1:] - first
    nonempty = lengths > 0
    n_out = np.where(nonempty, lengths + closed, 0)  # points written, the repeated first one included
    out_first = np.zeros(n_out.size + 1, dtype=np.int64)
    np.cumsum(n_out, out=out_first[1:])
    total = int(out_first[-1])
    # point index of each written point: first[r] + k, and first[r] again for the closing repeat
    idx = np.repeat(first - out_first[:-1], n_out) + np.arange(total)
    rep = nonempty & closed
    idx[out_first[1:][rep] - 1] = first[rep]
    values = pts[idx].astype(np.float64) / units

    written = np.flatnonzero(nonempty)
    dirs, ns = direction[written].tolist(), n_out[written].tolist()
    prefixes = [b"$$POLYLINE/1,%d,%d," % (d, n) for d, n in zip(dirs, ns, strict=True)]
    sep = np.full(2 * total, ord(","), dtype=np.uint8)
    sep[2 * out_first[1:][nonempty] - 1] = ord("\n")
    before = [(2 * out_first[:-1][written], prefixes)]
    buf, starts = format_fixed(values, decimals, sep, before)
    return buf, starts[2 * out_first]


_CLI_COMMENT = re.compile(r"//.*?//", re.DOTALL)


def read_cli(path: PathLike) -> list[tuple[float, list[tuple[int, np.ndarray]]]]:
    """Read the layers and polylines of an ASCII CLI file.

    Parameters
    ----------
    path
        A CLI 2.0 ASCII file, e.g. one written by :func:`write_cli`.

    Returns
    -------
    list of (z, polylines)
        One entry per ``$$LAYER`` in file order: ``z`` the layer height in mm (file value times
        ``$$UNITS``; for files from :func:`write_cli`, the layer's top) and ``polylines`` a list of
        ``(dir, points)`` with ``dir`` the CLI direction code (0 clockwise/hole, 1 counter-clockwise/outer,
        2 open) and ``points`` an (n, 2) float64 array in mm, exactly as stored: closed polylines keep
        their repeated first point. ``$$HATCHES`` and other commands are skipped.

    Raises
    ------
    MeshFileError
        The file cannot be read, is binary CLI, or is malformed.
    """
    p = Path(os.fspath(path))
    try:
        text = p.read_bytes().decode("ascii", errors="replace")
    except OSError as exc:
        raise MeshFileError(f"{p}: cannot read ({exc.strerror or exc})") from None
    text = _CLI_COMMENT.sub(" ", text)
    units = 1.0
    layers: list[tuple[float, list[tuple[int, np.ndarray]]]] = []
    try:
        commands = text.split("$$")
        if commands[0].strip():
            raise ValueError("text before the first $$ command")
        for command in commands[1:]:
            name, _, params = command.partition("/")
            name = name.strip().upper()
            params = "".join(params.split())  # parameters may span lines
            if name == "BINARY":
                raise ValueError("binary CLI is not supported")
            elif name == "UNITS":
                units = float(params)
                if not (math.isfinite(units) and units > 0):
                    raise ValueError(f"bad $$UNITS {params!r}")
            elif name == "LAYER":
                layers.append((float(params) * units, []))
            elif name == "POLYLINE":
                if not layers:
                    raise ValueError("$$POLYLINE before the first $$LAYER")
                fields = params.split(",")
                _id, direction, n = int(fields[0]), int(fields[1]), int(fields[2])
                coords = np.array(fields[3:], dtype=np.float64)
                if coords.size != 2 * n:
                    raise ValueError(f"$$POLYLINE announces {n} points but has {coords.size / 2:g}")
                layers[-1][1].append((direction, coords.reshape(n, 2) * units))
    except (ValueError, IndexError) as exc:
        raise MeshFileError(f"{p}: not a valid ASCII CLI file ({exc})") from None
    return layers


