"""``.npz``: the whole :class:`~gpuslice.slicing.result.SliceResult` (arrays and meta), byte-identical for identical
results; read back with :meth:`SliceResult.load <gpuslice.slicing.result.SliceResult.load>`.

Two ways to the same bytes: :func:`write_npz` writes a finished result (``np.savez``); :class:`NpzStream` writes
the points, the one array that grows with the model, while the slicer still makes them (each batch of layers' points
as soon as they are nested, while the next batch is cut and chained), and the other arrays, which are per loop and
per layer, at the end. The result's ``points`` are then a read-only view of the file (``np.memmap``), not a second
copy in memory.

How the stream gets numpy's bytes: an ``.npz`` is a zip of ``.npy`` members, stored (not compressed) with zip64
headers, ``points.npy`` first. Its local zip header and its ``.npy`` header have fixed lengths whatever the number
of points (numpy pads a header so that its first dimension can grow in place), so the points are written at their
final offset; the two headers are written last, once the count is known, with the member's CRC-32 made from the
headers' CRC and the points' (:func:`crc32_combine`). The other members and the zip's directory are then written by
Python's ``zipfile`` exactly as ``np.savez`` writes them. ``tests/formats/test_npz_stream.py`` compares the bytes.
"""

from __future__ import annotations

import io
import os
import time
import zipfile
import zlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

__all__ = ["NpzStream", "crc32_combine", "write_npz"]


def write_npz(result: SliceResult, path: str | os.PathLike) -> None:
    """Write ``result`` as ``.npz`` (uncompressed, fixed zip dates, meta without timings), atomically."""
    result.save(path)


# ---- CRC-32 of two pieces from their own CRCs (zlib's crc32_combine, which Python's zlib does not expose) ----------
_POLY = 0xEDB88320  # CRC-32's polynomial, bits reversed (as zlib.crc32 computes it)


def _mult_mod_p(a: int, b: int) -> int:
    """a(x) b(x) modulo the CRC-32 polynomial, both bit-reversed as zlib holds them."""
    m, p = 1 << 31, 0
    while m:
        if a & m:
            p ^= b
        b = (b >> 1) ^ _POLY if b & 1 else b >> 1
        m >>= 1
    return p


_X2N = [1 << 30]  # x^(2^k) modulo the polynomial, k = 0..31
for _ in range(31):
    _X2N.append(_mult_mod_p(_X2N[-1], _X2N[-1]))


def crc32_combine(crc1: int, crc2: int, len2: int) -> int:
    """The CRC-32 (``zlib.crc32``) of ``A + B`` from ``crc1`` = CRC of A, ``crc2`` = CRC of B and ``len2`` = len(B)
    in bytes: A's CRC carried over B's length (x^(8 len2) modulo the polynomial), plus B's."""
    p, n, k = 1 << 31, int(len2), 3  # x^0; len2 bytes are 8 len2 = len2 * 2^3 bits
    while n:
        if n & 1:
            p = _mult_mod_p(_X2N[k & 31], p)
        n >>= 1
        k += 1
    return _mult_mod_p(p, crc1) ^ crc2


def _npy_header(shape: tuple[int, ...], dtype: np.dtype) -> bytes:
    """The ``.npy`` header (version 1.0, as ``np.save`` writes it) of a C-ordered array."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                               "fortran_order": False, "shape": shape})
    return buf.getvalue()


class NpzStream:
    """A result's ``.npz`` written while it is sliced: the points batch by batch (:meth:`append`, as the slicer's
    ``points_sink``), the rest at :meth:`commit`; atomic as every output (a temporary beside ``path``, renamed at
    :meth:`commit`, removed by :meth:`abort`). The bytes are those of :meth:`SliceResult.save` for the same result.

    Use::

        stream = NpzStream(path)                      # the temporary is made now (a bad folder fails here)
        try:
            result = slice_mesh(mesh, params, points_sink=stream)
            stream.commit(result)                     # result.points is stream.array(): the file's points
        except BaseException:
            stream.abort()
            raise

    ``seconds``: the time spent writing (appends and commit), for the report's ``write`` stage.
    """

    #: the points' dtype and columns (:class:`SliceResult`'s layout)
    DTYPE = np.dtype("<f4")

    def __init__(self, path: str | os.PathLike) -> None:
        from ..io.atomic import atomic_path

        self.path = Path(os.fspath(path))
        self._cm = atomic_path(self.path)
        self._tmp = self._cm.__enter__()
        try:
            self._fh = open(self._tmp, "w+b")  # noqa: SIM115 (closed by commit or abort)
        except BaseException as exc:
            self._cm.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._info = zipfile.ZipInfo("points.npy")  # as ZipFile.open(name, "w") makes it (np.savez)
        self._info.compress_type = zipfile.ZIP_STORED
        self._info.compress_size = self._info.CRC = self._info.flag_bits = 0
        self._info.external_attr = 0o600 << 16
        self._info.header_offset = 0
        self._local = len(self._info.FileHeader(True))
        self._npy = len(_npy_header((0, 2), self.DTYPE))
        self._fh.seek(self._local + self._npy)  # the points go at their final offset; the headers come last
        self._rows = 0
        self._crc = 0
        self._view: np.ndarray | None = None
        self._done = False
        self.seconds = 0.0

    def _named(self, exc: OSError) -> OSError:
        """``exc`` naming the output (not its temporary, nor nothing: a full disk's write names no file)."""
        return OSError(exc.errno, exc.strerror or str(exc), str(self.path))

    def append(self, points: np.ndarray) -> None:
        """Write the next (n, 2) float32 points after those already written."""
        try:
            self._append(points)
        except OSError as exc:
            raise self._named(exc) from None

    def _append(self, points: np.ndarray) -> None:
        t = time.perf_counter()
        pts = np.ascontiguousarray(points, dtype=self.DTYPE)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"points must be (n, 2), got {pts.shape}")
        if pts.size == 0:
            return
        data = memoryview(pts.reshape(-1)).cast("B")
        self._fh.write(data)
        self._crc = zlib.crc32(data, self._crc)
        self._rows += pts.shape[0]
        self.seconds += time.perf_counter() - t

    def array(self) -> np.ndarray:
        """All points appended, (P, 2) float32: a read-only view of the file (nothing more is appended after)."""
        if self._view is None:
            self._fh.flush()
            if self._rows == 0:
                self._view = np.zeros((0, 2), self.DTYPE)
            else:
                self._view = np.memmap(self._tmp, self.DTYPE, "r", offset=self._local + self._npy,
                                       shape=(self._rows, 2))
        return self._view

    def commit(self, result: SliceResult) -> None:
        """Write ``result``'s other arrays and the zip's directory after the points, then rename the file to
        ``path``. ``result.points`` must be :meth:`array`'s."""
        try:
            self._commit(result)
        except OSError as exc:
            raise self._named(exc) from None

    def _commit(self, result: SliceResult) -> None:
        if self._done:
            raise RuntimeError(f"{self.path}: already committed or aborted")
        if result.points is not self.array():
            raise ValueError(f"{self.path}: the result's points are not the ones streamed")
        t = time.perf_counter()
        arrays = result.npz_arrays()
        del arrays["points"]
        fh, info = self._fh, self._info
        head = _npy_header((self._rows, 2), self.DTYPE)
        if len(head) != self._npy:  # (numpy leaves room for 21 digits: a count no file reaches)
            raise RuntimeError(f"{self.path}: the .npy header grew to {len(head)} bytes")
        n_data = self._rows * 8
        info.file_size = info.compress_size = len(head) + n_data
        info.CRC = crc32_combine(zlib.crc32(head), self._crc, n_data)
        end = self._local + self._npy + n_data
        fh.seek(0)
        fh.write(info.FileHeader(True))  # (the same length as the first: zip64's extra is always there)
        fh.write(head)
        fh.seek(end)
        with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:  # (np.savez's, from here on)
            zf.filelist.append(info)
            zf.NameToInfo[info.filename] = info
            for name, value in arrays.items():
                with zf.open(name + ".npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
        fh.close()
        self._done = True
        self._cm.__exit__(None, None, None)  # the rename
        self.seconds += time.perf_counter() - t

    def abort(self) -> None:
        """Remove the temporary (after a failure); nothing is left under ``path``. Safe to call twice."""
        if self._done:
            return
        self._done = True
        self._fh.close()
        exc = RuntimeError(f"{self.path}: not written")
        try:
            self._cm.__exit__(RuntimeError, exc, None)  # (atomic_path removes its temporary, then re-raises)
        except RuntimeError as raised:
            if raised is not exc:
                raise
