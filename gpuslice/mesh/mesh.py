"""Stage 1: the mesh. Raw triangles in, a welded, placed mesh with vertex and edge ids out.

Loading (``stl.py`` reads the file) is followed by, in this order:

1. **Weld**: corners with bit-identical float32 coordinates as stored (after turning -0.0 into 0.0) become one
   vertex. No tolerance is used: nearby but distinct vertices stay distinct, so cracks stay visible as open chains.
   Vertex ids are numbered by first occurrence, so the same file always gives the same ids.
2. **Transform** the unique vertices in float64: ``scale`` (a factor) or ``fit`` (scale so the longest
   bounding-box side is ``fit`` mm), then a translation so the lowest point is at z = 0 (the bed); X and Y are
   kept. Coordinates are then rounded to float32.
3. **Degenerate facets**, whose corners weld to fewer than three distinct vertices, are dropped and counted.
4. **Edges**: side k of facet f runs from corner k to corner (k + 1) % 3; each undirected vertex pair gets one edge
   id (numbered by first occurrence), stored in ``face_edges`` (F, 3). The same pass pairs the sides along each
   edge (``Mesh.edge_sides``: count, first and last side, forward sides), kept for the mesh check (``defects.py``).

With a ``device`` (meshes above :data:`DEVICE_WELD_MIN_FACETS` facets) steps 1 and 4 run on it (``weld.py``,
``kernels/weld.cl``), with the same ids; the mesh remembers the device (``Mesh.device``) for its mesh check.

Normals are computed from the winding (the paper's eq. 1, then normalised to unit length); stored normals are only
compared with them (``stored_normal_mismatch``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import EmptyMeshError, InvalidGeometryError, ParameterError
from ..options import check_flag, is_finite, option, shown
from .sources import _arrays, real_array
from .weld import EdgeSides, WeldKernel, edge_table_numpy, weld_numpy

__all__ = ["Mesh", "Placement", "load_mesh", "mesh_from_triangles", "mesh_from_arrays"]

#: below this many facets the numpy weld is faster than a kernel launch round trip
DEVICE_WELD_MIN_FACETS = 20_000
#: X/Y beyond this (mm) are "far from the origin": float32 coordinates there lie 2^-11 mm (0.49 µm) or more apart,
#: so the crossings lose precision the model had (a float64 source) or need not lose (a resin job centres the part)
FAR_XY_MM = 4096.0


@dataclass
class Mesh:
    """A welded triangle mesh placed on the bed, in mm.

    Attributes
    ----------
    vertices : (V, 3) float32
        Unique vertex positions, mm; the lowest z is 0.
    faces : (F, 3) int32
        Vertex ids of each facet's corners, in the file's winding order (counter-clockwise seen from outside).
    face_edges : (F, 3) int32
        Undirected edge id of each facet side; side k joins corners k and (k + 1) % 3.
    edge_vertices : (E, 2) int32
        The two vertex ids of each edge, smaller first.
    stored_normals : (F, 3) float32 or None
        Normals as stored in the file, for the kept facets.

    Normals, the edge pairing and the mesh check's counts are computed once per mesh and kept: change a mesh by
    making another (``dataclasses.replace(mesh, vertices=...)`` starts with nothing kept), not by editing its arrays
    in place.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_edges: np.ndarray
    edge_vertices: np.ndarray
    stored_normals: np.ndarray | None = None
    name: str = "<mesh>"
    source_format: str = "arrays"
    scale: float = 1.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    dropped_degenerate: int = 0
    solids: int = 1
    #: normals, edge sides, mesh-check counts and the device, computed once for these arrays: not an argument, so a
    #: copy made by ``dataclasses.replace(mesh, vertices=...)`` starts with its own (it used to share this dict)
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def height(self) -> float:
        """Height of the mesh above the bed, mm (its top z)."""
        return float(self.vertices[:, 2].max()) if self.vertices.size else 0.0

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: bounding-box minimum and maximum, mm (per-column reductions: fast)."""
        v = self.vertices
        return np.array([[v[:, k].min() for k in range(3)], [v[:, k].max() for k in range(3)]], dtype=np.float64)

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) float32 corner coordinates."""
        return self.vertices[self.faces]

    def face_normals(self) -> np.ndarray:
        """(F, 3) float32 unit normals from the winding: ``(p2 - p1) × (p3 - p1)``, normalised (0 if degenerate)."""
        if "normals" not in self._cache:
            t = self.triangles.astype(np.float64)
            n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
            length = np.sqrt(np.einsum("ij,ij->i", n, n))
            with np.errstate(invalid="ignore", divide="ignore"):
                n = np.where(length[:, None] > 0, n / length[:, None], 0.0)
            self._cache["normals"] = n.astype(np.float32)
        return self._cache["normals"]

    def edge_face_counts(self) -> np.ndarray:
        """(E,) int32: how many facets use each edge (2 on a closed manifold)."""
        return self.edge_sides().count

    def edge_sides(self) -> EdgeSides:
        """Each edge's number of facet sides, first and last side (3f + k): kept from the edge numbering when the
        mesh was built here, else computed once from ``face_edges``."""
        if "edge_sides" not in self._cache:
            e = self.face_edges.reshape(-1)
            n_e = self.edge_vertices.shape[0]
            side = np.arange(e.size, dtype=np.int32)
            first = np.empty(n_e, dtype=np.int32)
            last = np.empty(n_e, dtype=np.int32)
            first[e[::-1]] = side[::-1]  # the last write wins: the smallest side
            last[e] = side
            count = np.bincount(e, minlength=n_e).astype(np.int32)
            f = self.faces
            fw = (f < np.roll(f, -1, axis=1)).reshape(-1)  # the side runs from the smaller vertex id to the larger
            forward = np.bincount(e[fw], minlength=n_e).astype(np.int32)
            self._cache["edge_sides"] = EdgeSides(count, first, last, forward)
        return self._cache["edge_sides"]

    @property
    def device(self):
        """The OpenCL device the mesh was welded on (its mesh check runs there too), or None."""
        return self._cache.get("device")

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_cache"] = {k: v for k, v in self._cache.items() if k != "device"}  # a device does not pickle
        return state

    def info(self) -> dict:
        """Summary figures: facets, vertices, distinct normals, bbox, watertight, bodies, volume (mm, mm^3).

        ``signed_volume`` is the facets' signed sum (negative for a closed mesh turned inside out, meaningless for an
        open or inconsistently wound one); ``volume`` is its size where the mesh is closed and consistently wound,
        None elsewhere (the slices' ``SliceResult.volume`` is then what prints); ``inside_out``: closed, consistent
        and wound with its normals inwards (sliced as the solid it bounds all the same)."""
        counts = self.edge_face_counts()
        normals = self.face_normals()
        distinct_normals = int(np.unique(normals.view(np.dtype((np.void, 12))).reshape(-1)).size) if len(
            normals
        ) else 0
        directed_ok = _directed_edges_paired(self)
        t = self.triangles.astype(np.float64)
        signed = float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)
        closed = bool(counts.size > 0 and np.all(counts == 2))
        mismatch = None
        if self.stored_normals is not None:
            mismatch = int(stored_normal_mismatch(self.stored_normals, normals).sum())
        b = self.bounds
        return {
            "file": self.name,
            "format": self.source_format,
            "facets": self.n_faces,
            "vertices": int(self.vertices.shape[0]),
            "edges": int(self.edge_vertices.shape[0]),
            "distinct_normals": distinct_normals,
            "bbox_min": b[0].tolist(),
            "bbox_max": b[1].tolist(),
            "size": (b[1] - b[0]).tolist(),
            "scale": self.scale,
            "watertight": closed,
            "winding_consistent": directed_ok,
            "boundary_edges": int(np.sum(counts == 1)),
            "nonmanifold_edges": int(np.sum(counts > 2)),
            "bodies": count_bodies(self),
            "volume": abs(signed) if closed and directed_ok else None,
            "signed_volume": signed,
            "inside_out": bool(closed and directed_ok and signed < 0),
            "degenerate_dropped": self.dropped_degenerate,
            "stored_normal_mismatch": mismatch,
            "solids": self.solids,
        }


def need_mesh(mesh: object, fn: str) -> None:
    """A one-line :class:`ParameterError` when ``mesh`` handed to ``fn`` is not a loaded :class:`Mesh` (a path, a
    Trimesh ...)."""
    if not isinstance(mesh, Mesh):
        raise ParameterError(f"{fn} takes a gpuslice Mesh (gpuslice.load_mesh(source) first), got "
                             f"{type(mesh).__name__}")


def stored_normal_mismatch(stored: np.ndarray, computed: np.ndarray) -> np.ndarray:
    """(F,) bool: stored normals that are missing (zero, NaN, inf) or more than 45° away from the winding's."""
    with np.errstate(invalid="ignore", over="ignore"):  # (a signalling NaN, as a file may hold, warns when cast)
        s = stored.astype(np.float64)
        length = np.sqrt(np.einsum("ij,ij->i", s, s))
        cos = np.einsum("ij,ij->i", s, computed.astype(np.float64)) / length
    bad = ~np.isfinite(cos) | (cos < np.sqrt(0.5))
    # a degenerate facet has no direction to disagree with
    return bad & np.any(computed != 0, axis=1)


def _directed_edges_paired(mesh: Mesh) -> bool:
    """True when every edge shared by exactly two facets is used once in each direction (consistent winding)."""
    sides = mesh.edge_sides()
    return bool(np.all(sides.forward[sides.count == 2] == 1))


def with_faces(mesh: Mesh, faces: np.ndarray, **changes) -> Mesh:
    """A copy of ``mesh`` (the same vertices) with other ``faces`` (F, 3) and their edge numbering (host), other
    fields as ``changes``; its edge sides kept, the device it was welded on too (the slicer's prepared copies:
    :mod:`gpuslice.mesh.seams`, :mod:`gpuslice.mesh.holes`)."""
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    face_edges, edge_vertices, sides = edge_table_numpy(faces, mesh.vertices.shape[0])
    out = replace(mesh, faces=faces, face_edges=face_edges, edge_vertices=edge_vertices, **changes)
    out._cache["edge_sides"] = sides
    if mesh.device is not None:
        out._cache["device"] = mesh.device
    return out


def count_bodies(mesh: Mesh) -> int:
    """Connected components of facets sharing a vertex (bodies, shells)."""
    if mesh.n_faces == 0:
        return 0
    from .graph import components

    f = mesh.faces.astype(np.int64)
    rows = np.concatenate([f[:, 0], f[:, 1]])
    cols = np.concatenate([f[:, 1], f[:, 2]])
    labels = components(mesh.vertices.shape[0], rows, cols)
    return int(np.unique(labels[f.reshape(-1)]).size)


@dataclass(frozen=True)
class Placement:
    """How a mesh is scaled before slicing (declared once, :mod:`gpuslice.options`). It then always stands on the
    bed: its lowest point at z = 0, X and Y kept unless ``center``. Give ``scale`` or ``fit``, or neither (file units
    are mm)."""

    scale: float | None = option(None, "Multiply coordinates by this factor (to mm)")
    fit: float | None = option(None, "Scale so the longest side is this many mm")
    center: bool = option(False, "Move the centre of the model's X/Y box to the origin, in float64 before the one "
                          "rounding to float32 (a model far from the origin keeps its precision)")

    def __post_init__(self) -> None:
        _check_scale_fit(self.scale, self.fit)


def _check_scale_fit(scale, fit) -> None:
    """:class:`ParameterError` naming ``scale``/``fit`` unless each is None or a positive finite number, not both."""
    if scale is not None and fit is not None:
        raise ParameterError("give scale or fit, not both", param=("scale", "fit"))
    if fit is not None and not (is_finite(fit) and float(fit) > 0):
        raise ParameterError(f"fit must be a positive length in mm, got {shown(fit)}",
                             param="fit")
    if scale is not None and not (is_finite(scale) and float(scale) > 0):
        raise ParameterError(f"scale must be a positive factor, got {shown(scale)}",
                             param="scale")


def mesh_from_triangles(
    triangles: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    scale: float | None = None,
    fit: float | None = None,
    name: str = "<triangles>",
    source_format: str = "arrays",
    solids: int = 1,
    device=None,
    center: bool | None = False,
) -> Mesh:
    """Build a :class:`Mesh` from (F, 3, 3) corner coordinates (file units).

    ``scale`` multiplies every coordinate; ``fit`` scales so the longest bounding-box side is ``fit`` mm (give one
    or neither). The result always stands on the bed: its lowest point is moved to z = 0; X and Y are kept, unless
    ``center`` (True: the centre of the X/Y box is moved to the origin; None: only where the model reaches beyond
    :data:`FAR_XY_MM`, as resin jobs ask, since they centre the part on the display anyway; ``Mesh.offset`` holds
    the move).
    Corners are stored as float32: float32 values (an STL's) are welded bit for bit as given, then placed; finer
    values (float64, integers beyond 2^24) are placed in float64 first and rounded once (a model far above the bed
    loses nothing to the rounding of its own frame).
    ``device`` (a :class:`gpuslice.device.Device`, or a spec :func:`~gpuslice.device.get_device` takes): weld and
    number edges with ``kernels/weld.cl`` (the same ids as the numpy path) for meshes of more than
    :data:`DEVICE_WELD_MIN_FACETS` facets.
    """
    tri = real_array(triangles, "triangles", name)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3):
        raise ParameterError(f"{name}: triangles must have shape (F, 3, 3), got {tri.shape}")
    if device is not None:  # (a Device, or a spec such as "0:0": checked whatever the mesh's size)
        from ..device import get_device

        device = get_device(device)
    if tri.shape[0] == 0:
        raise EmptyMeshError(f"{name}: no facets")
    _check_scale_fit(scale, fit)
    if normals is not None:
        normals = real_array(normals, "normals", name)
        if normals.shape != (tri.shape[0], 3):
            raise ParameterError(f"{name}: normals must have shape ({tri.shape[0]}, 3), one per facet, got "
                                 f"{normals.shape}")
    # float32 is the precision of STL; the weld reads -0.0 as 0.0, so both weld together (no normalised copy)
    flat = tri.reshape(-1, 3)
    with np.errstate(over="ignore"):  # (beyond float32: inf, refused below with its one-line error)
        corners = np.ascontiguousarray(flat, dtype=np.float32)
    placed = None
    # (values beyond float32's range, or NaN, take the float32 path: its one-line error as before)
    if flat.dtype != np.float32 and np.isfinite(corners).all() and not np.array_equal(corners, flat):
        # finer than float32 (float64 arrays, OBJ, PLY, 3MF): scaled and put on the bed in float64 first, rounded
        # once after, so a model far from z = 0 (or large, then fitted) loses nothing to the rounding of its own
        # far-away frame. Sources whose values are float32 already (an STL's, a Trimesh loaded from one) are
        # welded as stored, then placed: the same mesh as their binary STL.
        placed = _placement(flat, name, scale, fit, center)
        factor, offset = placed
        corners = np.ascontiguousarray(flat.astype(np.float64) * factor + offset, dtype=np.float32)
    return _from_corners(
        corners, normals, name=name, source_format=source_format, scale=scale, fit=fit, solids=solids,
        device=device if tri.shape[0] > DEVICE_WELD_MIN_FACETS else None, placed=placed, center=center,
    )


def _placement(verts: np.ndarray, name: str, scale: float | None, fit: float | None, center: bool | None = False):
    """The scale factor and the offset that put the (scaled) mesh on the bed (and its X/Y centre at the origin when
    ``center``; None: when it reaches beyond :data:`FAR_XY_MM`)."""
    if center is not None:  # ("no" was taken as True)
        center = check_flag(center, "center")
    lo = np.array([verts[:, k].min() for k in range(3)], dtype=np.float64)
    hi = np.array([verts[:, k].max() for k in range(3)], dtype=np.float64)
    factor = 1.0
    longest = float((hi - lo).max())
    if fit is not None:
        if longest <= 0:
            raise InvalidGeometryError(f"{name}: the mesh has no extent to fit")
        factor = float(fit) / longest
    elif scale is not None:
        factor = float(scale)
    extreme = float(np.abs(np.concatenate([lo, hi])).max())
    if extreme * factor > 1e18:
        raise InvalidGeometryError(f"{name}: coordinates up to {extreme * factor:.3g} overflow float32 arithmetic")
    # every coordinate would round to 0 or a subnormal (--fit 5e-324 made the factor itself 0: a mesh of one point)
    if 0 < longest and longest * factor < np.finfo(np.float32).tiny:
        what = f"fit {float(fit):.3g} mm" if fit is not None else f"scale {factor:.3g}"
        raise InvalidGeometryError(f"{name}: {what} shrinks the mesh ({longest:.3g} units across) below float32's "
                                   "smallest length")
    if center is None:
        center = extreme_xy(lo, hi) * factor > FAR_XY_MM
    mid = 0.5 * (lo + hi) * factor if center else np.zeros(3)
    return factor, np.array([-mid[0], -mid[1], -lo[2] * factor])


def extreme_xy(lo, hi) -> float:
    """The largest |x| or |y| of a box (lo, hi), in its units."""
    return float(np.abs(np.concatenate([np.asarray(lo)[:2], np.asarray(hi)[:2]])).max())


def _from_corners(corners, normals, *, name, source_format, scale, fit, solids, device=None, placed=None,
                  center=False) -> Mesh:
    """The mesh of float32 ``corners`` (3 a facet): welded bit for bit, then scaled and put on the bed
    (:func:`_placement`) unless ``placed`` = (factor, offset) says the caller did that already."""
    n_faces = corners.shape[0] // 3

    # bit-identical as stored (-0.0 as 0.0), before any transform
    kernel = WeldKernel.of(device) if device is not None else None
    vid, first = (kernel.weld(corners, signed_zero=False) if kernel is not None
                  else weld_numpy(corners, signed_zero=False))
    verts = corners[first] + np.float32(0.0)  # + 0.0 turns -0.0 into 0.0
    del first
    if not np.all(np.isfinite(verts)):  # every corner is one of the vertices, bit for bit
        raise InvalidGeometryError(f"{name}: NaN or infinite vertex coordinates")
    if placed is not None:  # (the corners came placed and rounded once)
        factor, offset = placed
    else:
        factor, offset = _placement(verts, name, scale, fit, center)
        if factor != 1.0 or offset.any():
            verts = (verts.astype(np.float64) * factor + offset).astype(np.float32) + np.float32(0.0)
    faces = vid.reshape(n_faces, 3)
    good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    dropped = int(n_faces - good.sum())
    if dropped:
        faces = faces[good]
        if normals is not None:
            normals = np.asarray(normals)[good]
    if faces.shape[0] == 0:
        raise EmptyMeshError(f"{name}: every facet is degenerate")
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    if kernel is not None:
        face_edges, edge_vertices, sides = kernel.edge_table(faces, verts.shape[0], check=False)  # the weld's ids
        kernel.release()  # a large mesh's tables are not kept through slicing (peak memory)
    else:
        face_edges, edge_vertices, sides = edge_table_numpy(faces, verts.shape[0])
    mesh = Mesh(
        vertices=np.ascontiguousarray(verts),
        faces=np.ascontiguousarray(faces, dtype=np.int32),
        face_edges=face_edges,
        edge_vertices=edge_vertices,
        stored_normals=None if normals is None else np.asarray(normals, dtype=np.float32),
        name=name,
        source_format=source_format,
        scale=float(factor),
        offset=tuple(float(x) for x in offset),
        dropped_degenerate=dropped,
        solids=solids,
    )
    mesh._cache["edge_sides"] = sides  # the pairing the mesh check needs (defects.py), a by-product
    if device is not None:
        mesh._cache["device"] = device
    return mesh


def mesh_from_arrays(
    vertices: np.ndarray, faces: np.ndarray, *, scale: float | None = None, fit: float | None = None,
    name: str = "<arrays>", center: bool | None = False,
) -> Mesh:
    """Build a :class:`Mesh` from indexed arrays: vertices (V, 3) and faces (F, 3), counter-clockwise outward
    (``scale``, ``fit``, ``center``: :func:`mesh_from_triangles`)."""
    return mesh_from_triangles(_arrays(vertices, faces, name), scale=scale, fit=fit, name=name, center=center)


def load_mesh(
    source, *, scale: float | None = None, fit: float | None = None, device=None, name: str | None = None,
    center: bool | None = False,
) -> Mesh:
    """Load a mesh from a file or from memory, scale it and place it on the bed (lowest z = 0).

    Parameters
    ----------
    source : a path of an STL (binary or ASCII), OBJ, PLY, OFF or 3MF file; or, without a temporary file
        (:mod:`gpuslice.mesh.sources`): a ``trimesh.Trimesh``, a ``trimesh.Scene`` (concatenated, transforms
        applied), ``(vertices, faces)`` arrays, the ``bytes`` of a mesh file or a binary file object (format from
        ``name``'s suffix, else a zip is a 3MF and anything else an STL), or a :class:`Mesh` (returned as it is
        unless ``scale``/``fit`` are given, which then apply to its current coordinates). A ``Trimesh`` of float32
        values (loaded from an STL) gives the same mesh as its binary STL export; finer float64 coordinates are
        scaled and put on the bed before they are rounded to float32 (:func:`mesh_from_triangles`).
    scale : multiply every coordinate by this factor (file units to mm).
    fit : instead, scale so the longest bounding-box side is ``fit`` mm.
    center : move the centre of the X/Y box to the origin (None: only beyond :data:`FAR_XY_MM`), in float64 before
        the coordinates are rounded to float32 (:func:`mesh_from_triangles`).
    device : optional OpenCL :class:`~gpuslice.device.Device` to weld on (see :func:`mesh_from_triangles`).
    name : how messages and ``Mesh.name`` call an in-memory source (its suffix picks the format of bytes).

    Raises
    ------
    MeshFileError, EmptyMeshError, InvalidGeometryError
        With a one-line message naming the file and the problem (a 3MF is refused past the inflation limit of
        :func:`gpuslice.io.meshfile.zip_inflate_limit`).
    ParameterError
        A source of no known kind, or malformed arrays.
    """
    if name is not None and not isinstance(name, str):
        raise ParameterError(f"name must be a string (how messages call the source), got {type(name).__name__}")
    _check_scale_fit(scale, fit)
    if isinstance(source, Mesh):
        if scale is None and fit is None and not center:
            return source
        return mesh_from_triangles(source.triangles, source.stored_normals, scale=scale, fit=fit,
                                   name=name or source.name, source_format=source.source_format,
                                   solids=source.solids, device=device, center=center)
    if isinstance(source, str | os.PathLike):
        from ..io.meshfile import read_mesh_file

        raw = read_mesh_file(source)
        label, normals, fmt, solids = str(Path(source)), raw.normals, raw.source_format, raw.solids
        triangles = raw.triangles
    else:
        from .sources import read_source

        src = read_source(source, name)
        label, normals, fmt, solids = src.name, src.normals, src.source_format, src.solids
        triangles = src.triangles
    return mesh_from_triangles(
        triangles,
        normals,
        scale=scale,
        fit=fit,
        name=label,
        source_format=fmt,
        solids=solids,
        device=device,
        center=center,
    )
