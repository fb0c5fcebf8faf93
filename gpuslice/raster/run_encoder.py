"""Archive layer images encoded on the OpenCL device straight from run-length runs: the driver the run-length
formats' kernels share (``kernels/goo.cl``: :class:`gpuslice.raster.goo.GooEncoder`, ``kernels/ctb.cl``:
:class:`gpuslice.raster.ctb.CtbEncoder`).

Each format's kernel file has two passes over the runs of a group of layers (one work-item per run): *sizes*, the
bytes run k writes (its records: the blank gap before it, itself, its layer's blank tail, as the format merges and
splits them) plus flags where the group must go to the numpy twin (a case the kernels leave to it, or runs the twin
refuses: it then raises its own error); and *write*, run k's bytes at the inclusive prefix sum of the sizes, less
its own size, from its layer's first byte. The host does the prefix sum, places each layer (a few bytes of its own
before and after the runs' bytes: :attr:`RunImageEncoder.HEAD`, :attr:`RunImageEncoder.TAIL`) and cuts the result
into one ``bytes`` per layer: no numpy pass per record field. The bytes equal the twin's, layer by layer (tests).

Thread safety: the writers call :meth:`RunImageEncoder.encode` from their encoder threads at once; each thread
enqueues on a command queue of its own, and the kernels' arguments are set under a lock.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod

import numpy as np

from ..buffers import OutputBuffers, drained, input_buffer
from ..device import KernelDriver, aligned_empty

__all__ = ["RunKernels", "RunImageEncoder", "RUN_DTYPES"]

#: the run arrays' dtypes (row, x, length, grey) the kernels take as they are (the runs kernel's)
RUN_DTYPES = (np.dtype(np.int32), np.dtype(np.int32), np.dtype(np.int32), np.dtype(np.uint8))


class RunKernels(KernelDriver):
    """What the encoders' drivers share: ``FILE`` (the kernel file), ``SIZES`` and ``WRITE`` (its two kernels), a
    command queue per thread, the group's runs copied to the device (:meth:`_inputs`) and the sizes pass with its
    prefix sum (:meth:`_counted`); ``fallbacks`` counts the groups left to the numpy twin."""

    FILE = SIZES = WRITE = ""

    def __init__(self, device) -> None:
        super().__init__(device)
        prog = device.program(self.FILE)
        self._sizes, self._write = getattr(prog, self.SIZES), getattr(prog, self.WRITE)
        self._lock = threading.Lock()
        self._local = threading.local()
        #: groups left to the twin
        self.fallbacks = 0
        self._blanks: dict[int, bytes] = {}  # RunImageEncoder.blank's bytes by image size

    def _queue(self):
        import pyopencl as cl

        q = getattr(self._local, "queue", None)
        if q is None:
            q = self._local.queue = cl.CommandQueue(self.device.context, self.device.device)
        return q

    def _inputs(self, runs, a: int, b: int) -> tuple | None:
        """``(m, n_img, img_off, its buffer, the run arrays' buffers)`` of entries ``a`` … ``b`` − 1 of ``runs`` (the
        group's runs for the device: :func:`~gpuslice.buffers.input_buffer`), or None when the arrays are not typed
        as the runs kernel types them."""
        lo, hi = int(runs.layer_offsets[a]), int(runs.layer_offsets[b])
        arrays = (runs.row, runs.x, runs.length, runs.grey)
        if any(arr.dtype != dt or not arr.flags.c_contiguous for arr, dt in zip(arrays, RUN_DTYPES, strict=True)):
            return None
        img_off = np.ascontiguousarray(runs.layer_offsets[a : b + 1] - lo, np.int32)
        b_runs = [input_buffer(self.device, arr[lo:hi]) for arr in arrays]
        b_off = input_buffer(self.device, img_off)
        return hi - lo, b - a, img_off, b_off, b_runs

    def _counted(self, q, head: tuple, m: int, img_off: np.ndarray) -> tuple | None:
        """The sizes pass (arguments ``head``) over ``m`` runs and the host's prefix sum: ``(cum buffer, cum, first,
        before, after, nonempty)`` (each layer's first run, the sums before and after its runs, whether it has
        any), or None when the kernel flagged the group for the twin."""
        import pyopencl as cl

        ctx, mf = self.device.context, cl.mem_flags
        b_width = cl.Buffer(ctx, mf.READ_WRITE, 4 * m)
        flags = np.zeros(1, np.int32)
        b_flags = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=flags)
        grid, local = self._grid(m)
        with self._lock:
            self._sizes(q, grid, local, *head, b_width, b_flags)
        cum = np.empty(m, np.int32)
        self._read((flags, b_flags), (cum, b_width), queue=q)  # (one wait: cum is not used when flagged)
        if flags[0]:
            self.fallbacks += 1
            return None
        np.cumsum(cum, out=cum)  # inclusive, in place (the callers bound the sum below 2^31)
        b_cum = input_buffer(self.device, cum)
        first, end = img_off[:-1].astype(np.int64), img_off[1:].astype(np.int64)
        before = np.where(first > 0, cum[np.maximum(first - 1, 0)], 0).astype(np.int64)
        after = np.where(end > 0, cum[np.maximum(end - 1, 0)], 0).astype(np.int64)
        return b_cum, cum, first, before, after, end > first


class RunImageEncoder(RunKernels, ABC):
    """Base of the byte-oriented encoders (GOO, CTB, PW0): ``MAX_RUN`` (the longest record: larger images go to the
    twin), ``HEAD``/``TAIL`` (bytes of each layer before/after its runs' bytes, set by :meth:`finish`), ``EXTRA``
    (dtypes of per-run arrays the write pass also fills, after its output: :meth:`reduce` makes per-layer values of
    them), :meth:`blank` (the bytes of a layer without runs: the twin's)."""

    MAX_RUN = 0
    HEAD = TAIL = 0
    EXTRA: tuple = ()
    #: more runs than this in one call: the twin (the prefix sum is int32; a run writes at most ~20 bytes)
    MAX_RUNS = 100_000_000

    @abstractmethod
    def blank(self, n_pixels: int) -> bytes:
        """The runs' bytes of a layer with no runs (``n_pixels`` blank pixels), as the twin writes them."""

    def reduce(self, extra: list[np.ndarray], first: np.ndarray, nonempty: np.ndarray, blank: bytes):
        """Per-layer values of the write pass's :attr:`EXTRA` arrays (layer k's runs: ``first[k]`` onwards, none
        where not ``nonempty[k]``; ``blank``: the bytes of a layer without runs). Default: None."""
        return None

    def finish(self, img: np.ndarray, start: np.ndarray, stats) -> None:
        """Write each layer's own bytes into ``img`` (layer k: ``start[k]`` … ``start[k + 1]`` − 1), given
        :meth:`reduce`'s ``stats``. Default: nothing (no bytes of their own)."""

    def encode(self, runs, a: int, b: int, cols: int, n_pixels: int) -> list[bytes] | None:
        """The layer images of entries ``a`` … ``b`` − 1 of ``runs`` (a :class:`~gpuslice.raster.runs.Runs` of
        ``cols`` columns, images of ``n_pixels``), one ``bytes`` each; None where the twin must encode them (no runs,
        arrays not typed as the runs kernel types them, an image too large, or the kernels' flags)."""
        out = self.encode_stats(runs, a, b, cols, n_pixels)
        return None if out is None else out[0]

    def encode_stats(self, runs, a: int, b: int, cols: int, n_pixels: int) -> tuple[list[bytes], object] | None:
        """:meth:`encode` and :meth:`reduce`'s per-layer values: ``(images, stats)``, or None (the twin's turn)."""
        m = int(runs.layer_offsets[b]) - int(runs.layer_offsets[a])
        got = self._inputs(runs, a, b) if 0 < m <= self.MAX_RUNS and 0 < n_pixels <= self.MAX_RUN and cols > 0 \
            else None
        if got is None:
            return None
        q = self._queue()
        with drained(q):  # (host arrays the kernels use in place are freed when an exception lets them go)
            return self._encode_group(q, got, cols, n_pixels)

    def _encode_group(self, q, got: tuple, cols: int, n_pixels: int) -> tuple[list[bytes], object] | None:
        """:meth:`encode_stats` of the group ``got`` (:meth:`_inputs`) on the queue ``q``."""
        m, n_img, img_off, b_off, b_runs = got
        head = (np.int32(m), np.int32(n_img), np.int32(cols), np.int64(n_pixels), b_off, *b_runs)
        counted = self._counted(q, head, m, img_off)
        if counted is None:
            return None
        b_cum, _, first, before, after, nonempty = counted
        grid, local = self._grid(m)
        blank = self._blanks.get(int(n_pixels))
        if blank is None:  # (the same for every group of a job: made once; two threads may both make it)
            blank = self._blanks[int(n_pixels)] = self.blank(int(n_pixels))
        size = self.HEAD + self.TAIL + np.where(nonempty, after - before, len(blank))
        start = np.zeros(n_img + 1, np.int64)
        np.cumsum(size, out=start[1:])
        total = int(start[-1])
        base = start[:-1] + self.HEAD - before
        # (never 0 bytes with correct kernels: a buffer cannot be empty)
        outs = OutputBuffers(self.device, [aligned_empty(max(total, 1), np.uint8),
                                           *(aligned_empty(m, dt) for dt in self.EXTRA)])
        b_base = input_buffer(self.device, base)
        with self._lock:
            self._write(q, grid, local, *head, b_cum, b_base, *outs.buffers)
        img, *extra = outs.fetch(q)
        img = img[:total]
        stats = self.reduce(extra, first, nonempty, blank)
        for k in np.flatnonzero(~nonempty):
            img[start[k] + self.HEAD : start[k] + self.HEAD + len(blank)] = np.frombuffer(blank, np.uint8)
        self.finish(img, start, stats)
        data = [img[start[k] : start[k + 1]].tobytes() for k in range(n_img)]
        outs.release(q)
        q.finish()
        return data, stats
