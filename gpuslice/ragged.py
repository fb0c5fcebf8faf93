"""Ragged-array index helpers shared by the stages (numpy only)."""

from __future__ import annotations

import numpy as np

__all__ = ["expand_ranges", "group_ranks", "unique_ints", "isin_ints", "loop_chunks", "LOOP_CHUNK"]


def expand_ranges(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every run ``starts[i] .. starts[i] + counts[i] - 1``, concatenated in order, without a Python loop.

    Returns ``(owner, values)``, both (N,) int64 with N = ``counts.sum()``: ``values`` the integers of the runs and
    ``owner`` the run ``i`` each came from. ``counts`` must be ≥ 0 (empty runs give nothing).

    >>> expand_ranges(np.array([10, 0, 5]), np.array([2, 0, 3]))
    (array([0, 0, 2, 2, 2]), array([10, 11,  5,  6,  7]))
    """
    counts = np.asarray(counts, dtype=np.int64)
    owner = np.repeat(np.arange(counts.size, dtype=np.int64), counts)
    local = np.arange(owner.size, dtype=np.int64) - np.repeat(np.cumsum(counts) - counts, counts)
    return owner, np.asarray(starts, dtype=np.int64)[owner] + local


def group_ranks(g: np.ndarray) -> np.ndarray:
    """0, 1, 2, … within each run of equal consecutive values of ``g`` (int64), without a Python loop.

    >>> group_ranks(np.array([4, 4, 7, 7, 7, 2]))
    array([0, 1, 0, 1, 2, 0])
    """
    if g.size == 0:
        return np.zeros(0, np.int64)
    start = np.empty(g.size, bool)
    start[0] = True
    np.not_equal(g[1:], g[:-1], out=start[1:])
    first = np.flatnonzero(start)
    return np.arange(g.size) - np.repeat(first, np.diff(np.append(first, g.size)))


def unique_ints(*arrays: np.ndarray) -> np.ndarray:
    """The sorted distinct values of the integer ``arrays`` together: ``np.unique`` of one, ``np.union1d`` of two.
    (numpy's own import ``numpy.ma`` at their first call, ~16 ms of a command's start; this sorts and compares.)

    >>> unique_ints(np.array([3, 1, 3]), np.array([2, 1]))
    array([1, 2, 3])
    """
    s = np.sort(np.concatenate([np.ravel(a) for a in arrays]) if len(arrays) > 1 else np.ravel(arrays[0]))
    if s.size < 2:
        return s
    keep = np.empty(s.size, bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


def isin_ints(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.isin(a, b)`` for integer arrays (a binary search in sorted ``b``; numpy's imports ``numpy.ma``).

    >>> isin_ints(np.array([5, 1, 7]), np.array([7, 2, 5]))
    array([ True, False,  True])
    """
    a = np.asarray(a)
    s = np.sort(np.ravel(b))
    if s.size == 0:
        return np.zeros(a.shape, bool)
    at = np.minimum(np.searchsorted(s, a), s.size - 1)
    return s[at] == a


#: edges per chunk of a loop in nesting's containment tests (:class:`gpuslice.slicing.contain.Chunks`), whose boxes
#: the device makes beside chaining (``chunk_boxes`` in ``kernels/walk.cl``)
LOOP_CHUNK = 64


def loop_chunks(offsets: np.ndarray, size: int = LOOP_CHUNK, ids: np.ndarray | None = None):
    """The closed loops ``offsets[r] .. offsets[r + 1] - 1`` of ``ids`` (all when None) cut into chunks of ``size``
    edges from each loop's first point (edge k: point k to the next, the last back to the first). Returns ``(off,
    loop, start, end, nxt)``: loop r's chunks are ``off[r]`` to ``off[r + 1] - 1`` (none for the loops not in
    ``ids``); chunk c holds the edges from points ``start[c]`` to ``end[c] - 1`` of loop ``loop[c]``, and ``nxt[c]``
    is the point its last edge ends at (the loop's first point after its last chunk)."""
    first, last = offsets[:-1], offsets[1:]
    n = np.zeros(first.size, dtype=np.int64)
    at = slice(None) if ids is None else ids
    n[at] = np.maximum((last[at] - first[at] + size - 1) // size, 1)
    off = np.zeros(n.size + 1, dtype=np.int64)
    np.cumsum(n, out=off[1:])
    loop, rank = expand_ranges(np.zeros(n.size, dtype=np.int64), n)
    start = first[loop] + size * rank
    end = np.minimum(start + size, last[loop])
    return off, loop, start, end, np.where(end < last[loop], end, first[loop])
