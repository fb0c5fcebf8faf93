"""The weld and the edge ids on the OpenCL device (``kernels/weld.cl``), bit for bit the numpy path of ``mesh.py``.

Two numberings by first occurrence (see :func:`first_occurrence_ids`):

* **weld**: corners (N, 3) float32 with bit-identical coordinates share a vertex id (with ``signed_zero=False``,
  -0.0 counts as 0.0); ids are numbered in the order of their first corner. Returns ``vid`` (N,) int32 and
  ``first`` (V,) int64, the corner index of each id's first occurrence, so the vertices are ``corners[first]``.
* **edge ids**: side k of facet f (item 3f + k) joins ``faces[f, k]`` and ``faces[f, (k + 1) % 3]``; each undirected
  vertex pair gets one id, numbered in the order of its first side. Returns ``face_edges`` (F, 3) int32 and
  ``edge_vertices`` (E, 2) int32, the smaller vertex id first. :func:`edge_table_numpy` and
  :meth:`WeldKernel.edge_table` also give the **pairing** the mesh check uses (:class:`EdgeSides`): each edge's
  number of sides, its first and its last side (the two sides of a manifold edge), a by-product of the numbering.

The device path uses a hash table with atomics but is deterministic: each slot ends up holding the smallest index
with its key (atomic_min after the insert), and ids are the ranks of those firsts (a prefix sum), so the result is
exactly that of :func:`weld_numpy` / :func:`edge_ids_numpy`, the numpy twins (the code of ``mesh.py``).
:class:`ComponentsKernel` is the mesh check's connected components (a union-find, roots the smallest nodes), with
buffers, kernels and a lock of its own, on a queue of its own (:data:`COMPONENTS_LANE`): the mesh check counts
beside the slicing (``pipeline._slice``) without waiting for the slicer's turn on the device.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from ..device import KernelDriver, locked

__all__ = ["EdgeSides", "WeldKernel", "ComponentsKernel", "COMPONENTS_LANE", "first_occurrence_ids", "weld_device",
           "edge_ids_device", "weld_numpy", "edge_ids_numpy", "edge_table_numpy"]

# items per work-item in the counting and numbering passes
_CHUNK = 32
# the largest item count: table slots (a power of two > items) must stay addressable by int32
_MAX_ITEMS = 2**30 - 1
_NEGATIVE_ZERO = np.uint32(0x80000000)
# device buffers a driver keeps for reuse after building a mesh (WeldKernel.release)
_KEEP_BYTES = 64 << 20
_KERNEL_NAMES = (
    "insert_corners",
    "insert_sides",
    "count_firsts",
    "scan_counts",
    "emit_corners",
    "emit_sides",
    "gather_ids",
    "gather_sides",
)
#: the device lane (:meth:`gpuslice.device.Device.lane`: a queue of its own) of :class:`ComponentsKernel`: the
#: runs' lanes are 0 .. LANES - 1
COMPONENTS_LANE = 8


@dataclass
class EdgeSides:
    """How the facet sides pair up along each edge (by-products of the edge numbering, for the mesh check).

    ``count`` (E,) int32: sides (facets) per edge (2 on a closed manifold); ``first``, ``last`` (E,) int32: the
    smallest and the largest side index (3f + k) of the edge, equal when it has one side; ``forward`` (E,) int32:
    how many of its sides run from the smaller vertex id to the larger (1 of 2: the two facets agree in winding).
    """

    count: np.ndarray
    first: np.ndarray
    last: np.ndarray
    forward: np.ndarray

    @classmethod
    def empty(cls) -> EdgeSides:
        return cls(*(np.zeros(0, np.int32) for _ in range(4)))


def _first_occurrence(keys: np.ndarray, *, with_groups: bool = False, weights: np.ndarray | None = None):
    n = keys.shape[0]
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    start = np.empty(n, dtype=bool)
    start[0] = True
    np.not_equal(sk[1:], sk[:-1], out=start[1:])
    del sk
    group = np.cumsum(start) - 1
    starts = np.flatnonzero(start)
    firsts = order[starts]  # stable sort: the smallest index of each group
    rank = np.empty(firsts.size, dtype=np.int64)
    by_first = np.argsort(firsts)
    rank[by_first] = np.arange(firsts.size)
    ids = np.empty(n, dtype=np.int32)
    ids[order] = rank[group]
    if not with_groups:
        return ids, firsts[by_first]
    ends = np.append(starts[1:], n)
    # per id (first-occurrence order): the group's size, its largest index (the stable sort's last), its weights' sum
    total = np.add.reduceat(weights[order], starts) if weights is not None else None
    return ids, firsts[by_first], (ends - starts)[by_first], order[ends - 1][by_first], total[by_first]


def first_occurrence_ids(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Number equal keys by first occurrence.

    Returns ``ids`` (N,) int32 with ``ids[i] == ids[j]`` iff ``keys[i] == keys[j]``, numbered 0, 1, … in the order
    the distinct keys first appear, and ``first`` (K,) int64, the index of each id's first occurrence.
    """
    if keys.shape[0] == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int64)
    return _first_occurrence(keys)


def weld_numpy(corners: np.ndarray, *, signed_zero: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ids (N,) int32 and first corners (V,) int64 of bit-identical corners (the host weld of ``mesh.py``).

    ``signed_zero=False``: -0.0 welds with 0.0 (the corners need not be normalised by ``+ 0.0`` first).
    """
    corners = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 3)
    bits = corners.view(np.uint32)
    if not signed_zero:
        bits = np.where(bits == _NEGATIVE_ZERO, np.uint32(0), bits)
    wide = bits.astype(np.uint64)
    # a 64-bit mix of the three 32-bit patterns; equal patterns give equal keys, collisions are checked below
    key = wide[:, 0] * np.uint64(0x9E3779B97F4A7C15)
    key ^= (wide[:, 1] + np.uint64(0x632BE59BD9B4E019)) * np.uint64(0xBF58476D1CE4E5B9)
    key ^= (wide[:, 2] + np.uint64(0x8CB92BA72F3D8DD7)) * np.uint64(0x94D049BB133111EB)
    del wide
    ids, first = first_occurrence_ids(key)
    if not np.array_equal(bits[first][ids], bits):
        exact = np.ascontiguousarray(bits).view(np.dtype((np.void, 12))).reshape(-1)
        ids, first = first_occurrence_ids(exact)
    return ids, first


def _side_keys(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = faces.reshape(-1).astype(np.int64)
    b = np.roll(faces, -1, axis=1).reshape(-1).astype(np.int64)
    return np.minimum(a, b), np.maximum(a, b)


def edge_ids_numpy(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Edge id of each facet side (F, 3) int32 (side k joins corners k and k + 1) and each edge's (min, max) vertex
    ids (E, 2) int32, numbered by first occurrence (the host path of ``mesh.py``)."""
    faces = np.asarray(faces).reshape(-1, 3)
    lo, hi = _side_keys(faces)
    eid, efirst = first_occurrence_ids(lo * np.int64(n_vertices) + hi)
    edge_vertices = np.stack([lo[efirst], hi[efirst]], axis=1).astype(np.int32)
    return eid.reshape(-1, 3).astype(np.int32), edge_vertices


def edge_table_numpy(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, EdgeSides]:
    """:func:`edge_ids_numpy` and the :class:`EdgeSides` pairing, from one sort of the sides."""
    faces = np.asarray(faces).reshape(-1, 3)
    if faces.size == 0:
        return np.zeros((0, 3), np.int32), np.zeros((0, 2), np.int32), EdgeSides.empty()
    lo, hi = _side_keys(faces)
    forward = (faces.reshape(-1) < hi).astype(np.int32)  # the side runs from its smaller vertex to the larger
    eid, efirst, count, last, fw = _first_occurrence(lo * np.int64(n_vertices) + hi, with_groups=True, weights=forward)
    edge_vertices = np.stack([lo[efirst], hi[efirst]], axis=1).astype(np.int32)
    sides = EdgeSides(count.astype(np.int32), efirst.astype(np.int32), last.astype(np.int32), fw.astype(np.int32))
    return eid.reshape(-1, 3), edge_vertices, sides


def _table_size(n: int, factor: float) -> int:
    """The smallest power of two >= factor * n and > n (so a probe always finds an empty slot)."""
    want = max(int(np.ceil(factor * n)), n + 1, 2)
    return 1 << (want - 1).bit_length()


class WeldKernel(KernelDriver):
    """Driver of ``kernels/weld.cl`` on one device: keeps its kernels and reuses grown buffers across calls.

    Parameters
    ----------
    device : gpuslice.device.Device
    table_factor : float
        Hash-table slots per item, rounded up to a power of two (always more slots than items). 2 keeps the load
        at most 1/2 whatever the input; values near 1 give long collision chains (for tests).
    hash_bits : int
        Bits of the hash used (32 normally); tests use a few to force almost every key onto a few chains.
    """

    def __init__(self, device, *, table_factor: float = 2.0, hash_bits: int = 32) -> None:
        import pyopencl as cl

        if not table_factor >= 1.0:
            raise ValueError(f"table_factor must be at least 1, got {table_factor}")
        if not 0 <= hash_bits <= 32:
            raise ValueError(f"hash_bits must be in 0..32, got {hash_bits}")
        super().__init__(device)
        self.table_factor = float(table_factor)
        self._hash_and = np.uint32((1 << hash_bits) - 1)
        prg = device.program("weld.cl")
        self._k = {name: cl.Kernel(prg, f"weld_{name}") for name in _KERNEL_NAMES}

    def _number(self, kind: str, d_keys, n: int, key_arg) -> tuple[int, object, object]:
        """The passes on n > 0 items of ``kind`` ("corners" or "sides"): (number of ids, ids buffer, per-id buffer).

        The per-id buffer holds ``first`` (int64) for corners and ``edge_vertices`` (2 x int32) for sides (then
        also the buffers ``first_side``, ``count`` and ``last_side``). ``key_arg``: the insert kernel's extra
        argument (corners: the bits read as 0, sides: the probe spread).
        """
        import pyopencl as cl

        if n > _MAX_ITEMS:
            raise ValueError(f"{n} items: more than the device weld handles ({_MAX_ITEMS})")
        q, k = self.device.queue, self._k
        size = _table_size(n, self.table_factor)
        if size > 2**31:
            raise ValueError(f"{n} items: a table of {size} slots is more than int32 slot indices address")
        n_chunks = (n + _CHUNK - 1) // _CHUNK
        d_slots = self._fill("slots", 4 * size, np.int32(-1))
        d_slot_of = self._buffer("slot_of", 4 * n)
        d_flags = self._buffer("is_first", n)
        d_counts = self._buffer("counts", 4 * n_chunks)
        d_offsets = self._buffer("offsets", 4 * n_chunks)
        d_total = self._buffer("total", 4)
        d_ids = self._buffer("ids", 4 * n)
        d_per_id = self._buffer("per_id", 8 * n)
        n_, chunk, nc = np.int32(n), np.int32(_CHUNK), np.int32(n_chunks)
        items, chunks = self._grid(n), self._grid(n_chunks)
        mask = np.uint32(size - 1)
        if kind == "sides":  # the first probe: lo * spread + hash(hi) % spread (see weld.cl)
            spread = np.uint32(1 << max(0, (size // max(1, int(key_arg))).bit_length() - 1))
            k["insert_sides"](q, *items, d_keys, n_, d_slots, mask, self._hash_and, spread, d_slot_of)
        else:
            k["insert_corners"](q, *items, d_keys, n_, d_slots, mask, self._hash_and, np.uint32(key_arg), d_slot_of)
        k["count_firsts"](q, *chunks, d_slots, d_slot_of, n_, chunk, nc, d_flags, d_counts)
        k["scan_counts"](q, *self._grid(1), d_counts, nc, d_offsets, d_total)
        if kind == "sides":
            d_first_side = self._buffer("first_side", 4 * n)
            d_count = self._buffer("side_count", 4 * n)
            d_last = self._buffer("last_side", 4 * n)
            d_forward = self._buffer("forward", 4 * n)
            k["emit_sides"](q, *chunks, d_slots, d_slot_of, n_, chunk, nc, d_flags, d_offsets, d_keys, d_per_id,
                            d_first_side, d_count, d_last, d_forward)
            k["gather_sides"](q, *items, d_slots, d_slot_of, n_, d_keys, d_ids, d_count, d_last, d_forward)
        else:
            k["emit_corners"](q, *chunks, d_slots, d_slot_of, n_, chunk, nc, d_flags, d_offsets, d_per_id)
            k["gather_ids"](q, *items, d_slots, d_slot_of, n_, d_ids)
        total = np.empty(1, dtype=np.int32)
        cl.enqueue_copy(q, total, d_total, is_blocking=True)
        return int(total[0]), d_ids, d_per_id

    @locked
    def weld(self, corners: np.ndarray, *, signed_zero: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """``(vid, first)`` of (N, 3) float32 corners: the same arrays as :func:`weld_numpy` (``signed_zero=False``:
        -0.0 welds with 0.0, read so by the kernel: no normalised copy of the corners is needed)."""
        corners = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 3)
        n = corners.shape[0]
        if n == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.int64)
        zero = 0 if signed_zero else int(_NEGATIVE_ZERO)
        n_ids, d_ids, d_first = self._number("corners", self._put("corners", corners), n, zero)
        vid = np.empty(n, dtype=np.int32)
        first = np.empty(n_ids, dtype=np.int64)
        self._read((vid, d_ids), (first, d_first))
        if corners.nbytes > _KEEP_BYTES // 4:  # not kept through the edge pass (peak memory)
            del self._buffers["corners"]
        return vid, first

    @locked
    def edge_table(self, faces: np.ndarray, n_vertices: int | None = None, *, check: bool = True):
        """``(face_edges, edge_vertices, sides)``: the arrays of :func:`edge_ids_numpy` and the :class:`EdgeSides`
        pairing (the same as :func:`edge_table_numpy`'s), of (F, 3) vertex ids.

        The ids are only used as keys; ``n_vertices`` (optional) is checked: every id must lie in [0, n_vertices)
        (``check=False``: trusted, e.g. the weld's own ids; it then only spreads the hash table's first probes).
        """
        faces = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
        n = faces.size
        if n == 0:
            return np.zeros((0, 3), np.int32), np.zeros((0, 2), np.int32), EdgeSides.empty()
        if n_vertices is None or check:
            lo, hi = int(faces.min()), int(faces.max())
            if n_vertices is not None and (lo < 0 or hi >= n_vertices):
                raise ValueError(f"face vertex ids outside [0, {n_vertices})")
            n_vertices = max(hi + 1, 1) if n_vertices is None else n_vertices
        n_ids, d_ids, d_ev = self._number("sides", self._put("faces", faces), n, n_vertices)
        face_edges = np.empty((n // 3, 3), dtype=np.int32)
        edge_vertices = np.empty((n_ids, 2), dtype=np.int32)
        sides = EdgeSides(*(np.empty(n_ids, np.int32) for _ in range(4)))
        self._read((face_edges, d_ids), (edge_vertices, d_ev), (sides.count, self.buffer("side_count")),
                   (sides.first, self.buffer("first_side")), (sides.forward, self.buffer("forward")),
                   (sides.last, self.buffer("last_side")))
        return face_edges, edge_vertices, sides

    def edge_ids(self, faces: np.ndarray, n_vertices: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(face_edges, edge_vertices)`` of (F, 3) vertex ids: the same arrays as :func:`edge_ids_numpy`."""
        return self.edge_table(faces, n_vertices)[:2]

    @locked
    def release(self, keep_bytes: int = _KEEP_BYTES) -> None:
        """Drop this driver's device buffers when together they hold more than ``keep_bytes``: a large mesh's tables
        (~140 bytes a facet) would otherwise stay allocated through slicing, raising the job's peak memory; small
        ones are kept for reuse (batches of small models). They are made again, at the size needed, on next use."""
        _drop_buffers_over(self, keep_bytes)


def _drop_buffers_over(driver: KernelDriver, keep_bytes: int) -> None:
    """Drop ``driver``'s device buffers when together they hold more than ``keep_bytes`` (its caller's lock held)."""
    if sum(size for _, size in driver._buffers.values()) > keep_bytes:
        driver._buffers.clear()


class ComponentsKernel(KernelDriver):
    """Driver of the union-find of ``kernels/weld.cl``: connected components on one device (or lane), with kernel
    objects, buffers and a lock of its own (not one of :data:`gpuslice.device.SHARED_DRIVERS`): a thread may use it
    while another holds the device's turn (:meth:`gpuslice.device.Device.exclusive`), on its lane's queue."""

    def __init__(self, device) -> None:
        import pyopencl as cl

        super().__init__(device)
        prg = device.program("weld.cl")
        self._k = {name: cl.Kernel(prg, f"weld_{name}") for name in ("cc_init", "cc_hook", "cc_flatten")}
        self._lock = threading.Lock()

    def components(self, n: int, a: np.ndarray, b: np.ndarray, keep_bytes: int = _KEEP_BYTES) -> np.ndarray:
        """Connected components of the graph on nodes ``0 .. n - 1`` with edges ``a[i] -- b[i]``: (n,) int32 labels,
        each node labelled with the smallest node of its component (as :func:`gpuslice.mesh.graph.connected_labels`).
        The buffers are dropped afterwards when they hold more than ``keep_bytes``."""
        if n == 0:
            return np.zeros(0, np.int32)
        if n > 2**31 - 1:
            raise ValueError(f"{n} nodes: more than int32 node ids address")
        self.device.check_process()  # (a forked child's context: a DeviceError, not a wait for ever)
        with self._lock:
            q, k = self.device.queue, self._k
            m = int(np.asarray(a).shape[0])
            d_parent = self._buffer("cc_parent", 4 * n)
            d_label = self._buffer("cc_label", 4 * n)
            k["cc_init"](q, *self._grid(n), d_parent, np.int32(n))
            if m:
                d_a = self._put("cc_a", np.asarray(a, dtype=np.int32))
                d_b = self._put("cc_b", np.asarray(b, dtype=np.int32))
                k["cc_hook"](q, *self._grid(m), d_parent, d_a, d_b, np.int32(m))
            k["cc_flatten"](q, *self._grid(n), d_parent, np.int32(n), d_label)
            label = np.empty(n, dtype=np.int32)
            self._read((label, d_label))  # (waits for the queue: the uploads' arrays may go now)
            _drop_buffers_over(self, keep_bytes)
        return label


def weld_device(corners: np.ndarray, device, *, signed_zero: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ids (N,) int32 and first corners (V,) int64 of bit-identical corners, on ``device``."""
    return WeldKernel.of(device).weld(corners, signed_zero=signed_zero)


def edge_ids_device(faces: np.ndarray, n_vertices: int, device) -> tuple[np.ndarray, np.ndarray]:
    """Edge ids (F, 3) int32 of the facet sides and each edge's (min, max) vertex ids (E, 2) int32, on ``device``."""
    return WeldKernel.of(device).edge_ids(faces, n_vertices)
