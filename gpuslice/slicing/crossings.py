"""Stage 3: facet–plane crossings of all layers at once, into one flat segment buffer.

The rule for vertices, edges and facets lying exactly on a plane is stated once, at the top of
``kernels/crossings.cl``: a vertex with ``z >= plane`` counts as above (half-open), so the section at a plane is the
limit of the sections just below it. :func:`crossings_numpy` is the numpy twin of the kernel with the same
semantics, used as the test oracle and as ``backend="numpy"``.

Segments are ordered by facet, then by layer. Segment s lies in layer ``layer[s]``, runs from ``points[s, :2]`` on
mesh edge ``edges[s, 0]`` to ``points[s, 2:]`` on mesh edge ``edges[s, 1]`` (mm), with material on its left for an
outward-wound mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..device import KernelDriver
from ..mesh.mesh import Mesh

__all__ = ["Segments", "DeviceSegments", "crossings_numpy", "CrossingsKernel", "compute_crossings", "batch_facets",
           "batch_layers"]


@dataclass
class Segments:
    """The segment buffer: ``layer`` (S,) int32, ``edges`` (S, 2) int32, ``points`` (S, 4) float32 (x0, y0, x1, y1)."""

    layer: np.ndarray
    edges: np.ndarray
    points: np.ndarray

    def __len__(self) -> int:
        return int(self.layer.shape[0])


@dataclass
class DeviceSegments:
    """The segment buffer left on the device (valid until the kernel's next call); :meth:`fetch` reads it back."""

    n: int
    layer: object
    edges: object
    points: object
    kernel: CrossingsKernel

    def __len__(self) -> int:
        return self.n

    def fetch_points(self) -> np.ndarray:
        import pyopencl as cl

        out = np.empty((self.n, 4), dtype=np.float32)
        if self.n:
            cl.enqueue_copy(self.kernel.device.queue, out, self.points)
        return out

    def fetch(self) -> Segments:
        seg = Segments(np.empty(self.n, np.int32), np.empty((self.n, 2), np.int32), np.empty((self.n, 4), np.float32))
        if self.n:
            self.kernel._read((seg.layer, self.layer), (seg.edges, self.edges), (seg.points, self.points))
        return seg


def _planes32(z: np.ndarray, name: str | None = None) -> np.ndarray:
    """The cutting planes as the kernels cut them (float32), refused where two coincide (``name``: the model's, for
    the message)."""
    z = np.asarray(z)
    if z.size and not (np.abs(z) <= 1e18).all():  # (beyond float32 they overflow the cast: inf planes, a warning)
        from ..errors import ParameterError

        where = f"{name}: " if name else ""
        raise ParameterError(f"{where}cutting planes must lie within 1e18 mm of the bed, got z up to "
                             f"{float(np.max(np.abs(z))):.3g} mm")
    zs = np.ascontiguousarray(z, dtype=np.float32)
    if zs.size > 1 and not np.all(np.diff(zs) > 0):
        from ..errors import ParameterError

        where = f"{name}: " if name else ""
        raise ParameterError(f"{where}layers closer than float32 resolution: cutting planes coincide (from "
                             f"z = {float(zs[np.flatnonzero(np.diff(zs) <= 0)[0]]):.6g} mm)")
    return zs


#: the largest error of a float32 cutting plane, as a share of the thinnest layer, that a slice accepts
PLANE_ERROR_MAX = 0.05


def check_plane_spacing(z: np.ndarray, zs: np.ndarray, name: str | None = None) -> None:
    """Refuse layers so thin for their height that float32 planes ``zs`` (as cut) stray from the schedule's ``z``
    (mm) by more than :data:`PLANE_ERROR_MAX` of the thinnest layer, i.e. layers under about 10 float32 steps of
    their height (0.0003 mm at 300 mm, 0.00002 mm at 20 mm), which would come out unevenly thick without a word (a
    helper's probe: planes off by 30 % of a layer at 0.00005 mm over 300 mm)."""
    z = np.asarray(z, np.float64)
    if z.size < 2:
        return
    gap = float(np.min(np.diff(z)))
    err = np.abs(zs.astype(np.float64) - z)
    k = int(np.argmax(err))
    if gap > 0 and err[k] > PLANE_ERROR_MAX * gap:
        from ..errors import ParameterError

        where = f"{name}: " if name else ""
        raise ParameterError(f"{where}layers of {gap:.3g} mm are too thin for float32 planes at z = {z[k]:.6g} mm "
                             f"(a plane off by {100 * err[k] / gap:.0f} % of a layer); use thicker layers")


def vertex_layers(mesh: Mesh, zs: np.ndarray) -> np.ndarray:
    """(V,) int32: for each vertex the first layer whose plane is above it (``upper_bound`` of its z)."""
    return np.searchsorted(zs, mesh.vertices[:, 2], side="right").astype(np.int32)


def facet_layer_ranges(mesh: Mesh, zs: np.ndarray, vl: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(first layer, count) of the layers each facet crosses: layers k with zmin < zs[k] <= zmax (``vl``: the
    :func:`vertex_layers`, when at hand)."""
    vl = vertex_layers(mesh, zs) if vl is None else vl
    a, b, c = (vl[mesh.faces[:, i]] for i in range(3))  # three columns: min(axis=1) on (F, 3) is ~6x slower
    lo = np.minimum(np.minimum(a, b), c)
    return lo, np.maximum(np.maximum(a, b), c) - lo


def _edge_points(verts: np.ndarray, a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    u, w = np.minimum(a, b), np.maximum(a, b)
    vu, vw = verts[u], verts[w]
    zu, zw = vu[:, 2], vw[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p - zu) / (zw - zu)
    x = vu[:, 0] + t * (vw[:, 0] - vu[:, 0])
    y = vu[:, 1] + t * (vw[:, 1] - vu[:, 1])
    at_w, at_u = zw == p, zu == p
    x = np.where(at_w, vw[:, 0], np.where(at_u, vu[:, 0], x))
    y = np.where(at_w, vw[:, 1], np.where(at_u, vu[:, 1], y))
    return np.stack([x, y], axis=1).astype(np.float32)


def crossings_numpy(mesh: Mesh, z: np.ndarray) -> Segments:
    """The numpy reference of ``kernels/crossings.cl``: the same segments, in the same order."""
    zs = _planes32(z)
    lo, count = facet_layer_ranges(mesh, zs)
    total = int(count.sum(dtype=np.int64))
    facet = np.repeat(np.arange(mesh.n_faces, dtype=np.int64), count)
    start = np.cumsum(count, dtype=np.int64) - count
    layer = (lo[facet] + (np.arange(total, dtype=np.int64) - start[facet])).astype(np.int32)
    p = zs[layer]
    v = mesh.faces[facet]
    below = mesh.vertices[:, 2][v] < p[:, None]
    nxt = np.roll(below, -1, axis=1)
    down = np.argmax(~below & nxt, axis=1)
    up = np.argmax(below & ~nxt, axis=1)
    rows = np.arange(total)
    va, vb = v[rows, down], v[rows, (down + 1) % 3]
    wa, wb = v[rows, up], v[rows, (up + 1) % 3]
    pts = np.empty((total, 4), dtype=np.float32)
    pts[:, :2] = _edge_points(mesh.vertices, va, vb, p)
    pts[:, 2:] = _edge_points(mesh.vertices, wa, wb, p)
    fe = mesh.face_edges[facet]
    edges = np.stack([fe[rows, down], fe[rows, up]], axis=1).astype(np.int32)
    return Segments(layer, edges, pts)


class CrossingsKernel(KernelDriver):
    """Driver of ``kernels/crossings.cl`` on one device: builds once, keeps the kernels and reuses buffers."""

    def __init__(self, device) -> None:
        super().__init__(device)
        prg = device.program("crossings.cl")
        self._vertex = prg.vertex_layers
        self._count = prg.count_crossings
        self._emit = prg.emit_segments
        self._emit_of = prg.emit_segments_of

    def __call__(self, mesh: Mesh, z: np.ndarray, *, read_back: bool = True,
                 layers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                 mesh_on_device: bool = False, facets: np.ndarray | None = None) -> Segments | DeviceSegments:
        """The segments of ``mesh`` cut at ``z``; ``layers``: optional (vertex_layers, first layer, count) of the
        vertices and facets for these planes (:func:`vertex_layers`, :func:`facet_layer_ranges`, int32), when the
        host has them: uploaded instead of computed here (chaining reads the vertices' from this driver).
        ``facets``: with ``layers``, the increasing ids of the only facets that may cross these planes (a layer
        batch's), ``layers``' first layer and count then given for them alone: the others are not visited (the
        segments are the same, in the same order). ``mesh_on_device``: the call before uploaded this same
        mesh and nothing has used this driver since (the slicer's later layer batches, under
        :meth:`~gpuslice.device.Device.exclusive`): its vertices, faces and edges are not uploaded again."""
        import pyopencl as cl

        q = self.device.queue
        zs = _planes32(z)
        n_f, n_l = mesh.n_faces, int(zs.size)
        if mesh_on_device:
            d_verts, d_faces, d_edges = (self.buffer(k) for k in ("verts", "faces", "face_edges"))
        else:
            d_verts = self._put("verts", mesh.vertices)
            d_faces = self._put("faces", mesh.faces)
            d_edges = self._put("face_edges", mesh.face_edges)
        d_zs = self._put("zs", zs)
        n_v = int(mesh.vertices.shape[0])
        if facets is not None and layers is None:
            raise ValueError("crossings of a subset of the facets need their layers")
        if layers is not None:
            vub, first, count = (np.ascontiguousarray(a, dtype=np.int32) for a in layers)
            self._put("vub", vub)  # (not read here: chaining reads it, walk.py's edge ranges)
            d_first = self._put("first", first)
            d_count = self._put("count", count)
        else:
            d_vub = self._buffer("vub", 4 * n_v)
            self._vertex(q, *self._grid(n_v), d_verts, np.int32(n_v), d_zs, np.int32(n_l), d_vub)
            d_first = self._buffer("first", 4 * n_f)
            d_count = self._buffer("count", 4 * n_f)
            self._count(q, *self._grid(n_f), d_vub, d_faces, np.int32(n_f), d_first, d_count)
            count = np.empty(n_f, dtype=np.int32)
            cl.enqueue_copy(q, count, d_count)
        n_emit = int(count.size)  # (the facets, or the batch's own)
        offsets = np.cumsum(count, dtype=np.int64)
        total = int(offsets[-1]) if n_emit else 0
        offsets -= count
        if total == 0:
            empty = Segments(np.empty(0, np.int32), np.empty((0, 2), np.int32), np.empty((0, 4), np.float32))
            return empty if read_back else DeviceSegments(0, None, None, None, self)
        d_off = self._put("offsets", offsets)
        d_layer = self._buffer("seg_layer", 4 * total)
        d_sedges = self._buffer("seg_edges", 8 * total)
        d_spts = self._buffer("seg_points", 16 * total)
        if facets is None:
            self._emit(q, *self._grid(n_f), d_verts, d_faces, d_edges, np.int32(n_f), d_zs, d_first, d_count, d_off,
                       d_layer, d_sedges, d_spts)
        else:
            d_ids = self._put("facet_ids", np.ascontiguousarray(facets, dtype=np.int32))
            self._emit_of(q, *self._grid(n_emit), d_verts, d_faces, d_edges, d_ids, np.int32(n_emit), d_zs, d_first,
                          d_count, d_off, d_layer, d_sedges, d_spts)
        dseg = DeviceSegments(total, d_layer, d_sedges, d_spts, self)
        return dseg.fetch() if read_back else dseg


def compute_crossings(mesh: Mesh, z: np.ndarray, device=None, *, read_back: bool = True, layers=None,
                      mesh_on_device: bool = False, facets: np.ndarray | None = None):
    """All segments of ``mesh`` cut at the planes ``z`` (mm, increasing): on ``device``, or numpy when None.

    With ``read_back=False`` (device only) the segments stay on the device as :class:`DeviceSegments`. ``layers``,
    ``mesh_on_device``, ``facets``: see :meth:`CrossingsKernel.__call__` (device only).
    """
    if device is None:
        return crossings_numpy(mesh, z)
    return CrossingsKernel.of(device)(mesh, z, read_back=read_back, layers=layers, mesh_on_device=mesh_on_device,
                                      facets=facets)


def batch_facets(ranges: tuple, batches: list[tuple[int, int]]) -> list[np.ndarray]:
    """Each batch's facets: the increasing int32 ids of those crossing at least one of its planes (``ranges`` as
    ``slicer._batches`` returns them: vertex layers, facets' first layer and count for all planes), so that its
    crossings visit them alone (``facets=``). Grouped by the batch of each facet's
    first layer (a stable sort of small integers), then each facet reaching into later batches added to those."""
    from ..ragged import expand_ranges

    _, lo, count = ranges
    nb = len(batches)
    key = np.int16 if nb < 2**15 else np.int32  # (numpy sorts 16-bit keys stably by radix)
    layer_batch = np.repeat(np.arange(nb, dtype=key), [b - a for a, b in batches])
    ids = np.flatnonzero(count > 0).astype(np.int32)
    first = lo[ids]
    bf = layer_batch[first]
    bl = layer_batch[first + count[ids] - 1]
    main = ids[np.argsort(bf, kind="stable")]
    cuts = np.concatenate([[0], np.cumsum(np.bincount(bf, minlength=nb))])
    span = np.flatnonzero(bl > bf)  # facets crossing planes of several batches: also in the later ones
    owner, batch = expand_ranges(bf[span].astype(np.int64) + 1, (bl[span] - bf[span]).astype(np.int64))
    order = np.argsort(batch, kind="stable")
    extra, ecuts = ids[span][owner[order]], np.searchsorted(batch[order], np.arange(nb + 1))
    return [np.sort(np.concatenate([main[cuts[k] : cuts[k + 1]], extra[ecuts[k] : ecuts[k + 1]]]), kind="stable")
            for k in range(nb)]  # (two sorted runs: one merge)


def batch_layers(ranges: tuple, a: int, b: int, facets: np.ndarray, out: np.ndarray | None = None) -> tuple:
    """The (vertex layers, first layer, count) of ``ranges`` (for all planes) for the planes ``zs[a:b]`` alone, int32,
    as :meth:`CrossingsKernel.__call__` takes them with ``facets``: of every vertex (written into ``out`` when
    given: done per batch, so in place) and of ``facets`` (:func:`batch_facets`) alone."""
    vl, lo, count = ranges
    n = b - a
    v = out if out is not None else np.empty(vl.shape, np.int32)
    np.subtract(vl, a, out=v, casting="unsafe")
    np.clip(v, 0, n, out=v)
    f = lo[facets]
    c = np.clip(f + count[facets] - a, 0, n).astype(np.int32)
    f = np.clip(f - a, 0, n).astype(np.int32)
    c -= f
    return v, f, c
