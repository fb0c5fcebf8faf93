"""The previews' height map (gpuslice.raster.layers.HeightMap): from runs a batch at a time, only the pixels a layer
covers and the next does not, against the plain maximum over every layer's mask."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.mesh import shapes
from gpuslice.prefetch import live_threads
from gpuslice.raster import RasterSpec, masks
from gpuslice.raster.coverage import Tile
from gpuslice.raster.layers import HeightMap, RunLayer, run_groups
from gpuslice.raster.runs import iter_runs


def reference(res, spec, step: int, layers) -> np.ndarray:
    """The highest of ``layers`` whose mask is at least 128 on each sampled pixel, level-coded as HeightMap."""
    rows, cols = spec.shape
    img = np.zeros((-(-rows // step), -(-cols // step)), np.uint8)
    n = max(res.n_layers - 1, 1)
    for i, m in zip(layers, masks(res, spec, layers=list(layers)), strict=True):
        level = np.uint8(1 + (254 * i) // n)
        cov = m[::step, ::step] >= 128
        img[cov] = np.maximum(img[cov], level)
    return img


@pytest.fixture(scope="module")
def hollow():
    # a closed cavity: the middle layers have a hole that the lid's layers cover again (a pixel covered by a layer,
    # not by the next one, but by a later one), plus a torus beside it (sides sloping both ways)
    tris = np.concatenate([shapes.hollow_box(20.0, 8.0), shapes.torus(9.0, 3.0, 48, 24) + [30.0, 0.0, 0.0]])
    return slice_mesh(mesh_from_triangles(tris), thickness=0.5, backend="numpy")


@pytest.mark.parametrize("pieces", [1, 3_000, 1 << 22])  # a layer per batch, several batches, one batch
@pytest.mark.parametrize("step", [1, 3, 8])
def test_height_map_from_runs_equals_every_layers_maximum(device, hollow, pieces, step):
    spec = RasterSpec(resolution=(1200, 700), pixel=0.05)
    hm = HeightMap(spec.shape, hollow.n_layers, step)
    seen = 0
    for runs in iter_runs(hollow, spec, device=device, max_batch_pieces=pieces):
        for j in range(len(runs.layers)):
            hm.add(RunLayer(int(runs.layers[j]), runs, j))
            seen += 1
    assert seen == hollow.n_layers
    ref = reference(hollow, spec, step, range(hollow.n_layers))
    assert np.count_nonzero(ref) > 100 and len(np.unique(ref)) > 5  # a real height map, not a blank one
    assert np.array_equal(hm.img, ref)


def test_height_map_of_a_selection_out_of_order(device, hollow):
    """Layers of a batch not in increasing order: every covered pixel is written (the shortcut needs the order)."""
    spec = RasterSpec(resolution=(1200, 700), pixel=0.05)
    pick = [30, 5, 18, 17]
    hm = HeightMap(spec.shape, hollow.n_layers, 4)
    for runs in iter_runs(hollow, spec, device=device, layers=pick):
        for j in range(len(runs.layers)):
            hm.add(RunLayer(int(runs.layers[j]), runs, j))
    assert np.array_equal(hm.img, reference(hollow, spec, 4, pick))


def test_height_map_from_tiles(hollow):
    spec = RasterSpec(resolution=(1200, 700), pixel=0.05)
    hm = HeightMap(spec.shape, hollow.n_layers, 5)
    for i, m in enumerate(masks(hollow, spec)):
        hm.add(Tile(i, 0, 0, m))
    assert np.array_equal(hm.img, reference(hollow, spec, 5, range(hollow.n_layers)))


def test_height_map_uses_the_items_index_not_the_batchs_numbering(device, hollow):
    """Runs numbered from 0 in their own batch (the z-sampled layers come a chunk at a time) but handed in as layers
    ``shift + k``: the levels follow the items' indices."""
    spec = RasterSpec(resolution=(1200, 700), pixel=0.05)
    shift, n_total = 7, hollow.n_layers + 7
    hm = HeightMap(spec.shape, n_total, 4)
    for runs in iter_runs(hollow, spec, device=device, max_batch_pieces=3_000):
        for j in range(len(runs.layers)):
            hm.add(RunLayer(int(runs.layers[j]) + shift, runs, j))
    rows, cols = spec.shape
    ref = np.zeros((-(-rows // 4), -(-cols // 4)), np.uint8)
    for i, m in enumerate(masks(hollow, spec)):
        cov = m[::4, ::4] >= 128
        ref[cov] = np.maximum(ref[cov], np.uint8(1 + (254 * (i + shift)) // (n_total - 1)))
    assert np.array_equal(hm.img, ref)


def test_height_map_raises_a_batchs_error_when_read_and_ends_its_thread(device, hollow):
    """A batch is added on the map's own thread: an error there is raised where the map is read (the writer's
    previews), not lost; reading it ends the thread."""
    spec = RasterSpec(resolution=(1200, 700), pixel=0.05)
    hm = HeightMap(spec.shape, hollow.n_layers, 4)
    runs = next(iter(iter_runs(hollow, spec, device=device)))
    hm.add(RunLayer(int(runs.layers[0]), runs, 0))
    assert runs.n_runs > 2
    broken = dataclasses.replace(runs, grey=runs.grey[:2])  # arrays that disagree: numpy refuses to combine them
    hm.add(RunLayer(int(runs.layers[0]), broken, 0))
    with pytest.raises(ValueError):
        hm.img  # noqa: B018
    mine = f"gpuslice-heightmap-{id(hm):x}"
    deadline = time.monotonic() + 5  # (a batch's thread ends just after its result is set)
    while time.monotonic() < deadline and mine in live_threads():
        time.sleep(0.01)
    assert mine not in live_threads()
    assert hm.img.shape == (-(-spec.shape[0] // 4), -(-spec.shape[1] // 4))  # read again: the error was given once


def test_run_groups_keep_consecutive_entries_of_one_batch():
    """The writers' groups: consecutive entries of one batch of runs, at most ``size`` of them; a new batch, a
    skipped entry or a tile starts a new group (a tile is a group of its own); nothing lost or reordered."""
    a, b = object(), object()
    tile = Tile(7, 0, 0, np.zeros((1, 1), np.uint8))
    items = [RunLayer(k, a, k) for k in range(5)] + [RunLayer(5, b, 0), RunLayer(6, b, 1), RunLayer(9, b, 4), tile,
                                                       RunLayer(10, b, 5)]
    groups = list(run_groups(items, size=3))
    assert [x for g in groups for x in g] == items
    assert [[x.index if isinstance(x, RunLayer) else "t" for x in g] for g in groups] == [
        [0, 1, 2], [3, 4], [5, 6], [9], ["t"], [10]]
