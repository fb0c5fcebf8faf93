"""The pipeline: mesh → layer schedule → crossings (kernel) → chaining → nesting → :class:`SliceResult`.

Each stage is one module (``mesh``, ``schedule``, ``crossings``, ``chain``, ``nest``); this one only wires them,
times them and fills the report. Huge models are sliced in batches of layers (``max_segments_per_batch``) so peak
memory is set by the batch, not by the model.
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import asdict, fields, replace
from typing import Any

import numpy as np

from ..errors import InvalidGeometryError, ParameterError
from ..mesh.defects import wound_for_slicing
from ..mesh.mesh import Mesh
from ..prefetch import prefetch
from ..schedule.adaptive import AdaptiveSchedule
from ..schedule.uniform import Schedule, from_z, uniform
from .chain import REPAIR_KINDS, chain_segments
from .crossings import (
    _planes32,
    batch_facets,
    batch_layers,
    check_plane_spacing,
    compute_crossings,
    facet_layer_ranges,
    vertex_layers,
)
from .nest import nest_loops
from .params import SliceParams
from .result import SliceResult

__all__ = ["SliceParams", "slice_mesh", "make_schedule", "roi_schedule"]


def make_schedule(mesh: Mesh, params: SliceParams, z=None, thickness=None) -> Schedule:
    """The schedule for ``mesh``: explicit ``z`` (with optional ``thickness``) or uniform from ``params``."""
    if z is not None:
        return from_z(z, thickness)
    if params.adaptive is not None:
        from ..schedule.adaptive import adaptive_schedule

        return adaptive_schedule(mesh, params, slicer=lambda sched: slice_mesh(mesh, params, schedule=sched))
    return uniform(mesh.height, params.thickness, first_layer=params.first_layer, z_mode=params.z_mode)


def roi_schedule(mesh: Mesh, ladder: tuple[float, ...] = (1.0, 0.5, 0.1), *, params: SliceParams | None = None,
                 **options) -> AdaptiveSchedule:
    """The paper's adaptive schedule (:func:`gpuslice.schedule.adaptive.roi_schedule`) with its level slices made
    by :func:`slice_mesh` under ``params`` (backend, device, fill rule; default :class:`SliceParams`); ``options``:
    ``threshold``, ``quantile``, ``min_layers``, ``max_windows``."""
    from ..schedule.adaptive import roi_schedule as roi

    p = params if params is not None else SliceParams()
    return roi(mesh, ladder, slicer=lambda sched: slice_mesh(mesh, p, schedule=sched), **options)


def _batches(mesh: Mesh, zs: np.ndarray, limit: int) -> tuple[list[tuple[int, int]], np.ndarray, tuple]:
    """Contiguous layer ranges whose segment counts stay under ``limit`` (one range if the whole fits), the
    segment count of every layer (the facets crossing it), and (vertex layers, facets' first layer, count)."""
    vl = vertex_layers(mesh, zs)
    lo, count = facet_layer_ranges(mesh, zs, vl)
    # a difference array: +1 at each facet's first layer, -1 after its last
    n = zs.size + 1
    per_layer = np.cumsum(np.bincount(lo, minlength=n) - np.bincount(lo + count, minlength=n))[:-1]
    if per_layer.sum() <= limit:
        return [(0, int(zs.size))], per_layer, (vl, lo, count)
    out, start, acc = [], 0, 0
    for k, c in enumerate(per_layer):
        if acc + c > limit and k > start:
            out.append((start, k))
            start, acc = k, 0
        acc += int(c)
    out.append((start, int(zs.size)))
    return out, per_layer, (vl, lo, count)


def slice_mesh(
    mesh: Mesh | Any,
    params: SliceParams | None = None,
    *,
    z: np.ndarray | None = None,
    layer_thickness: np.ndarray | float | None = None,
    schedule: Schedule | None = None,
    points_sink: Any = None,
    **overrides,
) -> SliceResult:
    """Slice ``mesh`` into closed, nested contours for every layer.

    Parameters
    ----------
    mesh : a :class:`~gpuslice.mesh.Mesh` (mm, standing on the bed), or anything :func:`~gpuslice.load_mesh`
        takes: a path, a ``trimesh.Trimesh`` or ``Scene``, ``(vertices, faces)`` arrays, the bytes of a mesh file
        or a binary file object (loaded first, in memory; a ``Trimesh`` of float32 values, one loaded from an
        STL, slices exactly as its binary STL; finer coordinates are placed before they are rounded).
    params : a :class:`SliceParams`; keyword ``overrides`` replace its fields (e.g. ``thickness=0.2``; ``device`` may
        also be a :class:`~gpuslice.device.Device`, e.g. ``get_device()``); the
        overrides ``scale``, ``fit`` (mm) and ``name`` go to :func:`~gpuslice.load_mesh` instead (any source but
        a placed ``Mesh`` without them).
    z : optional explicit cutting planes, mm above the bed, strictly increasing; ``layer_thickness`` gives their
        thicknesses (an array or one number; default: from the midpoints between planes).
    schedule : optional :class:`~gpuslice.schedule.Schedule` (not with ``z``: either gives the planes).
    points_sink : optional; takes each batch's points as soon as they are nested (``append((n, 2) float32)``),
        and gives all of them back at the end (``array()``: the result's ``points``), so that the slicer does not
        hold them: :class:`gpuslice.formats.npz.NpzStream` writes them to an ``.npz`` while the next batch is cut.

    Returns
    -------
    SliceResult
        Columnar contours; ``result.meta`` holds the report (timings per stage in s, repairs, device).

    Examples
    --------
    >>> from gpuslice import mesh_from_arrays, slice_mesh
    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0],
    ...               [0, 0, 10], [10, 0, 10], [10, 10, 10], [0, 10, 10]], float)
    >>> f = [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
    ...      [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]]
    >>> r = slice_mesh(mesh_from_arrays(v, f), thickness=2.5, backend="numpy")
    >>> r.z.tolist(), r.area.tolist()
    ([1.25, 3.75, 6.25, 8.75], [100.0, 100.0, 100.0, 100.0])
    """
    from ..device import Device

    given_device = overrides.pop("device") if isinstance(overrides.get("device"), Device) else None
    placement = {k: overrides.pop(k) for k in ("scale", "fit", "name") if k in overrides}
    if params is not None and not isinstance(params, SliceParams):
        raise ParameterError(f"params must be a SliceParams, got {type(params).__name__} (options go as keywords: "
                             "slice_mesh(mesh, thickness=0.1))")
    unknown = sorted(set(overrides) - {f.name for f in fields(SliceParams)})
    if unknown:
        raise ParameterError(f"unknown slicing option '{unknown[0]}' (use a SliceParams field, or scale, fit, name)")
    if schedule is not None and not isinstance(schedule, Schedule):
        raise ParameterError(f"schedule must be a Schedule (gpuslice.from_z, uniform, cusp_schedule), got "
                             f"{type(schedule).__name__}")
    if layer_thickness is not None and (z is None or schedule is not None):
        raise ParameterError("layer_thickness goes with explicit z planes (slice_mesh(mesh, z=..., layer_thickness="
                             "...)); uniform layers take thickness=")
    _refuse_ignored(overrides, params, z, schedule)
    params = SliceParams(**{**asdict(params or SliceParams()), **overrides})
    timings: dict[str, float] = {}
    device = None
    device_name = "numpy (reference)"
    if params.backend == "opencl":
        from ..device import get_device

        t = time.perf_counter()
        device = given_device or get_device(params.device)
        device.program("crossings.cl")
        device.program("walk.cl")
        device_name = device.name
        timings["device"] = time.perf_counter() - t
    # the device's shared drivers (crossings to chaining hand buffers on) are this thread's until the layers are
    # nested: another thread's slice waits (device.Device.exclusive)
    with device.exclusive() if device is not None else contextlib.nullcontext():
        if not isinstance(mesh, Mesh) or placement.get("scale") is not None or placement.get("fit") is not None:
            from ..mesh.mesh import load_mesh

            mesh = load_mesh(mesh, device=device, **placement)  # welded on the slicing device, when there is one
        # open edges joined to their nearby partners, holes filled, shells of mixed winding turned outward (a loop's
        # direction says which side is material): counted with the mesh's topology
        t0 = time.perf_counter()
        mesh = wound_for_slicing(mesh, params.join_edges, params.fill_holes, params.max_gap)
        timings["topology"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        sched = schedule if schedule is not None else make_schedule(mesh, params, z, layer_thickness)
        zs = _planes32(sched.z, mesh.name)
        check_plane_spacing(sched.z, zs, mesh.name)
        timings["schedule"] = time.perf_counter() - t0
        n_layers = int(zs.size)
        for key in ("crossings", "chaining", "nesting"):
            timings[key] = 0.0
        parts = []
        n_segments = 0
        t0 = time.perf_counter()  # (the facets' layer ranges, which the crossings take: counted with them)
        batches, per_layer, ranges = _batches(mesh, zs, params.max_segments_per_batch) if n_layers else ([], None, None)
        # several batches on a device: each visits only the facets that cross its planes
        facets = batch_facets(ranges, batches) if len(batches) > 1 and device is not None else None
        scratch = np.empty(ranges[0].shape, np.int32) if facets is not None else None  # (the vertices' layers)
        timings["crossings"] += time.perf_counter() - t0

        def chained():  # crossings and chaining of each batch (on the prefetch thread when there are several)
            for k, (a, b) in enumerate(batches):
                t = time.perf_counter()
                if device is not None:  # (after the first batch the mesh's arrays are on the device already)
                    if facets is None:
                        seg = compute_crossings(mesh, zs[a:b], device, read_back=False, layers=ranges)
                    else:
                        own = batch_layers(ranges, a, b, facets[k], scratch)
                        seg = compute_crossings(mesh, zs[a:b], device, read_back=False, mesh_on_device=k > 0,
                                                layers=own, facets=facets[k])
                        facets[k] = None  # (each batch's ids are used once)
                    device.queue.finish()  # so the kernels' time counts here, not in the next stage
                else:
                    seg = compute_crossings(mesh, zs[a:b])
                timings["crossings"] += time.perf_counter() - t
                count = len(seg)
                t = time.perf_counter()
                loops = chain_segments(seg, mesh, zs[a:b], b - a, max_gap=params.max_gap, device=device,
                                       layer_counts=per_layer[a:b], mesh_on_device=k > 0)
                del seg
                timings["chaining"] += time.perf_counter() - t
                yield a, b, loops, count

        # several batches: batch k + 1 is cut and chained (device kernels, GEOS and numpy, which release the GIL) while
        # batch k is nested; the stages' times then overlap and add up to more than the wall time
        gather = len(batches) > 1 or points_sink is not None
        if points_sink is not None:
            points = points_sink
        else:
            points = _PointsBuffer(2 * int(per_layer.sum()) if gather else 0)
        for a, b, loops, count in prefetch(chained(), 1 if len(batches) > 1 else 0):
            n_segments += count
            t = time.perf_counter()
            try:
                nested = nest_loops(loops, b - a, params.fill_rule)
            except InvalidGeometryError as exc:  # (rings.node_groups: loops GEOS cannot node on a grid)
                raise InvalidGeometryError(f"{mesh.name}: layers {a}-{b - 1}: {exc}") from None
            if gather and points_sink is None:  # the batch's points join the others' now, and its own array goes
                points.append(nested.points)
                nested = replace(nested, points=_GATHERED)
            timings["nesting"] += time.perf_counter() - t
            if points_sink is not None:  # (the sink's own time: written while the next batch is cut and chained)
                points_sink.append(nested.points)
                nested = replace(nested, points=_GATHERED)
            parts.append((a, nested, loops.repairs))
            del loops, nested
        result = _assemble(parts, sched, n_layers, points.array() if gather else None)
    result.segment_exact = _segment_exact(parts, result, n_layers)
    if getattr(sched, "info", None):
        result.meta["adaptive"] = sched.info
    result.meta.update(
        {
            "file": mesh.name,
            "facets": mesh.n_faces,
            "layers": n_layers,
            "segments": n_segments,
            "loops": result.n_loops,
            "points": int(result.points.shape[0]),
            "open_chains": int((~result.loop_closed).sum()),
            # (open mesh edges joined and holes filled before slicing: mesh counts, listed only where there were some)
            "repairs": {k: int(v.sum()) for k, v in result.repairs.items()} | {
                k: mesh._cache[k] for k in ("joined_edges", "filled_holes") if mesh._cache.get(k)},
            "device": device_name,
            "backend": params.backend,
            "batches": len(batches),
            "params": asdict(params),
            "schedule_mode": sched.mode,
            "scale": mesh.scale,
            "dropped_degenerate_facets": mesh.dropped_degenerate,
            "timings_s": timings,
        }
    )
    return result


def _refuse_ignored(overrides: dict, params: SliceParams | None, z, schedule) -> None:
    """A one-line :class:`ParameterError` for a keyword that the layers asked for would ignore, as the command line
    refuses its flag: a schedule option (or ``z`` itself) with explicit ``z`` or ``schedule`` (the planes are
    given), ``thickness`` with an adaptive mode, ``max_cusp`` without ``adaptive="cusp"``
    (:attr:`SliceParams.FOR_MODES`)."""
    shaping = set(SliceParams.FOR_MODES) | {"adaptive", "first_layer", "z_mode"}
    if z is not None and schedule is not None:
        raise ParameterError("z= gives planes of its own, which schedule= gives already: leave one out", param="z")
    if z is not None or schedule is not None:
        given = sorted(k for k in overrides if k in shaping)
        if given:
            planes = "schedule=" if schedule is not None else "z="
            raise ParameterError(f"{given[0]} shapes the layers, which {planes} gives already: leave it out",
                                 param=given[0])
        return
    mode = overrides.get("adaptive", params.adaptive if params is not None else None)
    for name, modes in SliceParams(adaptive=mode).not_for_mode(sorted(overrides)):
        kind = "uniform" if modes == (None,) else f"adaptive {' or '.join(map(repr, modes))}"
        raise ParameterError(f"{name} shapes {kind} layers" + (f", not adaptive {mode!r} ones" if mode else
                                                             f"; add adaptive={modes[0]!r}"), param=name)


def _segment_exact(parts, result: SliceResult, n_layers: int) -> np.ndarray:
    """(L,) bool: layers whose polygons are exactly their segments' edges: no repair of any kind counted and no
    loop turned round by nesting (``Nested.reoriented``)."""
    exact = np.ones(n_layers, bool)
    for counts in result.repairs.values():
        exact &= np.asarray(counts) == 0
    for a, nd, _ in parts:
        exact[a : a + nd.reoriented.size] &= nd.reoriented == 0
    return exact


#: a batch's points once :class:`_PointsBuffer` holds them (its ``loop_offsets`` still count them)
_GATHERED = np.zeros((0, 2), np.float32)


class _PointsBuffer:
    """Several batches' points gathered into one (P, 2) float32 array as the batches are nested, so that a batch's
    own points can go at once and the result's points are not a second copy of them all at the end (peak memory:
    the model's points once, not twice). Sized for ``hint`` points (twice the segments: a closed loop has as many
    points as segments, an open chain one more, rebuilt overlaps and soups more again, and pages never written cost
    nothing), grown by half beyond that, and cut to what was used at the end (``realloc``: no copy)."""

    def __init__(self, hint: int) -> None:
        self.buf = np.empty((max(int(hint), 0), 2), np.float32)  # (pages are only touched as they are written)
        self.used = 0

    def append(self, pts: np.ndarray) -> None:
        k = pts.shape[0]
        if self.used + k > self.buf.shape[0]:
            grown = np.empty((max(self.used + k, self.buf.shape[0] * 3 // 2), 2), np.float32)
            grown[: self.used] = self.buf[: self.used]
            self.buf = grown
        self.buf[self.used : self.used + k] = pts
        self.used += k

    def array(self) -> np.ndarray:
        # (no view of the buffer was handed out: append copies in)
        self.buf.resize((self.used, 2), refcheck=False)
        return self.buf


def _assemble(parts, sched: Schedule, n_layers: int, points: np.ndarray | None = None) -> SliceResult:
    """The result from the batches' nested layers ``parts`` ((first layer, Nested, repairs)); ``points``: all their
    points, when :class:`_PointsBuffer` gathered them (each part's ``points`` is then :data:`_GATHERED`)."""
    if not parts:
        return SliceResult(
            points=points if points is not None else np.zeros((0, 2), np.float32), loop_offsets=np.zeros(1, np.int64),
            layer_offsets=np.zeros(n_layers + 1, np.int64), loop_layer=np.zeros(0, np.int32),
            loop_is_hole=np.zeros(0, bool), loop_parent=np.zeros(0, np.int32), loop_closed=np.zeros(0, bool),
            z=sched.z, thickness=sched.thickness, area=np.zeros(n_layers),
            repairs={k: np.zeros(n_layers, np.int32) for k in (*REPAIR_KINDS, "unfilled_loops", "overlaps_resolved")},
        )
    if len(parts) == 1 and points is None:
        _, nd, rep = parts[0]
        repairs = dict(rep)
        repairs["unfilled_loops"] = nd.unfilled_loops
        repairs["overlaps_resolved"] = nd.overlaps_resolved
        return SliceResult(
            nd.points, nd.loop_offsets, nd.layer_offsets, nd.loop_layer, nd.loop_is_hole, nd.loop_parent,
            nd.loop_closed, sched.z, sched.thickness, nd.area, repairs,
        )
    pts, loff, lay, hole, par, closed, area = [], [np.zeros(1, np.int64)], [], [], [], [], []
    repairs: dict[str, list] = {}
    p_base = r_base = 0
    for a, nd, rep in parts:
        if points is None:
            pts.append(nd.points)
        loff.append(nd.loop_offsets[1:] + p_base)
        lay.append(nd.loop_layer + a)
        hole.append(nd.loop_is_hole)
        par.append(np.where(nd.loop_parent >= 0, nd.loop_parent + r_base, -1))
        closed.append(nd.loop_closed)
        area.append(nd.area)
        for k, v in {**rep, "unfilled_loops": nd.unfilled_loops, "overlaps_resolved": nd.overlaps_resolved}.items():
            repairs.setdefault(k, []).append(v)
        p_base += int(nd.loop_offsets[-1])
        r_base += nd.loop_layer.size
    loop_layer = np.concatenate(lay).astype(np.int32)
    layer_offsets = np.zeros(n_layers + 1, np.int64)
    np.cumsum(np.bincount(loop_layer, minlength=n_layers), out=layer_offsets[1:])
    return SliceResult(
        np.concatenate(pts) if points is None else points, np.concatenate(loff), layer_offsets, loop_layer,
        np.concatenate(hole),
        np.concatenate(par).astype(np.int32), np.concatenate(closed), sched.z, sched.thickness,
        np.concatenate(area), {k: np.concatenate(v) for k, v in repairs.items()},
    )
