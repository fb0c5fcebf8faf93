"""Resin layers as run-length runs, never a bitmap: the same greys as :mod:`gpuslice.raster.coverage`'s OpenCL
rasteriser, byte for byte.

A layer's grey at pixel (row i, column j) is ``lut[min(255, |S| >> 8)]`` where S is the running sum along row i of
16.16 fixed-point area contributions (``kernels/raster.cl``). Only cells that an edge piece touches have a
contribution, so S is constant between two touched cells of a row: a row is a few runs. Both backends here compute
the touched cells' integer contributions with the float32 formulas and ``rint`` of ``raster.cl`` (so the integers are
identical), sum them per cell, order them by column, prefix-sum them and emit runs; blank rows and the blank ends of
rows are never visited. Coordinates are display pixels (the tile offsets of :func:`gpuslice.raster.layer_edges`
are added back); pixels outside a layer's tile are 0, as in the raster path.

**Layout** (:class:`Runs`, one batch of layers, columnar)::

    layers         (L,) int64     the SliceResult layer index of each entry
    layer_offsets  (L + 1,) int64 entry k owns runs layer_offsets[k]:layer_offsets[k + 1]
    row            (N,) int32     display row (0 = top row of the PNG)
    x              (N,) int32     first display column of the run
    length         (N,) int32     pixels in the run (>= 1)
    grey           (N,) uint8     grey of every pixel of the run (never 0: blank pixels have no run)
    shape          (rows, cols)   of the display (RasterSpec.shape)

Runs are ordered by (layer, row, x); two runs of one row never touch with the same grey (they are merged).

Backends: ``"numpy"`` (:func:`runs_numpy`, the vectorised reference, in :mod:`gpuslice.raster.runs_twin` with
:class:`Runs`) and ``"opencl"`` (``kernels/runs.cl``, :class:`RunsKernel`, here). On OpenCL, :func:`iter_runs`
makes :data:`LANES` batches at once, each on its own queue and thread (:meth:`gpuslice.device.Device.lane`): a
batch waits twice for the device (its rows' capacities, then its run counts: prefix sums on the host), and the
other lane's kernels fill those waits.
"""

from __future__ import annotations

import numbers
import threading
from collections import deque
from collections.abc import Iterable, Iterator, Sequence

import numpy as np

from ..buffers import OutputBuffers
from ..device import KernelDriver, aligned_empty, get_device
from ..errors import ParameterError
from ..prefetch import Workers, current_name, prefetch
from ..ragged import expand_ranges, group_ranks
from .edges import LayerEdges, check_fits, check_raster_args, iter_layer_edges
from .runs_twin import Runs, _cells_to_runs, _piece_records, _rows, _sum_cells, runs_numpy, runs_to_mask
from .spec import RasterSpec, gamma_lut

__all__ = ["Runs", "runs_numpy", "RunsKernel", "layer_runs", "iter_runs", "runs_to_mask", "BACKENDS"]

BACKENDS = ("opencl", "numpy")


# ---- OpenCL -------------------------------------------------------------------------------------------------------
def _owners(counts: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``np.repeat(np.arange(len(counts)), counts)`` written into ``out`` (``counts.sum()`` items, int): each item's
    group. Built in place (no new array): 1 after each group's end, then a prefix sum."""
    out[:] = 0
    ends = np.cumsum(counts[:-1])
    np.add.at(out, ends[ends < out.size], 1)
    np.cumsum(out, out=out)
    return out


def _units(e: np.ndarray, edge_h: np.ndarray, rows_max: int) -> np.ndarray:
    """Work units of ``runs_pieces``: (edge, first row, last row, 0), each at most ``rows_max`` rows of an edge
    (a piece is one descriptor whatever its width: flat edges need no cutting)."""
    va, vb = np.minimum(e[:, 1], e[:, 3]), np.maximum(e[:, 1], e[:, 3])
    ra = np.maximum(np.floor(va).astype(np.int64), 0)
    rb = np.minimum(edge_h - 1, np.ceil(vb).astype(np.int64) - 1)
    nr = np.where(e[:, 1] != e[:, 3], np.maximum(rb - ra + 1, 0), 0)
    ue, j = expand_ranges(np.zeros(len(e), np.int64), (nr + rows_max - 1) // rows_max)
    units = np.zeros((ue.size, 4), np.int32)
    units[:, 0], units[:, 1] = ue, ra[ue] + j * rows_max
    units[:, 2] = np.minimum(units[:, 1] + rows_max - 1, rb[ue])
    return units


class RunsKernel(KernelDriver):
    """Driver of ``kernels/runs.cl`` (see the comment at its top): per-row capacities from per-edge bounds, one
    descriptor per row piece written into its row, rows sorted and resolved cell by cell on the device; rows with
    more than ``CH`` cell records (or many overlapping pieces) are finished on the host by the numpy back half
    (:attr:`long_rows` counts them). Host work: cutting the few edges of many rows into units, prefix sums over
    rows. Should a row's pieces ever exceed its capacity (the bound is proven, this is a safety net), the batch is
    redone by :func:`runs_numpy` (:attr:`fallbacks`)."""

    CH = 1024  # the most cell records a row finished on the device has (bounded work; --z-samples rows are long)
    ROWS_PER_UNIT = 32  # rows of an edge per work-item (32 rather than 16: ~8% less CPU on the armadillo job)
    CAP_EXTRA = 0  # added to every edge's per-row record bound (tests: negative, to force the fallback)

    def __init__(self, device) -> None:
        super().__init__(device)
        import pyopencl as cl

        prog = device.program("runs.cl")
        # kernel objects of this driver's own: a lane's driver sets their arguments from its own thread
        self._prep, self._edges, self._pieces, self._rows_k, self._emit = (
            cl.Kernel(prog, name) for name in ("runs_prep", "runs_edges", "runs_pieces", "runs_rows", "runs_emit"))
        #: rows finished on the host so far (more than CH records), batches redone by the numpy twin; the most
        #: piece slots (int2, 8 bytes each) one batch's capacities reserved
        self.long_rows = self.fallbacks = self.peak_slots = 0
        #: set to a dict to get seconds per stage added up in it (the queue is then drained after each stage)
        self.timings: dict[str, float] | None = None
        self._t = 0.0
        self._lock = threading.Lock()

    def _host(self, name: str, n: int, dtype) -> np.ndarray:
        """The reused host array ``name``: ``n`` items of ``dtype`` (contents undefined), kept with the device
        buffers (:func:`gpuslice.device.release_scratch` drops both), grown like them."""
        key = "host:" + name
        a = self._buffers.get(key, (None, 0))[0]
        if a is None or a.dtype != dtype or a.size < n:
            a = np.empty(max(n, int(1.5 * a.size) if a is not None and a.dtype == dtype else 0, 16), dtype)
            self._buffers[key] = (a, a.nbytes)
        return a[:n]

    def _mark(self, name: str | None) -> None:
        if self.timings is None:
            return
        import time

        self.device.queue.finish()
        now = time.perf_counter()
        if name is not None:
            self.timings[name] = self.timings.get(name, 0.0) + now - self._t
        self._t = now

    def run(self, le: LayerEdges, batch: range, lut: np.ndarray, shape: tuple[int, int],
            layers: np.ndarray | None = None) -> Runs:
        """Runs of the layers ``batch`` (positions in ``le``); ``layers`` their SliceResult indices. One call at a
        time per driver (a writer's runs are made on a prefetch thread while its caller may ask for others)."""
        with self._lock:
            return self._run(le, batch, lut, shape, layers)

    def _run(self, le: LayerEdges, batch: range, lut: np.ndarray, shape: tuple[int, int],
             layers: np.ndarray | None = None) -> Runs:
        import pyopencl as cl

        q = self.device.queue
        lut = np.ascontiguousarray(lut, np.uint8)
        lay = np.asarray(batch, np.int64) if layers is None else np.asarray(layers, np.int64)
        t = le.tiles[batch.start : batch.stop]
        e0, e1 = int(le.edge_offsets[batch.start]), int(le.edge_offsets[batch.stop])
        row_off_t = np.zeros(len(t) + 1, np.int64)
        np.cumsum(t[:, 2], out=row_off_t[1:])
        n_rows, n_edges = int(row_off_t[-1]), e1 - e0
        if n_rows == 0 or n_edges == 0 or int(t[:, 3].max()) >= 1 << 15:  # (a piece's cells are 15-bit columns)
            return runs_numpy(le, lut, shape, batch, lay)
        self._mark(None)
        e = np.asarray(le.edges[e0:e1], np.float32)
        # host scratch arrays are reused across batches (fresh ones cost a page fault per 4 KiB each time: numpy's
        # cumsum into a new array was ~1 ms per 160k rows, 10x the sum); they never leave this call, and an upload
        # from one is complete before it is written again (an in-order queue: edge_tile and row_tile are uploaded
        # before this batch's blocking reads, the others are rewritten only after the next batch's first one)
        edge_k = _owners(np.diff(le.edge_offsets[batch.start : batch.stop + 1]),
                         self._host("edge_tile", n_edges, np.int32))
        tiles = np.zeros((len(t) + 1, 4), np.int32)
        tiles[:, 0] = row_off_t
        tiles[:-1, 1], tiles[:-1, 2], tiles[:-1, 3] = t[:, 3], t[:, 0], t[:, 1]
        b_edges, b_et = self._put("edges", e), self._put("edge_tile", edge_k)
        b_tiles, b_lut = self._put("tiles", tiles), self._put("lut", lut)
        b_rt = self._put("row_tile", _owners(t[:, 2], self._host("row_tile", n_rows, np.int32)))
        b_whole = self._buffer("whole", n_edges)
        b_diff = self._fill("cap_diff", 4 * (n_rows + 1), np.int32(0))
        ge, le_ = self._grid(n_edges)
        self._prep(q, ge, le_, np.int32(n_edges), np.int32(self.ROWS_PER_UNIT), np.int32(self.CAP_EXTRA), b_edges,
                   b_et, b_tiles, b_whole, b_diff)
        whole, diff = self._host("whole", n_edges, np.uint8), self._host("cap_diff", n_rows, np.int32)
        self._read((whole, b_whole), (diff, b_diff))
        row_off = self._host("row_off", n_rows + 1, np.int64)
        row_off[0], cap = 0, row_off[1:]
        cap[:] = diff
        np.cumsum(cap, out=cap)  # each row's capacity (int2 slots), even: its pieces are int4
        cap += 1
        np.bitwise_and(cap, ~1, out=cap)
        np.cumsum(cap, out=cap)  # (in place: row_off[1:])
        if row_off[-1] >= 2**31:
            raise ParameterError("too many pieces in one batch of layers: lower max_batch_pieces")
        self.peak_slots = max(self.peak_slots, int(row_off[-1]))
        split = np.flatnonzero(whole == 0)
        self._mark("prep: bounds, capacities")
        off32 = self._host("row_off32", n_rows + 1, np.int32)
        off32[:] = row_off
        b_off = self._put("row_off", off32)
        b_units = None
        if split.size:  # edges of many rows: cut into bands of rows
            units = _units(e[split], t[edge_k[split], 2], self.ROWS_PER_UNIT)
            units[:, 0] = split[units[:, 0]]
            # cut and uploaded before the edges kernel is enqueued: the upload does not queue behind it (when its
            # event was dropped, that wait held the GIL: ~70 ms of the armadillo job; device.TRANSFERS)
            b_units = self._put("units", units)
        b_pcs = self._buffer("pcs", 8 * max(int(row_off[-1]), 2))
        b_cnt = self._fill("row_count", 4 * n_rows, np.int32(0))
        self._edges(q, ge, le_, np.int32(n_edges), b_whole, b_edges, b_et, b_tiles, b_cnt, b_off, b_pcs)
        self._mark("pieces: whole edges")
        if b_units is not None:
            gu, lu = self._grid(len(units))
            self._pieces(q, gu, lu, np.int32(len(units)), b_units, b_edges, b_et, b_tiles, b_cnt, b_off, b_pcs)
        self._mark("pieces: cut edges")
        b_recs = self._buffer("recs", 4 * max(int(row_off[-1]), 1))  # one int (column << 8 | grey) a slot
        b_m, b_runs = self._buffer("row_m", 4 * n_rows), self._buffer("row_runs", 4 * n_rows)
        gr, lr = self._grid(n_rows)
        self._rows_k(q, gr, lr, np.int32(n_rows), np.int32(self.CH), b_off, b_cnt, b_pcs, b_recs, b_rt, b_tiles,
                     b_lut, np.int32(lut.size - 1), b_m, b_runs)
        row_runs = self._host("row_runs", n_rows, np.int32)
        cl.enqueue_copy(q, row_runs, b_runs, is_blocking=True)
        self._mark("rows: sort, grey changes")
        flagged = row_runs.min() < 0  # (one pass: rows are nearly never flagged)
        if flagged and np.any(row_runs == -2):  # a capacity bound too low (never seen but with CAP_EXTRA < 0)
            self.fallbacks += 1
            return runs_numpy(le, lut, shape, batch, lay)
        long_rows = np.flatnonzero(row_runs < 0) if flagged else np.zeros(0, np.int64)
        self.long_rows += long_rows.size
        host = None
        if long_rows.size:  # rows too long for one work-item: the numpy back half from their pieces
            host = self._host_rows(long_rows, row_off, b_cnt, b_pcs, t, lut)
            row_runs[long_rows] = np.bincount(host[0], minlength=n_rows)[long_rows]
        self._mark("host: long rows")
        run_off = self._host("run_off", n_rows + 1, np.int32)  # (int32: runs <= records <= row_off[-1] < 2^31)
        run_off[0] = 0
        np.cumsum(row_runs, out=run_off[1:])
        n_runs = int(run_off[-1])
        b_ro = self._put("run_off", run_off[:-1])
        # the outputs: new host arrays, written in place on a CPU device, copied into from a GPU's own buffers
        # (gpuslice.buffers); the reused scratch buffers never leave this call
        arrs = [aligned_empty(n_runs, d) for d in (np.int32, np.int32, np.int32, np.uint8)]
        if n_runs:
            outs = OutputBuffers(self.device, arrs)
            self._emit(q, gr, lr, np.int32(n_rows), b_off, b_recs, b_m, b_rt, b_tiles, b_lut, b_ro, *outs.buffers)
            self._mark("emit")
            outs.fetch(q)
            outs.release(q)
            q.finish()
        row, x, length, grey = arrs
        if host is not None:
            rows = _rows(t)
            pos = run_off[host[0]] + group_ranks(host[0])
            row[pos], x[pos] = rows.drow[host[0]], host[1] + rows.col0[host[0]]
            length[pos], grey[pos] = host[2], host[3]
        off = np.zeros(len(t) + 1, np.int64)
        off[1:] = run_off[row_off_t[1:]]  # (a new array: it leaves with the runs)
        self._mark("map, long rows in")
        return Runs(lay, off, row, x, length, grey, shape)

    def _host_rows(self, long_rows: np.ndarray, row_off: np.ndarray, b_cnt, b_pcs, t: np.ndarray, lut: np.ndarray):
        """The runs (g, x tile-local, length, grey) of the rows ``long_rows`` from their pieces on the device."""
        cnt = np.empty(len(row_off) - 1, np.int32)
        pcs = np.empty((int(row_off[-1]) // 2, 4), np.int32)
        self._read((cnt, b_cnt), (pcs, b_pcs))
        owner, idx = expand_ranges(row_off[long_rows] // 2, cnt[long_rows])
        g = long_rows[owner]
        f = pcs[idx].view(np.float32)
        rows = _rows(t)
        g, c, v = _piece_records(g, rows.width[g], f[:, 1].copy(), f[:, 2].copy(), f[:, 3].copy())
        g, c, s = _sum_cells(g, c, v, int(t[:, 3].max()))
        return _cells_to_runs(g, c, s, rows, lut)


#: batches of layers made at once by :func:`iter_runs` on OpenCL, each on a queue and a thread of its own (the module
#: docstring; BENCHMARKS, "Runs in two lanes"); 1: one at a time, in the caller's thread. Memory: each lane keeps
#: its own scratch (about 30 bytes per cell record of its largest batch), and a finished batch may wait for the one
#: before it (a runs stage of the armadillo job at 80 mm: 270 against 210 MB peak; whole jobs: BENCHMARKS)
LANES = 2


def _in_lanes(kerns: list[RunsKernel], calls: Iterable[tuple]) -> Iterator[Runs]:
    """``kerns[i % n].run(*args)`` for the i-th ``args`` of ``calls``, yielded in order, up to n = len(kerns) at once
    (one thread a lane, each lane's calls one after the other: its driver's buffers are reused). An exception in a
    lane is raised where its batch would have been yielded (one from ``calls`` itself, at once); closing the
    iterator early waits for the batches under way."""
    n = len(kerns)
    if n == 1:
        for args in calls:
            yield kerns[0].run(*args)
        return
    pools = [Workers(1, f"gpuslice-runs-lane{i}") for i in range(n)]
    pending: deque = deque()
    try:
        for i, args in enumerate(calls):
            pending.append(pools[i % n].submit(kerns[i % n].run, *args))
            if len(pending) == n:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        for f in pending:
            f.cancel()
        # (closed by the garbage collector on a lane's thread, this job's or another's holding a lane's lock: it
        # waits for no lane)
        inside = current_name().startswith("gpuslice-runs-lane")
        for pool in pools:
            pool.shutdown(wait=not inside)


# ---- public entry points ------------------------------------------------------------------------------------------
def _batches(le: LayerEdges, max_pieces: int) -> Iterator[range]:
    """Consecutive layer ranges of at most about ``max_pieces`` cell records each (at least one layer)."""
    e, off, n = le.edges, le.edge_offsets, len(le.tiles)
    d = np.subtract(e[: off[-1], 3], e[: off[-1], 1])  # cells an edge touches, roughly: |dv| + |du| + 2
    np.abs(d, out=d)
    du = np.subtract(e[: off[-1], 2], e[: off[-1], 0])
    d += np.abs(du, out=du)
    per = 2.0 * np.diff(off) + 64.0  # a floor per layer: rows and bookkeeping
    nz = np.flatnonzero(off[1:] > off[:-1])
    if nz.size:
        per[nz] += np.add.reduceat(d, off[nz])  # per layer (float32 sums: an estimate)
    cum = np.zeros(n + 1)
    np.cumsum(per, out=cum[1:])
    start = 0
    while start < n:
        stop = int(np.searchsorted(cum, cum[start] + max_pieces, side="right")) - 1
        stop = min(max(stop, start + 1), n)
        yield range(start, stop)
        start = stop


def iter_runs(
    result,
    spec: RasterSpec | None = None,
    *,
    backend: str = "opencl",
    device=None,
    bounds=None,
    layers: Sequence[int] | None = None,
    max_batch_pieces: int = 1 << 20,
    edges: LayerEdges | None = None,
    z_samples: int = 1,
    merged: LayerEdges | None = None,
    lanes: int | None = None,
    clip: bool = False,
) -> Iterator[Runs]:
    """Yield one :class:`Runs` per batch of consecutive layers (``layers``, default all, in order).

    backend : ``"opencl"`` (:class:`RunsKernel`) or ``"numpy"`` (:func:`runs_numpy`); device : the OpenCL device
    (default :func:`get_device`); bounds : the (xmin, ymin, xmax, ymax) mm centred on the bed (default: the
    result's points), as :func:`gpuslice.raster.iter_tiles`. max_batch_pieces : about how many cell records
    (touched pixel cells) one batch may hold; memory is about 30 bytes per record on either backend.
    edges : the :func:`layer_edges` of exactly these arguments, when the caller already has them.
    z_samples : K > 1: ``result`` holds K sub-layers per layer (layers K·i … K·i + K − 1 are layer i's sub-planes,
        :func:`gpuslice.raster.coverage.z_sample_planes`); each layer's grey is that of its mean coverage over them
        (the K sub-layers' records go into one row sum, read through a K-fold gamma table: exact, no extra pass).
    merged : instead of ``result``'s polygons, every layer's edges with its K sub-planes' already merged (its
        tile the union of theirs, :func:`~gpuslice.raster.edges.merge_layer_groups`): the segment-buffer shortcut of
        :mod:`gpuslice.raster.segment_edges`; ``result`` is then not read.
    clip : keep only what lies on the display of a layer that reaches outside it (default: ``ParameterError`` "does
        not fit", as :func:`~gpuslice.raster.iter_tiles`; not checked with ``edges`` or ``merged``: their maker's).
    """
    if backend not in BACKENDS:
        raise ParameterError(f"unknown runs backend '{backend}' (use {', '.join(BACKENDS)})")
    if merged is None and edges is None:
        check_raster_args(result, spec, layers, bounds)
    spec = spec or RasterSpec()
    if merged is None and edges is None and not clip:
        check_fits(result, spec, bounds, layers=layers)
    if isinstance(z_samples, bool) or not isinstance(z_samples, numbers.Integral) or not 1 <= z_samples <= 64:
        raise ParameterError(f"z_samples must be a whole number from 1 to 64, got {z_samples!r}", param="z_samples")
    k = int(z_samples)
    if merged is not None:
        if layers is not None or edges is not None:
            raise ParameterError("merged edges are every layer's: no layer selection, no other edges")
    elif k > 1 and (layers is not None or result.n_layers % k):
        raise ParameterError(f"z_samples={k} needs every layer's {k} sub-layers (and no layer selection)",
                             param="z_samples")
    n_layers = len(merged.tiles) if merged is not None else result.n_layers // max(k, 1)
    index = np.arange(n_layers) if layers is None else np.asarray(layers, dtype=np.int64)
    lut = np.repeat(gamma_lut(spec.gamma), max(k, 1))  # lut[i] = gamma_lut[i // k]: see kernels/runs.cl
    if lut[0] != 0:  # pragma: no cover - gamma_lut maps no coverage to black for every gamma
        raise ParameterError("the gamma table must map coverage 0 to grey 0")
    kerns = []
    if backend == "opencl":
        dev = device if device is not None else get_device()
        n_lanes = LANES if lanes is None else int(lanes)
        if n_lanes < 1:
            raise ParameterError(f"lanes must be at least 1, got {lanes}", param="lanes")
        kerns = [RunsKernel.of(dev.lane(i)) for i in range(n_lanes)]
    # the next chunk's edges are made on a thread while this one's batches run (numpy releases the GIL)
    if merged is not None:
        chunks = iter([(0, merged)])
    else:
        chunks = prefetch(iter_layer_edges(result, spec, bounds, layers, edges, k, dtype=np.float32),
                          depth=0 if edges is not None else 1)

    def calls() -> Iterator[tuple]:
        for pos, le in chunks:
            if le.edges.dtype != np.float32:  # every backend computes on float32: convert once, not per batch
                le = LayerEdges(le.edges.astype(np.float32), le.edge_offsets, le.tiles)
            for batch in _batches(le, max_batch_pieces):
                yield le, batch, lut, spec.shape, index[pos + batch.start : pos + batch.stop]

    if not kerns:
        for le, batch, lut_, shape, sel in calls():
            yield runs_numpy(le, lut_, shape, batch, sel)
    else:
        yield from _in_lanes(kerns, calls())


def layer_runs(result, spec: RasterSpec | None = None, **options) -> Runs:
    """Every selected layer's runs as one :class:`Runs` (options as :func:`iter_runs`)."""
    spec = spec or RasterSpec()
    return Runs.concat(list(iter_runs(result, spec, **options)), spec.shape)
