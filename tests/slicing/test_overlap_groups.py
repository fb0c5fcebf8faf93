"""Nesting's exact rebuild of loops that cross (``overlaps.resolve_overlaps``): only the group of loops around a
crossing one is rebuilt, the rest of the layer keeps its fast result, and every layer's area is the nonzero area of
the arrangement of all its loops (built here with shapely, apart from the code under test)."""

from __future__ import annotations

import numpy as np
import shapely

from gpuslice.slicing.chain import Loops
from gpuslice.slicing.nest import nest_loops
from gpuslice.slicing.rings import _winding_numbers


def make_loops(layers: list[list[np.ndarray]]) -> Loops:
    pts, off, lay = [], [0], []
    for k, rings in enumerate(layers):
        for r in rings:
            pts.append(np.asarray(r, np.float32))
            off.append(off[-1] + len(r))
            lay.append(k)
    return Loops(np.concatenate(pts), np.array(off, np.int64), np.array(lay, np.int32), np.ones(len(lay), bool))


def truth_area(loops: Loops, k: int) -> float:
    """Nonzero-filled area of layer ``k``: the faces of all its loops' noded boundaries, each kept when the sum of
    the loops' winding numbers at a point inside it is not 0."""
    ids = np.flatnonzero(loops.layer == k)
    rings = [loops.points[loops.offsets[i] : loops.offsets[i + 1]].astype(float) for i in ids]
    lines = shapely.multilinestrings([shapely.linestrings(np.vstack([r, r[:1]])) for r in rings])
    faces = shapely.get_parts(shapely.polygonize(shapely.get_parts(shapely.node(lines))))
    reps = shapely.point_on_surface(faces)
    q = shapely.get_x(reps) + 1j * shapely.get_y(reps)
    pc = loops.points.astype(np.float64).view(np.complex128).reshape(-1)
    pi, pj = np.repeat(np.arange(faces.size), ids.size), np.tile(ids, faces.size)
    w = np.bincount(pi, weights=_winding_numbers(pc, loops.offsets, pi, pj, q), minlength=faces.size)
    return float(shapely.area(faces[np.rint(w) != 0]).sum())


def square(x0, y0, s, ccw=True):
    r = np.array([[x0, y0], [x0 + s, y0], [x0 + s, y0 + s], [x0, y0 + s]], float)
    return r if ccw else r[::-1]


def bowtie(x0, y0, s):
    """A loop that crosses itself once (two lobes of opposite orientation)."""
    return np.array([[x0, y0], [x0 + s, y0 + s], [x0 + s, y0], [x0, y0 + s]], float)


def twice_around(x0, y0):
    """A loop that passes through one of its own points (GEOS: ring self-intersection) and winds twice around a
    part of its inside: its signed area counts that part twice."""
    return np.array([[x0, y0], [x0 + 10, y0], [x0 + 10, y0 + 10], [x0, y0 + 10], [x0, y0],
                     [x0 + 2, y0 + 2], [x0 + 6, y0 + 2], [x0 + 6, y0 + 6], [x0 + 2, y0 + 6]], float)


def test_a_plate_keeps_its_other_parts():
    """A bow-tie beside two plain squares (one with a hole): only the bow-tie is rebuilt; the squares keep their
    points exactly; the area is the arrangement's."""
    far = [square(100, 0, 10), square(103, 3, 4, ccw=False), square(200, 0, 10)]
    loops = make_loops([[bowtie(0, 0, 10), *far]])
    nd = nest_loops(loops, 1)
    assert nd.overlaps_resolved[0] == 1
    assert abs(nd.area[0] - truth_area(loops, 0)) < 1e-9
    assert abs(nd.area[0] - (50.0 + 100.0 - 16.0 + 100.0)) < 1e-9
    plain = nest_loops(make_loops([far]), 1)  # the same squares alone: no rebuild
    kept = [nd.points[nd.loop_offsets[i] : nd.loop_offsets[i + 1]] for i in range(len(nd.loop_layer))]
    for i in range(len(plain.loop_layer)):
        ring = plain.points[plain.loop_offsets[i] : plain.loop_offsets[i + 1]]
        assert any(r.shape == ring.shape and np.array_equal(r, ring) for r in kept)  # kept as the fast path had it


def test_a_loop_through_its_own_point_is_rebuilt():
    """Alone in its layer (nothing else makes the layer suspect), a loop winding twice around part of its inside
    fills 100 mm², not its signed area's 116."""
    loops = make_loops([[twice_around(0, 0)]])
    nd = nest_loops(loops, 1)
    assert abs(truth_area(loops, 0) - 100.0) < 1e-9
    assert nd.overlaps_resolved[0] == 1 and abs(nd.area[0] - 100.0) < 1e-9


def test_a_loop_inside_another_touching_its_boundary():
    """A square inside another whose first edge lies on the outer one's boundary (its query point is on it, so
    the point-in-polygon test says outside): both wind the same way, so the inner one bounds nothing more."""
    outer = square(0, 0, 10)
    inner = np.array([[0, 0], [4, 0], [4, 4], [0, 4]], float)  # shares the corner and two edges' parts
    loops = make_loops([[outer, inner]])
    nd = nest_loops(loops, 1)
    assert abs(truth_area(loops, 0) - 100.0) < 1e-9
    assert abs(nd.area[0] - 100.0) < 1e-9


def test_groups_grow_by_the_hull_of_crossing_loops():
    """Two bow-ties far apart and a square between them whose box meets neither's: one layer, two groups rebuilt,
    the square kept; plus a square around a bow-tie (its box holds it): rebuilt with it (the bow-tie's lobe that
    winds the other way cuts a 25 mm² hole in it)."""
    loops = make_loops([[bowtie(0, 0, 10), square(50, 0, 5), bowtie(100, 0, 10)],
                        [square(-5, -5, 30), bowtie(0, 0, 10), square(60, 0, 5)]])
    nd = nest_loops(loops, 2)
    for k in range(2):
        assert abs(nd.area[k] - truth_area(loops, k)) < 1e-9
    assert abs(nd.area[0] - (50 + 25 + 50)) < 1e-9 and abs(nd.area[1] - (900 - 25 + 25)) < 1e-9
