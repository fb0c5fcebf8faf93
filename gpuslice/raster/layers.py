"""One resin layer in flight, as the archive writers take it: a :class:`~gpuslice.raster.coverage.Tile` (a bitmap
of the layer's bounding box: the numpy, GL and bitmap-kernel rasterisers) or a :class:`RunLayer` (the layer's
run-length runs: the default OpenCL rasteriser, never a bitmap). :func:`encode_png` and :func:`sample` serve both,
so a writer never asks which it got.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from ..prefetch import beside
from ..ragged import expand_ranges
from .coverage import Tile
from .png import PngEncoder
from .runs import Runs

__all__ = ["RunLayer", "HeightMap", "top_view", "iter_run_layers", "encode_png", "sample", "pixel_runs",
           "image_segments", "batch_pixel_runs", "batch_image_segments", "run_groups"]


@dataclass(frozen=True)
class RunLayer:
    """Layer ``index`` of a result: entry ``j`` of the batch ``runs`` (display pixels)."""

    index: int
    runs: Runs
    j: int


#: batches of runs made ahead of the writer (:func:`gpuslice.prefetch.prefetch`: the kernel works while the
#: previous batch is encoded)
PREFETCH = 1


def iter_run_layers(result, spec, *, device=None, bounds=None, layers: Sequence[int] | None = None,
                    z_samples: int = 1, merged=None, clip: bool = False) -> Iterator[RunLayer]:
    """Every selected layer's runs, in order (:func:`gpuslice.raster.runs.iter_runs` on the OpenCL device, on a
    thread of its own :data:`PREFETCH` batches ahead of the caller; ``z_samples``: ``result`` holds that many
    sub-layers per layer, averaged; ``merged``: their edges given instead; ``clip``: see ``iter_runs``)."""
    from ..prefetch import prefetch
    from .runs import iter_runs

    batches = prefetch(iter_runs(result, spec, backend="opencl", device=device, bounds=bounds, layers=layers,
                                 z_samples=z_samples, merged=merged, clip=clip), PREFETCH)
    try:
        for runs in batches:
            for j in range(len(runs.layers)):
                yield RunLayer(int(runs.layers[j]), runs, j)
    finally:  # closed early (a writer failed): the producer thread stops now, not when the generator is collected
        batches.close()


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
    _, r, c = _sample_runs(runs, a, b, step, threshold)
    return r, c


def _sample_runs(runs: Runs, a: int, b: int, step: int, threshold: int):
    """(run index, sampled row, sampled column) of the runs ``a:b`` of a batch, as :func:`sample`."""
    idx, r, first, end = _sampled_intervals(runs, a, b, step, threshold)
    owner, cols = expand_ranges(first, end - first)
    return idx[owner], r[owner], cols


def _sampled_intervals(runs: Runs, a: int, b: int, step: int, threshold: int):
    """(run index, sampled row, first, end) of the runs ``a:b`` that cover at least one sampled pixel: the sampled
    columns ``first <= c < end`` (units of ``step``); a row's intervals are disjoint and sorted."""
    row = runs.row[a:b]
    # the sampled rows by a table, not a remainder per run; only the runs kept are widened to int64
    sampled = np.zeros(max(int(runs.shape[0]), int(row.max()) + 1 if row.size else 0), bool)
    sampled[::step] = True
    keep = np.flatnonzero(sampled[row] & (runs.grey[a:b] >= threshold))
    x = runs.x[a:b][keep].astype(np.int64)
    first = -(-x // step)  # the first sampled column of each run, in units of step
    end = (x + runs.length[a:b][keep] - 1) // step + 1
    ok = end > first
    return a + keep[ok], row[keep[ok]].astype(np.int64) // step, first[ok], end[ok]


class HeightMap:
    """The part seen from above, for archive previews: on every ``step``-th row and column of the display (a pixel
    counts when its grey is at least half), the highest layer covering it, as ``img`` uint8: 0 where no layer
    does, else ``1 + 254 * index // (n_layers - 1)``. Layers may come in any order.

    Runs are taken a whole batch at a time (when its first layer comes), and only the sampled pixels a layer covers
    and the next layer of its batch does not are written: the highest layer covering a pixel is one of those (the
    layer above it does not cover it), every other layer written there is lower, so the maximum is the same as over
    every covered pixel of every layer, at the cost of the part's sides instead of its volume.

    A batch of runs is added on a thread of its own (:func:`gpuslice.prefetch.beside`; one batch at a time under the
    map's lock, so the batches' maxima never race), off the writer's thread that feeds the encoders, at most
    :data:`PENDING` batches behind it (their memory is held until then); :attr:`img` waits for the batches given so
    far. Tiles are added on the caller's thread, after them. The threads end with their batch: a writer that fails
    leaves none behind, also while its exception is kept (a pool of the map's own stayed as long as the map)."""

    #: batches of runs waiting for the map's thread before :meth:`add` waits for the oldest
    PENDING = 2

    def __init__(self, shape: tuple[int, int], n_layers: int, step: int) -> None:
        rows, cols = shape
        self.step = int(step)
        self.n = max(n_layers - 1, 1)
        self._img = np.zeros((-(-rows // self.step), -(-cols // self.step)), np.uint8)
        self._batch: Runs | None = None
        self._lock = threading.Lock()
        self._pending: list[Future] = []

    @property
    def img(self) -> np.ndarray:
        """The map, (rows, cols) uint8 of the sampled pixels, once every batch given so far is in (an error of one
        is raised here)."""
        self._drain()
        return self._img

    def _drain(self) -> None:
        """Wait for the batches given so far (raising a batch's error)."""
        pending, self._pending = self._pending, []
        for f in pending:
            f.result()

    def add(self, item: Tile | RunLayer) -> None:
        """Raise the map where the layer (a tile, or runs: then every layer of its batch) covers a sampled pixel."""
        flat = self._img.reshape(-1)
        if isinstance(item, RunLayer):
            if item.runs is not self._batch:
                self._batch = item.runs
                # the batch's layers as the result's indices: a caller may number them from elsewhere (the z-sampled
                # layers come a chunk at a time, each numbered from 0), by a constant shift
                self._pending = [f for f in self._pending if not f.done() or f.exception() is not None]
                if len(self._pending) >= self.PENDING:
                    self._pending[0].result()  # (raises a batch's error here; it stays pending for img)
                self._pending.append(beside(self._add_runs, item.runs, item.index - int(item.runs.layers[item.j]),
                                            name=f"gpuslice-heightmap-{id(self):x}"))
            return
        if self._pending:  # (never with one writer's layers, all tiles or all runs: the map is not shared)
            self._drain()
        r, c = sample(item, self.step)
        if r.size:  # the sampled pixels of one layer are distinct: a plain fancy-indexed maximum
            cells = r * self._img.shape[1] + c
            flat[cells] = np.maximum(flat[cells], np.uint8(1 + (254 * item.index) // self.n))

    def _add_runs(self, runs: Runs, shift: int) -> None:
        with self._lock:
            self._add_runs_locked(runs, shift)

    def _add_runs_locked(self, runs: Runs, shift: int) -> None:
        idx, r, first, end = _sampled_intervals(runs, 0, runs.n_runs, self.step, 128)
        if not idx.size:
            return
        k = np.searchsorted(runs.layer_offsets, idx, side="right") - 1  # each interval's layer in the batch
        rows, width = self._img.shape
        group = k * rows + r  # (layer in the batch, sampled row)
        if len(runs.layers) > 1 and np.all(np.diff(runs.layers) > 0):
            # A \ B per group, with A = the layer's intervals and B = the next layer's (moved to this layer's group):
            # coverage code A + 2B along the row from +-1 / +-2 events; the stretches of code 1 are A \ B. Each of
            # the four event lists is sorted by (group, column), so the stable sort only merges them.
            nb = np.flatnonzero(k >= 1)
            g = np.concatenate([group, group, group[nb] - rows, group[nb] - rows])
            col = np.concatenate([first, end, first[nb], end[nb]])
            delta = np.concatenate([np.ones(idx.size, np.int8), np.full(idx.size, -1, np.int8),
                                    np.full(nb.size, 2, np.int8), np.full(nb.size, -2, np.int8)])
            order = np.argsort(g * (width + 1) + col, kind="stable")
            g, col = g[order], col[order]
            code = np.cumsum(delta[order], dtype=np.int16)
            seg = np.flatnonzero((code[:-1] == 1) & (g[1:] == g[:-1]) & (col[1:] > col[:-1]))
            group, first, end = g[seg], col[seg], col[seg + 1]
        owner, cols = expand_ranges(first, end - first)
        level = (1 + (254 * (runs.layers.astype(np.int64) + shift)) // self.n).astype(np.uint8)
        np.maximum.at(self._img.reshape(-1), (group % rows)[owner] * width + cols, level[group // rows][owner])


def top_view(img: np.ndarray, spec) -> np.ndarray:
    """``img``, an image in the display's frame (a :class:`HeightMap`'s, rows and columns of ``spec``'s PNG), as the
    part is seen from above: columns along +x, rows down along -y, whatever the display's orientation and mirrors
    (a preview shows the part as the user placed it; the layers themselves are mirrored for the printer's optics).
    A cell then spans ``spec.px`` along a row and ``spec.py`` down a column, in any orientation. A view, no copy."""
    if spec.portrait:  # the PNG's columns run along y, its rows along x (u = (h - Y)/py, v = (w - X)/px)
        img = img.T
        flip_rows, flip_cols = spec.mirror_x, not spec.mirror_y
    else:  # u = X/px, v = (h - Y)/py
        flip_rows, flip_cols = spec.mirror_y, spec.mirror_x
    return img[::-1 if flip_rows else 1, ::-1 if flip_cols else 1]


def pixel_runs(item: Tile | RunLayer, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The layer as run-length runs in display order, what run-length archive formats store: ``(start, length,
    grey)`` with ``start`` the int64 row-major pixel index (``row * cols + column``, row 0 the PNG's top row),
    ``length`` int64 (>= 1) and ``grey`` uint8 (never 0: the pixels between runs are blank). Runs are sorted, never
    overlap and never cross a row end; two runs of one row never touch with the same grey. ``cols``: the display's
    columns (:attr:`RasterSpec.shape` [1]). Runs come straight from the rasteriser's runs; a tile is run-length
    coded row by row (time proportional to the tile, never the display)."""
    if isinstance(item, RunLayer):
        return batch_pixel_runs(item.runs, item.j, item.j + 1, cols)[:3]
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


def run_groups(items: Iterable, size: int = 16, key=None) -> Iterator[list]:
    """``items`` in lists of up to ``size`` consecutive :class:`RunLayer` entries of one batch of runs (what
    :func:`batch_pixel_runs` takes at once); a :class:`~gpuslice.raster.coverage.Tile` is a list of its own.
    ``key``: the layer of an item when the items are not layers themselves (e.g. ``(k, layer)`` pairs)."""
    group: list = []
    last = None
    for entry in items:
        item = entry if key is None else key(entry)
        if group and (not isinstance(item, RunLayer) or len(group) == size or item.runs is not last.runs
                      or item.j != last.j + 1):
            yield group
            group = []
        if not isinstance(item, RunLayer):
            yield [entry]
            continue
        group.append(entry)
        last = item
    if group:
        yield group


def batch_pixel_runs(runs: Runs, a: int, b: int, cols: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`pixel_runs` of entries ``a`` … ``b`` − 1 of the batch ``runs`` at once: ``(start, length, grey,
    offsets)``, the entries' runs one after the other, entry ``a + k`` owning ``offsets[k]:offsets[k + 1]``."""
    lo, hi = int(runs.layer_offsets[a]), int(runs.layer_offsets[b])
    start = runs.row[lo:hi].astype(np.int64) * cols + runs.x[lo:hi]
    return start, runs.length[lo:hi].astype(np.int64), runs.grey[lo:hi], runs.layer_offsets[a : b + 1] - lo


def batch_image_segments(start: np.ndarray, length: np.ndarray, value: np.ndarray, offsets: np.ndarray,
                         n_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`image_segments` of several images at once (one numpy pass over all their runs instead of one per
    image): image k has the runs ``offsets[k]:offsets[k + 1]`` of ``start``, ``length``, ``value``. Returns ``(n, v,
    seg_offsets)``: image k's segments are ``seg_offsets[k]:seg_offsets[k + 1]`` of ``n`` and ``v``, exactly what
    :func:`image_segments` gives for it alone."""
    start = np.asarray(start, np.int64)
    length = np.asarray(length, np.int64)
    value = np.asarray(value, np.uint8)
    offsets = np.asarray(offsets, np.int64)
    n_img = offsets.size - 1
    m = start.size
    image = np.repeat(np.arange(n_img, dtype=np.int64), np.diff(offsets))
    first = np.zeros(m, bool)
    first[offsets[:-1][offsets[:-1] < offsets[1:]]] = True  # each image's first run
    end = start + length
    if m:
        join = ~first[1:] & (start[1:] == end[:-1]) & (value[1:] == value[:-1])
        if join.any():  # touching runs of one value in one image: one run
            head = np.flatnonzero(np.concatenate(([True], ~join)))
            last = np.append(head[1:] - 1, m - 1)
            start, value, image, first = start[head], value[head], image[head], first[head]
            end = end[last]
            length = end - start
            m = start.size
    counts = np.bincount(image, minlength=n_img) if m else np.zeros(n_img, np.int64)
    prev_end = np.empty(m, np.int64)
    prev_end[1:] = end[:-1]
    prev_end[first] = 0
    gaps = start - prev_end
    tail = np.full(n_img, n_pixels, np.int64)
    has = counts > 0
    tail[has] -= end[np.cumsum(counts)[has] - 1]
    # per image: gap 0, run 0, gap 1, run 1, ..., its tail gap
    base = np.zeros(n_img + 1, np.int64)
    np.cumsum(2 * counts + 1, out=base[1:])
    pos = 2 * np.arange(m, dtype=np.int64) + image  # run k of the whole batch sits after its own gap
    n = np.empty(int(base[-1]), np.int64)
    v = np.zeros(n.size, np.uint8)
    n[pos], n[pos + 1], n[base[1:] - 1] = gaps, length, tail
    v[pos + 1] = value
    keep = n > 0
    seg_image = np.repeat(np.arange(n_img, dtype=np.int64), 2 * counts + 1)[keep]
    seg_offsets = np.zeros(n_img + 1, np.int64)
    np.cumsum(np.bincount(seg_image, minlength=n_img), out=seg_offsets[1:])
    return n[keep], v[keep], seg_offsets
