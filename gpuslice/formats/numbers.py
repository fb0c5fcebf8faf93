"""Text of coordinates for the text formats: a vectorised fixed-point formatter (no Python work per point) and the
result checks and layer chunking the writers share.

Coordinates are written in fixed-point decimal, ``decimals`` digits after the point (4 by default, i.e. 0.1 µm),
rounded half-to-even from the float32 value, never in exponent notation, with no ``-`` on zero. Text is streamed
out in chunks of layers (about ``CHUNK_POINTS`` points), so a result with millions of points neither builds one
giant string nor spends seconds in ``%`` formatting.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..errors import ParameterError

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

PathLike = str | os.PathLike

__all__ = ["Token", "CHUNK_POINTS", "MAX_ABS", "format_numbers", "format_fixed", "fmt_scalar", "check_decimals",
           "result_arrays", "checked_result", "stacked_slabs", "point_bounds", "layer_chunks"]

# Points formatted per vectorised batch; bounds the memory the writers use (about 100 bytes a point).
CHUNK_POINTS = 1 << 19
# Largest |coordinate| (in output units) the fixed-point formatter accepts: far beyond any printer, far
# below int64 overflow at 9 decimals.
MAX_ABS = 1e9
_POW10 = 10 ** np.arange(19, dtype=np.int64)


Token = tuple[np.ndarray, "bytes | Sequence[bytes]"]


def format_numbers(values: np.ndarray, decimals: int, sep: np.ndarray | int | None) -> tuple[np.ndarray, np.ndarray]:
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


def format_fixed(
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
    finite values with ``|v| <= MAX_ABS``.

    Returns ``(buf, starts)``: ``buf`` the uint8 text, value ``i`` spanning ``buf[starts[i]:starts[i + 1]]``
    (its tokens included).
    """
    text, c_start = format_numbers(values, decimals, sep)
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


def fmt_scalar(x: float, decimals: int = 6) -> str:
    """One number as short fixed-point text: at most ``decimals`` decimals, trailing zeros dropped."""
    s = f"{round(float(x), decimals) + 0.0:.{decimals}f}"
    if "." in s:
        s = s.rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def check_decimals(decimals: int) -> int:
    if isinstance(decimals, bool) or not isinstance(decimals, int | np.integer) or not 0 <= decimals <= 9:
        raise ParameterError(f"decimals must be an integer from 0 to 9, got {decimals!r}")
    return int(decimals)


def result_arrays(result: SliceResult) -> tuple[np.ndarray, ...]:
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


def point_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(min x, min y), (max x, max y) as float64; column by column (``min(axis=0)`` on (P, 2) is slow)."""
    lo = np.array([points[:, 0].min(), points[:, 1].min()], dtype=np.float64)
    hi = np.array([points[:, 0].max(), points[:, 1].max()], dtype=np.float64)
    return lo, hi


def layer_chunks(point_counts_cum: np.ndarray, points: int = CHUNK_POINTS) -> Iterator[tuple[int, int]]:
    """Split layers into runs ``[a, b)`` of about ``points`` points each (at least one layer): a writer whose text
    takes more bytes a point asks for fewer (:func:`format_fixed`'s temporaries are ~40 bytes an output byte)."""
    n_layers = point_counts_cum.size - 1
    a = 0
    while a < n_layers:
        b = int(np.searchsorted(point_counts_cum, point_counts_cum[a] + points, side="right")) - 1
        b = min(max(b, a + 1), n_layers)
        yield a, b
        a = b




def stacked_slabs(result: SliceResult, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(bottom, top) float64 (L,) of ``result``'s slabs, mm, for a format that states each layer by its top alone
    (``what``: "a 3MF slice stack", ...), the layer below ending where it starts: a :class:`ParameterError` when
    the slabs do not stack so (explicit planes whose slabs, centred on them, leave gaps or overlap)."""
    bottom = np.asarray(result.bottom, dtype=np.float64)
    top = bottom + np.asarray(result.thickness, dtype=np.float64)
    if top.size > 1:
        eps = 1e-9 * max(1.0, float(np.max(np.abs(top))))
        off = np.flatnonzero(np.abs(bottom[1:] - top[:-1]) > eps)
        if off.size:
            k = int(off[0]) + 1
            raise ParameterError(f"{what} states each layer by its top, the one below ending where it starts, but "
                                 f"layer {k - 1} ends at {top[k - 1]:g} mm and layer {k} starts at {bottom[k]:g} mm "
                                 "(explicit planes): write .npz, .svg or .geojson, which state each slab")
    return bottom, top


def checked_result(result: SliceResult, decimals: int) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """What every text writer checks first: ``decimals`` (0..9), the result's arrays (:func:`result_arrays`) and
    coordinates within ``MAX_ABS`` mm; returns (decimals, points, loop_offsets, layer_offsets)."""
    decimals = check_decimals(decimals)
    points, loop_offsets, layer_offsets = result_arrays(result)
    if points.size and np.abs(points).max() > MAX_ABS:
        raise ParameterError("result coordinates are too large to write (beyond 1e9 mm)")
    return decimals, points, loop_offsets, layer_offsets
