"""Solid pixels of consecutive layers as row intervals, and the vectorised queries the checks make on them.

A layer rasterised with a hard threshold (coverage ≥ 50 %, :func:`solid_intervals`) is, row by row, a few disjoint
intervals of columns ``[start, end)``. A batch of consecutive layers is one :class:`Lines`: every (layer, row) is a
*line* ``line = (layer - layer0) · rows + row``, and all intervals sit on one global axis
``g = line · stride + x + 1`` (``stride = cols + 3``, so ``x`` from −1 to ``cols + 1`` never reaches another line).
Intervals are sorted along that axis, never overlap and never touch, so their starts and their ends are both sorted:
every question below is a ``searchsorted`` over all queries at once, with no loop over rows or pixels.

*Gaps* are the empty runs between two intervals of a line: gap ``j`` lies between interval ``j`` and ``j + 1``
(``[end[j], start[j + 1])``) and is *interior* when both are on the same line. The empty pixels before a line's first
interval and after its last one, and whole empty lines, touch the grid's border.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..ragged import expand_ranges

__all__ = ["Lines", "solid_intervals", "merge_intervals", "components"]


def solid_intervals(runs, threshold: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(layer, row, start, end)`` int64 of the pixels of ``runs`` (:class:`gpuslice.raster.runs.Runs`) whose grey is
    at least ``threshold``, touching runs of a row merged; ``layer`` is the result's layer index."""
    counts = np.diff(runs.layer_offsets)
    layer = np.repeat(np.asarray(runs.layers, np.int64), counts)
    keep = runs.grey >= threshold
    layer, row = layer[keep], runs.row[keep].astype(np.int64)
    start = runs.x[keep].astype(np.int64)
    end = start + runs.length[keep]
    return merge_intervals(layer, row, start, end)


def merge_intervals(layer, row, start, end, *, sort: bool = False):
    """Intervals sorted by (layer, row, start) with overlapping or touching ones of a line merged into one
    (``sort``: sort them first; a stable sort, fast on a few sorted pieces put one after another)."""
    if start.size < 2:
        return layer, row, start, end
    # one key per line, then positions on one axis: a line's intervals never reach the next line's
    key = (layer - layer.min()) * (int(row.max()) + 2) + row
    span = int(max(end.max(), 1)) + 2
    if sort:
        order = np.argsort(key * span + start, kind="stable")
        layer, row, start, end, key = layer[order], row[order], start[order], end[order], key[order]
    # the running end of a line's intervals (ends only grow inside a line: the line's key is added)
    run_end = np.maximum.accumulate(key * span + end)
    new = np.ones(start.size, bool)
    new[1:] = (key[1:] != key[:-1]) | (key[1:] * span + start[1:] > run_end[:-1])
    first = np.flatnonzero(new)
    last = np.append(first[1:], start.size) - 1
    return layer[first], row[first], start[first], run_end[last] - key[first] * span


@dataclass
class Lines:
    """The solid intervals of layers ``layer0 .. layer0 + n_layers - 1`` on a grid of ``rows`` × ``cols`` pixels
    (module docstring): ``line``, ``start``, ``end`` (N,) int64, sorted, disjoint, never touching."""

    layer0: int
    n_layers: int
    rows: int
    cols: int
    line: np.ndarray
    start: np.ndarray
    end: np.ndarray

    @classmethod
    def from_parts(cls, layer0: int, n_layers: int, rows: int, cols: int,
                   parts: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> Lines:
        """Join ``(layer, row, start, end)`` parts given in layer order (each sorted and merged)."""
        parts = [p for p in parts if p[0].size]
        if not parts:
            z = np.zeros(0, np.int64)
            return cls(layer0, n_layers, rows, cols, z, z, z)
        layer, row, start, end = (np.concatenate([p[k] for p in parts]) for k in range(4))
        return cls(layer0, n_layers, rows, cols, (layer - layer0) * rows + row, start, end)

    @property
    def stride(self) -> int:
        return self.cols + 3

    @property
    def n(self) -> int:
        return int(self.start.size)

    @property
    def layer(self) -> np.ndarray:
        """(N,) the result's layer index of each interval."""
        return self.line // self.rows + self.layer0

    @property
    def row(self) -> np.ndarray:
        return self.line % self.rows

    def layer_slice(self, k: int) -> slice:
        """The intervals of the ``k``-th layer of the batch (``layer0 + k``)."""
        a, b = np.searchsorted(self.line, [k * self.rows, (k + 1) * self.rows])
        return slice(int(a), int(b))

    def _g(self, line: np.ndarray, x: np.ndarray) -> np.ndarray:
        return line * self.stride + (x + 1)

    @property
    def gs(self) -> np.ndarray:
        g = getattr(self, "_gs", None)
        if g is None:
            g = self._gs = self._g(self.line, self.start)
        return g

    @property
    def ge(self) -> np.ndarray:
        g = getattr(self, "_ge", None)
        if g is None:
            g = self._ge = self._g(self.line, self.end)
        return g

    def valid_line(self, layer_k: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Whether (batch layer ``layer_k``, ``row``) is a line of this batch (False: an empty line)."""
        return (layer_k >= 0) & (layer_k < self.n_layers) & (row >= 0) & (row < self.rows)

    def line_first(self, line: np.ndarray) -> np.ndarray:
        """Index of the first interval of each ``line`` (where it would be, for an empty line)."""
        return np.searchsorted(self.gs, line * self.stride, side="left")

    def overlapping(self, line: np.ndarray, a: np.ndarray, b: np.ndarray, valid: np.ndarray | None = None):
        """For each query, the intervals of ``line`` that share a pixel with ``[a, b)``: global indices
        ``[lo, hi)`` (empty where ``valid`` is False)."""
        lo = np.searchsorted(self.ge, self._g(line, a), side="right")  # first with end > a
        hi = np.searchsorted(self.gs, self._g(line, b), side="left")  # past the last with start < b
        if valid is not None:
            hi = np.where(valid, hi, lo)
        return lo, np.maximum(hi, lo)

    def gaps_touching(self, line: np.ndarray, a: np.ndarray, b: np.ndarray, valid: np.ndarray):
        """The empty pixels of ``line`` that share a column with ``[a, b)``: ``(lo, hi, border)``, the interior gaps
        ``lo .. hi - 1`` (global gap indices, gap j between interval j and j + 1) and whether any of those pixels
        lies before the line's first interval or after its last one (an empty line: all of it)."""
        first = self.line_first(line)
        nxt = np.searchsorted(self.gs, line * self.stride + self.stride, side="left")  # past the line's last
        k1 = np.searchsorted(self.gs, self._g(line, a), side="right") - 1  # gap k1 = the one after interval k1
        k2 = np.searchsorted(self.ge, self._g(line, b), side="left") - 1
        m_last = nxt - 1  # the line's last interval (first - 1 when empty)
        some = (k1 <= k2) & valid
        border = ~valid | (some & ((k1 < first) | (k2 >= m_last)))
        lo = np.maximum(k1, first)
        hi = np.minimum(k2, m_last - 1) + 1
        hi = np.where(some, np.maximum(hi, lo), lo)
        return lo, hi, border

    def measure(self, g: np.ndarray, cum: np.ndarray) -> np.ndarray:
        """Pixels of the intervals before the global coordinate ``g`` (``cum``: the exclusive cumulative lengths)."""
        k = np.searchsorted(self.gs, g, side="right") - 1
        kk = np.maximum(k, 0)
        inside = np.minimum(g - self.gs[kk], self.end[kk] - self.start[kk])
        return np.where(k >= 0, cum[kk] + inside, 0)

    def covered(self, line: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Pixels of ``[a, b)`` on ``line`` covered by these intervals (int64, per query)."""
        if self.n == 0:
            return np.zeros(line.size, np.int64)
        length = self.end - self.start
        cum = np.concatenate(([0], np.cumsum(length)[:-1]))
        return self.measure(self._g(line, b), cum) - self.measure(self._g(line, a), cum)


def components(n: int, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(n,) component label of each of ``n`` nodes joined by the edges ``src``–``dst``: labels 0, 1, … numbered in
    order of each component's first node (as scipy's ``connected_components``). By
    :func:`gpuslice.mesh.graph.components`: numpy for the graphs the checks make (a few thousand nodes), scipy
    only for large ones, so that `gpuslice check` does not import scipy.sparse (~0.16 s) for a typical model."""
    if n == 0:
        return np.zeros(0, np.int64)
    from ..mesh.graph import components as smallest_node_labels

    labels = smallest_node_labels(n, np.asarray(src, np.int64), np.asarray(dst, np.int64))
    return np.unique(labels, return_inverse=True)[1].astype(np.int64).reshape(n)


def expand_pairs(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(query, index)`` for every ``index`` in ``[lo[q], hi[q])``: the ranges of the queries flattened."""
    return expand_ranges(lo, np.maximum(hi - lo, 0))
