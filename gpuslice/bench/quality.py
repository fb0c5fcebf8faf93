"""Schedule quality: layer count, cusp heights and volume deviation of any schedule, uniform or adaptive.

**Cusp height** (Dolenc & Mäkelä): a facet with unit normal n printed in a layer of thickness t leaves a staircase
whose cusp is t·|n_z| high. Horizontal facets (zmax = zmin) make no staircase and are left out.

* ``cusp_mm[l]`` = t_l · (largest |n_z| of the facets touching or overlapping layer l's slab), mm;
  ``max_cusp_mm`` is its maximum over the layers.
* ``mean_cusp_mm`` = the surface-area-weighted mean of t·|n_z| over the non-horizontal facets, each facet's t
  being the mean layer thickness over its z range (exact for a piecewise-constant thickness; above the last slab the
  last thickness is assumed, below the first the first). It is the average staircase height a user would see on the
  surface.

**Volume deviation**: the stacked layers (each layer's polygons extruded over its slab) against the mesh, measured
against a fine uniform reference slice (default thickness: a fifth of the schedule's thinnest layer, at least
height / 20000): for every pair of a schedule layer l and a reference layer j whose slabs overlap by w_lj mm,
``w_lj · area(P_l XOR Q_j)``, with ``area(P XOR Q) = area(P) + area(Q) - 2·area(P ∩ Q)`` (shapely/GEOS,
vectorised over all pairs, two threads). Parts of the reference not covered by any schedule slab count as missing
material and parts of schedule slabs outside the reference as excess. Reported in mm³ and as a percentage of the
reference volume. The reference itself is a staircase of height h_ref, so deviations well below
``perimeter·h_ref²/8`` per mm of height are not resolved.
"""

from __future__ import annotations

import numpy as np

from ..mesh.mesh import Mesh
from ..ragged import expand_ranges
from ..schedule.adaptive import facet_slopes, slab_max_nz
from ..schedule.uniform import Schedule, slab_bottoms
from ..slicing.result import SliceResult

__all__ = ["schedule_edges", "cusp_heights", "mean_cusp", "cusp_summary", "layer_geometries", "volume_deviation",
           "reference_thickness", "schedule_quality"]


def schedule_edges(schedule: Schedule | SliceResult) -> np.ndarray:
    """(L + 1,) float64 slab edges of a schedule (or a result): bottoms, then the last top, mm. The slabs are where
    the exports put them (``bottom``: from the bed for every uniform and adaptive schedule; explicit planes may start
    higher); slabs with gaps or overlaps between them (explicit planes, each slab centred on its plane) have no such
    edges, and their quality is refused (:class:`ParameterError`)."""
    from ..errors import ParameterError

    t = np.asarray(schedule.thickness, dtype=np.float64)
    bottom = slab_bottoms(schedule.z, t) if t.size else np.zeros(0)  # (as the schedule's and the result's bottom)
    edges = (float(bottom[0]) if t.size else 0.0) + np.concatenate(([0.0], np.cumsum(t)))
    if t.size and not np.allclose(edges[:-1], bottom, rtol=0.0, atol=1e-9 * max(1.0, float(np.max(np.abs(edges))))):
        raise ParameterError("schedule quality: the layers' slabs do not stack (explicit planes, each slab centred "
                             "on its plane, with gaps or overlaps between them): no cusp or volume figures")
    return edges


def cusp_heights(mesh: Mesh, schedule: Schedule | SliceResult, device=None) -> np.ndarray:
    """(L,) float64: per layer its thickness times the largest |n_z| of the facets overlapping its slab, mm."""
    if len(schedule.thickness) == 0:
        return np.zeros(0)
    nz = slab_max_nz(mesh, schedule_edges(schedule), device).astype(np.float64)
    return np.asarray(schedule.thickness, dtype=np.float64) * nz


#: facets whose float64 corners are made at once (:func:`mean_cusp`): 12 MB of them, not the whole model's
AREA_CHUNK = 1 << 17


def _facet_areas(mesh: Mesh, which: np.ndarray) -> np.ndarray:
    """(len(which),) float64 areas (mm²) of the facets ``which``, :data:`AREA_CHUNK` at a time (each value as one
    float64 pass over the whole gives it: the chunks only bound the temporaries, 30 bytes a facet less fresh memory)."""
    area = np.empty(which.size)
    cols = [np.ascontiguousarray(mesh.vertices[:, k]) for k in range(3)]  # 1-D gathers: 2-D fancy indexing is slow
    for a in range(0, which.size, AREA_CHUNK):
        f = mesh.faces[which[a : a + AREA_CHUNK]]
        (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) = ([c[f[:, j]].astype(np.float64) for c in cols] for j in range(3))
        ux, uy, uz, vx, vy, vz = x1 - x0, y1 - y0, z1 - z0, x2 - x0, y2 - y0, z2 - z0
        cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx  # (np.cross's terms, in its order)
        area[a : a + AREA_CHUNK] = 0.5 * np.sqrt(cx * cx + cy * cy + cz * cz)
    return area


def mean_cusp(mesh: Mesh, schedule: Schedule | SliceResult, slopes=None, device=None) -> float:
    """The surface-area-weighted mean cusp height t·|n_z| over the non-horizontal facets, mm (0 if none); the
    facets' slopes on ``device`` when given (bit-identical to numpy's)."""
    t = np.asarray(schedule.thickness, dtype=np.float64)
    zmin, zmax, nz = slopes if slopes is not None else facet_slopes(mesh, device)
    slanted = zmax > zmin
    if not slanted.any() or t.size == 0:
        return 0.0
    area = _facet_areas(mesh, np.flatnonzero(slanted))
    # F(z) = integral of the thickness t(z) from 0: piecewise linear, slope t_l inside layer l
    edges = schedule_edges(schedule)
    big = max(float(mesh.height), float(edges[-1])) + 1.0
    low = min(0.0, float(edges[0])) - 1.0
    knots = np.concatenate(([low], edges, [big]))
    f = np.concatenate(([-t[0] * (edges[0] - low)], [0.0], np.cumsum(t * t),
                        [np.sum(t * t) + t[-1] * (big - edges[-1])]))
    lo, hi = zmin[slanted].astype(np.float64), zmax[slanted].astype(np.float64)
    tbar = (np.interp(hi, knots, f) - np.interp(lo, knots, f)) / (hi - lo)
    total = float(np.sum(area))
    if not total > 0:  # slanted facets of no area (slivers): nothing to weigh (was NaN: invalid JSON)
        return 0.0
    return float(np.sum(area * nz[slanted] * tbar) / total)


def cusp_summary(mesh: Mesh, schedule: Schedule | SliceResult, device=None) -> dict:
    """``{"max_cusp_mm", "mean_cusp_mm", "cusp_mm" (per layer)}`` for the report."""
    c = cusp_heights(mesh, schedule, device)
    return {"max_cusp_mm": float(c.max()) if c.size else 0.0, "mean_cusp_mm": mean_cusp(mesh, schedule, device=device),
            "cusp_mm": c.tolist()}


def layer_geometries(result: SliceResult):
    """(L,) array of shapely (Multi)Polygons, one per layer: closed loops, outer loops with their holes."""
    import shapely

    n_pts = np.diff(result.loop_offsets)
    keep = result.loop_closed & (n_pts >= 3)
    # a hole whose outer loop was dropped is dropped too
    parent_ok = np.ones_like(keep)
    holes = np.flatnonzero(result.loop_is_hole)
    parent_ok[holes] = keep[result.loop_parent[holes]]
    keep &= parent_ok
    loops = np.flatnonzero(keep)
    if loops.size == 0:
        return np.array([shapely.MultiPolygon() for _ in range(result.n_layers)], dtype=object)
    starts, counts = result.loop_offsets[loops], n_pts[loops]
    ring_len = counts + 1  # closed rings repeat their first point
    ring_off = np.concatenate(([0], np.cumsum(ring_len)))
    pos = np.arange(ring_off[-1]) - np.repeat(ring_off[:-1], ring_len)
    src = np.repeat(starts, ring_len) + np.where(pos == np.repeat(counts, ring_len), 0, pos)
    coords = result.points[src].astype(np.float64)
    outer = ~result.loop_is_hole[loops]
    poly_off = np.concatenate((np.flatnonzero(outer), [loops.size]))
    per_layer = np.bincount(result.loop_layer[loops][outer], minlength=result.n_layers)
    multi_off = np.concatenate(([0], np.cumsum(per_layer)))
    return shapely.from_ragged_array(
        shapely.GeometryType.MULTIPOLYGON, coords, (ring_off, poly_off, multi_off)
    )


def _intersection_areas(a, b, threads: int = 2) -> np.ndarray:
    import shapely

    def work(lo: int, hi: int) -> np.ndarray:
        x, y = a[lo:hi], b[lo:hi]
        try:
            return shapely.area(shapely.intersection(x, y))
        except shapely.errors.GEOSException:  # an invalid ring (broken mesh): repair and retry
            return shapely.area(shapely.intersection(shapely.make_valid(x), shapely.make_valid(y)))

    n = len(a)
    if n < 64 or threads < 2:
        return work(0, n)
    from concurrent.futures import ThreadPoolExecutor

    bounds = np.linspace(0, n, threads * 4 + 1).astype(int)
    with ThreadPoolExecutor(threads) as ex:  # GEOS releases the GIL
        parts = list(ex.map(lambda k: work(bounds[k], bounds[k + 1]), range(len(bounds) - 1)))
    return np.concatenate(parts)


def volume_deviation(result: SliceResult, reference: SliceResult, *, geoms=None, ref_geoms=None) -> dict:
    """Symmetric-difference volume between the stacked layers of ``result`` and of a fine ``reference``, mm³.

    Returns ``{"volume_deviation_mm3", "volume_deviation_pct" (of the reference volume; None when the reference
    holds none: an empty reference gave 0 %), "reference_thickness_mm"}``.
    """
    e_s, e_r = schedule_edges(result), schedule_edges(reference)
    a_s, a_r = np.asarray(result.area, np.float64), np.asarray(reference.area, np.float64)
    ref_volume = float(np.dot(a_r, np.diff(e_r)))
    out = {"reference_thickness_mm": float(np.median(reference.thickness)) if reference.n_layers else None}
    if result.n_layers == 0 or reference.n_layers == 0:
        dev = float(np.dot(a_s, np.diff(e_s))) + ref_volume
        return {**out, "volume_deviation_mm3": dev, "volume_deviation_pct": 100.0 * dev / ref_volume if ref_volume
                else None}
    # overlapping slab pairs (l, j): both edge lists are sorted, so each l meets a contiguous run of j
    j0 = np.searchsorted(e_r, e_s[:-1], side="right") - 1
    j1 = np.searchsorted(e_r, e_s[1:], side="left")
    j0 = np.clip(j0, 0, reference.n_layers)
    j1 = np.clip(j1, 0, reference.n_layers)
    cnt = np.maximum(j1 - j0, 0)
    pl, pj = expand_ranges(j0, cnt)
    w = np.minimum(e_s[pl + 1], e_r[pj + 1]) - np.maximum(e_s[pl], e_r[pj])
    good = w > 0
    pl, pj, w = pl[good], pj[good], w[good]
    g_s = geoms if geoms is not None else layer_geometries(result)
    g_r = ref_geoms if ref_geoms is not None else layer_geometries(reference)
    both = (a_s[pl] > 0) & (a_r[pj] > 0)
    inter = np.zeros(pl.size)
    if both.any():
        inter[both] = _intersection_areas(g_s[pl[both]], g_r[pj[both]])
    xor = np.maximum(a_s[pl] + a_r[pj] - 2.0 * inter, 0.0)
    dev = float(np.dot(w, xor))
    covered_r = np.bincount(pj, weights=w, minlength=reference.n_layers)
    covered_s = np.bincount(pl, weights=w, minlength=result.n_layers)
    dev += float(np.dot(np.maximum(np.diff(e_r) - covered_r, 0.0), a_r))  # reference material no layer covers
    dev += float(np.dot(np.maximum(np.diff(e_s) - covered_s, 0.0), a_s))  # layer material beyond the reference
    return {**out, "volume_deviation_mm3": dev,
            "volume_deviation_pct": 100.0 * dev / ref_volume if ref_volume > 0 else None}


def reference_thickness(height: float, thinnest: float) -> float:
    """The default reference thickness: a fifth of the thinnest layer compared, at least height / 20000 mm."""
    return float(max(thinnest / 5.0, height / 20000.0))


def schedule_quality(mesh: Mesh, result: SliceResult, reference: SliceResult | None = None, *,
                     ref_thickness: float | None = None, device=None, params=None) -> dict:
    """Quality figures of a sliced schedule: ``layers``, ``max_cusp_mm``, ``mean_cusp_mm`` and, with a
    ``reference`` (or ``ref_thickness`` mm to slice one), ``volume_deviation_mm3`` / ``_pct``."""
    q = {"layers": int(result.n_layers)}
    c = cusp_summary(mesh, result, device)
    q["max_cusp_mm"], q["mean_cusp_mm"] = c["max_cusp_mm"], c["mean_cusp_mm"]
    if reference is None and ref_thickness is not None:
        from ..slicing.slicer import slice_mesh

        # (uniform, mid-slab planes, no first layer of its own: the fine reference, whatever params' schedule)
        reference = slice_mesh(mesh, params, thickness=ref_thickness, adaptive=None, first_layer=None, z_mode="mid")
    if reference is not None:
        q.update(volume_deviation(result, reference))
    return q
