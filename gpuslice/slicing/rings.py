"""The loop primitives that nesting (:mod:`.nest`) and its exact rebuild of crossing loops (:mod:`.overlaps`) share:
the :class:`Nested` layout, shoelace areas, winding numbers of points around loops, the groups of loops a rebuild
takes together, and the loops as rings or shapely polygons. Columnar: points (P, 2) float32 mm, loop offsets."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from ..mesh.graph import connected_labels
from ..prefetch import beside as _beside
from ..ragged import expand_ranges, isin_ints, unique_ints

__all__ = ["Nested", "signed_areas", "filled", "cycle_labels", "beside", "in_halves", "node_lines", "node_groups",
           "move_chains"]

#: points above which nesting runs independent GEOS steps on a second thread (GEOS and numpy release the GIL)
BESIDE_MIN_POINTS = 100_000
#: points (coordinates) above which :func:`in_halves` splits a GEOS call over two threads
HALVES_MIN_POINTS = 20_000
_WORKER = "gpuslice-nest"


def beside(fn, *args) -> Future:
    """``fn(*args)`` on a daemon thread of its own named ``gpuslice-nest`` (:func:`gpuslice.prefetch.beside`): for
    steps independent of what the caller does meanwhile, so that a second core works on them."""
    return _beside(fn, *args, name=_WORKER)


def in_halves(fn, work: np.ndarray, *arrays: np.ndarray) -> np.ndarray:
    """``fn(*arrays)`` for a function of arrays element by element (a shapely predicate or constructor): its first
    half (cut where the cumulative ``work``, e.g. each element's points, reaches half) :func:`beside` the second,
    concatenated, when the work is large (else, or on the worker thread itself, one call). When a half raises, the
    other is waited for and the first half's exception, if any, is raised (the one a single call would raise)."""
    from ..prefetch import current_name

    total = np.cumsum(work)
    n = int(total.size)
    if n < 2 or total[-1] < HALVES_MIN_POINTS or current_name().startswith(_WORKER):
        return fn(*arrays)
    half = max(1, min(int(np.searchsorted(total, total[-1] / 2)), n - 1))
    first = beside(fn, *(x[:half] for x in arrays))
    try:
        rest = fn(*(x[half:] for x in arrays))
    except BaseException:
        early = first.exception()  # (waited for: nothing of the call runs on once it has raised)
        if early is not None:  # the first half's failure, as one call over all the elements would raise it
            raise early from None
        raise
    return np.concatenate([first.result(), rest])


def node_lines(lines: np.ndarray) -> np.ndarray:
    """``shapely.node`` of each geometry of ``lines`` (noded one by one): :func:`in_halves`."""
    import shapely

    return in_halves(shapely.node, shapely.get_num_coordinates(lines), lines)


#: mm: the precision grid a group's lines are snapped to when GEOS cannot node them as they are (as the checks'
#: overlays retry: ``checks/islands._overlay``): a float32 coordinate's resolution near 10 mm (its ulp 9.5e-7 mm)
SNAP_GRID = 1e-6


def node_groups(lines: np.ndarray) -> np.ndarray:
    """``shapely.node`` of every group's lines (:func:`node_lines`: GEOS, half of the groups on a second thread when
    large). Where GEOS fails (its noding does not converge: a broken file whose coordinates span some 40 orders of
    magnitude, e.g. float32 subnormals beside millimetres), each group is noded alone and a failing one again on the
    :data:`SNAP_GRID` grid; one that still fails raises :class:`~gpuslice.errors.InvalidGeometryError` (the slicer
    names the file and the layers)."""
    import shapely

    try:
        return node_lines(lines)
    except shapely.errors.GEOSException:
        pass
    out = np.empty(lines.size, dtype=object)
    for g in range(lines.size):  # (only after a failure: a loop over the groups of one batch)
        for grid in (None, SNAP_GRID):
            try:
                out[g] = shapely.node(lines[g] if grid is None else
                                      shapely.set_precision(lines[g], grid, mode="pointwise"))
                break
            except shapely.errors.GEOSException as exc:
                failure = exc
        else:
            from ..errors import InvalidGeometryError, one_line

            raise InvalidGeometryError(f"GEOS could not node its crossing loops ({one_line(failure)})") from None
    return out


@dataclass
class Nested:
    points: np.ndarray
    loop_offsets: np.ndarray
    layer_offsets: np.ndarray
    loop_layer: np.ndarray
    loop_is_hole: np.ndarray
    loop_parent: np.ndarray
    loop_closed: np.ndarray
    area: np.ndarray
    unfilled_loops: np.ndarray
    overlaps_resolved: np.ndarray
    #: (L,) loops per layer that nesting turned round (their winding disagreed with the fill: an inside-out shell)
    reoriented: np.ndarray


def _as_complex(points: np.ndarray) -> np.ndarray:
    """(P,) complex128 view-copy x + iy of (P, 2) float32 points (1-D gathers are fast, 2-D fancy indexing is not)."""
    return np.ascontiguousarray(points, dtype=np.float32).view(np.complex64).reshape(-1).astype(np.complex128)


def signed_areas(points: np.ndarray, offsets: np.ndarray, pc: np.ndarray | None = None) -> np.ndarray:
    """(R,) float64 shoelace area of each loop, mm^2, positive for counter-clockwise.

    Products of float32 coordinates are exact in float64, so the sum is accurate to ~1e-16 of the coordinates'
    squared magnitude per point (1e-10 mm^2 for a 100 mm part with a million points).
    """
    n = offsets.size - 1
    if points.shape[0] == 0 or n == 0:
        return np.zeros(n)
    pc = _as_complex(points) if pc is None else pc
    x, y = pc.real, pc.imag
    cross = np.empty(pc.size)
    np.multiply(x[:-1], y[1:], out=cross[:-1])
    cross[:-1] -= y[:-1] * x[1:]  # (products of float32 values are exact: one rounding, as (conj(a) * b).imag)
    first, last = offsets[:-1], offsets[1:] - 1
    cross[last] = x[last] * y[first] - y[last] * x[first]
    return np.add.reduceat(cross, first) / 2.0


def _winding_numbers(pc, offsets, pairs_i, pairs_j, q) -> np.ndarray:
    """Winding number of query point q[i] (complex) around loop j for every pair (i, j).

    Counts the edges a -> b of loop j that cross the horizontal line through q (a below or on it, b above:
    +1 when q is left of the edge; b below or on it, a above: -1 when q is right of it). Only those edges' cross
    products are computed; the others are only compared in y."""
    lens = np.diff(offsets)[pairs_j]
    ends = np.cumsum(lens)
    total = int(ends[-1]) if ends.size else 0
    first = ends - lens
    a = np.arange(total, dtype=np.int64)
    a += np.repeat(offsets[:-1][pairs_j] - first, lens)  # every edge a -> b of loop j, once per pair
    ay = pc.imag[a]
    ay -= np.repeat(q.imag[pairs_i], lens)
    by = np.empty_like(ay)
    by[:-1] = ay[1:]
    has = lens > 0
    by[ends[has] - 1] = ay[first[has]]  # each loop's last edge goes back to its first point
    above_a, above_b = ay > 0, by > 0
    e = np.flatnonzero(above_a != above_b)  # only the edges across the point's horizontal line can count
    pair_of = np.searchsorted(ends, e, side="right")
    ea = a[e]
    eb = np.where(e + 1 == ends[pair_of], offsets[:-1][pairs_j][pair_of], ea + 1)
    p = q[pairs_i][pair_of]
    pa, pb = pc[ea] - p, pc[eb] - p
    left = (pa.conj() * pb).imag  # > 0: the point is left of the edge a -> b
    up = above_b[e]
    contrib = (up & (left > 0)).astype(np.int64) - (~up & (left < 0))
    return np.bincount(pair_of, weights=contrib, minlength=pairs_i.size).astype(np.int64)


def _groups(layer, closed, layers, seeds, lo, hi):
    """(layer, ids) of every group of loops the exact rebuild (:mod:`.overlaps`) takes in the suspect layers
    (``layers``), ascending: those that may share a face with a ``seeds`` loop (:func:`_affected_all`), a group per
    cluster of them (loops whose boxes meet no other cluster's loop box, e.g. the parts of a plate: what one cluster
    bounds does not depend on another's, so a cluster the arrangement path cannot take goes to GEOS alone), in order
    of layer and then of their smallest loop."""
    cand = np.flatnonzero(closed)
    cand = cand[np.argsort(layer[cand], kind="stable")]
    is_seed = np.zeros(layer.size, dtype=bool)
    is_seed[seeds] = True
    bounds = np.searchsorted(layer[cand], np.stack([layers, layers + 1]))
    size = bounds[1] - bounds[0]
    owner, at = expand_ranges(bounds[0], size)  # every candidate of every suspect layer (g: its layer's place)
    x = cand[at]
    take, label = _affected_all(owner, lo[x], hi[x], is_seed[x], size, with_label=True)
    ids, label = x[take], label[take]  # (in order of layer, then id: a label is its cluster's first place)
    o = np.argsort(label, kind="stable")
    ids, label = ids[o], label[o]
    cut = np.flatnonzero(label[1:] != label[:-1]) + 1
    parts = np.split(ids, cut)
    return [(int(layer[p[0]]), p) for p in parts if p.size]


#: pairs of loops whose boxes are compared at once (memory: ~80 bytes a pair in flight)
PAIR_BLOCK = 1 << 20


def _meeting_pairs(g, first, size, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i, j) of loops of one layer (``g``: layer place of each loop, sorted; ``first``/``size``: each
    layer's first loop and count, 0 to skip it) whose closed boxes meet, i's rows in order; made a block of about
    :data:`PAIR_BLOCK` pairs at a time, so a layer of thousands of loops never holds all its pairs at once."""
    n = g.size
    per_row = size[g]
    cum = np.cumsum(per_row)
    ii, jj = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    start = 0
    while start < n:
        done = int(cum[start - 1]) if start else 0
        stop = max(int(np.searchsorted(cum, done + PAIR_BLOCK, side="right")), start + 1)
        rows = np.arange(start, min(stop, n))
        _, pj = expand_ranges(first[g[rows]], per_row[rows])
        pi = np.repeat(rows, per_row[rows])
        meet = np.all((lo[pi] <= hi[pj]) & (lo[pj] <= hi[pi]), axis=1)
        ii.append(pi[meet])
        jj.append(pj[meet])
        start = int(rows[-1]) + 1
    return np.concatenate(ii), np.concatenate(jj)


def _affected_all(g, lo, hi, seed, size, with_label=False):
    """Which loops (``g``: layer place of each, sorted; ``size``: loops per layer; boxes ``lo``, ``hi``) can share
    a face of their layer's arrangement with the ``seed`` loops (those that cross): per layer, the groups of loops
    joined by overlapping boxes that hold a seed, grown by every loop whose box meets a group's hull box until none
    does (all layers at once). A loop left out has a box apart from each group's hull, so no face of the group's
    arrangement (inside that hull) lies inside it or around it: its classification and the group's region do not
    depend on each other. Layers of more than 4000 loops, or without a seed: all their loops. Returns the (n,) mask
    of the loops taken; ``with_label``: and each one's cluster, the smallest place among its loops (the loops of a
    layer taken whole: one cluster, its layer's first place), so that two clusters' loops' boxes never meet and the
    labels ascend with the layers."""
    n = g.size
    first = np.cumsum(size) - size
    whole = (size > 4000) | (np.bincount(g, weights=seed, minlength=size.size) == 0)  # all loops, untested
    all_in = whole[g]
    size = np.where(whole, 0, size)
    ii, jj = _meeting_pairs(g, first, size, lo, hi)
    while True:
        label = connected_labels(n, ii, jj)
        groups = unique_ints(label[seed])
        member = isin_ints(label, groups)
        g_lo = np.full((n, 2), np.inf)  # hull box of each group (by its label)
        g_hi = np.full((n, 2), -np.inf)
        np.minimum.at(g_lo, label[member], lo[member])
        np.maximum.at(g_hi, label[member], hi[member])
        gi, gx = expand_ranges(np.zeros(groups.size, dtype=np.int64), size[g[groups]])
        gx += first[g[groups]][gi]
        gi = groups[gi]  # every (group, loop of its layer) pair
        touch = np.all((g_lo[gi] <= hi[gx]) & (lo[gx] <= g_hi[gi]), axis=1) & (label[gx] != gi)
        touch &= ~all_in[gx]
        if not touch.any():
            if with_label:
                return member | all_in, np.where(all_in, first[g], label)
            return member | all_in
        t, k = gx[touch], gi[touch]  # joined to the group's smallest index
        ii, jj = np.concatenate([ii, t, k]), np.concatenate([jj, k, t])


def _ring_points(points: np.ndarray, offsets: np.ndarray, ids: np.ndarray, pc: np.ndarray | None = None,
                 always_close: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(P,) complex128 points x + iy (of the float32 points) of loops ``ids``, each followed by its first point
    again (when it is not already its last one, or ``always_close``), and the rings' offsets (R + 1,). ``pc``:
    all the points as complex128, when at hand. Ascending ``ids`` (the usual case) are gathered by a mask over the
    points, without an index per point."""
    counts = np.diff(offsets)[ids]
    if pc is None:
        pc = np.ascontiguousarray(points, dtype=np.float32).view(np.complex64).reshape(-1)
    first = pc[offsets[:-1][ids]]
    shut = np.ones(ids.size, dtype=bool) if always_close else first != pc[offsets[1:][ids] - 1]
    ring_off = np.zeros(ids.size + 1, dtype=np.int64)
    np.cumsum(counts + shut, out=ring_off[1:])
    if ids.size and np.all(ids[1:] > ids[:-1]):
        take = np.zeros(offsets.size - 1, dtype=bool)
        take[ids] = True
        inner = np.asarray(pc[np.repeat(take, np.diff(offsets))], dtype=np.complex128)
        return np.insert(inner, np.cumsum(counts)[shut], first[shut]), ring_off
    owner, sel = expand_ranges(offsets[:-1][ids], counts)
    ring = np.empty(int(ring_off[-1]), dtype=np.complex128)
    ring[sel - offsets[:-1][ids][owner] + ring_off[:-1][owner]] = pc[sel]
    ring[(ring_off[1:] - 1)[shut]] = first[shut]
    return ring, ring_off


def move_chains(src_start: np.ndarray, offsets: np.ndarray, arrays: tuple) -> list[np.ndarray]:
    """``arrays`` with the chain that starts at ``src_start[c]`` moved to ``offsets[c]`` (chains in their new order).
    Chains that follow each other in both orders move as one run: the walk leaves most in place, so the runs are
    few and are copied as slices (a per-point index only when they are many)."""
    n = int(offsets[-1])
    brk = np.ones(src_start.size, dtype=bool)
    brk[1:] = src_start[1:] != src_start[:-1] + np.diff(offsets[:-1])
    runs = np.flatnonzero(brk)
    dst = offsets[:-1][runs]
    length = np.diff(np.append(dst, n))
    if runs.size > 4096:  # many runs: one gather by a per-point index instead of a slice copy each
        src = np.arange(n, dtype=np.int64) + np.repeat(src_start[runs] - dst, length)
        return [x[src] for x in arrays]
    out = [np.empty((n, *x.shape[1:]), dtype=x.dtype) for x in arrays]
    for s, d, m in zip(src_start[runs].tolist(), dst.tolist(), length.tolist(), strict=True):
        for x, y in zip(arrays, out, strict=True):
            y[d : d + m] = x[s : s + m]
    return out


def _polygons(points: np.ndarray, offsets: np.ndarray, ids: np.ndarray, pc: np.ndarray | None = None) -> np.ndarray:
    """Shapely polygons (no holes) of loops ``ids``, each ring closed by repeating its first point (float64 of the
    float32 points; the same geometry as ``shapely.polygons(shapely.linearrings(...))``, made about 3x faster; in
    halves on two threads when large, :func:`in_halves`). ``pc``: all the points as complex128, when at hand."""
    import shapely

    def make(ids: np.ndarray) -> np.ndarray:
        ring, ring_off = _ring_points(points, offsets, ids, pc)
        coords = ring.view(np.float64).reshape(-1, 2)
        return shapely.from_ragged_array(shapely.GeometryType.POLYGON, coords, (ring_off, np.arange(ids.size + 1)))

    return in_halves(make, np.diff(offsets)[ids], ids)


def filled(w: np.ndarray, fill_rule: str) -> np.ndarray:
    """Where the fill rule fills, given ``w``: the winding number (``nonzero``, ``positive``) or any count of the
    same parity as the loops around the point (``evenodd``)."""
    if fill_rule == "nonzero":
        return w != 0
    if fill_rule == "positive":
        return w > 0
    return w % 2 != 0


def cycle_labels(nxt: np.ndarray) -> np.ndarray:
    """The smallest member of each element's cycle of the permutation ``nxt`` (pointer jumping)."""
    lab = np.arange(nxt.size)
    p = nxt.copy()
    for _ in range(max(1, int(nxt.size).bit_length())):
        lab = np.minimum(lab, lab[p])
        p = p[p]
    return lab
