"""Adaptive layer schedules: the paper's region-of-interest ladder (``roi``) and error-bounded heights (``cusp``,
``area``).

Every schedule returned here is a :class:`~gpuslice.schedule.Schedule` (built with :func:`~gpuslice.schedule.from_z`)
whose layers tile ``[0, height]`` of the mesh contiguously, from the bed up: layer i spans ``[e_i, e_{i+1}]`` with
``e_0 = 0`` and the last edge exactly at the mesh's top (so the last layer may be thinner than the rest; a sliver
under :data:`SLIVER_MM` joins the layer below). Each layer is cut at the middle of its slab, ``z_i = (e_i +
e_{i+1}) / 2`` (the project's convention, as Slic3r and CuraEngine). The schedule also carries ``info`` (a
JSON-able dict: the mode, its parameters, and for ``roi`` the windows chosen at each level) and is accepted by
:func:`~gpuslice.slicer.slice_mesh` as ``schedule=``.

``cusp`` (Dolenc & Mäkelä): the cusp height of a facet with unit normal n in a layer of thickness t is t·|n_z|; each
layer is as thick as allowed by ``t·|n_z| <= C`` over every non-horizontal facet that overlaps its slab, clamped to
``[min_height, max_height]``. ``area``: the staircase's error area per unit length of a surface at angle α to the bed
is t² / (2·tan α), so ``t <= sqrt(2·A_max·tan α)`` with ``cos α = |n_z|``. Horizontal facets (zmax = zmin) make no
staircase and never limit a layer. Like PrusaSlicer's SlicingAdaptive, facets that *start inside* a proposed layer
count too: a steep facet starting in the upper part of a thick candidate pushes the layer's top down to where it is
allowed. Layers are found greedily from the bed up on a fine grid of bins (width ``min_height / 10`` by default):
the device computes, per facet, its z range and |n_z| (``kernels/adaptive.cl``: ``adaptive_facets``) and, per
bin, the largest |n_z| of the facets touching it (``adaptive_slab_blocks``: two atomic max per facet into a sparse
table of power-of-two blocks, then ``adaptive_push_down`` level by level); a layer made of bins s .. s+n-1 is allowed
when ``n·δ <= limit(max |n_z| over those bins)``. Layer edges lie on the bin grid, so the bound is exact (it is
conservative by facets that only touch a slab's edge), and thicknesses are multiples of the bin width δ. Only when
``min_height`` is above what a facet allows can the bound be exceeded (``info["bound_violations"]`` counts such
layers). ``smooth = g`` limits how fast the thickness may change, by at most g mm per mm of height (a Lipschitz
envelope, taken below the allowed thickness, so the bound still holds).

``roi`` (the paper's method, generalised): slice the whole object at the first thickness of the ladder
(default 1, 0.5, 0.1 mm), take the signal of points per layer, find the window(s) of consecutive layers whose points
are at or above a threshold (default: the 0.75 quantile of that level's signal; or an absolute number of points,
one per level), re-slice each window at the next thickness and repeat inside it. The levels merge into one
schedule: each layer keeps the thickness of the deepest level that covers it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..device import KernelDriver, locked
from ..errors import ParameterError
from ..mesh.mesh import Mesh, need_mesh
from .uniform import Schedule, from_z
from .validate import check_error_bounded, check_roi

__all__ = [
    "AdaptiveSchedule",
    "AdaptiveKernel",
    "ADAPTIVE_MODES",
    "facet_slopes",
    "facet_slopes_numpy",
    "slab_max_nz",
    "slab_max_nz_numpy",
    "slope_limit",
    "cusp_schedule",
    "roi_schedule",
    "adaptive_schedule",
    "schedule_from_edges",
]

ADAPTIVE_MODES = ("roi", "cusp", "area")
#: the most bins of the error-bounded schedules: their width is at least the model's height / MAX_BINS
MAX_BINS = 400_000

#: a last layer thinner than this and than the step asked for joins the layer below, mm: no Z axis steps finer
SLIVER_MM = 0.001
#: relative safety on |n_z| so float32 rounding never lets t·|n_z| exceed the bound in float64
_NZ_SAFETY = 1.0 + 1e-6


@dataclass(frozen=True)
class AdaptiveSchedule(Schedule):
    """A :class:`Schedule` with ``info``: the adaptive mode, its parameters and (roi) the windows per level."""

    info: dict = field(default_factory=dict, compare=False)


def schedule_from_edges(edges: np.ndarray, mode: str = "custom", info: dict | None = None) -> AdaptiveSchedule:
    """The schedule of slabs ``[edges[i], edges[i+1]]`` (mm, strictly increasing), each cut at its middle."""
    e = np.asarray(edges, dtype=np.float64)
    base = from_z((e[1:] + e[:-1]) / 2, np.diff(e))
    return AdaptiveSchedule(base.z, base.thickness, mode=mode, info=dict(info or {}))


# ---- kernels and their numpy twins ----------------------------------------------------------------------------


def facet_slopes_numpy(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The numpy twin of ``adaptive_facets``: per facet (zmin, zmax, |n_z|), float32, bit-identical to the kernel."""
    t = mesh.vertices[mesh.faces]  # (F, 3, 3) float32
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    u, v = b - a, c - a
    nx = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    ny = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    nz = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    length = np.sqrt((nx * nx + ny * ny) + nz * nz)
    with np.errstate(divide="ignore", invalid="ignore"):
        anz = np.where(length > 0, np.abs(nz) / length, np.float32(0)).astype(np.float32)
    z = t[:, :, 2]
    return z.min(axis=1), z.max(axis=1), anz


def _slab_ranges(zmin: np.ndarray, zmax: np.ndarray, edges32: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[first, last) slabs each facet touches (the kernel's binary searches, in float32)."""
    n = edges32.size - 1
    first = np.searchsorted(edges32[1:], zmin, side="left")
    last = np.searchsorted(edges32[:n], zmax, side="right")
    return first, last


def _range_max(n: int, lo: np.ndarray, hi: np.ndarray, val: np.ndarray) -> np.ndarray:
    """out[i] = max(val[k] for ranges [lo[k], hi[k]) containing i), 0 elsewhere; vectorised (sparse table pushed
    down: each range is covered by two power-of-two blocks)."""
    out = np.zeros(n, dtype=val.dtype)
    keep = hi > lo
    lo, hi, val = lo[keep], hi[keep], val[keep]
    if n == 0 or lo.size == 0:
        return out
    length = hi - lo
    k = np.floor(np.log2(length)).astype(np.int64)
    k = np.where((1 << (k + 1)) <= length, k + 1, k)  # guard log2 rounding
    k = np.where((1 << k) > length, k - 1, k)
    levels = int(k.max()) + 1
    table = np.zeros((levels, n), dtype=val.dtype)
    np.maximum.at(table, (k, lo), val)
    np.maximum.at(table, (k, hi - (1 << k)), val)
    for j in range(levels - 1, 0, -1):
        half = 1 << (j - 1)
        np.maximum(table[j - 1], table[j], out=table[j - 1])
        np.maximum(table[j - 1][half:], table[j][: n - half], out=table[j - 1][half:])
    return table[0]


def slab_max_nz_numpy(zmin: np.ndarray, zmax: np.ndarray, nz: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The numpy twin of ``adaptive_slab_blocks`` + ``adaptive_push_down``: (L,) float32, per slab
    ``[edges[l], edges[l+1]]`` the largest |n_z| of the non-horizontal facets touching or overlapping it (0 if
    none)."""
    e32 = np.ascontiguousarray(edges, dtype=np.float32)
    n = max(e32.size - 1, 0)
    slanted = zmax > zmin
    first, last = _slab_ranges(zmin[slanted], zmax[slanted], e32)
    return _range_max(n, first.astype(np.int64), last.astype(np.int64), nz[slanted].astype(np.float32))


def _search_guide(edges32: np.ndarray) -> tuple[int, np.float32, np.float32, np.ndarray]:
    """The guesses ``adaptive_slab_blocks`` starts its searches of ``edges32`` from (``kernels/adaptive.cl``):
    ``(n_guide, e0, inv_w, guide)``, guide[b] (int32, n_guide + 1 of them) the first edge at or above e0 + b / inv_w.
    Any guess gives the same answer; a good one saves the steps: two buckets a slab."""
    n_guide = 2 * max(edges32.size - 1, 1)
    e0, span = float(edges32[0]), float(edges32[-1]) - float(edges32[0])
    inv_w = np.float32(n_guide / span) if span > 0 else np.float32(0.0)
    if not np.isfinite(inv_w):
        inv_w = np.float32(0.0)  # (edges closer than float32 resolves: every guess from bucket 0)
    starts = e0 + np.arange(n_guide + 1) * (span / n_guide)
    guide = np.searchsorted(edges32, starts.astype(np.float32), side="left").astype(np.int32)
    return n_guide, np.float32(e0), inv_w, guide


class AdaptiveKernel(KernelDriver):
    """Driver of ``kernels/adaptive.cl``: per-facet slopes and per-slab max |n_z| on one device."""

    def __init__(self, device) -> None:
        super().__init__(device)
        prg = device.program("adaptive.cl")
        self._facets = prg.adaptive_facets
        self._blocks = prg.adaptive_slab_blocks
        self._push = prg.adaptive_push_down

    @locked
    def facets(self, mesh: Mesh, *, read_back: bool = True):
        """Per facet (zmin, zmax, |n_z|) float32; left on the device (buffers ``zmin``, ``zmax``, ``nz``) too."""
        q = self.device.queue
        n_f = mesh.n_faces
        d_v = self._put("verts", mesh.vertices)
        d_f = self._put("faces", mesh.faces)
        d_lo, d_hi, d_nz = (self._buffer(k, 4 * max(n_f, 1)) for k in ("zmin", "zmax", "nz"))
        if n_f:
            self._facets(q, *self._grid(n_f), d_v, d_f, np.int32(n_f), d_lo, d_hi, d_nz)
        if not read_back:
            return None
        out = tuple(np.empty(n_f, np.float32) for _ in range(3))
        if n_f:
            self._read(*zip(out, (d_lo, d_hi, d_nz), strict=True))
        return out

    @locked
    def slab_max(self, mesh: Mesh, edges: np.ndarray) -> np.ndarray:
        """(L,) float32 max |n_z| per slab of ``edges`` (L + 1 values, mm) over the facets touching it."""
        import pyopencl as cl

        q = self.device.queue
        self.facets(mesh, read_back=False)  # (each call: a mesh's arrays may have changed since, even in place)
        e32 = np.ascontiguousarray(edges, dtype=np.float32)
        n_l = max(e32.size - 1, 0)
        out = np.zeros(n_l, np.uint32)
        if n_l == 0 or mesh.n_faces == 0:
            return out.view(np.float32)
        levels = int(n_l).bit_length()  # a run of at most n_l slabs: level floor(log2(n_l)) at most
        d_e = self._put("edges", e32)
        n_guide, e0, inv_w, guide = _search_guide(e32)
        d_g = self._put("guide", guide)
        d_t = self._fill("table", 4 * n_l * levels, np.uint32(0))
        self._blocks(q, *self._grid(mesh.n_faces), self.buffer("zmin"), self.buffer("zmax"), self.buffer("nz"),
                     np.int32(mesh.n_faces), d_e, np.int32(n_l), d_g, np.int32(n_guide), e0, inv_w, d_t)
        for level in range(levels - 1, 0, -1):
            self._push(q, *self._grid(n_l), d_t, np.int32(n_l), np.int32(level))
        cl.enqueue_copy(q, out, d_t)  # row 0: the first n_l values
        return out.view(np.float32)


def facet_slopes(mesh: Mesh, device=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per facet (zmin, zmax, |n_z|), float32 (mm, mm, unit-normal z); on ``device`` when given."""
    if device is None:
        return facet_slopes_numpy(mesh)
    return AdaptiveKernel.of(device).facets(mesh)


def slab_max_nz(mesh: Mesh, edges: np.ndarray, device=None) -> np.ndarray:
    """(L,) float32: per slab ``[edges[l], edges[l+1]]`` (mm) the largest |n_z| of the non-horizontal facets that
    touch or overlap it; on ``device`` when given, else numpy."""
    if device is None:
        return slab_max_nz_numpy(*facet_slopes_numpy(mesh), edges)
    return AdaptiveKernel.of(device).slab_max(mesh, edges)


# ---- error-bounded schedules ----------------------------------------------------------------------------------


def slope_limit(nz: np.ndarray, mode: str, max_cusp: float = 0.05, max_area: float = 0.0025) -> np.ndarray:
    """The largest layer thickness (mm, float64; inf where unlimited) that facets with these |n_z| allow.

    ``cusp``: t = C / |n_z| (cusp height t·|n_z| <= C). ``area``: t = sqrt(2·A_max·tan α), cos α = |n_z|.
    """
    a = np.clip(np.asarray(nz, dtype=np.float64) * _NZ_SAFETY, 0.0, 1.0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # (max_cusp 1e308 over a small |n_z|: inf)
        if mode == "cusp":
            return np.where(a > 0, max_cusp / a, np.inf)
        if mode == "area":
            tan = np.where(a > 0, np.sqrt(np.maximum(1.0 - a * a, 0.0)) / a, np.inf)
            return np.sqrt(2.0 * max_area * tan)
    raise ParameterError(f"unknown adaptive mode '{mode}' (use {', '.join(ADAPTIVE_MODES)})")


def cusp_schedule(
    mesh: Mesh,
    *,
    mode: str = "cusp",
    max_cusp: float = 0.05,
    max_area: float = 0.0025,
    min_height: float = 0.05,
    max_height: float = 0.3,
    smooth: float = 0.0,
    resolution: float | None = None,
    device=None,
) -> AdaptiveSchedule:
    """An error-bounded adaptive schedule for ``mesh`` (see the module docstring).

    Parameters
    ----------
    mode : ``"cusp"`` (``t·|n_z| <= max_cusp``, mm) or ``"area"`` (staircase error area per unit length
        ``<= max_area``, mm²).
    min_height, max_height : clamp of every layer's thickness, mm (A and B).
    smooth : if > 0, the thickness changes by at most this many mm per mm of height.
    resolution : the bin width δ, mm (default ``min_height / 10``; at least height / :data:`MAX_BINS`, given or
        not); thicknesses are multiples of δ except the last layer, which ends at the top.
    device : an OpenCL :class:`~gpuslice.device.Device` for the per-facet work, or None for numpy.
    """
    need_mesh(mesh, "cusp_schedule")
    check_error_bounded(mode, max_cusp, max_area, min_height, max_height, smooth, resolution)
    if device is not None:  # (a Device, or a spec such as "0:0")
        from ..device import get_device

        device = get_device(device)
    height = mesh.height
    info = {"mode": mode, "max_cusp_mm": max_cusp if mode == "cusp" else None,
            "max_area_mm2": max_area if mode == "area" else None, "min_height_mm": min_height,
            "max_height_mm": max_height, "smooth": smooth}
    if height <= 0:
        return schedule_from_edges(np.zeros(0) if height == 0 else np.zeros(0), f"adaptive-{mode}", info)
    delta = float(resolution) if resolution else max(min_height / 10, height / MAX_BINS)
    if resolution is None and delta > min_height:  # the bins are at least height / 400000 wide
        raise ParameterError(f"min_height must be at least {delta:g} mm for a {height:g} mm tall model (its height "
                             f"/ 400000), got {min_height:g}", param="min_height")
    if not (delta > 0 and delta <= min_height):
        raise ParameterError(f"adaptive resolution must be in (0, min_height], got {resolution}", param="min_height")
    if height / delta > MAX_BINS + 1e-6:  # (the bins' arrays: 1e-7 mm bins of a 40 mm model would take 36 GiB)
        raise ParameterError(f"resolution must be at least {height / MAX_BINS:g} mm for a {height:g} mm tall model "
                             f"(its height / {MAX_BINS}), got {delta:g}", param="resolution")
    n_bins = max(1, int(np.ceil(height / delta - 1e-9)))  # (a model thinner than a bin is one: min_height 1e30)
    n_min = max(1, int(min(np.ceil(min_height / delta - 1e-9), n_bins)))  # (never under min_height, never above
    # the model; min in floats first: a height of 1e308 mm over 1e-3 mm bins is inf, which no int holds)
    # (no layer is taller than the model: a max_height of 1e6 mm does not make a million-bin loop below)
    n_max = max(n_min, int(min(np.floor(max_height / delta + 1e-9), n_bins)))
    edges = np.arange(n_bins + 1, dtype=np.float64) * delta
    edges[-1] = max(min(edges[-1], 2 * height), height)  # (one bin wider than the model: its top, not 1e308)
    bin_nz = slab_max_nz(mesh, edges, device)
    limit = np.concatenate((slope_limit(bin_nz, mode, max_cusp, max_area), np.full(n_max, np.inf)))
    # allowed[s]: the most bins n (<= n_max) a layer starting at bin s may hold: n·δ <= min(limit[s .. s+n-1])
    run_min = np.full(n_bins, np.inf)
    allowed = np.zeros(n_bins, dtype=np.int64)
    ok = np.ones(n_bins, dtype=bool)
    for n in range(1, n_max + 1):
        np.minimum(run_min, limit[n - 1 : n - 1 + n_bins], out=run_min)
        ok &= n * delta <= run_min
        if not ok.any():  # no layer can hold n bins anywhere: nor more
            break
        allowed += ok
    if smooth > 0:
        # a rate of n_max or more bounds nothing (one bin's step lets a layer change by its largest size): taken as
        # n_max, so that t - rate·k keeps t's digits (a rate of 1e12 lost them: 714 layers where 702 was right,
        # and 1e308 overflowed)
        rate = min(float(smooth), float(n_max))
        t = allowed * delta
        k = np.arange(n_bins) * delta
        fwd = np.minimum.accumulate(t - rate * k) + rate * k
        bwd = (np.minimum.accumulate((t + rate * k)[::-1]))[::-1] - rate * k
        allowed = np.floor(np.minimum(fwd, bwd) / delta + 1e-9).astype(np.int64)
    violated = allowed < n_min
    allowed = np.maximum(allowed, n_min)
    starts = [0]
    s = 0
    take = allowed.tolist()
    while s < n_bins:  # one step per layer (sequential by nature); the per-bin work above is vectorised
        s += take[s]
        starts.append(min(s, n_bins))
    bins = np.asarray(starts, dtype=np.int64)
    layer_edges = bins * delta
    layer_edges[-1] = height
    joined = _join_sliver(layer_edges, min_height)
    if joined.size < layer_edges.size:  # the last layer took the sliver above it: beyond its bound when it had none
        bins = np.delete(bins, -2)
        violated[bins[-2]] |= n_bins - bins[-2] > allowed[bins[-2]]
    layer_edges = joined
    info["resolution_mm"] = delta
    info["bound_violations"] = int(violated[bins[:-1][bins[:-1] < n_bins]].sum())
    return schedule_from_edges(layer_edges, f"adaptive-{mode}", info)


# ---- the paper's region-of-interest ladder --------------------------------------------------------------------


def _join_sliver(edges: np.ndarray, step: float) -> np.ndarray:
    """``edges`` with a last slab thinner than both :data:`SLIVER_MM` and ``step`` (mm) joined to the one below."""
    if edges.size > 2 and edges[-1] - edges[-2] < min(SLIVER_MM, step):
        return np.delete(edges, -2)
    return edges


def _tile(a: float, b: float, t: float) -> np.ndarray:
    """Edges of slabs of thickness t tiling [a, b] from a; a remainder r under t/2 is shared with the slab below it
    (two slabs of (t + r)/2), so that no slab is thinner than t/2 unless [a, b] is (a window of a ladder whose steps
    do not divide each other ended in a 0.0015 mm layer inside the part)."""
    n = max(1, int(np.ceil((b - a) / t - 1e-9)))
    e = a + np.arange(n + 1, dtype=np.float64) * t
    e[-1] = b
    if n >= 2 and b - e[-2] < 0.5 * t:
        e[-2] = 0.5 * (e[-3] + b)
    return e


def _windows(signal: np.ndarray, threshold: float, min_layers: int, max_windows: int) -> list[tuple[int, int]]:
    """Runs [i0, i1] (inclusive) of consecutive layers with signal >= threshold, at least ``min_layers`` long; the
    ``max_windows`` with the most points, in order of height."""
    above = np.concatenate(([False], signal >= threshold, [False]))
    d = np.diff(above.astype(np.int8))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1
    runs = [(int(a), int(b)) for a, b in zip(starts, stops, strict=True) if b - a + 1 >= min_layers]
    runs.sort(key=lambda r: -int(signal[r[0] : r[1] + 1].sum()))
    return sorted(runs[:max_windows]) if max_windows > 0 else sorted(runs)


def roi_schedule(
    mesh: Mesh,
    ladder: tuple[float, ...] = (1.0, 0.5, 0.1),
    *,
    threshold: float | tuple[float, ...] | None = None,
    quantile: float = 0.75,
    min_layers: int = 2,
    max_windows: int = 1,
    slicer: Callable[[Schedule], Any],
) -> AdaptiveSchedule:
    """The paper's adaptive method, generalised: slice at ``ladder[0]`` mm, pick windows of layers whose points per
    layer are >= the threshold, re-slice them at ``ladder[1]``, and so on; merged into one schedule.

    Parameters
    ----------
    ladder : layer thicknesses, mm, coarse to fine (each level refines the windows of the one before).
    threshold : points per layer, absolute: one number for every level or one per refinement step
        (``len(ladder) - 1`` values, as the paper's 1000 points at 1 mm). None: use ``quantile``.
    quantile : the threshold as this quantile (0..1) of the points-per-layer signal of the level being
        refined (default 0.75: the busiest quarter of the layers).
    min_layers : shorter runs above the threshold are ignored.
    max_windows : windows kept per refined region, those with the most points (the paper: 1); 0 keeps all.
    slicer : slices ``mesh`` at a schedule and returns the result (its ``points_per_layer`` and ``z``): the slicing
        stage passes itself here (:func:`gpuslice.slicing.slicer.roi_schedule` binds it), so this stage never
        imports the slicer.

    ``info["levels"]`` lists, per level, its thickness, the region(s) sliced, their points per layer and z, the
    threshold and the windows chosen (layer indices within the region and z ranges in mm).
    """
    need_mesh(mesh, "roi_schedule")
    if not callable(slicer):
        raise ParameterError("roi_schedule needs slicer= (gpuslice.roi_schedule and slice_mesh(..., adaptive='roi') "
                             "pass the slicer themselves)", param="slicer")
    ladder, thr = check_roi(ladder, threshold, quantile, min_layers, max_windows)
    height = mesh.height
    if height / ladder[-1] > 5e7:  # as uniform schedules: the finest level may cover the whole height
        raise ParameterError(f"roi_ladder's finest step: {height:g} mm at {ladder[-1]:g} mm would make more than 5e7 "
                             "layers", param="roi_ladder")
    info: dict = {"mode": "roi", "ladder_mm": list(ladder), "quantile": None if thr else quantile,
                  "threshold_points": list(thr) if thr else None, "min_layers": min_layers,
                  "max_windows": max_windows, "levels": []}
    if height <= 0:
        return schedule_from_edges(np.zeros(0), "adaptive-roi", info)

    def refine(a: float, b: float, level: int) -> np.ndarray:
        t = ladder[level]
        e = _tile(a, b, t)
        if level == len(ladder) - 1:
            return e
        res = slicer(schedule_from_edges(e))
        sig = res.points_per_layer
        cut = float(thr[level]) if thr else float(np.quantile(sig, quantile)) if sig.size else 0.0
        wins = _windows(sig, max(cut, 1.0), min_layers, max_windows)
        info["levels"].append({
            "level": level, "thickness_mm": t, "region_mm": [a, b], "layers": int(sig.size),
            "threshold_points": cut, "points": sig.tolist(), "z": res.z.tolist(),
            "windows": [{"layers": [i0, i1], "z_mm": [float(e[i0]), float(e[i1 + 1])],
                         "points": [int(sig[i0]), int(sig[i1])]} for i0, i1 in wins],
        })
        parts, prev = [], 0
        for i0, i1 in wins:
            parts.append(e[prev:i0])
            parts.append(refine(float(e[i0]), float(e[i1 + 1]), level + 1)[:-1])
            prev = i1 + 1
        parts.append(e[prev:])
        return np.concatenate(parts)

    edges = refine(0.0, float(height), 0)
    return schedule_from_edges(edges, "adaptive-roi", info)


def adaptive_schedule(mesh: Mesh, params, device=None, *, slicer: Callable[[Schedule], Any] | None = None
                      ) -> AdaptiveSchedule:
    """The schedule that ``params.adaptive`` (``"roi"``, ``"cusp"`` or ``"area"``) asks for, with ``params``'
    adaptive fields (see :class:`~gpuslice.slicing.params.SliceParams`); ``slicer``: see :func:`roi_schedule`
    (needed for roi only)."""
    if not hasattr(params, "adaptive"):  # (SliceParams imports this module: duck-typed, no import circle)
        raise ParameterError(f"params must be a SliceParams (its adaptive fields), got {type(params).__name__}")
    mode = params.adaptive
    if mode == "roi":
        if slicer is None:
            raise ParameterError("adaptive 'roi' slices the mesh as it goes: call gpuslice.roi_schedule(mesh, ...) or "
                                 "slice_mesh(mesh, adaptive='roi'), which pass the slicer", param="adaptive")
        return roi_schedule(mesh, params.roi_ladder, threshold=params.roi_threshold, quantile=params.roi_quantile,
                            max_windows=params.roi_windows, slicer=slicer)
    if mode in ("cusp", "area"):
        if device is None and params.backend == "opencl":
            from ..device import get_device

            device = get_device(params.device)
        return cusp_schedule(mesh, mode=mode, max_cusp=params.max_cusp, max_area=params.max_area,
                             min_height=params.min_height, max_height=params.max_height, smooth=params.smooth,
                             device=device)
    raise ParameterError(f"unknown adaptive mode '{mode}' (use {', '.join(ADAPTIVE_MODES)})")
