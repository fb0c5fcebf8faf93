"""The segment-buffer shortcut: layers rasterised from the crossings' oriented segments, without chaining or nesting.

The runs (:mod:`gpuslice.raster.runs`) depend only on the set of a layer's edges in pixels: each row sums integer
area contributions of the pieces that cross it, in any order. A layer's polygons (chained and nested) have exactly
its segments' edges when nothing was repaired, dropped, turned round or rebuilt on the way: every segment's end is
its successor's start (the same mesh edge cut by the same plane gives the same float32 point,
``kernels/crossings.cl``). Then the pixel edges here equal :func:`gpuslice.raster.edges.layer_edges`'s bit for bit
(the same float64 mapping, rounded once, and the same tile: the pixel box of the loops' points), and the runs are
identical. A plane through no mesh vertex cuts no zero-length segment, and on a closed, consistently wound mesh
without two facets on the same three vertices every loop it cuts has at least three distinct points (two facets
sharing two edges would share all three vertices): nothing for chaining to drop. A plane through a vertex can cut
loops that touch there or degenerate (a ridge edge lying on the plane, both its facets below it, is a loop of two
points that nesting drops, and its points would widen the tile): the layers with such a sub-plane are cut the
polygon way (:func:`layers_through_vertices`; 81 of the armadillo job's 1,900 layers, 13 of nefertiti's 1,600),
spliced into their chunk (:func:`gpuslice.raster.edges.splice_layers`).

**Where it is taken** (:func:`shortcut_refusal` returns None): the sub-planes of ``--z-samples`` (one to
sixty-three more planes per layer, the cost of that option), when

* the fill rule is ``nonzero`` (the runs' ``|winding sum|`` is its coverage);
* the mesh is closed and consistently wound (every edge used by two facets, once in each direction), with no
  two facets on the same three vertices (a zero-volume shell of two facets, whose sections are loops of two points);
* every layer of the job's own slice is *segment-exact* (:attr:`SliceResult.segment_exact`: chaining repaired
  nothing, nesting dropped, turned round and rebuilt nothing), which overlapping or inside-out shells, and
  self-intersecting facets that the layers cut, are not;
* the device has doubles (``cl_khr_fp64``).

What this does not prove: a self-intersection or a shell that lies wholly between two layer planes (thinner than a
layer), or a zero-volume shell of more than two facets whose loops the layers' planes happen to leave alone, is met
only by sub-planes, whose greys there are then the plain winding sum of their segments (nesting might have rebuilt,
dropped or turned loops round). Elsewhere the masks are those of the polygon path, byte for byte
(``tests/raster/test_segment_edges.py``: the closed, consistently wound shared meshes, a ridge and an apex on a
sub-plane, mirrored and portrait displays, several chunks).

Device: ``kernels/segment_edges.cl`` (:class:`SegmentEdgesKernel`) on the segments the crossings kernel left there;
numpy twin: :func:`segment_edges_numpy` (the reference in tests).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from ..device import KernelDriver
from ..slicing.crossings import DeviceSegments, Segments
from .edges import LayerEdges, box_tiles, iter_layer_edges, merge_tiles, splice_layers
from .spec import RasterSpec

__all__ = ["shortcut_refusal", "layers_through_vertices", "iter_sub_plane_edges", "segment_edges_numpy",
           "SegmentEdgesKernel"]

_BIG = np.iinfo(np.int32).max


def _affine(spec: RasterSpec, bounds) -> np.ndarray | None:
    """The display's 2 x 3 mapping mm -> pixels (:meth:`RasterSpec.affine`), or None where it is not finite."""
    a = np.asarray(spec.affine(bounds), np.float64)
    return a if np.isfinite(a).all() else None


def shortcut_refusal(mesh, result, fill_rule: str, spec: RasterSpec, bounds) -> str | None:
    """Why the z sub-planes of ``result`` (sliced from ``mesh``) may not be rasterised from their segments, or None
    when they may (module docstring)."""
    if fill_rule != "nonzero":
        return f"the fill rule is {fill_rule}"
    if mesh is None or mesh.n_faces == 0:
        return "no mesh"
    sides = mesh.edge_sides()
    if not (np.all(sides.count == 2) and np.all(sides.forward == 1)):
        return "the mesh is not closed and consistently wound"
    f = mesh.faces
    first, last = sides.first, sides.last  # the two sides 3f + k of every edge
    third = lambda side: f[side // 3, (side % 3 + 2) % 3]  # noqa: E731 - the corner opposite a side
    if np.any(third(first) == third(last)):
        return "two facets share their three vertices"
    exact = getattr(result, "segment_exact", None)
    if exact is None or not np.all(exact):
        return "some layers' polygons are not their segments (repaired, overlapping or inside-out shells)"
    if _affine(spec, bounds) is None:
        return "the display's mapping is not finite"
    return None


def layers_through_vertices(mesh, z: np.ndarray, k: int) -> np.ndarray:
    """(L,) bool: the layers one of whose ``k`` sub-planes ``z`` (mm, as float32: as the crossings cut them) passes
    through a mesh vertex. There loops may touch or degenerate (a ridge edge lying on the plane cuts a loop of two
    points, which nesting drops): those layers' sub-planes are cut the polygon way (module docstring)."""
    hit = np.isin(np.asarray(z, np.float32), np.asarray(mesh.vertices[:, 2], np.float32))
    return hit.reshape(-1, k).any(axis=1)


def iter_sub_plane_edges(mesh, z: np.ndarray, k: int, spec: RasterSpec, bounds, device,
                         slice_planes: Callable[[np.ndarray], object], chunk: int,
                         timings: dict[str, float] | None = None) -> Iterator[tuple[int, LayerEdges]]:
    """(first layer, the merged edges of layers first … first + chunk − 1) for every chunk of layers, each layer's
    ``k`` sub-planes ``z`` (mm) from their segments on ``device``, except the layers with a sub-plane through a
    vertex (:func:`layers_through_vertices`), whose sub-planes are cut by ``slice_planes(indices into z)`` (a
    :class:`~gpuslice.slicing.result.SliceResult`), at most ``chunk`` layers at a time, and spliced in. ``timings``:
    seconds added up under ``z_samples``. Memory: one chunk's segments and edges, one block's polygons."""
    import time

    from ..slicing.crossings import compute_crossings

    kern = SegmentEdgesKernel.of(device)
    on_vertex = np.flatnonzero(layers_through_vertices(mesh, z, k))
    block, block_edges = np.zeros(0, np.int64), None
    n_layers = len(z) // k
    for a in range(0, n_layers, chunk):
        b = min(a + chunk, n_layers)
        t = time.perf_counter()
        seg = compute_crossings(mesh, z[a * k : b * k], device, read_back=False)
        merged = kern(seg, (b - a) * k, k, spec, bounds)
        del seg
        need = on_vertex[(on_vertex >= a) & (on_vertex < b)]
        if need.size and not np.isin(need, block).all():
            block = on_vertex[on_vertex >= a][: min(chunk, 256)]  # (<= EDGE_CHUNK layers: one chunk of edges)
            sub = slice_planes((block[:, None] * k + np.arange(k)).reshape(-1))
            ((_, block_edges),) = iter_layer_edges(sub, spec, bounds, k=k, dtype=np.float32)
        if need.size:
            merged = splice_layers(merged, need - a, block_edges, np.searchsorted(block, need))
        if timings is not None:
            timings["z_samples"] = timings.get("z_samples", 0.0) + time.perf_counter() - t
        yield a, merged


def _group_tiles(box: np.ndarray, k: int, spec: RasterSpec) -> np.ndarray:
    """Merged tiles of the groups of ``k`` sub-planes from each sub-plane's floor box (min u, max u, min v, max v;
    min = INT32 max where it has no point)."""
    sub = np.zeros((len(box), 4), np.int64)
    has = box[:, 0] != _BIG
    if has.any():
        sub[has] = box_tiles(box[has, 0], box[has, 1], box[has, 2], box[has, 3], spec)
    return merge_tiles(sub, k)


def segment_edges_numpy(seg: Segments, n_planes: int, k: int, spec: RasterSpec, bounds) -> LayerEdges:
    """The numpy twin of :class:`SegmentEdgesKernel`: the edges of ``seg`` (cut at ``n_planes`` planes, ``k`` per
    layer) as every layer's, its sub-planes merged, float32, grouped by layer (in segment order within a layer)."""
    layer = np.asarray(seg.layer, np.int64)
    p = np.asarray(seg.points, np.float32)
    u0, v0 = spec.to_pixels_xy(p[:, 0], p[:, 1], bounds)  # (the kernel's formula; see kernels/segment_edges.cl)
    u1, v1 = spec.to_pixels_xy(p[:, 2], p[:, 3], bounds)
    box = np.empty((n_planes, 4), np.int64)
    box[:, 0::2], box[:, 1::2] = _BIG, -_BIG - 1
    moving = ~((p[:, 0] == p[:, 2]) & (p[:, 1] == p[:, 3]))
    lm = layer[moving]
    for j, w in enumerate((u0[moving], v0[moving])):
        fw = np.floor(w).astype(np.int64)
        np.minimum.at(box[:, 2 * j], lm, fw)
        np.maximum.at(box[:, 2 * j + 1], lm, fw)
    tiles = _group_tiles(box, k, spec)
    group = layer // k
    order = np.argsort(group, kind="stable")
    offsets = np.zeros(len(tiles) + 1, np.int64)
    np.cumsum(np.bincount(group, minlength=len(tiles)), out=offsets[1:])
    g = group[order]
    c0, r0 = tiles[g, 1].astype(np.float64), tiles[g, 0].astype(np.float64)
    edges = np.stack([u0[order] - c0, v0[order] - r0, u1[order] - c0, v1[order] - r0], axis=1).astype(np.float32)
    return LayerEdges(edges, offsets, tiles)


class SegmentEdgesKernel(KernelDriver):
    """Driver of ``kernels/segment_edges.cl``: the edges of a segment buffer left on the device, grouped by layer
    (``k`` sub-planes each), relative to each layer's tile, read back as float32 :class:`LayerEdges`."""

    def __init__(self, device) -> None:
        super().__init__(device)
        import pyopencl as cl

        prog = device.program("segment_edges.cl")
        try:
            self._bounds, self._scatter = prog.segment_bounds, prog.segment_scatter
        except (AttributeError, cl.Error):  # built without doubles: no cl_khr_fp64 on this device
            self._bounds = self._scatter = None

    @property
    def available(self) -> bool:
        """Whether the device built the kernels (it has doubles)."""
        return self._bounds is not None

    def __call__(self, seg: DeviceSegments | Segments, n_planes: int, k: int, spec: RasterSpec,
                 bounds) -> LayerEdges:
        """The edges of ``seg`` (left on the device by the crossings kernel, or on the host: uploaded) cut at
        ``n_planes`` planes, ``k`` per layer; ``bounds`` (xmin, ymin, xmax, ymax) mm as the archive centres it."""
        import pyopencl as cl

        q = self.device.queue
        if k < 1 or n_planes % k:
            from ..errors import ParameterError

            raise ParameterError(f"{n_planes} planes are not layers of {k} sub-planes", param="z_samples")
        if isinstance(seg, Segments):
            seg = DeviceSegments(len(seg), self._put("seg_layer", np.ascontiguousarray(seg.layer, np.int32)), None,
                                 self._put("seg_points", np.ascontiguousarray(seg.points, np.float32)), None)
        m = np.zeros((2, 4), np.float64)
        m[:, :3] = _affine(spec, bounds)
        au, av = (m[j].view(cl.cltypes.double4)[0] for j in (0, 1))
        n, groups = seg.n, n_planes // k
        box = np.empty((n_planes, 4), np.int32)
        box[:, 0::2], box[:, 1::2] = _BIG, -_BIG - 1
        b_box = self._put("box", box)
        b_count = self._fill("count", 4 * max(groups, 1), np.int32(0))
        grid = self._grid(max(n, 1))
        count = np.zeros(groups, np.int32)
        if n:
            self._bounds(q, *grid, np.int32(n), seg.layer, seg.points, au, av, np.int32(k), b_box, b_count)
            cl.enqueue_copy(q, box, b_box, is_blocking=False)
            cl.enqueue_copy(q, count, b_count, is_blocking=True)
        tiles = _group_tiles(box.astype(np.int64), k, spec)
        offsets = np.zeros(groups + 1, np.int64)
        np.cumsum(count, out=offsets[1:])
        edges = np.empty((n, 4), np.float32)
        if n:
            first = self._put("first", offsets[:-1].astype(np.int32))
            corner = self._put("corner", np.ascontiguousarray(tiles[:, :2], np.int32))
            cursor = self._fill("cursor", 4 * max(groups, 1), np.int32(0))
            out = self._buffer("edges", 16 * n)
            self._scatter(q, *grid, np.int32(n), seg.layer, seg.points, au, av, np.int32(k), first, corner, cursor,
                          out)
            cl.enqueue_copy(q, edges, out, is_blocking=True)
        return LayerEdges(edges, offsets, tiles)
