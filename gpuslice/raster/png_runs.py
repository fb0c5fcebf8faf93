"""PNG layers encoded on the OpenCL device straight from run-length runs (``kernels/png.cl``): the driver.

The PNGs are those of :func:`gpuslice.raster.deflate_runs.encode_png_from_runs` with ``huffman="static"``, its
numpy twin, byte for byte: greyscale, 8 bits, filter 0 on every row, one IDAT holding one final dynamic deflate
block whose code is the same for every layer (``deflate_runs.STATIC_LENGTHS``: a <258, 1> copy is two 0 bits). The
kernels write each layer's deflate bits (its block header, then per run the tokens of the blank stretch before it,
itself, and after the last run the blank tail and the end of block) and the runs' Adler-32 terms; the host does the
prefix sum of the bits, places each layer's stream on a byte, and wraps it: zlib header, Adler-32, the PNG chunks
and their CRCs. A layer without runs (or a group the kernels flag) is made by the twin.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from ..buffers import drained, input_buffer
from . import deflate_runs as _d
from .png import png_chunk
from .run_encoder import RunKernels

__all__ = ["PngRunsEncoder"]

_SIG = b"\x89PNG\r\n\x1a\n"
_MOD = 65521


def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The static code's tables for the kernels: literal/length codes and lengths, the length tokens for r = 3..258
    (code, extra bits, the 1-bit distance code 0), and the block header as 32-bit words and its bit count."""
    lengths, code = _d.STATIC_LENGTHS, _d.STATIC_CODE
    len_val, len_nb = np.zeros(259, np.uint32), np.zeros(259, np.uint8)
    r = np.arange(3, 259)
    sym = _d._LSYM[r]
    len_val[r] = code[sym] | (_d._LXVAL[r] << lengths[sym])
    len_nb[r] = lengths[sym] + _d._LXBITS[r] + 1
    _, _, hdr_val, hdr_nb, _ = _d._codes(None, None, None, "static")
    acc, pos = 0, 0
    for v, nb in zip(hdr_val.tolist(), hdr_nb.tolist(), strict=True):
        acc |= int(v) << pos
        pos += int(nb)
    n_words = (pos + 31) // 32
    hdr = np.array([(acc >> (32 * w)) & 0xFFFFFFFF for w in range(n_words)], np.uint32)
    return code.astype(np.uint32), lengths.astype(np.uint8), len_val, len_nb, hdr, pos


class PngRunsEncoder(RunKernels):
    """Driver of ``kernels/png.cl`` (module docstring), on what the run-length encoders share (its kernels, a command
    queue per thread, the kernels' arguments set under a lock, the sizes pass) with an :meth:`encode` of its own:
    bits, not bytes."""

    FILE, SIZES, WRITE = "png.cl", "png_sizes", "png_write"
    #: a group's bits are counted in int32: groups that could pass this go to the twin
    MAX_BITS = 2**31 - 2**24

    def __init__(self, device) -> None:
        import pyopencl as cl

        super().__init__(device)
        code, lengths, len_val, len_nb, hdr, self._hdr_bits = _tables()
        if int(len_val[258]) != 0:  # pragma: no cover - the static code's property the kernel relies on
            raise AssertionError("the static code's <258, 1> copy must be zero bits")
        mf, ctx = cl.mem_flags, device.context
        self._tabs = [cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=a) for a in (code, lengths, len_val,
                                                                                            len_nb)]
        self._hdr = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=hdr)
        self._little = bool(device.device.endian_little)

    def encode(self, runs, a: int, b: int, width: int, height: int) -> list[bytes] | None:
        """The PNGs (``width`` × ``height``) of entries ``a`` … ``b`` − 1 of ``runs``, or None where the twin must
        make them all (arrays not typed as the runs kernel types them, a group too large, the kernels' flags)."""
        m, n_img = int(runs.layer_offsets[b]) - int(runs.layer_offsets[a]), b - a
        n_bytes = height * (width + 1)
        if m == 0 and width > 0 and height > 0:  # blank layers only: the twin's bytes are the kernels'
            return [_d.encode_png_from_runs(runs, k, width, height, "static") for k in range(a, b)]
        worst = n_img * (n_bytes // 129 + 2 * self._hdr_bits) + 64 * m
        fits = 0 < m and worst < self.MAX_BITS and n_bytes < 2**31 and width > 0 and height > 0
        got = self._inputs(runs, a, b) if fits and self._little else None
        if got is None:
            return None
        q = self._queue()
        with drained(q):  # (host arrays the kernels use in place are freed when an exception lets them go)
            return self._encode_group(q, got, a, runs, width, height, n_bytes)

    def _encode_group(self, q, got: tuple, a: int, runs, width: int, height: int, n_bytes: int) -> list[bytes] | None:
        """:meth:`encode` of the group ``got`` (:meth:`_inputs`: entries from ``a`` of ``runs``) on the queue ``q``."""
        import pyopencl as cl

        m, n_img, img_off, b_off, b_runs = got
        ctx, mf = self.device.context, cl.mem_flags
        head = (np.int32(m), np.int32(n_img), np.int32(width), np.int32(height), b_off, *b_runs, *self._tabs)
        counted = self._counted(q, head, m, img_off)  # (worst < MAX_BITS: the bits' prefix sum fits)
        if counted is None:
            return None
        b_cum, _, first, before, after, nonempty = counted
        grid, local = self._grid(m)
        size = np.where(nonempty, (self._hdr_bits + after - before + 7) // 8, 0)  # each stream's bytes
        start = np.zeros(n_img + 1, np.int64)
        np.cumsum(size, out=start[1:])
        n_words = int(start[-1]) // 4 + 2
        base = 8 * start[:-1] + self._hdr_bits - before
        b_base = input_buffer(self.device, base)
        words = np.zeros(n_words, np.uint32)
        b_out = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=words)
        b_ad = [cl.Buffer(ctx, mf.WRITE_ONLY, 4 * m) for _ in range(2)]
        with self._lock:
            self._write(q, grid, local, *head, b_cum, b_base, self._hdr, np.int32(self._hdr_bits), b_out, *b_ad)
        ad = [np.empty(m, np.uint32), np.empty(m, np.uint32)]
        self._read((words, b_out), *zip(ad, b_ad, strict=True), queue=q)
        ne = np.flatnonzero(nonempty)
        sum_a, sum_b = np.zeros(n_img, np.int64), np.zeros(n_img, np.int64)
        if ne.size:
            sum_a[ne] = np.add.reduceat(ad[0], first[ne], dtype=np.int64)
            sum_b[ne] = np.add.reduceat(ad[1], first[ne], dtype=np.int64)
        adler = ((n_bytes + sum_b) % _MOD) << 16 | ((1 + sum_a) % _MOD)
        data = words.view(np.uint8)
        ihdr = png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
        tail = png_chunk(b"IEND", b"")
        out = []
        for k in range(n_img):
            if not nonempty[k]:  # no runs: the twin (the same bytes the kernels would give)
                out.append(_d.encode_png_from_runs(runs, a + k, width, height, "static"))
                continue
            idat = b"\x78\x01" + data[start[k] : start[k + 1]].tobytes() + struct.pack(">I", int(adler[k]))
            out.append(_SIG + ihdr + struct.pack(">I", len(idat)) + b"IDAT" + idat
                       + struct.pack(">I", zlib.crc32(idat, zlib.crc32(b"IDAT"))) + tail)
        return out


def png_encoders(level: int, device, workers: int | None) -> tuple:
    """``(device, pool)`` a PNG-layer writer encodes runs with at deflate ``level``: the device's kernels at
    :data:`~gpuslice.raster.layers.RUNS_LEVEL` when there is one, else the numpy encoder processes of
    :func:`gpuslice.raster.png_procs.process_pool` at that level (where the command allows them); each None when
    not used."""
    import os

    from .layers import RUNS_LEVEL
    from .png_procs import process_pool

    if level != RUNS_LEVEL:
        return None, None
    return (device, None) if device is not None else (None, process_pool(workers or os.cpu_count()))


def png_group(device, group: list, width: int, height: int) -> list[bytes] | None:
    """The PNGs of a writer's group of consecutive :class:`~gpuslice.raster.layers.RunLayer` entries of one batch,
    made by the kernels on ``device``; None when there is no device, the group is not runs, or the kernels leave it
    to the twin (the writer then encodes each layer itself)."""
    from .layers import RunLayer

    if device is None or not isinstance(group[0], RunLayer):
        return None
    return PngRunsEncoder.of(device).encode(group[0].runs, group[0].j, group[-1].j + 1, width, height)

