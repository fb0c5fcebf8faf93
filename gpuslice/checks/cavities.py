"""Resin traps and suction cups: connected empty space, layer to layer, on a voxel grid.

**Grid.** Voxels are the layers (their slabs in z) times square cells of ``g`` mm in x, y: a cell is solid when the
layer's polygons cover at least half of it (the rasteriser's exact coverage with a hard threshold at the layer's cut
plane), so the grid samples the model at its cell centres. The grid is the model's bounding box plus two empty cells
all round (the outside), or a printer's display. Empty cells are 6-connected (sides in x, y; the same cell in the
layers above and below), the complement of solid cells 18/26-connected: a cavity joined to another only by an edge
or a corner of a cell is not joined.

**Resolution and error** (``g`` = the cell): a cavity's cross-section is its cells, each of area g², so its outline
is placed to within about g/2; its volume error is at most about half its surface times g and, as cell centres fall
on both sides of the outline, usually far less (a 16 mm spherical cavity at g = 0.2 mm: 0.1 %, the tests). Walls
thinner than about g may vanish (a trap missed) and channels narrower than about g may close (a drain hole missed: a
trap reported); :data:`DEFAULT_GRID_MM` is 0.2 mm, give a finer grid or the printer's pixels for thin features.

**Memory.** Nothing is a 3D array: each layer is row intervals of solid cells (:mod:`gpuslice.checks.intervals`),
and only the empty runs between two solid runs of a row (*gaps*) can be enclosed. Layers come in batches; a batch's
gaps are joined into 2D components inside each layer (:func:`gpuslice.checks.intervals.components`); those that
reach the grid's border are outside, the others are *holes* and become nodes, linked to the holes of the layer
below and above where they share a cell, or marked open where they share a cell with the outside of the layer below
or above. Only the last layer of a batch is kept for the next, so memory is one batch of runs plus the holes. A
layer without a hole loop has no enclosed empty space, so only the layers with one and their neighbours are
rasterised (:func:`gpuslice.checks.hole_layers`).

**Holes the grid made.** A notch or slit narrower than a cell can close on the grid into a hole that the layer's
polygons do not enclose: its empty space reaches the outside within the layer. Given the polygons
(:meth:`CavityFinder.result`'s ``enclosed``, :func:`enclosed_in_outlines`), a hole counts as enclosed only where its
layer has a hole loop and its cell nearest the centroid lies inside one of the layer's closed outer loops; the others
are open to the outside in their own layer (as a hole of the first layer is open below). Without this, such a notch
whose layers end where the rasterised layers end was never seen to open and came out as a trap (a surface groove of
``rear_case``, a slit beside a vent).

**Traps**: connected holes of which none is open, none lies in the first layer (open to below once off the plate)
nor in the last (open above): they hold uncured resin after printing. **Suction cups**: while layer i prints, the
empty space of layers 0 .. i is closed below by the plate and above by the vat floor; a hole of layer i whose
connected empty space in layers 0 .. i does not reach the outside is a sealed pocket against the vat. The pocket
lasts until a layer closes it (it has no hole in the next layer) or opens it (it reaches the outside); pockets that
meet merge. Each is reported once: its first and last layers, its largest cross-section facing the vat and its
volume when it was last sealed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .intervals import Lines, components, expand_pairs

__all__ = ["Cavities", "CavityFinder", "enclosed_in_outlines", "DEFAULT_GRID_MM", "TRAP", "SUCTION_CUP", "KINDS"]

#: default cell of the voxel grid, mm
DEFAULT_GRID_MM = 0.2
TRAP, SUCTION_CUP = 0, 1
#: names of the ``kind`` codes
KINDS = ("trap", "suction_cup")


@dataclass
class Cavities:
    """Traps and suction cups as columns (T rows): ``kind`` int8 (:data:`TRAP`, :data:`SUCTION_CUP`), ``volume``
    mm³, ``layer_min``, ``layer_max`` int64, ``x``, ``y``, ``z`` a point inside (mm), ``max_area`` the largest
    cross-section (mm²), ``bbox`` (T, 4) xmin, ymin, xmax, ymax (mm); and the grid's cell ``grid_mm``."""

    kind: np.ndarray
    volume: np.ndarray
    layer_min: np.ndarray
    layer_max: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    max_area: np.ndarray
    bbox: np.ndarray
    grid_mm: float

    @property
    def n_traps(self) -> int:
        return int(np.count_nonzero(self.kind == TRAP))

    @property
    def n_cups(self) -> int:
        return int(np.count_nonzero(self.kind == SUCTION_CUP))


def enclosed_in_outlines(result, layer: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(K,) bool: whether the point ``(x[k], y[k])`` (mm, the result's frame) of layer ``layer[k]`` could lie in
    empty space that layer's polygons enclose: the layer has a closed hole loop, and the point lies inside one of its
    closed outer loops (then, being empty, it is in a hole; a point outside all of them reaches the outside). A point
    on a loop counts as it falls. Only loops whose box holds the point are walked (no Python loop per point)."""
    from ..ragged import expand_ranges
    from ..slicing.rings import _as_complex, _winding_numbers

    layer = np.asarray(layer, np.int64)
    out = np.zeros(layer.size, bool)
    if not layer.size or result.n_loops == 0:
        return out
    closed = np.asarray(result.loop_closed, bool)
    is_hole = np.asarray(result.loop_is_hole, bool)
    loop_layer = np.asarray(result.loop_layer, np.int64)
    has_hole = np.zeros(result.n_layers, bool)
    has_hole[loop_layer[closed & is_hole]] = True
    lay_off = np.asarray(result.layer_offsets, np.int64)
    k, loop = expand_ranges(lay_off[layer], lay_off[layer + 1] - lay_off[layer])
    keep = has_hole[layer[k]] & closed[loop] & ~is_hole[loop]
    k, loop = k[keep], loop[keep]
    if not k.size:
        return out
    offsets = np.asarray(result.loop_offsets, np.int64)
    pts = np.asarray(result.points)
    used = np.unique(loop)
    owner, at = expand_ranges(offsets[used], offsets[used + 1] - offsets[used])
    starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    px, py = pts[at, 0], pts[at, 1]
    box = np.empty((result.n_loops, 4), np.float64)
    box[used] = np.stack([np.minimum.reduceat(px, starts), np.minimum.reduceat(py, starts),
                          np.maximum.reduceat(px, starts), np.maximum.reduceat(py, starts)], axis=1)
    xk, yk = np.asarray(x, np.float64)[k], np.asarray(y, np.float64)[k]
    b = box[loop]
    near = (b[:, 0] <= xk) & (xk <= b[:, 2]) & (b[:, 1] <= yk) & (yk <= b[:, 3])
    k, loop = k[near], loop[near]
    if not k.size:
        return out
    q = np.asarray(x, np.float64) + 1j * np.asarray(y, np.float64)
    w = _winding_numbers(_as_complex(pts), offsets, k, loop, q)
    out[k[w != 0]] = True
    return out


class _DSU:
    """Union-find over the holes, with per-root volume, first layer and an open flag (a loop per hole: few)."""

    def __init__(self, vol: np.ndarray, layer: np.ndarray) -> None:
        self.parent = list(range(vol.size))
        self.vol = vol.astype(np.float64).tolist()
        self.lmin = layer.tolist()
        self.opened = [False] * vol.size

    def find(self, a: int) -> int:
        p = self.parent
        while p[a] != a:
            p[a] = p[p[a]]
            a = p[a]
        return a

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return
        if rb < ra:
            ra, rb = rb, ra
        self.parent[rb] = ra
        self.vol[ra] += self.vol[rb]
        self.lmin[ra] = min(self.lmin[ra], self.lmin[rb])
        self.opened[ra] = self.opened[ra] or self.opened[rb]


class CavityFinder:
    """Finds traps and suction cups on a grid of ``rows`` × ``cols`` cells, fed batches of consecutive layers'
    solid intervals (:meth:`feed`), then :meth:`result` (module docstring).

    to_mm : (2, 3) affine map from cell coordinates (u = column, v = row) to model mm; cell_area : mm²;
    thickness, z : the result's (L,) layer thicknesses and cut planes (mm); grid_mm : the cell, for the report.
    """

    def __init__(self, rows: int, cols: int, to_mm: np.ndarray, cell_area: float, thickness: np.ndarray,
                 z: np.ndarray, grid_mm: float) -> None:
        self.rows, self.cols = rows, cols
        self.to_mm = np.asarray(to_mm, np.float64)
        self.cell_area = float(cell_area)
        self.thickness, self.z = np.asarray(thickness, np.float64), np.asarray(z, np.float64)
        self.n_layers = int(self.z.size)
        self.grid_mm = grid_mm
        self.holes: list[dict[str, np.ndarray]] = []
        self.n_holes = 0
        self.edges: list[tuple[np.ndarray, np.ndarray]] = []
        self.open_above: list[np.ndarray] = []
        self.open_below: list[np.ndarray] = []
        self.context: tuple | None = None  # last layer of the previous batch: (layer, row, start, end, gap_hole)

    # ---- per batch -------------------------------------------------------------------------------------------------
    def feed(self, layer0: int, n: int, parts: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> None:
        """Layers ``layer0 .. layer0 + n - 1``: their solid intervals ``(layer, row, start, end)``."""
        rows = self.rows
        ctx = self.context if self.context is not None and self.context[5] == layer0 - 1 else None
        lines = Lines.from_parts(layer0 - 1, n + 1, rows, self.cols, [ctx[:4], parts] if ctx else [parts])
        gap = np.flatnonzero(lines.line[:-1] == lines.line[1:])  # interior gaps j: between intervals j and j + 1
        g_line, ga, gb = lines.line[gap], lines.end[gap], lines.start[gap + 1]
        hole_of = np.full(lines.n, -1, np.int64)  # per gap index: its hole, -1 for the outside (or no gap)
        n_ctx = int(np.count_nonzero(g_line < rows))
        if ctx is not None and n_ctx:
            hole_of[gap[:n_ctx]] = ctx[4]
        own = np.arange(n_ctx, gap.size)
        if own.size:
            self._holes_2d(lines, gap[own], g_line[own], ga[own], gb[own], hole_of)
        self._links(lines, gap, g_line, ga, gb, hole_of)
        last = lines.layer_slice(n)
        lg = (gap >= last.start) & (gap < last.stop)
        self.context = (lines.layer[last], lines.row[last], lines.start[last], lines.end[last], hole_of[gap[lg]],
                        layer0 + n - 1)

    def _holes_2d(self, lines: Lines, gj, line, a, b, hole_of) -> None:
        """2D components of this batch's gaps (4-connected inside a layer); those not reaching the border: holes."""
        rows = self.rows
        row = line % rows
        pos = np.full(lines.n, -1, np.int64)
        pos[gj] = np.arange(gj.size)
        src, dst, border = [], [], np.zeros(gj.size, bool)
        for d in (-1, 1):
            valid = (row + d >= 0) & (row + d < rows)
            lo, hi, out = lines.gaps_touching(line + d, a, b, valid)
            q, j = expand_pairs(lo, hi)
            src.append(q)
            dst.append(pos[j])
            border |= out
        comp = components(gj.size, np.concatenate(src), np.concatenate(dst))
        n_comp = int(comp.max()) + 1 if comp.size else 0
        outside = np.zeros(n_comp, bool)
        outside[comp[border]] = True
        rank = np.cumsum(~outside) - 1
        keep = ~outside[comp]
        if not keep.any():
            return
        hole = rank[comp[keep]] + self.n_holes
        hole_of[gj[keep]] = hole
        n_new = int(np.count_nonzero(~outside))
        self.n_holes += n_new
        self.holes.append(self._describe(hole - (self.n_holes - n_new), n_new, lines.layer[gj[keep]], row[keep],
                                         a[keep], b[keep]))

    def _describe(self, h, n, layer, row, a, b) -> dict[str, np.ndarray]:
        """Per hole: layer, cells, bbox (u0, v0, u1, v1 in cells) and a cell well inside it: the middle cell of the
        longest run of the hole's row nearest its centroid (the centroid itself may lie in a solid the hole
        surrounds, such as a loose ball in a hollow sphere; the middle of a run is as far as the row allows from
        the solid on either side)."""
        length = (b - a).astype(np.float64)
        cells = np.bincount(h, length, minlength=n)
        cu = np.bincount(h, length * (a + b) / 2.0, minlength=n) / cells
        cv = np.bincount(h, length * (row + 0.5), minlength=n) / cells
        hl = np.zeros(n, np.int64)
        hl[h] = layer
        bbox = np.empty((n, 4))
        bbox[:, :2] = np.inf
        bbox[:, 2:] = -np.inf
        np.minimum.at(bbox[:, 0], h, a)
        np.minimum.at(bbox[:, 1], h, row)
        np.maximum.at(bbox[:, 2], h, b)
        np.maximum.at(bbox[:, 3], h, row + 1)
        # the row nearest the centroid's, its longest run (then the one nearest the centroid), that run's middle cell
        u = np.floor((a + b) / 2.0) + 0.5
        order = np.lexsort((np.abs(u - cu[h]), -length, np.abs(row + 0.5 - cv[h]), h))
        first = order[np.r_[True, h[order][1:] != h[order][:-1]]]
        rep = np.zeros((n, 2))
        rep[h[first], 0], rep[h[first], 1] = u[first], row[first] + 0.5
        return {"layer": hl, "cells": cells, "bbox": bbox, "rep": rep}

    def _links(self, lines: Lines, gap, line, a, b, hole_of) -> None:
        """Holes of one layer against the empty space of the layers above and below (same cells)."""
        rows, n = self.rows, lines.n_layers
        h = hole_of[gap]
        k = line // rows
        up = np.flatnonzero((h >= 0) & (k < n - 1))  # every layer of the batch but its last: the next batch's
        if up.size:
            lo, hi, border = lines.gaps_touching(line[up] + rows, a[up], b[up], np.ones(up.size, bool))
            q, j = expand_pairs(lo, hi)
            other = hole_of[j]
            # one link per pair of holes, not one per grid row they share (kept for the whole model: memory)
            key = np.unique(h[up][q[other >= 0]].astype(np.int64) << 32 | other[other >= 0].astype(np.int64))
            self.edges.append((key >> 32, key & 0xFFFFFFFF))
            self.open_above.append(np.unique(np.concatenate([h[up][border], h[up][q[other < 0]]])))
        layer = k + lines.layer0
        down = np.flatnonzero((h >= 0) & (k >= 1) & (layer >= 1))  # this batch's own layers; layer 0: the plate
        if down.size:
            lo, hi, border = lines.gaps_touching(line[down] - rows, a[down], b[down], np.ones(down.size, bool))
            q, j = expand_pairs(lo, hi)
            self.open_below.append(np.unique(np.concatenate([h[down][border], h[down][q[hole_of[j] < 0]]])))

    # ---- the whole model -------------------------------------------------------------------------------------------
    def result(self, enclosed: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None) -> Cavities:
        """The traps and suction cups. ``enclosed(layer, x, y)``: (K,) bool, whether the point (mm) of a hole in that
        layer lies in empty space the layer's polygons enclose (:func:`enclosed_in_outlines`); the other holes are
        open to the outside in their own layer (module docstring). None: every hole is taken as enclosed."""
        n = self.n_holes
        if n == 0:
            return self._table([])
        hl = np.concatenate([d["layer"] for d in self.holes])
        cells = np.concatenate([d["cells"] for d in self.holes])
        bbox = np.concatenate([d["bbox"] for d in self.holes])
        rep = np.concatenate([d["rep"] for d in self.holes])
        area = cells * self.cell_area
        vol = area * self.thickness[hl]
        src = np.concatenate([e[0] for e in self.edges]) if self.edges else np.zeros(0, np.int64)
        dst = np.concatenate([e[1] for e in self.edges]) if self.edges else np.zeros(0, np.int64)
        if src.size:
            pairs = np.unique(np.stack([src, dst], axis=1), axis=0)
            src, dst = pairs[:, 0], pairs[:, 1]
        above = np.zeros(n, bool)
        below = np.zeros(n, bool)
        for part in self.open_above:
            above[part] = True
        for part in self.open_below:
            below[part] = True
        if enclosed is not None:  # holes the grid made (module docstring): open where they are
            t = self.to_mm
            x = t[0, 0] * rep[:, 0] + t[0, 1] * rep[:, 1] + t[0, 2]
            y = t[1, 0] * rep[:, 0] + t[1, 1] * rep[:, 1] + t[1, 2]
            below |= ~np.asarray(enclosed(hl, x, y), bool)
        rows = self._traps(n, hl, area, vol, bbox, rep, src, dst, above | below)
        rows += self._cups(n, hl, area, vol, bbox, rep, src, dst, above, below)
        return self._table(rows)

    def _point(self, hole: int, rep: np.ndarray, hl: np.ndarray) -> tuple[float, float, float]:
        u, v = rep[hole]
        t = self.to_mm
        return (float(t[0, 0] * u + t[0, 1] * v + t[0, 2]), float(t[1, 0] * u + t[1, 1] * v + t[1, 2]),
                float(self.z[hl[hole]]))

    def _bbox_mm(self, b: np.ndarray) -> list[float]:
        t = self.to_mm
        corners = np.array([[b[0], b[1]], [b[2], b[1]], [b[0], b[3]], [b[2], b[3]]])
        x = t[0, 0] * corners[:, 0] + t[0, 1] * corners[:, 1] + t[0, 2]
        y = t[1, 0] * corners[:, 0] + t[1, 1] * corners[:, 1] + t[1, 2]
        return [float(x.min()), float(y.min()), float(x.max()), float(y.max())]

    def _traps(self, n, hl, area, vol, bbox, rep, src, dst, opened) -> list[tuple]:
        comp = components(n, src, dst)
        n_comp = int(comp.max()) + 1
        bad = np.zeros(n_comp, bool)
        bad[comp[opened | (hl == 0) | (hl == self.n_layers - 1)]] = True
        members = np.flatnonzero(~bad[comp])
        if not members.size:
            return []
        # per trap (grouped by component, vectorised): volume, layers, largest cross-section, its biggest hole
        order = members[np.lexsort((hl[members], comp[members]))]
        c = comp[order]
        start = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
        volume = np.add.reduceat(vol[order], start)
        lmin, lmax = np.minimum.reduceat(hl[order], start), np.maximum.reduceat(hl[order], start)
        key = c * (self.n_layers + 1) + hl[order]  # cross-section per (trap, layer)
        kstart = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        face = np.add.reduceat(area[order], kstart)
        face_max = np.maximum.reduceat(face, np.searchsorted(kstart, start))
        big = np.lexsort((-area[order], c))  # each trap's biggest hole first
        biggest = order[big[np.r_[True, c[big][1:] != c[big][:-1]]]]
        lo = np.minimum.reduceat(bbox[order, :2], start)
        hi = np.maximum.reduceat(bbox[order, 2:], start)
        return [(TRAP, float(volume[k]), int(lmin[k]), int(lmax[k]), *self._point(int(biggest[k]), rep, hl),
                 float(face_max[k]), self._bbox_mm(np.r_[lo[k], hi[k]])) for k in range(start.size)]

    def _cups(self, n, hl, area, vol, bbox, rep, src, dst, above, below) -> list[tuple]:
        """The sweep over layers (module docstring): a union-find over the holes, in print order."""
        order = np.argsort(hl, kind="stable")
        lay_sorted = hl[order]
        layers, first = np.unique(lay_sorted, return_index=True)
        ends = np.append(first[1:], n)
        e_order = np.argsort(hl[dst], kind="stable")  # edges join a hole to one of the layer above: by that layer
        src, dst = src[e_order], dst[e_order]
        e_layer = hl[dst]
        above_holes = np.flatnonzero(above)
        above_holes = above_holes[np.argsort(hl[above_holes], kind="stable")]
        above_time = hl[above_holes] + 1  # a hole open above opens its pocket when the next layer prints
        dsu = _DSU(vol, hl)
        pockets: dict[int, dict] = {}  # root -> pocket, as of the previous layer
        done: list[dict] = []
        prev_t = None
        for t, a, b in zip(layers.tolist(), first.tolist(), ends.tolist(), strict=True):  # a loop per layer
            if prev_t is not None and t != prev_t + 1:  # a layer with no hole: every pocket is closed
                done += pockets.values()
                pockets = {}
            hs = order[a:b]
            for h in hs[below[hs]].tolist():
                dsu.opened[h] = True
            ea, eb = np.searchsorted(e_layer, [t, t + 1])
            for s, d in zip(src[ea:eb].tolist(), dst[ea:eb].tolist(), strict=True):
                dsu.union(s, d)
            oa, ob = np.searchsorted(above_time, [t, t + 1]) if above_holes.size else (0, 0)
            for h in above_holes[oa:ob].tolist():
                dsu.opened[dsu.find(h)] = True
            faces: dict[int, list[int]] = {}
            for h in hs.tolist():
                r = dsu.find(h)
                if not dsu.opened[r]:
                    faces.setdefault(r, []).append(h)
            now: dict[int, dict] = {}
            for r_prev, p in pockets.items():
                r = dsu.find(r_prev)
                if r not in faces:
                    done.append(p)  # closed over, or opened to the outside
                elif r in now:  # two pockets met: one pocket from now on
                    q = now[r]
                    if p["max_area"] > q["max_area"]:
                        q["max_area"], q["hole"] = p["max_area"], p["hole"]
                    q["layer_min"] = min(q["layer_min"], p["layer_min"])
                    q["box"] = np.r_[np.minimum(q["box"][:2], p["box"][:2]), np.maximum(q["box"][2:], p["box"][2:])]
                else:
                    now[r] = p
            for r, hs_face in faces.items():
                p = now.setdefault(r, {"layer_min": dsu.lmin[r], "max_area": -1.0, "hole": -1,
                                       "box": np.array([np.inf, np.inf, -np.inf, -np.inf])})
                face = float(area[hs_face].sum())
                if face > p["max_area"]:
                    p["max_area"], p["hole"] = face, hs_face[int(np.argmax(area[hs_face]))]
                fb = bbox[hs_face]
                p["box"] = np.r_[np.minimum(p["box"][:2], fb[:, :2].min(0)), np.maximum(p["box"][2:], fb[:, 2:].max(0))]
                p["layer_max"], p["volume"] = t, dsu.vol[r]
            pockets, prev_t = now, t
        done += pockets.values()
        return [(SUCTION_CUP, float(p["volume"]), int(p["layer_min"]), int(p["layer_max"]),
                 *self._point(p["hole"], rep, hl), float(p["max_area"]), self._bbox_mm(p["box"])) for p in done]

    def _table(self, rows: list[tuple]) -> Cavities:
        rows = sorted(rows, key=lambda r: (r[2], r[0], r[3], r[4], r[5]))
        col = lambda k, dt: np.array([r[k] for r in rows], dtype=dt)  # noqa: E731
        bbox = np.array([r[8] for r in rows], np.float64).reshape(-1, 4)
        return Cavities(col(0, np.int8), col(1, np.float64), col(2, np.int64), col(3, np.int64), col(4, np.float64),
                        col(5, np.float64), col(6, np.float64), col(7, np.float64), bbox, self.grid_mm)
