"""One resin layer in flight, as the archive writers take it: a :class:`~gpuslice.raster.coverage.Tile` (a bitmap
of the layer's bounding box: the numpy, GL and bitmap-kernel rasterisers) or a :class:`RunLayer` (the layer's
run-length runs: the default OpenCL rasteriser, never a bitmap). :func:`encode_png` and :func:`sample` serve both,
so a writer never asks which it got.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from ..ragged import expand_ranges
from .coverage import Tile
from .png import PngEncoder
from .runs import Runs

__all__ = ["RunLayer", "iter_run_layers", "encode_png", "sample", "pixel_runs", "image_segments"]


@dataclass(frozen=True)
class RunLayer:
    """Layer ``index`` of a result: entry ``j`` of the batch ``runs`` (display pixels)."""

    index: int
    runs: Runs
    j: int


def iter_run_layers(result, spec, *, device=None, bounds=None, layers: Sequence[int] | None = None,
                    z_samples: int = 1) -> Iterator[RunLayer]:
    """Every selected layer's runs, in order, one batch of layers in flight (:func:`gpuslice.raster.runs.iter_runs`
    on the OpenCL device; ``z_samples``: ``result`` holds that many sub-layers per layer, averaged)."""
    from .runs import iter_runs

    for runs in iter_runs(result, spec, backend="opencl", device=device, bounds=bounds, layers=layers,
                          z_samples=z_samples):
        for j in range(len(runs.layers)):
            yield RunLayer(int(runs.layers[j]), runs, j)


#: the deflate level runs are written at straight (no bitmap); another level goes through a tile and that deflater
RUNS_LEVEL = 1


def encode_png(item: Tile | RunLayer, encoder: PngEncoder) -> bytes:
    """The layer's PNG: a tile through ``encoder`` (ISA-L or zlib at its level); runs at :data:`RUNS_LEVEL` straight
    to deflate (:func:`gpuslice.raster.deflate_runs.encode_png_from_runs`: same pixels, ~10x faster at 12K), at
    another level through the tile of their bounding box."""
    if isinstance(item, Tile):
        return encoder.encode(item)
    if encoder.level != RUNS_LEVEL:
        return encoder.encode(_tile(item))
    from .deflate_runs import encode_png_from_runs

    return encode_png_from_runs(item.runs, item.j, encoder.nx, encoder.ny)


def _tile(item: RunLayer) -> Tile:
    """The bitmap of the runs' bounding box (display pixels)."""
    from .coverage import tile_from_runs

    runs, j = item.runs, item.j
    a, b = int(runs.layer_offsets[j]), int(runs.layer_offsets[j + 1])
    if a == b:
        return Tile(item.index, 0, 0, np.zeros((0, 0), np.uint8))
    row, x, n = runs.row[a:b], runs.x[a:b], runs.length[a:b]
    r0, c0 = int(row[0]), int(x.min())
    h, w = int(row[-1]) - r0 + 1, int((x + n).max()) - c0
    return Tile(item.index, r0, c0, tile_from_runs(runs, j, r0, c0, h, w))


def sample(item: Tile | RunLayer, step: int, threshold: int = 128) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the display pixels at multiples of ``step`` (in rows and columns) whose grey is at least
    ``threshold``, divided by ``step``: a coarse top view, in time proportional to the layer's tile or runs."""
    if isinstance(item, Tile):
        h, w = item.data.shape
        if not h or not w:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        dr, dc = (-item.row0) % step, (-item.col0) % step
        r, c = np.nonzero(item.data[dr::step, dc::step] >= threshold)
        return (item.row0 + dr) // step + r, (item.col0 + dc) // step + c
    runs, j = item.runs, item.j
    a, b = int(runs.layer_offsets[j]), int(runs.layer_offsets[j + 1])
    row, x = runs.row[a:b].astype(np.int64), runs.x[a:b].astype(np.int64)
    end = x + runs.length[a:b]
    keep = (row % step == 0) & (runs.grey[a:b] >= threshold)
    first = -(-x[keep] // step)  # the first sampled column of each run, in units of step
    count = np.maximum((end[keep] - 1) // step - first + 1, 0)
    owner, cols = expand_ranges(first, count)
    return row[keep][owner] // step, cols


def pixel_runs(item: Tile | RunLayer, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The layer as run-length runs in display order, what run-length archive formats store: ``(start, length,
    grey)`` with ``start`` the int64 row-major pixel index (``row * cols + column``, row 0 the PNG's top row),
    ``length`` int64 (>= 1) and ``grey`` uint8 (never 0: the pixels between runs are blank). Runs are sorted, never
    overlap and never cross a row end; two runs of one row never touch with the same grey. ``cols``: the display's
    columns (:attr:`RasterSpec.shape` [1]). Runs come straight from the rasteriser's runs; a tile is run-length
    coded row by row (time proportional to the tile, never the display)."""
    if isinstance(item, RunLayer):
        runs, j = item.runs, item.j
        a, b = int(runs.layer_offsets[j]), int(runs.layer_offsets[j + 1])
        start = runs.row[a:b].astype(np.int64) * cols + runs.x[a:b]
        return start, runs.length[a:b].astype(np.int64), runs.grey[a:b]
    data = item.data
    h, w = data.shape
    if not h or not w:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.uint8)
    # a run starts where the grey changes along a row (or at a row's start); blank runs are dropped
    change = np.ones((h, w), bool)
    change[:, 1:] = data[:, 1:] != data[:, :-1]
    r, c = np.nonzero(change)
    first = r * w + c
    ends = np.append(first[1:], h * w)
    row_end = (r + 1) * w
    length = np.minimum(ends, row_end) - first
    grey = data.reshape(-1)[first]
    keep = grey != 0
    start = (r[keep] + item.row0).astype(np.int64) * cols + (c[keep] + item.col0)
    return start, length[keep].astype(np.int64), grey[keep]


def image_segments(start: np.ndarray, length: np.ndarray, value: np.ndarray,
                   n_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """A whole image of ``n_pixels`` as consecutive segments of one value each, what run-length archive formats
    encode: ``(n, v)``, int64 lengths (>= 1) and uint8 values, in pixel order, blank gaps (value 0) included, from
    the non-blank runs ``start`` (row-major pixel index), ``length``, ``value`` (sorted, not overlapping, as
    :func:`pixel_runs` gives them). Touching runs of one value (across a row end, or equal after a format's
    quantisation) become one segment; empty gaps are dropped. Vectorised over the runs."""
    start = np.asarray(start, np.int64)
    length = np.asarray(length, np.int64)
    value = np.asarray(value, np.uint8)
    m = start.size
    if m:
        end = start + length
        join = (start[1:] == end[:-1]) & (value[1:] == value[:-1])
        if join.any():
            head = np.flatnonzero(np.concatenate(([True], ~join)))
            last = np.append(head[1:] - 1, m - 1)
            start, value = start[head], value[head]
            length = end[last] - start
            end = start + length
            m = start.size
        gaps = start - np.concatenate(([0], end[:-1]))
        tail = n_pixels - int(end[-1])
    else:
        gaps, tail = np.zeros(0, np.int64), n_pixels
    n = np.empty(2 * m + 1, np.int64)  # gap 0, run 0, gap 1, run 1, ..., the tail gap
    n[0:-1:2], n[1::2], n[-1] = gaps, length, tail
    v = np.zeros(2 * m + 1, np.uint8)
    v[1::2] = value
    keep = n > 0
    return n[keep], v[keep]
