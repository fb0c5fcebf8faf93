"""Nesting's exact rebuild of loops that cross (stage 5's slow path), for all suspect layers at once.

In each suspect layer the loops that may share a face with a crossing one (``rings._groups``), a group per cluster
of them whose boxes meet no other cluster's, are noded by GEOS (``shapely.node``, all groups in one call). The
regions are then built in one of two ways, with the same result:

- the *arrangement* path (numpy, most groups; :mod:`.arrangement`): the faces of the noded pieces' planar graph,
  each face's winding number from its neighbour's across a piece, the boundary pieces linked into rings;
- the *GEOS* path (the groups the arrangement path does not take on, e.g. loops with collinear overlapping edges,
  as the coplanar faces of overlapping parts give; half of them beside the other half when they are many):
  polygonize the noded lines into faces, keep those whose winding number at ``point_on_surface`` passes the fill
  rule, ``union_all`` them.

The regions of a layer's clusters are then taken together, and both paths go through the same ``normalize`` and
``orient_polygons``, so the output depends neither on the path nor on the clustering, with one exception: a group
GEOS cannot node as it is (a broken file's) is snapped to :data:`~.rings.SNAP_GRID` (:func:`~.rings.node_groups`),
and that group is now the one cluster, where it was its whole layer: the layer's other clusters keep their exact
points (a review: 1e-7 mm moved, the area 3e-7 mm² apart, on a file of float32 subnormals beside a crossing quad).
"""

from __future__ import annotations

import numpy as np

from . import rings as _rings
from .arrangement import Noded as _Noded
from .arrangement import arrangement as _arrangement
from .rings import Nested, _groups, _ring_points, _winding_numbers, filled, signed_areas

__all__ = ["resolve_overlaps"]


def _geos_region(noded, ids, pc, offsets, lo, hi, fill_rule):
    """The region of one group by GEOS: faces of the noded lines, kept by their winding number at
    ``point_on_surface``, unioned (None when the lines bound no face)."""
    import shapely

    faces = shapely.get_parts(shapely.polygonize(shapely.get_parts(noded)))
    if faces.size == 0:
        return None
    reps = shapely.point_on_surface(faces)
    q = shapely.get_x(reps) + 1j * shapely.get_y(reps)
    # a loop winds 0 times around a point outside its box: the (face, loop) pairs whose box holds the face's point,
    # from a tree of the boxes (every pair tested made faces x loops of them: 10^8 on a garbled file's layer)
    tree = shapely.STRtree(shapely.box(lo[ids, 0], lo[ids, 1], hi[ids, 0], hi[ids, 1]))
    pi, k = tree.query(reps, predicate="intersects")
    order = np.lexsort((k, pi))  # (face by face, loops in their order: the sums as before)
    pi, pj = pi[order], ids[k[order]]
    w = np.bincount(pi, weights=_winding_numbers(pc, offsets, pi, pj, q), minlength=faces.size)
    kept = faces[filled(np.rint(w).astype(np.int64), fill_rule)]
    if not kept.size:
        return shapely.Polygon()
    try:  # the faces of a polygonized arrangement are a coverage: their union is their outline (faster)
        region = shapely.coverage_union_all(kept)
        if shapely.is_valid(region):
            return region
    except shapely.errors.GEOSException:  # not noded as a coverage after all: the general union below
        pass
    return shapely.union_all(kept)


def _regions(points, pc, offsets, groups, lo, hi, fill_rule):
    """The region (polygonal geometry, or None: no face) of every group (layer, ids)."""
    import shapely

    lid = np.concatenate([ids for _, ids in groups])
    per = np.array([ids.size for _, ids in groups], dtype=np.int64)
    g_off = np.zeros(per.size + 1, dtype=np.int64)
    np.cumsum(per, out=g_off[1:])
    rz, roff = _ring_points(points, offsets, lid, pc, always_close=True)  # as np.vstack([ring, ring[:1]])
    lines = shapely.from_ragged_array(shapely.GeometryType.MULTILINESTRING, rz.view(np.float64).reshape(-1, 2),
                                      (roff, g_off))
    noded = _rings.node_groups(lines)
    loop_g = np.repeat(np.arange(per.size), per)
    ok, geoms = _arrangement(_Noded(noded), rz, roff, loop_g, lid, per.size,
                             pc, offsets, lo, hi, fill_rule)
    regions = np.empty(per.size, dtype=object)
    regions[ok] = geoms
    rest = np.flatnonzero(~ok)

    def by_geos(gs: np.ndarray) -> np.ndarray:  # (a loop over the groups the arrangement path left)
        out = np.empty(gs.size, dtype=object)
        out[:] = [_geos_region(noded[g], groups[g][1], pc, offsets, lo, hi, fill_rule) for g in gs.tolist()]
        return out

    if rest.size:  # (half of them beside the other half when they are many: GEOS releases the GIL)
        points_g = np.bincount(loop_g, weights=np.diff(roff), minlength=per.size)
        regions[rest] = _rings.in_halves(by_geos, points_g[rest], rest)
    return regions


def _by_layer(groups, regions):
    """The groups (clusters of one layer, ascending by layer) and their regions joined per layer: the layer's loops,
    and the polygons of its clusters as one MultiPolygon (None where no cluster of the layer bounds a face), which
    :func:`_region_rings` normalizes as it did the region of the layer's loops taken together."""
    import shapely

    lay = np.array([g[0] for g in groups], dtype=np.int64)
    if lay.size < 2 or (lay[1:] != lay[:-1]).all():
        return groups, regions
    cut = np.flatnonzero(np.diff(lay)) + 1
    out_groups, out_regions = [], []
    for a, b in zip(np.r_[0, cut].tolist(), np.r_[cut, lay.size].tolist(), strict=True):  # (a layer at a time)
        if b - a == 1:
            out_groups.append(groups[a])
            out_regions.append(regions[a])
            continue
        out_groups.append((groups[a][0], np.sort(np.concatenate([ids for _, ids in groups[a:b]]))))
        made = [r for r in regions[a:b] if r is not None]
        parts = shapely.get_parts(np.array(made, dtype=object)) if made else None
        out_regions.append(None if parts is None else shapely.multipolygons(
            parts[(shapely.get_type_id(parts) == shapely.GeometryType.POLYGON) & ~shapely.is_empty(parts)]))
    return out_groups, np.array(out_regions, dtype=object)


def _region_rings(regions):
    """Output rings of the regions: per polygon (normalized, as GEOS orders them) the exterior counter-clockwise
    then its holes clockwise, each without its closing point. Returns (points (P, 2) float64, counts, region of
    each ring, is-hole, the ring index of each ring's exterior). A polygon narrower on average (2·area / perimeter)
    than one float32 step of its coordinates is left out: the arrangement's slivers (8e-12 mm² on benchy) that no
    stored point can hold apart, which collapsed into self-touching rings in every export."""
    import shapely

    normal = _rings.in_halves(shapely.normalize, shapely.get_num_coordinates(regions), regions)
    parts, p_reg = shapely.get_parts(normal, return_index=True)
    area = shapely.area(parts)
    reach = np.abs(shapely.bounds(parts)).max(axis=1) if parts.size else np.zeros(0)
    step = np.spacing(np.nan_to_num(reach).astype(np.float32)).astype(np.float64)
    real = ~shapely.is_empty(parts) & (area > 0) & (2.0 * area > step * shapely.length(parts))
    parts, p_reg = shapely.orient_polygons(parts[real], exterior_cw=False), p_reg[real]
    rings, r_poly = shapely.get_rings(parts, return_index=True)
    counts = shapely.get_num_coordinates(rings).astype(np.int64)
    coords = shapely.get_coordinates(rings)
    off = np.zeros(counts.size + 1, dtype=np.int64)
    np.cumsum(counts, out=off[1:])
    drop = np.ones(coords.shape[0], dtype=bool)  # (applied below to one complex per point: a 1-D mask is ~10x faster)
    drop[off[1:] - 1] = False
    is_hole = np.ones(rings.size, dtype=bool)
    is_hole[np.searchsorted(r_poly, np.arange(parts.size))] = False
    exterior = np.maximum.accumulate(np.where(is_hole, 0, np.arange(rings.size))) if rings.size else r_poly
    kept = np.ascontiguousarray(coords).view(np.complex128).reshape(-1)[drop].view(np.float64).reshape(-1, 2)
    return kept, counts - 1, p_reg[r_poly], is_hole, exterior


def _copy_runs(old_pts, old_start, new_pts, new_start, order, counts, offsets) -> np.ndarray:
    """(P, 2) float32 points of the loops ``order`` (indices into old loops then new ones, starting at
    ``old_start`` in ``old_pts`` and ``new_start`` in ``new_pts``), copied run by run: loops that follow each other
    in their source form one run (a few per rebuilt layer), so no index per point is made."""
    n_old = old_start.size
    start = np.concatenate([old_start, new_start])[order]
    is_new = order >= n_old
    brk = np.ones(order.size, dtype=bool)
    brk[1:] = (start[1:] != start[:-1] + counts[:-1]) | (is_new[1:] != is_new[:-1])
    runs = np.flatnonzero(brk)
    total = int(offsets[-1])
    length = np.diff(np.append(offsets[:-1][runs], total))
    out = np.empty((total, 2), dtype=np.float32)
    for s, d, n, new in zip(start[runs].tolist(), offsets[:-1][runs].tolist(), length.tolist(), is_new[runs].tolist(),
                            strict=True):
        out[d : d + n] = (new_pts if new else old_pts)[s : s + n]
    return out


def resolve_overlaps(nested: Nested, points, pc, offsets, layer, closed, layers, fill_rule, n_layers, seeds,
                     new_index, loop_area, unfilled_loop, boxes) -> Nested:
    """Exact regions of the loops that cross, from the arrangement of their boundaries (see the module docstring).

    The loops of each suspect layer (``layers``) that may share a face with a crossing one (``seeds``;
    :func:`affected`) are replaced by the rings of their region; the layer's other loops (other parts of a plate,
    apart from the crossing ones) keep their fast result, and so do layers whose loops turn out to bound no face.
    ``pc``: the points as complex numbers; ``new_index``: each loop's place in ``nested`` (-1: dropped);
    ``loop_area``: signed areas, mm^2; ``unfilled_loop``: loops that bound nothing; ``boxes``: (lo, hi) of the loops.
    """
    lo, hi = boxes
    groups = _groups(layer, closed, np.asarray(layers), seeds, lo, hi)
    if not groups:
        return nested
    groups, regions = _by_layer(groups, _regions(points, pc, offsets, groups, lo, hi, fill_rule))
    done = np.array([r is not None for r in regions], dtype=bool)
    if not done.any():
        return nested
    fixed = np.array([lay for lay, _ in groups], dtype=np.int64)[done]
    rebuilt = np.concatenate([ids for (_, ids), d in zip(groups, done, strict=True) if d])
    new_pts, new_cnt, new_reg, new_hole, new_ext = _region_rings(regions[done])
    new_layer = fixed[new_reg]
    # the rebuilt loops are replaced; the rest of their layers (open chains, loops apart) stays, first in the layer
    gone = new_index[rebuilt]
    keep = np.ones(nested.loop_layer.size, dtype=bool)
    keep[gone[gone >= 0]] = False
    stay = np.ones(layer.size, dtype=bool)  # the loops (by their index here) that keep their fast result
    stay[rebuilt] = False
    counts = np.diff(nested.loop_offsets)
    old_index = np.flatnonzero(keep)
    remap = np.full(keep.size, -1, dtype=np.int64)
    n_old = old_index.size
    all_layer = np.concatenate([nested.loop_layer[keep], new_layer]).astype(np.int32)
    order = np.argsort(all_layer, kind="stable")
    position = np.empty(order.size, dtype=np.int64)
    position[order] = np.arange(order.size)
    remap[old_index] = position[:n_old]
    old_parent = nested.loop_parent[keep]
    parents = np.concatenate([
        np.where(old_parent >= 0, remap[np.maximum(old_parent, 0)], -1),
        np.where(new_hole, position[n_old + new_ext], -1),
    ])
    r_off = np.zeros(new_cnt.size + 1, dtype=np.int64)
    np.cumsum(new_cnt, out=r_off[1:])
    all_counts = np.concatenate([counts[keep], new_cnt]).astype(np.int64)
    new_offsets = np.zeros(order.size + 1, dtype=np.int64)
    np.cumsum(all_counts[order], out=new_offsets[1:])
    out_points = _copy_runs(nested.points, nested.loop_offsets[:-1][keep], new_pts.astype(np.float32), r_off[:-1],
                            order, all_counts[order], new_offsets)
    is_hole = np.concatenate([nested.loop_is_hole[keep], new_hole]).astype(bool)[order]
    closed_all = np.concatenate([nested.loop_closed[keep], np.ones(new_hole.size, bool)])[order]
    layer_offsets = np.zeros(n_layers + 1, dtype=np.int64)
    np.cumsum(np.bincount(all_layer, minlength=n_layers), out=layer_offsets[1:])
    area = nested.area.copy()
    resolved = nested.overlaps_resolved.copy()
    unfilled = nested.unfilled_loops.copy()
    # what stays of a rebuilt layer: its loops' areas as the fast path had them, and its loops that bound nothing
    at = np.maximum(new_index, 0)
    if nested.loop_layer.size:
        was_closed, was_hole = nested.loop_closed[at].astype(bool), nested.loop_is_hole[at].astype(bool)
    else:  # the fast path kept no loop at all
        was_closed = was_hole = np.zeros(layer.size, dtype=bool)
    still = stay & (new_index >= 0) & was_closed
    sign = np.where(was_hole[still], -1.0, 1.0)
    kept_area = np.bincount(layer[still], weights=sign * np.abs(loop_area[still]), minlength=n_layers)
    kept_unfilled = np.bincount(layer[stay & unfilled_loop], minlength=n_layers)
    r_off = np.zeros(new_cnt.size + 1, dtype=np.int64)
    np.cumsum(new_cnt, out=r_off[1:])
    ring_area = np.abs(signed_areas(new_pts, r_off)) * np.where(new_hole, -1, 1)
    bounds = np.searchsorted(new_reg, np.arange(fixed.size + 1))
    for lay, a, b in zip(fixed.tolist(), bounds[:-1].tolist(), bounds[1:].tolist(), strict=True):
        total = 0.0
        for v in ring_area[a:b]:  # in order, one addition at a time (as the loops are listed)
            total += v
        area[lay] = total
        area[lay] += kept_area[lay]
        resolved[lay] = 1
        unfilled[lay] = kept_unfilled[lay]
    return Nested(points=out_points, loop_offsets=new_offsets, layer_offsets=layer_offsets, loop_layer=all_layer[order],
                  loop_is_hole=is_hole, loop_parent=parents[order].astype(np.int32), loop_closed=closed_all, area=area,
                  unfilled_loops=unfilled, overlaps_resolved=resolved, reoriented=nested.reoriented)
