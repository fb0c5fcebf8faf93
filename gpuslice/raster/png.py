"""Greyscale PNG layers, encoded without touching blank pixels, on a thread pool.

A layer's PNG is greyscale, 8 bits, filter 0 on every row, one IDAT. Most rows of a resin layer are blank, so the
zlib stream is assembled from pieces that each end with a full flush (byte-aligned raw deflate that references
nothing before it, so pieces can be concatenated):

* ``k`` blank rows (filter byte + zeros): precomputed once per display width for every power of two, at level 9,
  and concatenated for the binary digits of ``k`` (above and below the layer's bounding box);
* the bounding box's rows (full width), compressed per layer at ``level`` (default 1);
* an empty final block (``03 00``), then the Adler-32 of the whole image, carried arithmetically over the blank
  runs (n zeros leave A unchanged and add n·A to B) and over the box rows from the tile's row and column sums.

The deflater is ISA-L's (``isal``, optional, 4-5x faster than zlib at level 1 here, see docs/BENCHMARKS.md) when
installed, else zlib's. Both release the GIL, so a thread pool encodes layers while the rasteriser runs
(:func:`encode_all`).
"""

from __future__ import annotations

import os
import struct
import threading
import zlib
from collections import deque
from collections.abc import Callable, Iterable

import numpy as np

from ..errors import ParameterError
from ..prefetch import Workers
from .coverage import Tile

__all__ = ["PngEncoder", "deflate_module", "encode_all", "png_chunk"]

_PNG_SIG = b"\x89PNG\r\n\x1a\n"
_MOD_ADLER = 65521
_FINAL_EMPTY_BLOCK = b"\x03\x00"


def deflate_module(prefer: str = "auto"):
    """The deflate implementation: ``isal.isal_zlib`` when installed (``prefer="auto"`` or ``"isal"``), else
    :mod:`zlib`. Both have the zlib API (``compressobj``, ``Z_FULL_FLUSH``)."""
    if prefer in ("auto", "isal"):
        try:
            from isal import isal_zlib

            return isal_zlib
        except ImportError:
            if prefer == "isal":
                raise ParameterError("isal is not installed (pip install isal)") from None
    if prefer not in ("auto", "isal", "zlib"):
        raise ParameterError(f"unknown deflater '{prefer}' (use auto, isal or zlib)")
    return zlib


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)))


def _adler_zeros(value: int, n: int) -> int:
    a, b = value & 0xFFFF, value >> 16
    return (((b + n * a) % _MOD_ADLER) << 16) | a


def _adler_tile(value: int, data: np.ndarray, c0: int, row_bytes: int) -> int:
    """Adler-32 continued over ``h`` full PNG rows that are zero except ``data`` (h, w) at byte ``1 + c0`` of each:
    from (a0, b0), n bytes d_i give a = a0 + Σ d_i and b = b0 + n·a0 + Σ (n − i)·d_i, and Σ i·d_i needs only the
    tile's row and column sums (a fraction of the cost of ``adler32`` over the zeros)."""
    h, w = data.shape
    n = h * row_bytes
    rs = np.add.reduce(data, axis=1, dtype=np.uint64)
    cs = np.add.reduce(data, axis=0, dtype=np.uint64)
    total = int(rs.sum())
    weighted = row_bytes * int(np.dot(np.arange(h, dtype=np.uint64), rs)) + int(
        np.dot(np.arange(1 + c0, 1 + c0 + w, dtype=np.uint64), cs)
    )
    a0, b0 = value & 0xFFFF, value >> 16
    a = (a0 + total) % _MOD_ADLER
    b = (b0 + n * a0 + n * total - weighted) % _MOD_ADLER
    return (b << 16) | a


class PngEncoder:
    """Encodes one display's layers (nx × ny greyscale) as PNG bytes from their :class:`~gpuslice.raster.Tile`.

    level : deflate level of the bounding-box rows (1: fastest; the blank rows are precomputed at 9).
    deflater : ``"auto"`` (isal if installed), ``"isal"`` or ``"zlib"``. Thread-safe: :meth:`encode` keeps no state.
    """

    def __init__(self, nx: int, ny: int, level: int = 1, deflater: str = "auto") -> None:
        if not 0 <= level <= 9:
            raise ParameterError(f"PNG level must be 0..9, got {level}")
        self.nx, self.ny, self.level = int(nx), int(ny), int(level)
        self.z = deflate_module(deflater)
        if self.z is not zlib and self.level > 3:  # isal has levels 0..3
            self.level = 3
        self.row_bytes = self.nx + 1
        self._blank_cache: list[bytes] | None = None  # made at the first tile (runs never need it)
        self._lock = threading.Lock()
        self._header = _PNG_SIG + png_chunk(b"IHDR", struct.pack(">IIBBBBB", self.nx, self.ny, 8, 0, 0, 0, 0))
        self._end = png_chunk(b"IEND", b"")

    @property
    def _blank(self) -> list[bytes]:
        """``[j]``: 2**j blank rows, raw deflate at level 9 ending in a full flush (0.3 s at 12K: made once, lazily)."""
        with self._lock:
            if self._blank_cache is None:
                blank, j = [], 0
                while (1 << j) <= self.ny:
                    c = zlib.compressobj(9, zlib.DEFLATED, -15, 9)
                    blank.append(c.compress(bytes(self.row_bytes << j)) + c.flush(zlib.Z_FULL_FLUSH))
                    j += 1
                self._blank_cache = blank
            return self._blank_cache

    def _blank_rows(self, k: int) -> list[bytes]:
        blank = self._blank
        return [blank[j] for j in range(len(blank)) if (k >> j) & 1]

    def encode(self, tile: Tile) -> bytes:
        """The PNG file of the layer whose non-blank part is ``tile``."""
        h, w = tile.data.shape
        r0, c0 = tile.row0, tile.col0
        if h == 0 or w == 0:
            r0, h = self.ny, 0
        parts = [b"\x78\x01", *self._blank_rows(r0)]
        adler = _adler_zeros(1, r0 * self.row_bytes)
        if h:
            rows = np.zeros((h, self.row_bytes), np.uint8)
            rows[:, 1 + c0 : 1 + c0 + w] = tile.data
            buf = rows.data
            c = self.z.compressobj(self.level, self.z.DEFLATED, -15)
            parts += [c.compress(buf), c.flush(self.z.Z_FULL_FLUSH)]
            adler = _adler_tile(adler, tile.data, c0, self.row_bytes)
        rest = self.ny - r0 - h
        parts += self._blank_rows(rest)
        adler = _adler_zeros(adler, rest * self.row_bytes)
        parts += [_FINAL_EMPTY_BLOCK, struct.pack(">I", adler)]
        return self._header + png_chunk(b"IDAT", b"".join(parts)) + self._end


def encode_all(
    tiles: Iterable[Tile],
    encoder: PngEncoder | Callable[[Tile], bytes | tuple[bytes, bytes]],
    sink: Callable[[int, object], None],
    workers: int | None,
    on_tile: Callable[[Tile], None] | None = None,
    progress: Callable[[int], None] | None = None,
    many: Callable[[list], list] | None = None,
    chunk: Callable[[Iterable], Iterable[list]] | None = None,
) -> dict[str, float]:
    """Encode ``tiles`` on a thread pool (``encoder.encode`` or ``encoder(tile)``: the PNG, or (PNG, more)) and hand
    ``(k, encoded)`` to ``sink`` in order; returns the layer count and PNG bytes.

    ``many`` and ``chunk``: the tiles grouped by ``chunk`` (lists of consecutive tiles) and each group encoded by one
    call ``many(group)`` (one result per tile, in order: fewer, larger numpy passes); ``on_tile``, ``sink`` and
    ``progress`` still see one tile at a time. An encoded tile may also be its size (an int: the encoder wrote it)."""
    workers = workers or os.cpu_count() or 1
    encode = getattr(encoder, "encode", encoder)
    if many is None or chunk is None:
        many, groups = (lambda group: [encode(group[0])]), ([t] for t in tiles)
    else:
        groups = chunk(tiles)
    n_bytes = 0
    count = 0

    def drain_one() -> None:
        nonlocal n_bytes, count, in_flight
        in_flight -= sizes.popleft()
        for data in pending.popleft().result():
            sink(count, data)
            n_bytes += data if isinstance(data, int) else len(data if isinstance(data, bytes) else data[0])
            count += 1
            if progress:
                progress(count)

    # in flight: at most 4 tasks a thread, and at most max(128, 16 per thread) layers (their runs' batches stay alive)
    max_layers = max(128, 16 * workers)
    in_flight = 0
    with Workers(workers, "gpuslice-encode") as pool:
        pending: deque = deque()
        sizes: deque = deque()
        for group in groups:
            if on_tile is not None:
                for tile in group:
                    on_tile(tile)
            pending.append(pool.submit(many, group))
            sizes.append(len(group))
            in_flight += len(group)
            while len(pending) > 4 * workers or in_flight > max_layers or (pending and pending[0].done()):
                drain_one()
        while pending:
            drain_one()
    return {"layers": count, "png_bytes": n_bytes}
