"""Ragged-array index helpers shared by the stages (numpy only)."""

from __future__ import annotations

import numpy as np

__all__ = ["expand_ranges"]


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
