"""Fuzz the segment-buffer shortcut of ``--z-samples`` against the polygon path (gpuslice.raster.segment_edges).

The claim under test (the module docstring of :mod:`gpuslice.raster.segment_edges`): where
:func:`~gpuslice.raster.segment_edges.shortcut_refusal` returns None, the runs of the K sub-planes of every layer made
from the crossings' segments (:func:`~gpuslice.raster.segment_edges.iter_sub_plane_edges`, layers with a sub-plane
through a vertex sliced the polygon way and spliced in) equal those of the polygon path (slicing the sub-planes,
chaining, nesting, :func:`~gpuslice.raster.runs.iter_runs` with ``z_samples=K``) byte for byte; and the device's raw
edges equal those of its numpy twin :func:`~gpuslice.raster.segment_edges.segment_edges_numpy`.

Every case is a random closed, consistently wound, outward mesh made of 1-3 disjoint parts side by side:

* ``hull``: the convex hull of random points (scipy), some of whose z are snapped *exactly* onto a sub-plane, a main
  plane or a layer boundary, *near* one (1-3 float32 ulps above or below), or onto another point's z (horizontal
  edges and faces, ridges);
* ``wedge``: the hull of a polygon and a horizontal ridge that overhangs it (or upside down: a keel), the ridge
  snapped exactly or nearly onto a plane (the family of the counterexample already fixed); ``sliver``: a wedge or
  a leaning pyramid whose ridge, keel or apex lies 1-3 (or 4-300) float32 ulps off a sub-plane, alone in a fifth of
  the cases (so what its collapsed sections add is the layer's extreme);
* ``boxes``: boxes and star-shaped prisms, top and bottom sometimes snapped; ``hollow``: a box with a closed cavity
  (sometimes thinner than a layer, sometimes with a floating core); ``torus``: tilted and turned;
  ``plate``: a plate or prism thinner than a layer; ``stair``: a staircase whose treads may lie on planes;

random layer thickness t, K in {2, 3, 4, 8}, a random display (400x300 … 1600x1200, pixel 0.02-0.1 mm, sometimes
mirrored, portrait or non-square pixels, gamma 0 or 1), fixed display bounds with the mesh at a random place inside
(so its pixels move), chunks of 3-7 layers. Each case is sliced with ``slice_mesh(mesh, thickness=t,
backend="opencl")``; refusals are counted by reason; where the shortcut is taken the runs fields ``layer_offsets,
row, x, length, grey`` and the raw edges are compared (as ``_both_paths`` and ``_same_edges`` of
``tests/raster/test_segment_edges.py`` do). Each differing layer is diagnosed: its tiles and edge sets on both paths,
whether it went the polygon way (a sub-plane through a vertex, or where the library reports it, any layer it
chose to slice), and the repairs that slicing its sub-planes counted.
Sub-planes the shortcut takes whose own slice is not segment-exact are counted too, by what slicing them did (the
claim's premise failing, whether or not the runs differ), with the shortest segment of such layers in float32
spacings of its coordinates (how a guard on short segments would have to be set).

``--time-limit`` stops starting cases after that many seconds. Failing cases are written under ``--out`` (default
/tmp/fuzz_z/) as ``s{seed}_c{case}.stl`` with a ``.json`` of their parameters (``--only CASE --seed SEED`` redoes
one). Exit status 1 on any difference, else 0.

    nice -n 19 python scripts/fuzz_z_samples.py --cases 20               # a quick look
    nice -n 19 python scripts/fuzz_z_samples.py --cases 300 --seed 7     # a longer run
    python scripts/fuzz_z_samples.py --only 17 --seed 7 -v               # one case again, verbose
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from gpuslice import mesh_from_triangles, slice_mesh
from gpuslice.mesh import shapes
from gpuslice.raster import RasterSpec
from gpuslice.raster.edges import iter_layer_edges, z_sample_planes
from gpuslice.raster.runs import Runs, iter_runs
from gpuslice.raster.segment_edges import (
    SegmentEdgesKernel,
    iter_sub_plane_edges,
    layers_through_vertices,
    segment_edges_numpy,
    shortcut_refusal,
)
from gpuslice.slicing.crossings import compute_crossings

FIELDS = ("layer_offsets", "row", "x", "length", "grey")
KINDS = ("hull", "hull", "wedge", "boxes", "hollow", "torus", "plate", "stair", "sliver")


# --------------------------------------------------------------------------------------------------- planes


class Planes:
    """The heights (mm, float32 as the crossings cut them) a case's vertices may be snapped onto: its sub-planes,
    main planes and layer boundaries for thickness ``t`` and ``k`` sub-planes, computed as the job computes them."""

    def __init__(self, t: float, k: int, height: float) -> None:
        n = int(np.ceil(height / t)) + 3
        th = np.full(n, t)
        fake = SimpleNamespace(bottom=np.concatenate(([0.0], np.cumsum(th)[:-1])), thickness=th, n_layers=n)
        self.sub = z_sample_planes(fake, k)[0].astype(np.float32)
        # the sub-planes above their layer's main plane: a top there is cut by its layer (a top on a lower one
        # ends the job a layer below, where no plane meets it)
        self.sub_hi = self.sub.reshape(-1, k)[:, (k + 1) // 2 :].reshape(-1)
        self.main = np.concatenate(([t / 2], t + (np.arange(1, n) - 0.5) * t)).astype(np.float32)
        self.bound = fake.bottom[1:].astype(np.float32)
        self.t = t

    def snap(self, rng: np.random.Generator, z: float, mode: str | None = None) -> tuple[float, str]:
        """``z`` moved onto (or 1-3 float32 ulps off) the nearest plane of a random family; (new z, how)."""
        mode = mode or str(rng.choice(["sub", "sub", "sub-hi", "near-sub", "near-sub", "near-sub-hi", "main",
                                       "near-main", "bound"]))
        fam = {"sub": self.sub, "sub-hi": self.sub_hi, "main": self.main, "bound": self.bound}[
            mode.removeprefix("near-").removeprefix("hair-")]
        i = int(np.clip(np.searchsorted(fam, np.float32(z)), 0, fam.size - 1))
        target = fam[i] if i == 0 or abs(fam[i] - z) < abs(fam[i - 1] - z) else fam[i - 1]
        if mode.startswith(("near-", "hair-")):
            ulps = int(rng.integers(1, 4) if mode.startswith("near-") else rng.integers(4, 300))
            ulps *= int(rng.choice([-1, 1]))
            for _ in range(abs(ulps)):
                target = np.nextafter(target, np.float32(np.sign(ulps) * np.inf), dtype=np.float32)
            mode = f"{mode}{ulps:+d}ulp"
        return float(max(target, np.float32(0.0))), mode


# --------------------------------------------------------------------------------------------------- shapes


def _outward(pts: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """Hull facets wound outward (each facet's normal away from the centroid)."""
    tri = pts[simplices].astype(np.float64)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inward = np.einsum("ij,ij->i", normal, tri[:, 0] - pts.mean(0)) < 0
    tri[inward] = tri[inward][:, ::-1]
    return tri


def _hull(pts: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    p = np.asarray(pts, np.float32).astype(np.float64)
    return _outward(p, ConvexHull(p).simplices)


def hull_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list) -> np.ndarray:
    n = int(rng.integers(5, 40))
    p = rng.uniform([0, 0, z0], [size, size * rng.uniform(0.3, 1), z0 + h], (n, 3))
    p[int(rng.integers(n)), 2] = z0  # (the part's bottom: z0 exactly)
    snapped = rng.random(n) < rng.uniform(0.1, 0.6)
    targets: list[float] = []
    for i in np.flatnonzero(snapped):
        if targets and rng.random() < 0.35:  # onto another snapped point's height: a horizontal edge or face
            p[i, 2] = targets[int(rng.integers(len(targets)))]
            notes.append("z=other")
        else:
            p[i, 2], how = pl.snap(rng, p[i, 2])
            targets.append(p[i, 2])
            notes.append(how)
    if rng.random() < 0.3:  # a top apex or ridge exactly at the highest snapped height
        top = np.argsort(p[:, 2])[-int(rng.integers(1, 3)):]
        z, how = pl.snap(rng, p[top, 2].max())
        p[top, 2] = z
        notes.append(f"top:{how}")
    return _hull(p)


def wedge_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list, mode: str | None = None) -> np.ndarray:
    m = int(rng.integers(3, 17))
    a = np.sort(rng.uniform(0, 2 * np.pi, m))
    r = size / 4
    base = np.stack([r * np.cos(a) + size / 2, r * np.sin(a) + size / 2, np.zeros(m)], 1)
    theta, half = rng.uniform(0, np.pi), rng.uniform(0.3, 0.5) * size
    ridge = np.array([[size / 2 - half * np.cos(theta), size / 2 - half * np.sin(theta), 0.0],
                      [size / 2 + half * np.cos(theta), size / 2 + half * np.sin(theta), 0.0]])
    ridge[:, :2] += rng.uniform(-r / 3, r / 3, 2)
    keel = rng.random() < 0.35
    zr, how = pl.snap(rng, z0 + (0 if keel else h) + rng.uniform(-0.5, 0.5) * pl.t,
                      mode or str(rng.choice(["sub", "sub-hi", "near-sub", "near-sub-hi", "main", "near-main"])))
    if keel:  # upside down: the base on top, the ridge below (overhanging)
        base[:, 2] = max(zr, z0) + h
        ridge[:, 2] = zr
    else:
        base[:, 2] = z0
        ridge[:, 2] = max(zr, z0 + pl.t / 4)
    notes.append(("keel:" if keel else "ridge:") + how)
    return _hull(np.concatenate([base, ridge]))


def sliver_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list) -> np.ndarray:
    """A ridge, keel or leaning apex a few float32 ulps off a sub-plane: sections there thinner than float32 can
    hold (loops that collapse to two points, to zero area, cross themselves or turn round)."""
    mode = str(rng.choice(["near-sub", "near-sub-hi", "near-sub-hi", "hair-sub", "hair-sub-hi"]))
    if rng.random() < 0.6:
        return wedge_part(rng, pl, size, z0, h, notes, mode)
    m = int(rng.integers(3, 9))
    a = (np.arange(m) + rng.uniform(0, 0.9, m)) * 2 * np.pi / m
    base = np.stack([size / 2 + size / 4 * np.cos(a), size / 2 + size / 4 * np.sin(a), np.full(m, z0)], 1)
    apex = np.array([[*(size / 2 + rng.uniform(-0.5, 0.5, 2) * size), z0 + h]])  # leaning, often past the base
    down = rng.random() < 0.4
    apex[0, 2], how = pl.snap(rng, (z0 + pl.t if down else apex[0, 2]) + rng.uniform(-0.5, 0.5) * pl.t, mode)
    if down:  # upside down: the base above, the apex below it
        base[:, 2] = apex[0, 2] + h
    notes.append(("apex down:" if down else "apex:") + how)
    return _hull(np.concatenate([base, apex]))


def _star(rng, size: float) -> np.ndarray:
    """A polygon star-shaped from the point (size/2, size/2), counter-clockwise: every angular gap under pi."""
    m = int(rng.integers(4, 12))
    a = (np.arange(m) + rng.uniform(0, 0.9, m)) * 2 * np.pi / m
    r = rng.uniform(0.25, 0.5, m) * size
    return np.stack([size / 2 + r * np.cos(a), size / 2 + r * np.sin(a)], 1)


def _star_prism(poly: np.ndarray, z0: float, z1: float, size: float) -> np.ndarray:
    """:func:`gpuslice.mesh.shapes.prism` with its caps fanned from the star's centre (a vertex of its own), so a
    polygon star-shaped from there but not from its first vertex still makes no overlapping cap facets."""
    c = np.array([size / 2, size / 2])
    m = len(poly)
    tris = []
    for i in range(m):
        a, b = poly[i], poly[(i + 1) % m]
        tris += [[(*c, z0), (*b, z0), (*a, z0)], [(*c, z1), (*a, z1), (*b, z1)]]
        tris += [[(*a, z0), (*b, z0), (*b, z1)], [(*a, z0), (*b, z1), (*a, z1)]]
    return shapes.orient_outward(np.array(tris, np.float64))


def _zpair(rng, pl: Planes, z0: float, h: float, notes: list) -> tuple[float, float]:
    lo, hi = z0, z0 + h
    if rng.random() < 0.5 and lo > 0:
        lo, how = pl.snap(rng, lo)
        notes.append(f"bottom:{how}")
    if rng.random() < 0.6:
        hi, how = pl.snap(rng, hi)
        notes.append(f"top:{how}")
    return lo, max(hi, lo + pl.t / 8)


def boxes_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list) -> np.ndarray:
    lo, hi = _zpair(rng, pl, z0, h, notes)
    if rng.random() < 0.5:
        x0, y0 = rng.uniform(0, size / 4, 2)
        return shapes.box((x0, y0, lo), (size - x0, size * rng.uniform(0.4, 1), hi))
    return _star_prism(_star(rng, size), lo, hi, size)


def hollow_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list) -> np.ndarray:
    lo, hi = _zpair(rng, pl, z0, max(h, 3 * pl.t), notes)
    c0 = rng.uniform(0.15, 0.35, 2) * size
    c1 = rng.uniform(0.65, 0.85, 2) * size
    if rng.random() < 0.5:  # a cavity thinner than a layer, somewhere between the planes
        cz0 = rng.uniform(lo + (hi - lo) * 0.2, lo + (hi - lo) * 0.6)
        cz1 = cz0 + rng.uniform(0.05, 0.95) * pl.t
        notes.append("thin cavity")
    else:
        cz0, cz1 = lo + (hi - lo) * 0.2, lo + (hi - lo) * 0.8
    if rng.random() < 0.4:
        cz1, how = pl.snap(rng, cz1)
        notes.append(f"cavity top:{how}")
    cz1 = max(cz1, cz0 + pl.t / 16)
    parts = [shapes.box((0, 0, lo), (size, size, hi)), shapes.box((*c0, cz0), (*c1, cz1))[:, ::-1]]
    if rng.random() < 0.3 and cz1 - cz0 > pl.t / 4:  # a core floating in the cavity
        m = (c1 - c0) * 0.25
        d = (cz1 - cz0) * 0.25
        parts.append(shapes.box((*(c0 + m), cz0 + d), (*(c1 - m), cz1 - d)))
        notes.append("core")
    return np.concatenate(parts)


def torus_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    minor = rng.uniform(0.08, 0.2) * size
    tri = shapes.torus(size / 2 - minor, minor, int(rng.integers(8, 40)), 2 * int(rng.integers(3, 12)))
    rot = Rotation.from_euler("xz", [rng.uniform(0, 0.4) if rng.random() < 0.6 else 0.0, rng.uniform(0, 6.3)])
    tri = rot.apply(tri.reshape(-1, 3)).reshape(-1, 3, 3)
    tri -= tri.reshape(-1, 3).min(0)
    tri[..., 2] += z0
    notes.append("torus")
    return tri


def plate_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list) -> np.ndarray:
    th = rng.uniform(0.05, 0.95) * pl.t
    lo = z0 + rng.uniform(0, 3) * pl.t
    if rng.random() < 0.4:
        lo, how = pl.snap(rng, lo)
        notes.append(f"plate bottom:{how}")
    notes.append(f"plate {th / pl.t:.2f}t")
    if rng.random() < 0.5:
        return shapes.box((0, 0, lo), (size, size * rng.uniform(0.2, 1), lo + th))
    return _star_prism(_star(rng, size), lo, lo + th, size)


def stair_part(rng, pl: Planes, size: float, z0: float, h: float, notes: list) -> np.ndarray:
    steps = int(rng.integers(2, 6))
    rise = h / steps
    if rng.random() < 0.6:  # the first tread on a sub-plane
        rise = float(pl.sub[int(rng.integers(1, 2 * len(pl.sub) // 3 // steps + 2))])
        notes.append("stair: first tread on a sub-plane")
    tri = shapes.stair(steps, rise, size / steps / 1.5, size * rng.uniform(0.3, 1))
    tri[..., 2] += z0
    return tri


BUILDERS = {"hull": hull_part, "wedge": wedge_part, "boxes": boxes_part, "hollow": hollow_part,
            "torus": torus_part, "plate": plate_part, "stair": stair_part, "sliver": sliver_part}


# --------------------------------------------------------------------------------------------------- a case


@dataclass
class Case:
    index: int
    tri: np.ndarray
    t: float
    k: int
    spec: RasterSpec
    bounds: tuple[float, float, float, float]
    chunk: int
    kinds: list[str]
    notes: list[str] = field(default_factory=list)

    def params(self) -> dict:
        s = self.spec
        return {"case": self.index, "t": self.t, "k": self.k, "chunk": self.chunk, "bounds": list(self.bounds),
                "resolution": list(s.resolution), "pixel": s.pixel, "pixel_y": s.pixel_y, "mirror_x": s.mirror_x,
                "mirror_y": s.mirror_y, "portrait": s.portrait, "gamma": s.gamma, "kinds": self.kinds,
                "notes": self.notes}


def make_case(seed: int, index: int) -> Case:
    """Case ``index`` of ``seed`` (its own generator: any case can be redone alone)."""
    rng = np.random.default_rng([seed, index])
    k = int(rng.choice([2, 3, 4, 8]))
    t = float(rng.choice([0.01, 0.02, 0.025, 0.03, 0.05, 0.1, 0.2, 0.3])) if rng.random() < 0.5 else \
        float(rng.uniform(0.01, 0.3))
    nx, ny = int(rng.integers(400, 1601)), int(rng.integers(300, 1201))
    px = float(rng.uniform(0.02, 0.1))
    py = float(rng.uniform(0.02, 0.1)) if rng.random() < 0.15 else None
    spec = RasterSpec(resolution=(nx, ny), pixel=px, pixel_y=py, mirror_x=bool(rng.random() < 0.3),
                      mirror_y=bool(rng.random() < 0.3), portrait=bool(rng.random() < 0.25),
                      gamma=float(rng.choice([0.0, 1.0])))
    usable = min(nx * px, ny * (py or px))  # mm along both axes, whichever way the display is turned
    alone = rng.random() < 0.2  # one sliver alone: its collapsed loops are the layer's extremes
    n_parts = 1 if alone else int(rng.integers(1, 4))
    cell = usable / (n_parts + 0.5)
    size = min(cell * 0.9, max(px, py or px) * float(rng.uniform(15, 250)))  # at most ~250 pixels across
    layers = float(rng.uniform(2, 40))
    height = layers * t
    pl = Planes(t, k, height * 3 + 3 * t)
    kinds, notes, parts = [], [], []
    for j in range(n_parts):
        kind = "sliver" if alone else str(rng.choice(KINDS))
        z0 = 0.0 if j == 0 else float(rng.choice([0.0, rng.uniform(0, height)]))
        tri = BUILDERS[kind](rng, pl, size, z0, height * rng.uniform(0.3, 1.0), notes)
        tri = np.array(tri, np.float64)
        tri[..., 0] += j * cell
        parts.append(tri)
        kinds.append(kind)
    if min(float(p[..., 2].min()) for p in parts) > 0:  # nothing on the bed: a foot there (no shift, which would
        f = cell * 0.3  # move the snapped heights off their planes)
        parts.append(shapes.box((n_parts * cell, 0.0, 0.0), (n_parts * cell + f, f, height / 2)))
        notes.append("foot")
    tri = np.concatenate(parts)
    # fixed display bounds (what is centred), the mesh somewhere inside, sometimes over an edge
    w, h = usable * 0.95, usable * 0.95
    bounds = (-w / 2, -h / 2, w / 2, h / 2)
    ext = tri[..., :2].reshape(-1, 2).max(0) - tri[..., :2].reshape(-1, 2).min(0)
    slack = np.maximum(np.array([w, h]) - ext, 0.0)
    off = np.array(bounds[:2]) + rng.uniform(0, 1, 2) * slack - tri[..., :2].reshape(-1, 2).min(0)
    if rng.random() < 0.1:
        off += rng.uniform(-0.3, 0.3, 2) * usable  # over the display's edge: clipped rows and columns
        notes.append("over the edge")
    tri[..., :2] += off
    tri = tri.astype(np.float32).astype(np.float64)
    return Case(index, tri, t, k, spec, bounds, int(rng.integers(3, 8)), kinds, notes)


# --------------------------------------------------------------------------------------------------- compare


def _cat_edges(chunks, n: int):
    """Per layer (edges sorted, tile) from (first, LayerEdges) chunks."""
    out: list = [None] * n
    for a, le in chunks:
        for i in range(len(le.tiles)):
            e = np.asarray(le.edges[le.edge_offsets[i] : le.edge_offsets[i + 1]], np.float32)
            if a + i < n:
                out[a + i] = (e[np.lexsort(e.T)], np.asarray(le.tiles[i]))
    return out


def _shortest_segments(seg, n: int, k: int) -> np.ndarray:
    """(n,) per layer: the length of its sub-planes' shortest segment in float32 spacings of its larger coordinate
    (0: a zero-length segment; inf: no segment)."""
    p = np.asarray(seg.points, np.float32)
    length = np.hypot(p[:, 2].astype(np.float64) - p[:, 0], p[:, 3].astype(np.float64) - p[:, 1])
    ulp = np.spacing(np.abs(p).max(axis=1)).astype(np.float64)
    out = np.full(n, np.inf)
    np.minimum.at(out, np.asarray(seg.layer, np.int64) // k, length / ulp)
    return out


def _inexact_kinds(sub, k: int, i: int) -> list[str]:
    """What slicing layer ``i``'s sub-planes repaired or turned round ('reoriented': exact by the repair counts,
    not by :attr:`SliceResult.segment_exact`)."""
    kinds = [key for key, v in sub.repairs.items() if np.asarray(v).reshape(-1, k)[i].any()]
    if not kinds and not np.asarray(sub.segment_exact, bool).reshape(-1, k)[i].all():
        kinds = ["reoriented"]
    return kinds


def _layer_runs(r: Runs, i: int):
    lo, hi = int(r.layer_offsets[i]), int(r.layer_offsets[i + 1])
    return tuple(getattr(r, f)[lo:hi] for f in ("row", "x", "length", "grey"))


def run_case(case: Case, device, verbose: bool = False) -> dict:
    """The case's outcome: {"refusal": reason} or {"taken": True, "diffs": [...], ...}."""
    mesh = mesh_from_triangles(case.tri)
    want_z = np.unique(case.tri[..., 2].astype(np.float32))
    if not np.array_equal(np.unique(mesh.vertices[:, 2]), want_z):
        case.notes.append("placement moved z")
    res = slice_mesh(mesh, thickness=case.t, backend="opencl")
    refusal = shortcut_refusal(mesh, res, "nonzero", case.spec, case.bounds)
    if refusal is not None:
        return {"refusal": refusal, "layers": res.n_layers}
    spec, bounds, k = case.spec, case.bounds, case.k
    z, th = z_sample_planes(res, k)
    sub = slice_mesh(mesh, z=z, layer_thickness=th, backend="opencl")
    poly = Runs.concat(list(iter_runs(sub, spec, device=device, bounds=bounds, z_samples=k, clip=True)), spec.shape)

    def cut(sel):
        return slice_mesh(mesh, z=z[sel], layer_thickness=th[sel], backend="opencl")

    parts, merged = [], []
    polygon_way = layers_through_vertices(mesh, z, k)  # (and, where the library reports them, its other choices)
    for item in iter_sub_plane_edges(mesh, z, k, spec, bounds, device, cut, case.chunk):
        a, le = item[0], item[1]
        if len(item) > 2:  # (first, edges, the layers cut the polygon way): the API with the short-segment guard
            polygon_way[np.asarray(item[2], np.int64)] = True
        merged.append((a, le))
        for r in iter_runs(None, spec, device=device, bounds=bounds, z_samples=k, merged=le):
            parts.append(Runs(r.layers + a, r.layer_offsets, r.row, r.x, r.length, r.grey, r.shape))
    got = Runs.concat(parts, spec.shape)
    seg = compute_crossings(mesh, z, device, read_back=False)
    raw = SegmentEdgesKernel.of(device)(seg, z.size, k, spec, bounds)
    twin = segment_edges_numpy(seg.fetch(), z.size, k, spec, bounds)
    flags_differ = None
    if isinstance(raw, tuple):  # (edges, the layers the kernel marks for the polygon way: short segments)
        (raw, raw_flags), (twin, twin_flags) = raw, twin
        flags_differ = np.flatnonzero(np.asarray(raw_flags) != np.asarray(twin_flags))

    n = res.n_layers
    through = polygon_way
    sub_exact = np.asarray(sub.segment_exact, bool).reshape(-1, k).all(axis=1)
    inexact = ~sub_exact & ~through
    short = _shortest_segments(seg.fetch(), n, k)
    kinds_of = lambda i: _inexact_kinds(sub, k, i)  # noqa: E731
    out = {"taken": True, "layers": n, "runs": int(poly.row.size), "polygon_way": int(through.sum()),
           "inexact_taken": int(inexact.sum()), "diffs": [], "causes": [],
           "inexact_kinds": sorted({c for i in np.flatnonzero(inexact) for c in kinds_of(i)}),
           # the shortest segment (float32 ulps of its coordinates) of the layers taken from segments: the inexact
           # ones' largest, and how many exact ones have one of 0-1, 2-4, 5-63 ulps
           "short_inexact": float(short[inexact].max()) if inexact.any() else None,
           "short_exact": np.histogram(short[~inexact & ~through], [0, 1.5, 4.5, 64])[0]}
    # runs: every field, then layer by layer
    fields = [f for f in FIELDS if not np.array_equal(getattr(poly, f), getattr(got, f))]
    if fields or not np.array_equal(poly.layers, got.layers):
        pe = _cat_edges(iter_layer_edges(sub, spec, bounds, k=k, dtype=np.float32), n)
        ge = _cat_edges(merged, n)
        bad = [i for i in range(min(len(poly.layers), len(got.layers)))
               if any(not np.array_equal(x, y) for x, y in zip(_layer_runs(poly, i), _layer_runs(got, i), strict=True))]
        for i in bad[:6]:
            (pe_e, pe_t), (ge_e, ge_t) = pe[i], ge[i]
            pr, gr = _layer_runs(poly, i), _layer_runs(got, i)
            rows = np.union1d(pr[0], gr[0])
            nrep = {key: int(np.asarray(v).reshape(-1, k)[i].sum()) for key, v in sub.repairs.items()
                    if np.asarray(v).reshape(-1, k)[i].sum()}
            same_set = pe_e.shape == ge_e.shape and np.array_equal(pe_e, ge_e)
            nonzero = ge_e[~((ge_e[:, 0] == ge_e[:, 2]) & (ge_e[:, 1] == ge_e[:, 3]))]
            same_nz = pe_e.shape == nonzero.shape and np.array_equal(pe_e, nonzero)
            out["diffs"].append(
                f"layer {i} (z {res.z[i]:.6g}, sub-planes {np.float32(z[i * k]):.9g}.."
                f"{np.float32(z[i * k + k - 1]):.9g})"
                f": runs {len(pr[0])} vs {len(gr[0])} rows {rows.min() if rows.size else '-'}.."
                f"{rows.max() if rows.size else '-'}; tile poly {pe_t.tolist()} shortcut {ge_t.tolist()}; "
                f"edges poly {len(pe_e)} shortcut {len(ge_e)} (same set: {same_set}, without zero-length: "
                f"{same_nz}); cut the polygon way {bool(through[i])}; sub-plane repairs {nrep or '-'}; "
                f"sub-planes exact {bool(sub_exact[i])}; shortest segment {short[i]:.3g} ulps")
            out["causes"].append("+".join(kinds_of(i) + (["tile"] if not np.array_equal(pe_t, ge_t) else [])))
        if len(bad) > 6:
            out["diffs"].append(f"... {len(bad)} layers in all")
        if not bad:
            out["diffs"].append(f"runs fields {fields} differ (layers {len(poly.layers)} vs {len(got.layers)})")
    # raw edges: kernel and twin
    if flags_differ is not None and flags_differ.size:
        out["diffs"].append(f"raw edges: the kernel's and the twin's short-segment layers differ "
                            f"(layers {flags_differ[:6].tolist()})")
    if not (np.array_equal(raw.tiles, twin.tiles) and np.array_equal(raw.edge_offsets, twin.edge_offsets)):
        g = np.flatnonzero((raw.tiles != twin.tiles).any(1))
        out["diffs"].append(f"raw edges: tiles or offsets differ (layers {g[:6].tolist()})")
    else:
        for g in range(len(raw.tiles)):
            x, y = (e[raw.edge_offsets[g] : raw.edge_offsets[g + 1]] for e in (raw.edges, twin.edges))
            if not np.array_equal(x[np.lexsort(x.T)], y[np.lexsort(y.T)]):
                out["diffs"].append(f"raw edges: layer {g} differs from the twin's")
                break
    if verbose and out["inexact_taken"]:
        bad = np.flatnonzero(~sub_exact & ~through)
        out["inexact_layers"] = bad[:10].tolist()
    return out


# --------------------------------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=200, help="number of random cases (default 200)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--start", type=int, default=0, help="first case index (default 0)")
    ap.add_argument("--only", type=int, action="append", help="run only these case indices (repeatable)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/fuzz_z"), help="where failing cases go")
    ap.add_argument("--keep", type=int, default=10, help="failing cases written at most (default 10)")
    ap.add_argument("--time-limit", type=float, default=None, help="stop starting cases after this many s")
    ap.add_argument("-v", "--verbose", action="store_true", help="one line per case")
    args = ap.parse_args(argv)

    from gpuslice.device import get_device

    device = get_device()
    indices = args.only or list(range(args.start, args.start + args.cases))
    t0 = time.perf_counter()
    refusals: Counter[str] = Counter()
    kinds_taken: Counter[str] = Counter()
    taken = failing = errors = kept = done = inexact_cases = through_cases = 0
    causes: Counter[str] = Counter()
    inexact_kinds: Counter[str] = Counter()
    short_inexact, short_exact = [], np.zeros(3, np.int64)
    for idx in indices:
        if args.time_limit and time.perf_counter() - t0 > args.time_limit:
            print(f"time limit: stopped before case {idx}")
            break
        case = make_case(args.seed, idx)
        try:
            r = run_case(case, device, args.verbose)
        except Exception as exc:  # noqa: BLE001 - a crash is a finding too
            errors += 1
            r = {"error": f"{type(exc).__name__}: {exc}"}
            if args.verbose:
                traceback.print_exc()
        done += 1
        desc = f"seed {args.seed} case {idx} [{'+'.join(case.kinds)}; t {case.t:.4g} K {case.k} " \
               f"{case.spec.nx}x{case.spec.ny} px {case.spec.pixel:.3g} chunk {case.chunk}]"
        if "refusal" in r:
            refusals[r["refusal"]] += 1
            if args.verbose:
                print(f"{desc}: refused ({r['refusal']})")
            continue
        if "error" in r:
            print(f"ERROR {desc}: {r['error']}")
        else:
            taken += 1
            kinds_taken.update(case.kinds)
            inexact_cases += r["inexact_taken"] > 0
            inexact_kinds.update(r["inexact_kinds"])
            causes.update(r["causes"])
            short_exact += r["short_exact"]
            if r["short_inexact"] is not None:
                short_inexact.append(r["short_inexact"])
            through_cases += r["polygon_way"] > 0
            if args.verbose:
                print(f"{desc}: taken, {r['layers']} layers, {r['runs']} runs, {r['polygon_way']} cut the polygon "
                      f"way, {r['inexact_taken']} inexact sub-plane layers taken "
                      f"{r.get('inexact_layers', '')}; notes {case.notes}")
        if r.get("diffs") or "error" in r:
            failing += "error" not in r
            for d in r.get("diffs", []):
                print(f"DIFF {desc}: {d}")
            if r.get("diffs"):
                print(f"     notes: {case.notes}")
            if kept < args.keep:
                args.out.mkdir(parents=True, exist_ok=True)
                stem = args.out / f"s{args.seed}_c{idx}"
                shapes.write_stl(case.tri, stem.with_suffix(".stl"))
                record = {**case.params(), **r, "seed": args.seed}
                text = json.dumps(record, indent=1, default=lambda o: np.asarray(o).tolist())
                stem.with_suffix(".json").write_text(text)
                kept += 1
    wall = time.perf_counter() - t0
    print(f"\n{done} cases in {wall:.0f} s (seed {args.seed}): shortcut taken in {taken} "
          f"({dict(kinds_taken)} parts), refused in {sum(refusals.values())}, errors {errors}, "
          f"differing {failing}; taken cases with a layer cut the polygon way: {through_cases}; "
          f"taken cases with a non-exact sub-plane taken from segments: {inexact_cases}")
    for reason, n in refusals.most_common():
        print(f"  refused {n:4d}: {reason}")
    print(f"  non-exact sub-plane layers taken from segments, by what slicing them did (cases): {dict(inexact_kinds)}")
    print(f"  their shortest segment: at most {max(short_inexact, default=float('nan')):.3g} float32 ulps; exact "
          f"layers taken from segments whose shortest is 0-1, 2-4, 5-63 ulps: {short_exact.tolist()}")
    print(f"  differing layers by cause: {dict(causes)}")
    if failing or errors:
        print(f"failing cases written under {args.out} (at most {args.keep})")
    return 1 if failing or errors else 0


if __name__ == "__main__":
    sys.exit(main())
