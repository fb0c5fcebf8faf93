"""Test helpers: layer images as run-length runs, as the runs kernel lays them out (for the encoding kernels' tests)."""

from __future__ import annotations

import numpy as np

from gpuslice.raster.runs import Runs


def image_runs(img: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(start, length, grey) of the non-blank runs of ``img`` row by row (a run never crosses a row end)."""
    h, w = img.shape
    flat = img.reshape(-1)
    change = np.ones(flat.size, bool)
    change[1:] = flat[1:] != flat[:-1]
    change[::w] = True
    start = np.flatnonzero(change)
    length = np.diff(np.append(start, flat.size))
    keep = flat[start] != 0
    return start[keep], length[keep], flat[start][keep]


def runs_of(images: list[np.ndarray]) -> Runs:
    """A :class:`~gpuslice.raster.runs.Runs` of ``images`` (each (rows, cols) uint8), typed as the runs kernel
    types it (int32 row, x, length; uint8 grey)."""
    cols = images[0].shape[1]
    parts = [image_runs(img) for img in images]
    offsets = np.concatenate(([0], np.cumsum([p[0].size for p in parts]))).astype(np.int64)
    start = np.concatenate([p[0] for p in parts]).astype(np.int64)
    length = np.concatenate([p[1] for p in parts]).astype(np.int32)
    grey = np.concatenate([p[2] for p in parts]).astype(np.uint8)
    return Runs(np.arange(len(images)), offsets, (start // cols).astype(np.int32), (start % cols).astype(np.int32),
                length, grey, images[0].shape)


def quantised_runs(start, length, grey, quantise) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs after a format's quantisation ``quantise(grey)`` (int64 greys), as a decoder returns them: blank ones
    dropped, touching ones of one grey merged."""
    g = quantise(grey)
    k = g > 0
    start, length, g = np.asarray(start, np.int64)[k], np.asarray(length, np.int64)[k], g[k]
    if not start.size:
        return start, length, g
    end = start + length
    head = np.flatnonzero(np.concatenate(([True], (start[1:] != end[:-1]) | (g[1:] != g[:-1]))))
    last = np.append(head[1:] - 1, start.size - 1)
    return start[head], end[last] - start[head], g[head]
