"""The exact rebuild of crossing loops cluster by cluster (``rings._groups``): loops of one layer whose boxes meet no
other cluster's are rebuilt apart, so a cluster the arrangement path refuses (collinear overlapping edges, as the
coplanar faces of a plate's parts give) goes to GEOS alone, and the result is the layer's as a whole."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from test_overlap_groups import bowtie, make_loops, square, truth_area  # (tests/slicing: on sys.path under pytest)

import gpuslice.slicing.overlaps as overlaps
import gpuslice.slicing.rings as rings
from gpuslice.slicing.nest import nest_loops


def _shared_edges(x0: float, y0: float) -> list[np.ndarray]:
    """Two squares that overlap, their bottom and top edges partly on one line: GEOS's noding merges the shared
    stretch into one piece, which the arrangement path does not take."""
    return [square(x0, y0, 10), square(x0 + 5, y0, 10)]


def _geos_calls(monkeypatch) -> list[list[int]]:
    calls: list[list[int]] = []
    real = overlaps._geos_region

    def spy(noded, ids, *args):
        calls.append(sorted(ids.tolist()))
        return real(noded, ids, *args)

    monkeypatch.setattr(overlaps, "_geos_region", spy)
    return calls


def test_only_the_refused_cluster_goes_to_geos(monkeypatch):
    calls = _geos_calls(monkeypatch)
    loops = make_loops([[*_shared_edges(0, 0), bowtie(100, 0, 10), *_shared_edges(0, 100)]])
    nd = nest_loops(loops, 1)
    assert nd.overlaps_resolved[0] == 1
    assert abs(nd.area[0] - truth_area(loops, 0)) < 1e-9
    assert abs(nd.area[0] - (150.0 + 50.0 + 150.0)) < 1e-9
    assert calls == [[0, 1], [3, 4]]  # each pair of squares on its own; the bow-tie by the arrangement path


def test_clusters_give_the_layer_as_a_whole(monkeypatch):
    """The same layers with every cluster's boxes made to meet (one cluster per layer, as before the split): the same
    points, loops, holes and areas."""
    layers = [[*_shared_edges(0, 0), bowtie(40, 0, 10), square(80, 0, 10), square(83, 3, 3, ccw=False)],
              [bowtie(0, 0, 10), *_shared_edges(40, 0), bowtie(80, 0, 10)],
              [*_shared_edges(0, 0), *_shared_edges(40, 0)]]
    split = nest_loops(make_loops(layers), len(layers))
    real = rings._affected_all

    def one_cluster(g, lo, hi, seed, size, with_label=False):
        take, label = real(g, lo, hi, seed, size, with_label=True)
        first = np.cumsum(size) - size
        return (take, first[g]) if with_label else take

    monkeypatch.setattr(rings, "_affected_all", one_cluster)
    whole = nest_loops(make_loops(layers), len(layers))
    for name in ("points", "loop_offsets", "layer_offsets", "loop_layer", "loop_is_hole", "loop_parent", "area",
                 "overlaps_resolved"):
        np.testing.assert_array_equal(getattr(split, name), getattr(whole, name), err_msg=name)
    assert split.overlaps_resolved.tolist() == [1, 1, 1]


@pytest.mark.parametrize("beside", [False, True])
def test_geos_clusters_beside_each_other(monkeypatch, beside):
    """Many refused clusters: half of them on a second thread (``in_halves``) gives what one thread gives."""
    layers = [[*_shared_edges(0, 0), *_shared_edges(30, k), bowtie(60, 0, 10 + k)] for k in range(6)]
    monkeypatch.setattr(rings, "HALVES_MIN_POINTS", 1 if beside else 1 << 60)
    threads = []
    real = overlaps._geos_region

    def spy(*args):
        threads.append(threading.current_thread().name)
        return real(*args)

    monkeypatch.setattr(overlaps, "_geos_region", spy)
    nd = nest_loops(make_loops(layers), len(layers))
    assert len(threads) == 12  # (two clusters a layer refused)
    assert any(t != "MainThread" for t in threads) == beside
    for k in range(len(layers)):
        assert abs(nd.area[k] - truth_area(make_loops(layers), k)) < 1e-9
    monkeypatch.setattr(rings, "HALVES_MIN_POINTS", 1 << 60 if beside else 1)
    other = nest_loops(make_loops(layers), len(layers))
    np.testing.assert_array_equal(nd.points, other.points)
    np.testing.assert_array_equal(nd.loop_offsets, other.loop_offsets)
    np.testing.assert_array_equal(nd.area, other.area)
