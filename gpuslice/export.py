"""Writing slicing results to disk: atomic files, SVG, CLI (Common Layer Interface) and JSON reports.

Every writer here goes through :func:`atomic_path`: the output is written under a temporary name in the
destination's directory and renamed over the final name only once it is complete, so an interrupted run
(an exception, Ctrl-C, a full disk) never leaves a truncated file under the name the user asked for.

Conventions shared by the writers:

* Lengths are in mm, as in :class:`~gpuslice.result.SliceResult`.
* Output bytes are a pure function of the input (no dates, no timings, no host names), so two writes of the
  same result are byte-identical.
* Coordinates are written in fixed-point decimal, ``decimals`` digits after the point (4 by default, i.e.
  0.1 µm), rounded half-to-even from the float32 value, never in exponent notation, with no ``-`` on zero.
  The text is produced by a vectorised numpy formatter (no Python-level work per point) and streamed out
  in chunks of layers, so a result with millions of points neither builds one giant string nor spends
  seconds in ``%`` formatting.

Formats:

* ``.svg`` (:func:`write_svg`): all layers in one file, one ``<g id="layer-i">`` per layer; 1 SVG user unit
  = 1 mm; y is negated (``y_svg = -y``) so that +y points up on the picture.
* ``.cli`` (:func:`write_cli`, read back by :func:`read_cli`): Common Layer Interface 2.0, ASCII; each
  layer is labelled with the height of its *top* (``bottom + thickness``).
* ``.npz``: :meth:`SliceResult.save <gpuslice.result.SliceResult.save>`.
* ``.json`` reports (:func:`write_report`): ``indent=1``, sorted keys, numpy values made plain.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import secrets
import shutil
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import MeshFileError, ParameterError

if TYPE_CHECKING:
    from .result import SliceResult

__all__ = [
    "atomic_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "write_svg",
    "write_cli",
    "read_cli",
    "write_report",
    "export",
    "CLI_CLOCKWISE",
    "CLI_COUNTER_CLOCKWISE",
    "CLI_OPEN",
]

PathLike = str | os.PathLike

#: CLI polyline direction codes (CLI 2.0): 0 clockwise = internal (hole), 1 counter-clockwise = external
#: (outer contour), 2 open line.
CLI_CLOCKWISE = 0
CLI_COUNTER_CLOCKWISE = 1
CLI_OPEN = 2

# Points formatted per vectorised batch; bounds the memory the writers use (about 100 bytes a point).
_CHUNK_POINTS = 1 << 19
# Largest |coordinate| (in output units) the fixed-point formatter accepts: far beyond any printer, far
# below int64 overflow at 9 decimals.
_MAX_ABS = 1e9
_POW10 = 10 ** np.arange(19, dtype=np.int64)


# ---------------------------------------------------------------------------------------------------------
# atomic files
# ---------------------------------------------------------------------------------------------------------
def _remove(path: Path) -> None:
    """Remove a file, link or directory tree at ``path`` if there is one; never raises."""
    with contextlib.suppress(OSError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def _fsync_file(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _fsync_dir(path: Path) -> None:
    # Makes the rename itself durable on POSIX; directories cannot be opened on Windows, hence best effort.
    with contextlib.suppress(OSError, AttributeError):
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextlib.contextmanager
def atomic_path(path: PathLike, *, fsync: bool = True) -> Iterator[Path]:
    """Context manager giving a temporary path that replaces ``path`` when the block succeeds.

    The temporary path lies in the same directory as ``path`` (so the final rename never crosses file
    systems) and is named ``.{name}.tmp-{pid}-{random}{suffix}``: hidden, unique, and ending with the final
    name's suffix for writers that look at it (``np.savez`` appends ``.npz`` otherwise). The block creates
    whatever it wants at that path, a file or a directory. When the block completes, the temporary is
    flushed to disk (``fsync=True``) and renamed over ``path`` with :func:`os.replace`; when the block
    raises anything, ``KeyboardInterrupt`` and ``SystemExit`` included, the temporary (file or directory
    tree) is removed and the exception propagates. Either way no partial output is ever visible under
    ``path`` and no temporary is left behind.

    Parameters
    ----------
    path
        The final output path. Its directory must exist.
    fsync
        Flush the written file and the directory entry to stable storage, so a power cut right after the
        rename cannot leave an empty file under ``path``.

    Yields
    ------
    Path
        The temporary path to write to (nothing exists there yet).

    Raises
    ------
    ParameterError
        The directory of ``path`` does not exist, or ``path`` is an existing directory and the block wrote
        a file.
    FileNotFoundError
        The block completed without creating anything at the temporary path.

    Notes
    -----
    A directory written by the block replaces an existing directory at ``path`` by two renames (the old
    tree is moved aside, the new one moved in, the old one deleted); readers see either the complete old
    tree or the complete new one, though there is an instant where ``path`` does not exist.

    Examples
    --------
    >>> with atomic_path("out.bin") as tmp:  # doctest: +SKIP
    ...     with open(tmp, "wb") as fh:
    ...         fh.write(data)
    """
    final = Path(os.fspath(path))
    directory = final.parent
    if not directory.is_dir():
        raise ParameterError(f"{final}: directory {directory} does not exist")
    tmp = directory / f".{final.name}.tmp-{os.getpid()}-{secrets.token_hex(4)}{final.suffix}"
    try:
        yield tmp
        if not tmp.exists() and not tmp.is_symlink():
            raise FileNotFoundError(f"{final}: nothing was written to the temporary path {tmp}")
        if tmp.is_dir() and not tmp.is_symlink():
            _replace_dir(tmp, final)
        else:
            if final.is_dir() and not final.is_symlink():
                raise ParameterError(f"{final}: is a directory")
            if fsync:
                _fsync_file(tmp)
            os.replace(tmp, final)
        if fsync:
            _fsync_dir(directory)
    except BaseException:
        _remove(tmp)
        raise


def _replace_dir(tmp: Path, final: Path) -> None:
    if not final.exists() and not final.is_symlink():
        os.replace(tmp, final)
        return
    if not final.is_dir() or final.is_symlink():
        os.replace(tmp, final)  # raises NotADirectoryError on POSIX: a directory cannot replace a file
        return
    old = final.parent / f".{final.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
    os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        os.replace(old, final)
        raise
    _remove(old)


def atomic_write_bytes(path: PathLike, data: bytes | bytearray | memoryview) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def atomic_write_text(path: PathLike, text: str, *, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically, encoded with ``encoding``, newlines written as given."""
    atomic_write_bytes(path, text.encode(encoding))


# ---------------------------------------------------------------------------------------------------------
# vectorised fixed-point formatting
# ---------------------------------------------------------------------------------------------------------
Token = tuple[np.ndarray, "bytes | Sequence[bytes]"]


def _format_numbers(values: np.ndarray, decimals: int, sep: np.ndarray | int | None) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-point text of ``values``, each followed by its one-byte separator ``sep`` (none if ``None``).

    Every value is first written right-aligned in a row of a (n, W) uint8 table, one column per character
    (sign, integer digits zero-padded to the widest, point, fraction digits, separator), column by
    column with whole-column numpy operations; the unused leading columns are then squeezed out with one
    boolean mask. Returns the text and the (n + 1,) start offset of each value in it.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    n = v.size
    q = np.rint(v * float(10**decimals)).astype(np.int64)
    neg = q < 0
    a = np.abs(q)
    a_max = int(a.max()) if n else 0
    n_digits = max(len(str(a_max)), decimals + 1)  # digit columns, integer and fraction
    n_int = n_digits - decimals  # integer digit columns
    width = 1 + n_digits + (1 if decimals else 0) + (0 if sep is None else 1)
    table = np.empty((n, width), dtype=np.uint8)
    x = a.astype(np.int32) if a_max < 2**31 else a.copy()
    col = width - 1
    if sep is not None:
        table[:, col] = sep
        col -= 1
    for j in range(n_digits):
        if decimals and j == decimals:
            table[:, col] = ord(".")
            col -= 1
        table[:, col] = x % 10 + 48
        x //= 10
        col -= 1
    # col == 0: the sign column. Integer digits actually needed, at least one:
    ip = a // _POW10[decimals] if decimals else a
    nd = np.ones(n, dtype=np.int64)
    for k in range(1, n_int):
        nd += ip >= _POW10[k]
    lead = n_int - nd  # zero-padding columns before the first digit (columns 1 .. lead)
    rows = np.flatnonzero(neg)
    table[rows, lead[rows]] = ord("-")
    first = lead + 1 - neg  # first column kept
    keep = np.ones((n, width), dtype=bool)
    for c in range(n_int):
        keep[:, c] = first <= c
    starts = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(width - first, out=starts[1:])
    return table[keep], starts


def _format_fixed(
    values: np.ndarray,
    decimals: int,
    sep: np.ndarray | int | None = None,
    before: Sequence[Token] = (),
    after: Sequence[Token] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """Format ``values`` as fixed-point decimal text, with byte strings inserted around the numbers.

    Value ``i`` becomes ``[before tokens at i] number sep[i] [after tokens at i]``, tokens in the order of
    the lists. Each token entry is ``(indices, token)`` where ``token`` is one ``bytes`` for all indices or
    a sequence of ``bytes``, one per index; indices within one entry must be distinct. ``sep`` is a uint8
    code per value, one code for all, or ``None`` for no separator. The number is
    ``round(v * 10**decimals)`` (half to even) written with exactly ``decimals`` digits after the point (no
    point when ``decimals == 0``), ``-`` only when the rounded value is non-zero. The caller guarantees
    finite values with ``|v| <= _MAX_ABS``.

    Returns ``(buf, starts)``: ``buf`` the uint8 text, value ``i`` spanning ``buf[starts[i]:starts[i + 1]]``
    (its tokens included).
    """
    text, c_start = _format_numbers(values, decimals, sep)
    n = c_start.size - 1
    # Every token is an insertion into ``text``: ``before`` tokens of value i at its start, in slot 2i;
    # ``after`` tokens at its end, in slot 2i + 1. Slots increase with the position; within a slot the
    # tokens keep the order of the lists.
    entries = [(0, e) for e in before] + [(1, e) for e in after]
    slot_parts, key_parts, len_parts, blob_parts = [], [], [], []
    for order, (kind, (idx, tok)) in enumerate(entries):
        idx = np.asarray(idx, dtype=np.int64)
        if isinstance(tok, bytes | bytearray):
            lens = np.full(idx.size, len(tok), dtype=np.int64)
            blob = np.tile(np.frombuffer(bytes(tok), dtype=np.uint8), idx.size)
        else:
            lens = np.fromiter(map(len, tok), dtype=np.int64, count=len(tok))
            blob = np.frombuffer(b"".join(tok), dtype=np.uint8)
        slot = 2 * idx + kind
        slot_parts.append(slot)
        key_parts.append(slot * len(entries) + order)
        len_parts.append(lens)
        blob_parts.append(blob)
    lens = np.concatenate(len_parts) if len_parts else np.zeros(0, dtype=np.int64)
    if not lens.sum():
        return text, c_start
    slot = np.concatenate(slot_parts)
    blob = np.concatenate(blob_parts)
    blob_first = np.zeros(lens.size, dtype=np.int64)
    np.cumsum(lens[:-1], out=blob_first[1:])
    order = np.argsort(np.concatenate(key_parts), kind="stable")
    slot, lens, blob_first = slot[order], lens[order], blob_first[order]
    ins_before = np.zeros(lens.size + 1, dtype=np.int64)  # token bytes before sorted insertion k
    np.cumsum(lens, out=ins_before[1:])
    total = int(ins_before[-1])
    pos = c_start[(slot + 1) // 2]  # where in ``text`` each insertion goes
    buf = np.empty(text.size + total, dtype=np.uint8)
    dst = np.repeat(pos, lens) + np.arange(total)
    buf[dst] = blob[np.repeat(blob_first - ins_before[:-1], lens) + np.arange(total)]
    is_text = np.ones(buf.size, dtype=bool)
    is_text[dst] = False
    buf[is_text] = text
    # value i starts after the tokens of every slot below 2i
    per_slot = np.zeros(2 * n + 2, dtype=np.int64)
    np.add.at(per_slot, slot, lens)
    starts = c_start.copy()
    starts[1:] += np.cumsum(per_slot)[1:-1:2]
    starts[-1] = buf.size
    return buf, starts


def _fmt_scalar(x: float, decimals: int = 6) -> str:
    """One number as short fixed-point text: at most ``decimals`` decimals, trailing zeros dropped."""
    s = f"{round(float(x), decimals) + 0.0:.{decimals}f}"
    if "." in s:
        s = s.rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _check_decimals(decimals: int) -> int:
    if isinstance(decimals, bool) or not isinstance(decimals, int | np.integer) or not 0 <= decimals <= 9:
        raise ParameterError(f"decimals must be an integer from 0 to 9, got {decimals!r}")
    return int(decimals)


def _arrays(result: SliceResult) -> tuple[np.ndarray, ...]:
    """The result's arrays with the dtypes the writers rely on, checked for consistency."""
    points = np.asarray(result.points)
    loop_offsets = np.asarray(result.loop_offsets, dtype=np.int64)
    layer_offsets = np.asarray(result.layer_offsets, dtype=np.int64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ParameterError(f"result points must be (P, 2), got shape {points.shape}")
    n_layers = int(np.asarray(result.z).shape[0])
    if (
        layer_offsets.shape != (n_layers + 1,)
        or loop_offsets.ndim != 1
        or loop_offsets.size < 1
        or layer_offsets[0] != 0
        or layer_offsets[-1] != loop_offsets.size - 1
        or loop_offsets[0] != 0
        or loop_offsets[-1] != points.shape[0]
        or np.any(np.diff(loop_offsets) < 0)
        or np.any(np.diff(layer_offsets) < 0)
    ):
        raise ParameterError("result offsets are inconsistent with its points and layers")
    if points.size and not np.isfinite(points).all():
        raise ParameterError("result has non-finite coordinates")
    return points, loop_offsets, layer_offsets


def _bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min x, min y), (max x, max y) as float64; column by column (``min(axis=0)`` on (P, 2) is slow)."""
    lo = np.array([points[:, 0].min(), points[:, 1].min()], dtype=np.float64)
    hi = np.array([points[:, 0].max(), points[:, 1].max()], dtype=np.float64)
    return lo, hi


def _layer_chunks(point_counts_cum: np.ndarray) -> Iterator[tuple[int, int]]:
    """Split layers into runs ``[a, b)`` of about ``_CHUNK_POINTS`` points each (at least one layer)."""
    n_layers = point_counts_cum.size - 1
    a = 0
    while a < n_layers:
        b = int(np.searchsorted(point_counts_cum, point_counts_cum[a] + _CHUNK_POINTS, side="right")) - 1
        b = min(max(b, a + 1), n_layers)
        yield a, b
        a = b


# ---------------------------------------------------------------------------------------------------------
# SVG
# ---------------------------------------------------------------------------------------------------------
def write_svg(
    result: SliceResult,
    path: PathLike,
    *,
    scale: float | None = None,
    decimals: int = 4,
) -> None:
    """Write every layer of ``result`` to one SVG file, atomically.

    Layout of the file:

    * One SVG user unit is 1 mm. Coordinates are written ``x,-y``: **y is negated** (``y_svg = -y``, no
      transform), so +y of the part points up on the picture as it does looking down on the bed from +z;
      outer loops, counter-clockwise in the result, appear clockwise in SVG coordinates.
    * ``viewBox`` is the XY bounding box of all points grown by a margin of 2 % of its larger side (at least
      0.5 mm) on each side, in those flipped coordinates; ``width``/``height`` are the viewBox size times
      ``scale`` in ``mm``, so at the default scale the drawing prints at true size.
    * One ``<g>`` per layer, all visible (overlaid, as Slic3r's ``--export-svg``), in layer order, with
      ``id="layer-{i}"``, ``class="layer"``, ``data-z`` (the cutting plane, mm), ``data-thickness`` (mm),
      ``data-bottom`` (mm), and ``inkscape:groupmode="layer"`` so Inkscape lists the layers and can show
      one at a time. Fill and stroke are presentation attributes on each layer group.
    * Each polygon (an outer loop and its holes) is one ``<path class="polygon" fill-rule="evenodd">`` whose
      ``d`` holds the outer loop then each hole as subpaths ``M x,y L x,y x,y ... Z``, so holes are
      drawn as holes. Open chains (``loop_closed`` False) are ``<path class="open" fill="none">`` with a
      red stroke and no ``Z``. A closed hole whose ``loop_parent`` is not an outer loop written before it
      in its layer is drawn as ``<path class="orphan" fill="none">``, so it never fills. Empty loops are
      skipped.

    Numbers: coordinates with exactly ``decimals`` decimals (4: 0.1 µm), rounded half-to-even from the
    float32 value; z, thickness and the header sizes as the shortest decimal with at most 6 decimals.
    The bytes depend only on the result's geometry (``meta`` and ``repairs`` are not written).

    Parameters
    ----------
    result
        The slicing result.
    path
        Output file, conventionally ``*.svg``.
    scale
        Drawing-size factor applied to ``width``/``height`` only (the viewBox stays in mm); ``None`` means 1,
        true size.
    decimals
        Digits after the decimal point for coordinates, 0 to 9.

    Raises
    ------
    ParameterError
        ``scale`` is not a positive finite number, ``decimals`` is out of range, or the result is
        malformed (inconsistent offsets, non-finite coordinates, coordinates beyond 1e9 mm).
    """
    decimals = _check_decimals(decimals)
    if scale is None:
        scale = 1.0
    if (
        isinstance(scale, bool)
        or not isinstance(scale, int | float | np.number)
        or not (math.isfinite(scale) and scale > 0)
    ):
        raise ParameterError(f"scale must be a positive finite number, got {scale!r}")
    points, loop_offsets, layer_offsets = _arrays(result)
    if points.size and np.abs(points).max() > _MAX_ABS:
        raise ParameterError("result coordinates are too large to write (beyond 1e9 mm)")
    z = np.asarray(result.z, dtype=np.float64)
    thickness = np.asarray(result.thickness, dtype=np.float64)
    bottom = np.asarray(result.bottom, dtype=np.float64)
    is_hole = np.asarray(result.loop_is_hole, dtype=bool).tolist()
    closed = np.asarray(result.loop_closed, dtype=bool)
    closed_list = closed.tolist()
    parent = np.asarray(result.loop_parent, dtype=np.int64).tolist()

    if points.size:
        lo, hi = _bounds(points)
    else:
        lo = hi = np.zeros(2)
    size = hi - lo
    margin = max(0.5, 0.02 * float(size.max()))
    vb_x, vb_y = lo[0] - margin, -hi[1] - margin
    vb_w, vb_h = size[0] + 2 * margin, size[1] + 2 * margin
    stroke = _fmt_scalar(max(0.01, 0.002 * max(vb_w, vb_h)), 4)
    f = _fmt_scalar
    header = (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<svg xmlns="http://www.w3.org/2000/svg"'
        ' xmlns:inkscape="http://www.inkscape.org/namespaces/inkscape" version="1.1"'
        f' width="{f(vb_w * scale)}mm" height="{f(vb_h * scale)}mm"'
        f' viewBox="{f(vb_x)} {f(vb_y)} {f(vb_w)} {f(vb_h)}">\n'
        f"<!-- gpuslice: {z.size} layers; 1 user unit = 1 mm; written as x,-y so that +y points up -->\n"
    )
    layer_attrs = (
        f' fill="#3b7dd8" fill-opacity="0.35" stroke="#1b3f73" stroke-width="{stroke}" stroke-linejoin="round"'
    )
    open_attrs = f'class="open" fill="none" stroke="#d62728" stroke-width="{stroke}"'

    counts = np.diff(loop_offsets).tolist()
    cum = loop_offsets[layer_offsets]
    with atomic_path(path) as tmp, open(tmp, "wb", buffering=1 << 20) as fh:
        fh.write(header.encode())
        for l0, l1 in _layer_chunks(cum):
            r0, r1 = int(layer_offsets[l0]), int(layer_offsets[l1])
            p0, p1 = int(loop_offsets[r0]), int(loop_offsets[r1])
            buf, starts = _svg_chunk(points[p0:p1], loop_offsets[r0 : r1 + 1] - p0, closed[r0:r1], decimals)
            mv = memoryview(buf)
            # byte range of loop r of the chunk: [lb[r], lb[r + 1]); each loop's text ends with one space
            lb = starts[2 * (loop_offsets[r0 : r1 + 1] - p0)].tolist()
            for i in range(l0, l1):
                zi, ti, bi = f(z[i]), f(thickness[i]), f(bottom[i])
                label = f'inkscape:groupmode="layer" inkscape:label="layer {i} z={zi}"'
                data = f'data-z="{zi}" data-thickness="{ti}" data-bottom="{bi}"'
                fh.write(f'<g id="layer-{i}" class="layer" {label} {data}{layer_attrs}>\n'.encode())
                order: list[tuple[int, list[int]]] = []  # (kind, loops): 0 polygon, 1 open, 2 orphan hole
                polygon_of: dict[int, list[int]] = {}
                for r in range(int(layer_offsets[i]), int(layer_offsets[i + 1])):
                    if counts[r] == 0:
                        continue
                    if not closed_list[r]:
                        order.append((1, [r]))
                    elif not is_hole[r]:
                        loops = [r]
                        polygon_of[r] = loops
                        order.append((0, loops))
                    elif parent[r] in polygon_of:
                        polygon_of[parent[r]].append(r)
                    else:
                        order.append((2, [r]))
                for kind, loops in order:
                    if kind == 0:
                        fh.write(b'<path class="polygon" fill-rule="evenodd" d="')
                    elif kind == 1:
                        fh.write(f'<path {open_attrs} d="'.encode())
                    else:
                        fh.write(b'<path class="orphan" fill="none" d="')
                    for r in loops[:-1]:
                        fh.write(mv[lb[r - r0] : lb[r - r0 + 1]])
                    r = loops[-1]
                    fh.write(mv[lb[r - r0] : lb[r - r0 + 1] - 1])  # drop the trailing space
                    fh.write(b'"/>\n')
                fh.write(b"</g>\n")
        fh.write(b"</svg>\n")


def _svg_chunk(
    pts: np.ndarray, offsets: np.ndarray, closed: np.ndarray, decimals: int
) -> tuple[np.ndarray, np.ndarray]:
    """Path text of every loop of a chunk: ``M x,y L x,y x,y ... Z `` (closed) or ``... x,y `` (open)."""
    n_pts = pts.shape[0]
    values = np.empty((n_pts, 2), dtype=np.float64)
    values[:, 0] = pts[:, 0]
    np.negative(pts[:, 1], out=values[:, 1])
    first, end = offsets[:-1], offsets[1:]
    nonempty = end > first
    lengths = end - first
    before = [
        (2 * first[nonempty], b"M "),
        (2 * (first[lengths >= 2] + 1), b"L "),
    ]
    after = [(2 * end[nonempty & closed] - 1, b"Z ")]
    sep = np.empty(2 * n_pts, dtype=np.uint8)
    sep[0::2] = ord(",")
    sep[1::2] = ord(" ")
    return _format_fixed(values, decimals, sep, before, after)


# ---------------------------------------------------------------------------------------------------------
# CLI (Common Layer Interface)
# ---------------------------------------------------------------------------------------------------------
def _cli_decimals(units_mm: float) -> int:
    # enough decimals for 0.1 µm resolution in the file's units
    return max(0, min(9, math.ceil(math.log10(units_mm / 1e-4) - 1e-9)))


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
      ``0.0001``), rounded half-to-even. No date or other varying header, so output is deterministic.

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
    decimals = _cli_decimals(units) if decimals is None else _check_decimals(decimals)
    if not isinstance(label, str) or re.search(r"[,/\r\n$]", label):
        raise ParameterError(f"label must be text without commas, slashes, '$' or line breaks, got {label!r}")
    points, loop_offsets, layer_offsets = _arrays(result)
    thickness = np.asarray(result.thickness, dtype=np.float64)
    bottom = np.asarray(result.bottom, dtype=np.float64)
    top = (bottom + thickness) / units
    if (points.size and np.abs(points).max() / units > _MAX_ABS) or np.abs(top).max(initial=0) > _MAX_ABS:
        raise ParameterError("result coordinates are too large to write in these units")
    is_hole = np.asarray(result.loop_is_hole, dtype=bool)
    closed = np.asarray(result.loop_closed, dtype=bool)
    direction = np.where(~closed, CLI_OPEN, np.where(is_hole, CLI_CLOCKWISE, CLI_COUNTER_CLOCKWISE))
    n_layers = int(thickness.size)

    def fnum(x: Sequence[float] | np.ndarray) -> list[str]:
        text, _ = _format_numbers(np.asarray(x, dtype=np.float64), decimals, ord("\n"))
        return text.tobytes().decode().split("\n")[:-1]

    lines = ["$$HEADERSTART", "$$ASCII", f"$$UNITS/{units_text}", "$$VERSION/200", f"$$LABEL/1,{label}"]
    if points.size and n_layers:
        lo, hi = _bounds(points)
        lo, hi = lo / units, hi / units
        box = (lo[0], lo[1], bottom[0] / units, hi[0], hi[1], top[-1])
        lines.append("$$DIMENSION/" + ",".join(fnum(box)))
    lines += [f"$$LAYERS/{n_layers:06d}", "$$HEADEREND", "$$GEOMETRYSTART", ""]
    top_text = fnum(top)

    cum = loop_offsets[layer_offsets]
    with atomic_path(path) as tmp, open(tmp, "wb", buffering=1 << 20) as fh:
        fh.write("\n".join(lines).encode())
        for l0, l1 in _layer_chunks(cum):
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
    buf, starts = _format_fixed(values, decimals, sep, before)
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


# ---------------------------------------------------------------------------------------------------------
# JSON reports
# ---------------------------------------------------------------------------------------------------------
def _plain(obj: Any) -> Any:
    """``obj`` with numpy values, tuples, sets and paths turned into JSON's own types, recursively."""
    if isinstance(obj, Mapping):
        return {_plain_key(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, set | frozenset):
        return sorted((_plain(v) for v in obj), key=repr)
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj


def _plain_key(key: Any) -> str:
    if isinstance(key, str):
        return key
    if isinstance(key, np.generic):
        key = key.item()
    return json.dumps(key) if isinstance(key, bool | None | float) else str(key)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def write_report(report: Mapping[str, Any], path: PathLike) -> None:
    """Write ``report`` as JSON, atomically.

    The text is ``json.dumps(report, indent=1, sort_keys=True)`` plus a final newline, UTF-8. Numpy arrays
    become (nested) lists, numpy integers/floats/bools plain ``int``/``float``/``bool``, tuples lists,
    sets sorted lists, paths strings, and dictionary keys strings (so keys of mixed types still sort).
    Non-finite floats are written as ``NaN``/``Infinity`` as Python's :mod:`json` does.

    Raises
    ------
    TypeError
        A value has no JSON form.
    """
    text = json.dumps(_plain(report), indent=1, sort_keys=True, ensure_ascii=False, default=_json_default)
    atomic_write_text(path, text + "\n")


# ---------------------------------------------------------------------------------------------------------
# dispatch
# ---------------------------------------------------------------------------------------------------------
def export(result: SliceResult, path: PathLike, **options: Any) -> None:
    """Write ``result`` in the format named by the suffix of ``path`` (case-insensitive).

    ``.npz`` → :meth:`SliceResult.save <gpuslice.result.SliceResult.save>`, ``.svg`` → :func:`write_svg`,
    ``.cli`` → :func:`write_cli`; ``options`` are passed on to the writer (``.npz`` takes none).

    Raises
    ------
    ParameterError
        Unknown suffix, or options the writer does not take.
    """
    p = Path(os.fspath(path))
    suffix = p.suffix
    kind = suffix.lower()
    if kind == ".npz":
        if options:
            raise ParameterError(f"{p}: .npz output takes no options, got {', '.join(sorted(options))}")
        result.save(p)
    elif kind in (".svg", ".cli"):
        writer = write_svg if kind == ".svg" else write_cli
        try:
            writer(result, p, **options)
        except TypeError as exc:
            if "unexpected keyword" not in str(exc):
                raise
            raise ParameterError(f"{p}: {exc}") from None
    else:
        raise ParameterError(f"{p}: unknown output format '{suffix}' (use .npz, .svg or .cli)")
