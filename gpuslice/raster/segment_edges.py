"""The segment-buffer shortcut: layers rasterised from the crossings' oriented segments, without chaining or nesting.

The runs (:mod:`gpuslice.raster.runs`) depend only on the set of a layer's edges in pixels: each row sums integer
area contributions of the pieces that cross it, in any order. A layer's polygons (chained and nested) have exactly
its segments' edges when nothing was repaired, dropped, turned round or rebuilt on the way: every segment's end is
its successor's start (the same mesh edge cut by the same plane gives the same float32 point,
``kernels/crossings.cl``). Then the pixel edges here equal :func:`gpuslice.raster.edges.layer_edges`'s bit for bit
(the same float64 mapping, rounded once, and the same tile: the pixel box of the loops' points), and the runs are
identical. In exact arithmetic, a plane through no mesh vertex of a closed, consistently wound mesh without two
facets on the same three vertices cuts loops of at least three distinct points (two facets sharing two edges would
share all three vertices): nothing for chaining to drop. Two things break that, and their layers are cut the polygon
way (sliced apart, a chunk's at a time, and spliced in: :func:`gpuslice.raster.edges.splice_layers`):

* a sub-plane through a vertex (:func:`layers_through_vertices`): loops may touch there or degenerate (a ridge edge
  lying on the plane, both its facets below it, is a loop of two points that nesting drops, and its points would
  widen the tile);
* a segment shorter than :data:`SHORT` of its coordinates, 8 float32 ulps (:func:`short_segments`, flagged by the
  kernel): a plane a few ulps from a vertex, where the crossings' float32 rounding can make points coincide or loops
  cross, which chaining and nesting then repair (``scripts/fuzz_z_samples.py`` found such layers at 0 and 1 ulp).
  Rounding moves a point by at most about an ulp, so loops it makes touch or cross come within a few ulps of each
  other, and then the loops' own segments near that vertex are that short.

Those of a few chunks are sliced together (one call per 256 of them: a call costs ~20 ms whatever its size). On the
armadillo job 317 of 1,900 layers go the polygon way (81 through a vertex), 71 of nefertiti's 1,600.

**Where it is taken** (:func:`shortcut_refusal` returns None): the sub-planes of ``--z-samples`` (one to
sixty-three more planes per layer, the cost of that option), when

* the fill rule is ``nonzero`` (the runs' ``|winding sum|`` is its coverage);
* the mesh is closed and consistently wound (every edge used by two facets, once in each direction), with no
  two facets on the same three vertices (a zero-volume shell of two facets, whose sections are loops of two points);
* every layer of the job's own slice is *segment-exact* (:attr:`SliceResult.segment_exact`: chaining repaired
  nothing, nesting dropped, turned round and rebuilt nothing), which overlapping or inside-out shells, and
  self-intersecting facets that the layers cut, are not;
* no two shells' boxes meet, except a cavity's (a shell wound inward) inside its model's (:func:`shells_meeting`):
  two bodies that meet only between two layer planes, or a body thinner than a layer lying there, are cut by the
  sub-planes alone, which would count their overlap twice;
* the device has doubles (``cl_khr_fp64``).

What this does not prove: a self-intersection of one shell, or of a cavity with its model, that lies wholly between
two layer planes, or a zero-volume shell of more than two facets whose loops the layers' planes happen to leave
alone, is met only by sub-planes, whose greys there are then the plain winding sum of their segments (nesting might
have rebuilt, dropped or turned loops round). Elsewhere the masks are those of the polygon path, byte for byte
(``tests/raster/test_segment_edges.py``: the closed, consistently wound shared meshes, a ridge and an apex on a
sub-plane, mirrored and portrait displays, several chunks).

Device: ``kernels/segment_edges.cl`` (:class:`SegmentEdgesKernel`) on the segments the crossings kernel left there;
numpy twin: :func:`segment_edges_numpy` (the reference in tests).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import numpy as np

from ..device import STRIPES, KernelDriver
from ..slicing.crossings import DeviceSegments, Segments
from .edges import LayerEdges, box_tiles, iter_layer_edges, merge_tiles, splice_layers
from .spec import RasterSpec

__all__ = ["shortcut_refusal", "shells_meeting", "layers_through_vertices", "short_segments", "iter_sub_plane_edges",
           "segment_edges_numpy", "SegmentEdgesKernel"]

_BIG = np.iinfo(np.int32).max
#: a segment shorter than this fraction of its largest coordinate (at least 1 mm) marks its layer for the polygon
#: way: float32 rounding near a vertex can make points coincide there (``kernels/segment_edges.cl``, SEG_SHORT)
SHORT = np.float32(2.0**-20)


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
    meeting = shells_meeting(mesh)
    if meeting:
        return meeting
    if _affine(spec, bounds) is None:
        return "the display's mapping is not finite"
    return None


#: candidate pairs of shells (boxes overlapping in x) beyond which :func:`shells_meeting` refuses without looking
MAX_SHELL_PAIRS = 4_000_000


def shells_meeting(mesh) -> str | None:
    """Why two shells (vertex-connected parts) of ``mesh`` might overlap where only sub-planes cut them, or None.

    The main layers' slice sees only the overlaps its planes cut: a body thinner than a layer lying wholly between
    two planes, or two bodies that meet only there, would be cut by sub-planes alone, whose summed windings then
    count the overlap twice (seen: a 0.03 mm plate across a box's edge, 141 pixels of a layer 51 greys too bright).
    So the shortcut is refused when the boxes of two shells meet (touching counts), except a cavity (a shell wound
    inward, negative volume) whose box lies within that of a shell wound outward: a hollowed model. Vectorised: the
    boxes sorted by their lowest x, each against those starting before it ends."""
    from ..mesh.graph import components

    f = np.asarray(mesh.faces, np.int64)
    labels = components(int(mesh.vertices.shape[0]), np.concatenate([f[:, 0], f[:, 1]]),
                        np.concatenate([f[:, 1], f[:, 2]]), device=getattr(mesh, "device", None))
    shell_ids, shell = np.unique(np.asarray(labels)[f[:, 0]], return_inverse=True)
    n = shell_ids.size
    if n < 2:
        return None
    tri = np.asarray(mesh.vertices, np.float64)[f]  # (F, 3 corners, xyz)
    order = np.argsort(shell, kind="stable")
    start = np.flatnonzero(np.r_[True, shell[order][1:] != shell[order][:-1]])
    lo = np.minimum.reduceat(tri.min(axis=1)[order], start)
    hi = np.maximum.reduceat(tri.max(axis=1)[order], start)
    volume = np.bincount(shell, np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])), minlength=n)
    by_x = np.argsort(lo[:, 0], kind="stable")
    ends = np.searchsorted(lo[by_x, 0], hi[by_x, 0], side="right")  # boxes starting at or before each one's end
    counts = np.maximum(ends - np.arange(n) - 1, 0)
    if int(counts.sum()) > MAX_SHELL_PAIRS:
        return f"{n} shells, too many side by side to check that none meets another"
    from ..ragged import expand_ranges

    owner, other = expand_ranges(np.arange(n) + 1, counts)
    a, b = by_x[owner], by_x[other]
    meet = np.all((lo[a] <= hi[b]) & (lo[b] <= hi[a]), axis=1)
    a, b = a[meet], b[meet]

    def within(inner, outer):  # a cavity inside a shell wound outward, by their boxes
        return (volume[inner] < 0) & (volume[outer] > 0) & np.all((lo[outer] <= lo[inner]) & (hi[inner] <= hi[outer]),
                                                                  axis=1)

    bad = ~(within(a, b) | within(b, a))
    if bad.any():
        return f"two of its {n} shells meet, by their boxes (a body that only sub-planes cut could overlap another)"
    return None


def layers_through_vertices(mesh, z: np.ndarray, k: int) -> np.ndarray:
    """(L,) bool: the layers one of whose ``k`` sub-planes ``z`` (mm, as float32: as the crossings cut them) passes
    through a mesh vertex. There loops may touch or degenerate (a ridge edge lying on the plane cuts a loop of two
    points, which nesting drops): those layers' sub-planes are cut the polygon way (module docstring)."""
    hit = np.isin(np.asarray(z, np.float32), np.asarray(mesh.vertices[:, 2], np.float32))
    return hit.reshape(-1, k).any(axis=1)


def iter_sub_plane_edges(mesh, z: np.ndarray, k: int, spec: RasterSpec, bounds, device,
                         slice_planes: Callable[[np.ndarray], object], chunk: int,
                         timings: dict[str, float] | None = None, group: int = 4
                         ) -> Iterator[tuple[int, LayerEdges, np.ndarray]]:
    """(first layer, the merged edges of layers first … first + chunk − 1, the layers among them cut the polygon
    way) for every chunk of layers, each layer's ``k`` sub-planes ``z`` (mm) from their segments on ``device``,
    except the layers with a sub-plane through a vertex (:func:`layers_through_vertices`) or a short segment
    (:func:`short_segments`), whose sub-planes are cut by ``slice_planes(indices into z)`` (a
    :class:`~gpuslice.slicing.result.SliceResult`), those of ``group`` chunks at once (at most 256 layers a call), and
    spliced in. ``timings``: seconds added up under ``z_samples``. Memory: one chunk's segments, ``group`` chunks'
    edges, one block's polygons."""
    import time

    from ..slicing.crossings import batch_facets, batch_layers, compute_crossings, facet_layer_ranges, vertex_layers

    kern = SegmentEdgesKernel.of(device)
    n_layers = len(z) // k
    on_vertex = layers_through_vertices(mesh, z, k)
    chunk = min(chunk, 256)
    starts = list(range(0, n_layers, chunk))
    # each chunk's crossings visit only the facets that cross its sub-planes (grouped once)
    vl = vertex_layers(mesh, z)
    ranges = (vl, *facet_layer_ranges(mesh, z, vl))
    facets = batch_facets(ranges, [(a * k, min(a + chunk, n_layers) * k) for a in starts])
    scratch = np.empty(vl.shape, np.int32)
    for g in range(0, len(starts), group):  # `group` chunks at a time: their polygon layers sliced in one go
        t = time.perf_counter()
        done = []
        for c, a in enumerate(starts[g : g + group], g):
            b = min(a + chunk, n_layers)
            own = batch_layers(ranges, a * k, b * k, facets[c], scratch)
            with device.exclusive():  # (the crossings' buffers are read by the edges' kernels: one thread's turn)
                seg = compute_crossings(mesh, z[a * k : b * k], device, read_back=False, layers=own, facets=facets[c])
                merged, short = kern(seg, (b - a) * k, k, spec, bounds)
                del seg
            facets[c] = None  # (each chunk's ids are used once)
            done.append((a, merged, a + np.flatnonzero(short | on_vertex[a:b])))
        cut = np.concatenate([d[2] for d in done])
        for i in range(0, cut.size, 256):  # (blocks of at most EDGE_CHUNK layers: one chunk of polygon edges each)
            block = cut[i : i + 256]
            sub = slice_planes((block[:, None] * k + np.arange(k)).reshape(-1))
            ((_, block_edges),) = iter_layer_edges(sub, spec, bounds, k=k, dtype=np.float32)
            for j, (a, merged, need) in enumerate(done):
                mine = need[(need >= block[0]) & (need <= block[-1])]
                done[j] = (a, splice_layers(merged, mine - a, block_edges, np.searchsorted(block, mine)), need)
        if timings is not None:
            timings["z_samples"] = timings.get("z_samples", 0.0) + time.perf_counter() - t
        yield from done


def short_segments(p: np.ndarray) -> np.ndarray:
    """(S,) bool: segments ``p`` ((S, 4) float32 x0, y0, x1, y1 mm) shorter than :data:`SHORT` of their largest
    coordinate (at least 1 mm), in float32 as the kernel computes it."""
    p = np.asarray(p, np.float32)
    dx, dy = p[:, 2] - p[:, 0], p[:, 3] - p[:, 1]
    m = np.maximum(np.abs(p).max(axis=1, initial=np.float32(0)), np.float32(1)) * SHORT
    return dx * dx + dy * dy <= m * m


def _group_tiles(box: np.ndarray, k: int, spec: RasterSpec) -> np.ndarray:
    """Merged tiles of the groups of ``k`` sub-planes from each sub-plane's floor box (min u, max u, min v, max v;
    min = INT32 max where it has no point)."""
    sub = np.zeros((len(box), 4), np.int64)
    has = box[:, 0] != _BIG
    if has.any():
        sub[has] = box_tiles(box[has, 0], box[has, 1], box[has, 2], box[has, 3], spec)
    return merge_tiles(sub, k)


def segment_edges_numpy(seg: Segments, n_planes: int, k: int, spec: RasterSpec,
                        bounds) -> tuple[LayerEdges, np.ndarray]:
    """The numpy twin of :class:`SegmentEdgesKernel`: the edges of ``seg`` (cut at ``n_planes`` planes, ``k`` per
    layer) as every layer's, its sub-planes merged, float32, grouped by layer (in segment order within a layer), and
    (L,) bool: the layers with a short segment (:func:`short_segments`)."""
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
    short = np.zeros(len(tiles), bool)
    short[group[short_segments(p)]] = True
    return LayerEdges(edges, offsets, tiles), short


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

    @staticmethod
    def _affine_args(spec: RasterSpec, bounds):
        """The display's mapping as the kernels' two double4 arguments (u's row, v's row)."""
        import pyopencl as cl

        m = np.zeros((2, 4), np.float64)
        m[:, :3] = _affine(spec, bounds)
        return tuple(m[j].view(cl.cltypes.double4)[0] for j in (0, 1))

    def _bounds_pass(self, seg: DeviceSegments, n_planes: int, k: int, au, av):
        """segment_bounds: (box (P, 4) int32, count (S, G) int32, short (G,) int32) of the planes, and per stripe of
        work-groups (``STRIPES``) and group of ``k`` planes; each segment's rank in its stripe's count stays on the
        device (``rank``) for the scatter."""
        q, n, groups = self.device.queue, seg.n, n_planes // k
        box = np.empty((STRIPES, n_planes, 4), np.int32)
        box[..., 0::2], box[..., 1::2] = _BIG, -_BIG - 1
        b_box = self._put("box", box)
        b_count = self._fill("count", 4 * max(STRIPES * groups, 1), np.int32(0))
        b_short = self._fill("short", 4 * max(groups, 1), np.int32(0))
        count, short = np.zeros((STRIPES, groups), np.int32), np.zeros(groups, np.int32)
        if n:
            b_rank = self._buffer("rank", 4 * n)
            self._bounds(q, *self._grid(n), np.int32(n), seg.layer, seg.points, au, av, np.int32(k),
                         np.int32(n_planes), b_box, b_count, b_short, b_rank)
            self._read((box, b_box), (short, b_short), (count, b_count))
        joined = np.empty((n_planes, 4), np.int32)
        joined[:, 0::2], joined[:, 1::2] = box[..., 0::2].min(axis=0), box[..., 1::2].max(axis=0)
        return joined, count, short

    @property
    def available(self) -> bool:
        """Whether the device built the kernels (it has doubles)."""
        return self._bounds is not None

    def __call__(self, seg: DeviceSegments | Segments, n_planes: int, k: int, spec: RasterSpec,
                 bounds) -> tuple[LayerEdges, np.ndarray]:
        """The edges of ``seg`` (left on the device by the crossings kernel, or on the host: uploaded) cut at
        ``n_planes`` planes, ``k`` per layer, and the layers with a short segment, as :func:`segment_edges_numpy`;
        ``bounds`` (xmin, ymin, xmax, ymax) mm as the archive centres it."""
        import pyopencl as cl

        q = self.device.queue
        if k < 1 or n_planes % k:
            from ..errors import ParameterError

            raise ParameterError(f"{n_planes} planes are not layers of {k} sub-planes", param="z_samples")
        if isinstance(seg, Segments):
            seg = DeviceSegments(len(seg), self._put("seg_layer", np.ascontiguousarray(seg.layer, np.int32)), None,
                                 self._put("seg_points", np.ascontiguousarray(seg.points, np.float32)), None)
        au, av = self._affine_args(spec, bounds)
        box, count, short = self._bounds_pass(seg, n_planes, k, au, av)
        n, groups = seg.n, n_planes // k
        grid = self._grid(max(n, 1))
        tiles = _group_tiles(box.astype(np.int64), k, spec)
        offsets = np.zeros(groups + 1, np.int64)
        np.cumsum(count.sum(axis=0), out=offsets[1:])
        edges = np.empty((n, 4), np.float32)
        if n:
            # each stripe's first slot in each group: the group's first, then the stripes before it (int32: n fits)
            first = np.cumsum(count, axis=0, dtype=np.int32)
            first -= count
            first += offsets[:-1].astype(np.int32)
            first = self._put("first", first)
            corner = self._put("corner", np.ascontiguousarray(tiles[:, :2], np.int32))
            out = self._buffer("edges", 16 * n)
            self._scatter(q, *grid, np.int32(n), seg.layer, seg.points, au, av, np.int32(k), np.int32(groups), first,
                          corner, self.buffer("rank"), out)
            cl.enqueue_copy(q, edges, out, is_blocking=True)
        return LayerEdges(edges, offsets, tiles), short.astype(bool)
