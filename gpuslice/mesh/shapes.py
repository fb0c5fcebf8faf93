"""Closed, outward-wound test solids with exactly known sections, and a binary STL writer.

Revolved solids (:func:`revolve`) are made of planar trapezoids between rings of ``n`` vertices, so the section
of a revolved solid at any height is a set of regular n-gons whose circumradius varies linearly between rings:
area ``n/2 · sin(2π/n) · ρ(z)²`` (see :func:`ngon_area`). That makes exact reference areas for tests.

All lengths in mm; every generator returns (F, 3, 3) float64 triangles, counter-clockwise seen from outside.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = [
    "ngon_area",
    "revolve",
    "cylinder",
    "uv_sphere",
    "torus",
    "cone",
    "prism",
    "box",
    "hollow_box",
    "stair",
    "icosphere",
    "orient_outward",
    "write_stl",
    "SHAPES",
]


def ngon_area(n: int, circumradius: float | np.ndarray) -> float | np.ndarray:
    """Area of the regular n-gon with the given circumradius."""
    return 0.5 * n * np.sin(2 * np.pi / n) * np.asarray(circumradius) ** 2


def signed_volume(tri: np.ndarray) -> float:
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def orient_outward(tri: np.ndarray) -> np.ndarray:
    """Reverse every facet if the solid's signed volume is negative (assumes a consistently wound mesh)."""
    return tri[:, ::-1].copy() if signed_volume(tri) < 0 else tri


def revolve(profile: np.ndarray, n: int, *, closed: bool = True) -> np.ndarray:
    """Revolve a polyline of (ρ, z) points about the z axis with ``n`` segments.

    ``closed``: the profile is a closed loop (a torus); otherwise its ends must lie on the axis (ρ = 0), where the
    degenerate triangles are dropped. Every quad between two profile points is a planar trapezoid split in two.
    """
    prof = np.asarray(profile, dtype=np.float64)
    theta = 2 * np.pi * np.arange(n) / n
    c, s = np.cos(theta), np.sin(theta)
    ring = np.stack(
        [prof[:, 0, None] * c[None, :], prof[:, 0, None] * s[None, :], np.repeat(prof[:, 1, None], n, 1)], axis=-1
    )
    m = len(prof)
    pairs = [(i, (i + 1) % m) for i in range(m if closed else m - 1)]
    tris = []
    for i, k in pairs:
        for j in range(n):
            j1 = (j + 1) % n
            a, b, cc, d = ring[i, j], ring[i, j1], ring[k, j1], ring[k, j]
            if prof[i, 0] != 0:
                tris.append((a, b, cc) if prof[k, 0] != 0 else (a, b, d))
            if prof[k, 0] != 0:
                tris.append((a, cc, d))
    return orient_outward(np.array(tris))


def cylinder(radius: float = 10.0, height: float = 20.0, n: int = 64) -> np.ndarray:
    """A faceted cylinder (a regular n-gon prism) standing on z = 0."""
    return revolve([(0, 0), (radius, 0), (radius, height), (0, height)], n, closed=False)


def cone(radius: float = 10.0, height: float = 10.0, n: int = 4) -> np.ndarray:
    """A faceted cone; n = 4 gives a square pyramid with its apex at z = height."""
    return revolve([(0, 0), (radius, 0), (0, height)], n, closed=False)


def uv_sphere(radius: float = 10.0, n_lat: int = 16, n_lon: int = 32) -> np.ndarray:
    """A UV sphere centred at z = radius (resting on z = 0) with rings at polar angles k·π/n_lat."""
    phi = np.pi * np.arange(n_lat + 1) / n_lat
    prof = np.stack([radius * np.sin(phi), radius * (1 - np.cos(phi))], axis=1)
    prof[0, 0] = prof[-1, 0] = 0.0
    return revolve(prof, n_lon, closed=False)


def torus(major: float = 15.0, minor: float = 5.0, n_major: int = 48, n_minor: int = 24) -> np.ndarray:
    """A faceted torus resting on z = 0; ``n_minor`` even, so the outer and inner rings share their heights."""
    if n_minor % 2:
        raise ValueError("n_minor must be even")
    phi = 2 * np.pi * np.arange(n_minor) / n_minor - np.pi / 2
    prof = np.stack([major + minor * np.cos(phi), minor + minor * np.sin(phi)], axis=1)
    prof[np.isclose(prof[:, 1], 0.0), 1] = 0.0
    prof[np.isclose(prof[:, 1], 2 * minor), 1] = 2 * minor
    return revolve(prof, n_major, closed=True)


def prism(polygon: np.ndarray, z0: float, z1: float) -> np.ndarray:
    """Extrude a polygon that is star-shaped from its first vertex (counter-clockwise) from z0 to z1."""
    p = np.asarray(polygon, dtype=np.float64)
    m = len(p)
    bottom = [(p[0], p[k + 1], p[k]) for k in range(1, m - 1)]
    top = [(p[0], p[k], p[k + 1]) for k in range(1, m - 1)]
    tris = [[(*a, z0), (*b, z0), (*c, z0)] for a, b, c in bottom]
    tris += [[(*a, z1), (*b, z1), (*c, z1)] for a, b, c in top]
    for k in range(m):
        a, b = p[k], p[(k + 1) % m]
        tris.append([(*a, z0), (*b, z0), (*b, z1)])
        tris.append([(*a, z0), (*b, z1), (*a, z1)])
    return orient_outward(np.array(tris, dtype=np.float64))


def box(lo=(0.0, 0.0, 0.0), hi=(20.0, 20.0, 20.0)) -> np.ndarray:
    """An axis-aligned box from ``lo`` to ``hi`` (12 facets)."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return prism([(x0, y0), (x1, y0), (x1, y1), (x0, y1)], z0, z1)


def hollow_box(outer: float = 20.0, inner: float = 10.0, core: float | None = None) -> np.ndarray:
    """A cube of side ``outer`` with a closed cubic cavity of side ``inner`` at its centre (inward-facing
    facets); with ``core``, a solid cube of that side floats inside the cavity (a box inside a box)."""
    c = outer / 2
    parts = [box((0, 0, 0), (outer, outer, outer)), box((c - inner / 2,) * 3, (c + inner / 2,) * 3)[:, ::-1]]
    if core is not None:
        parts.append(box((c - core / 2,) * 3, (c + core / 2,) * 3))
    return np.concatenate(parts)


def stair(steps: int = 4, rise: float = 2.0, run: float = 3.0, width: float = 10.0) -> np.ndarray:
    """A staircase: the profile in the x–z plane (steps of ``rise`` up, ``run`` back) extruded along y."""
    pts = [(0.0, 0.0), (steps * run, 0.0)]
    for k in range(steps):
        x = (steps - k) * run
        pts += [(x, (k + 1) * rise), (x - run, (k + 1) * rise)]
    pts = pts[:-1] + [(0.0, steps * rise)]
    tri = prism(pts, 0.0, width)  # x–y profile extruded along z …
    return orient_outward(tri[:, :, [0, 2, 1]])  # … then swap y and z


def icosphere(radius: float = 20.0, subdivisions: int = 4) -> np.ndarray:
    """An icosphere resting on z = 0 (trimesh's construction, subdivided ``subdivisions`` times)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    tri = np.array(m.triangles, dtype=np.float64)
    tri[..., 2] += radius
    return orient_outward(tri)


def write_stl(triangles: np.ndarray, path: str | os.PathLike, header: bytes = b"gpuslice") -> None:
    """Write (F, 3, 3) triangles as a binary STL (normals from the winding), atomically."""
    from ..io.atomic import atomic_path

    tri = np.asarray(triangles, dtype=np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    rec = np.zeros(len(tri), dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]))
    rec["n"], rec["v"] = n, tri
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header[:80].ljust(80, b" "))
        fh.write(np.uint32(len(tri)).tobytes())
        fh.write(rec.tobytes())


SHAPES = {
    "cube": lambda: box(),
    "cylinder": lambda: cylinder(),
    "sphere": lambda: uv_sphere(),
    "torus": lambda: torus(),
    "hollow-box": lambda: hollow_box(),
    "box-in-box": lambda: hollow_box(core=6.0),
    "pyramid": lambda: cone(),
    "stair": lambda: stair(),
    "icosphere": lambda: icosphere(),
}
