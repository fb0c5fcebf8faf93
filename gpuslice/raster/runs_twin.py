"""Resin layers as run-length runs: the columnar :class:`Runs` (the layout: :mod:`gpuslice.raster.runs`) and the
numpy reference of the runs kernel, :func:`runs_numpy` (the twin of :class:`gpuslice.raster.runs.RunsKernel`, whose
host side also finishes long rows with :func:`_piece_records`, :func:`_sum_cells` and :func:`_cells_to_runs`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..ragged import expand_ranges
from .edges import LayerEdges

__all__ = ["Runs", "runs_numpy", "runs_to_mask"]

_ONE = np.float32(65536.0)  # raster.cl's RASTER_ONE: 16.16 fixed point
_F0, _F1, _FH = np.float32(0.0), np.float32(1.0), np.float32(0.5)


@dataclass
class Runs:
    """Run-length greys of a batch of layers; the layout and conventions: :mod:`gpuslice.raster.runs`."""

    layers: np.ndarray
    layer_offsets: np.ndarray
    row: np.ndarray
    x: np.ndarray
    length: np.ndarray
    grey: np.ndarray
    shape: tuple[int, int]

    @property
    def n_runs(self) -> int:
        return int(self.row.shape[0])

    def layer(self, k: int) -> Runs:
        """Entry ``k`` (a position in :attr:`layers`, not a layer index) as a one-layer :class:`Runs` of views."""
        return self.entries(k, k + 1)

    def entries(self, a: int, b: int) -> Runs:
        """Entries ``a`` … ``b`` − 1 as a :class:`Runs` of their own (views)."""
        lo, hi = int(self.layer_offsets[a]), int(self.layer_offsets[b])
        return Runs(self.layers[a:b], self.layer_offsets[a : b + 1] - lo, self.row[lo:hi], self.x[lo:hi],
                    self.length[lo:hi], self.grey[lo:hi], self.shape)

    def to_mask(self, k: int) -> np.ndarray:
        """The full (rows, cols) uint8 mask of entry ``k``."""
        return runs_to_mask(self, k)

    def to_masks(self) -> np.ndarray:
        """(L, rows, cols) uint8 masks of every entry (beware: rows·cols bytes per layer)."""
        out = np.zeros((len(self.layers), *self.shape), np.uint8)
        for k in range(len(self.layers)):
            out[k] = runs_to_mask(self, k)
        return out

    @staticmethod
    def concat(parts: Sequence[Runs], shape: tuple[int, int]) -> Runs:
        """The batches ``parts`` one after another as one :class:`Runs`."""
        if not parts:
            z = np.zeros(0, np.int32)
            return Runs(np.zeros(0, np.int64), np.zeros(1, np.int64), z, z, z, np.zeros(0, np.uint8), shape)
        offs = [np.zeros(1, np.int64)]
        base = 0
        for p in parts:
            offs.append(p.layer_offsets[1:] + base)
            base += p.n_runs
        cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
        return Runs(cat("layers"), np.concatenate(offs), cat("row"), cat("x"), cat("length"), cat("grey"), shape)


def runs_to_mask(runs: Runs, k: int) -> np.ndarray:
    """The full (rows, cols) uint8 mask of entry ``k`` of ``runs`` (0 outside its runs)."""
    rows, cols = runs.shape
    a, b = int(runs.layer_offsets[k]), int(runs.layer_offsets[k + 1])
    out = np.zeros(rows * cols, np.uint8)
    start = runs.row[a:b].astype(np.int64) * cols + runs.x[a:b]
    _, idx = expand_ranges(start, runs.length[a:b])
    out[idx] = np.repeat(runs.grey[a:b], runs.length[a:b])
    return out.reshape(rows, cols)


# ---- the shared back half: sorted, summed cells of rows -> runs --------------------------------------------------
@dataclass
class _Rows:
    """The rows of a batch of layers: global row g (tile rows of the batch's layers one after another)."""

    layer: np.ndarray  # (G,) int64 batch position of each row's layer
    drow: np.ndarray  # (G,) int64 display row
    col0: np.ndarray  # (G,) int64 display column of the tile's column 0
    width: np.ndarray  # (G,) int64 tile columns
    tile_row_off: np.ndarray  # (L + 1,) int64 first global row of each layer


def _rows(tiles: np.ndarray) -> _Rows:
    h = tiles[:, 2].astype(np.int64)
    off = np.zeros(len(h) + 1, np.int64)
    np.cumsum(h, out=off[1:])
    layer, r = expand_ranges(np.zeros(len(h), np.int64), h)
    return _Rows(layer, tiles[layer, 0] + r, tiles[layer, 1].astype(np.int64), tiles[layer, 3].astype(np.int64), off)


def _cells_to_runs(g: np.ndarray, col: np.ndarray, s: np.ndarray, rows: _Rows, lut: np.ndarray):
    """Runs of rows from their touched cells: ``g`` (global row) and ``col`` (tile column) sorted by (g, col) and
    unique, ``s`` each cell's summed contribution. Returns (g, x tile-local, length, grey) of the non-blank runs."""
    if g.size == 0:
        z = np.zeros(0, np.int64)
        return z, z, z, np.zeros(0, np.uint8)
    new_row = np.empty(g.size, bool)
    new_row[0] = True
    np.not_equal(g[1:], g[:-1], out=new_row[1:])
    cs = np.cumsum(s)
    starts = np.flatnonzero(new_row)
    base = cs[starts] - s[starts]
    S = cs - np.repeat(base, np.diff(np.append(starts, g.size)))
    grey = lut[np.minimum(np.abs(S) >> 8, lut.size - 1)]  # 256 entries, or 256*K for K z samples
    prev = np.empty_like(grey)
    prev[1:] = grey[:-1]
    prev[new_row] = lut[0]
    idx = np.flatnonzero(grey != prev)  # grey changes: where runs (blank ones too) begin
    gi = g[idx]
    end = np.empty(idx.size, np.int64)
    end[:-1] = col[idx[1:]]
    last = np.ones(idx.size, bool)
    np.not_equal(gi[1:], gi[:-1], out=last[:-1])
    end[last] = rows.width[gi[last]]
    keep = grey[idx] != lut[0]
    idx, gi, end = idx[keep], gi[keep], end[keep]
    return gi, col[idx], end - col[idx], grey[idx]


def _assemble(cells, rows: _Rows, layers: np.ndarray, shape) -> Runs:
    """One :class:`Runs` from the (g, x, length, grey) of :func:`_cells_to_runs`."""
    g, x, n, grey = cells
    off = np.zeros(len(layers) + 1, np.int64)
    np.cumsum(np.bincount(rows.layer[g], minlength=len(layers)), out=off[1:])
    return Runs(np.asarray(layers, np.int64), off, rows.drow[g].astype(np.int32), (x + rows.col0[g]).astype(np.int32),
                n.astype(np.int32), grey.astype(np.uint8), shape)


def _sum_cells(g: np.ndarray, col: np.ndarray, v: np.ndarray, width: int):
    """Sort records by (g, col) and sum duplicates: unique (g, col) and int64 sums."""
    key = g * (width + 1) + col
    o = np.argsort(key, kind="stable")
    key, v = key[o], v[o]
    first = np.empty(key.size, bool)
    if key.size:
        first[0] = True
        np.not_equal(key[1:], key[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    s = np.add.reduceat(v, starts) if starts.size else np.zeros(0, np.int64)
    uk = key[starts]
    return uk // (width + 1), uk % (width + 1), s


# ---- numpy twin ---------------------------------------------------------------------------------------------------
def _records_numpy(e: np.ndarray, edge_h: np.ndarray, edge_w: np.ndarray, edge_g0: np.ndarray):
    """Every (global row, tile column, int contribution) that ``raster_accumulate`` adds, in float32 as there.

    e (E, 4) float32 tile-local edges; edge_h, edge_w, edge_g0: each edge's tile rows, columns, first global row."""
    u0, v0, u1, v1 = (np.ascontiguousarray(e[:, i]) for i in range(4))
    k = v0 != v1
    u0, v0, u1, v1, eh, ew, eg = u0[k], v0[k], u1[k], v1[k], edge_h[k], edge_w[k], edge_g0[k]
    sgn = np.where(v1 > v0, _F1, -_F1)
    va, vb = np.minimum(v0, v1), np.maximum(v0, v1)
    dudv = (u1 - u0) / (v1 - v0)
    ra = np.maximum(np.floor(va).astype(np.int64), 0)
    rb = np.minimum(eh - 1, np.ceil(vb).astype(np.int64) - 1)
    ei, r = expand_ranges(ra, np.maximum(rb - ra + 1, 0))
    ys = np.maximum(va[ei], r.astype(np.float32))
    ye = np.minimum(vb[ei], (r + 1).astype(np.float32))
    ok = ye > ys
    ei, r, ys, ye = ei[ok], r[ok], ys[ok], ye[ok]
    xs = u0[ei] + (ys - v0[ei]) * dudv[ei]
    xe = u0[ei] + (ye - v0[ei]) * dudv[ei]
    return _piece_records(eg[ei] + r, ew[ei], xs, xe, (ye - ys) * sgn[ei])


def _piece_records(g: np.ndarray, w: np.ndarray, xs: np.ndarray, xe: np.ndarray, dy: np.ndarray):
    """The (global row, tile column, int contribution) records of row pieces: row ``g``, tile ``w`` columns wide,
    u from ``xs`` to ``xe`` and signed height ``dy`` (float32, pixels), as ``raster_accumulate`` computes them: at
    each cell the piece's exact share of the row's running sum, S(c) = (a - umin)·slope + d·(1 - xm), rounded once,
    minus the previous cell's (the cell after the last gets the rest of rint(dy))."""
    umin, umax = np.minimum(xs, xe), np.maximum(xs, xe)
    out_g, out_c, out_a = [], [], []

    def add(gg, cc, aa, ww):
        keep = cc < ww
        out_g.append(gg[keep])
        out_c.append(cc[keep])
        out_a.append(aa[keep])

    def fixed(x):  # (float32 times a power of two: exact; rint as the kernels')
        return np.rint(x * _ONE).astype(np.int64)

    left = umax <= _F0
    add(g[left], np.zeros(int(left.sum()), np.int64), fixed(dy[left]), w[left])
    live = ~left & (umin < w.astype(np.float32))
    g, w, dy, umin, umax = g[live], w[live], dy[live], umin[live], umax[live]
    vert = umin == umax
    c = np.floor(umin[vert]).astype(np.int64)
    xm = umin[vert] - c.astype(np.float32)
    own = fixed(dy[vert] * (_F1 - xm))
    add(g[vert], c, own, w[vert])
    add(g[vert], c + 1, fixed(dy[vert]) - own, w[vert])
    sl = ~vert
    g, w, dy, umin, umax = g[sl], w[sl], dy[sl], umin[sl], umax[sl]
    slope = dy / (umax - umin)
    ca = np.maximum(np.floor(umin).astype(np.int64), 0)
    cb = np.minimum(w - 1, np.ceil(umax).astype(np.int64) - 1)
    n = np.maximum(cb - ca + 1, 0)
    pi, c = expand_ranges(ca, n)
    cf = c.astype(np.float32)
    a = np.maximum(umin[pi], cf)
    b = np.minimum(umax[pi], (c + 1).astype(np.float32))
    d = (b - a) * slope[pi]
    xm = (a + b) * _FH - cf
    run = fixed((a - umin[pi]) * slope[pi] + d * (_F1 - xm))  # the piece's running share after each of its cells
    step = run.copy()
    step[1:] -= run[:-1]
    first = np.cumsum(n) - n  # each piece's first cell
    has = n > 0
    step[first[has]] = run[first[has]]
    add(g[pi], c, step, w[pi])
    add(g[has], cb[has] + 1, fixed(dy[has]) - run[(first + n - 1)[has]], w[has])
    return np.concatenate(out_g), np.concatenate(out_c), np.concatenate(out_a)


def runs_numpy(le: LayerEdges, lut: np.ndarray, shape: tuple[int, int], batch: range | None = None,
               layers: np.ndarray | None = None) -> Runs:
    """The numpy twin of :class:`RunsKernel`: runs of the layers ``batch`` (positions in ``le``, default all);
    ``layers`` the SliceResult indices to record (default the positions); ``shape`` (rows, cols) of the display."""
    batch = range(len(le.tiles)) if batch is None else batch
    t, rows = le.tiles[batch.start : batch.stop], _rows(le.tiles[batch.start : batch.stop])
    edge_k = np.repeat(np.arange(len(t)), np.diff(le.edge_offsets[batch.start : batch.stop + 1]))
    e = np.asarray(le.edges[le.edge_offsets[batch.start] : le.edge_offsets[batch.stop]], np.float32)
    g, c, v = _records_numpy(e, t[edge_k, 2], t[edge_k, 3], rows.tile_row_off[edge_k])
    g, c, s = _sum_cells(g, c, v, int(t[:, 3].max()) if len(t) else 0)
    lay = np.asarray(batch, np.int64) if layers is None else np.asarray(layers, np.int64)
    return _assemble(_cells_to_runs(g, c, s, rows, np.asarray(lut, np.uint8)), rows, lay, shape)
