"""The weld and the edge ids on the OpenCL device (``kernels/weld.cl``), bit for bit the numpy path of ``mesh.py``.

Two numberings by first occurrence (see :func:`first_occurrence_ids`):

* **weld**: corners (N, 3) float32 (already ``+ 0.0``-normalised, so -0.0 is 0.0) with bit-identical coordinates
  share a vertex id; ids are numbered in the order of their first corner. Returns ``vid`` (N,) int32 and ``first``
  (V,) int64, the corner index of each id's first occurrence, so the vertices are ``corners[first]``.
* **edge ids**: side k of facet f (item 3f + k) joins ``faces[f, k]`` and ``faces[f, (k + 1) % 3]``; each undirected
  vertex pair gets one id, numbered in the order of its first side. Returns ``face_edges`` (F, 3) int32 and
  ``edge_vertices`` (E, 2) int32, the smaller vertex id first.

The device path uses a hash table with atomics but is deterministic: each slot ends up holding the smallest index
with its key (atomic_min after the insert), and ids are the ranks of those firsts (a prefix sum), so the result is
exactly that of :func:`weld_numpy` / :func:`edge_ids_numpy`, the numpy twins (the code of ``mesh.py``).
"""

from __future__ import annotations

import numpy as np

from ..device import KernelDriver

__all__ = ["WeldKernel", "first_occurrence_ids", "weld_device", "edge_ids_device", "weld_numpy", "edge_ids_numpy"]

# items per work-item in the counting and numbering passes
_CHUNK = 32
# the largest item count: table slots (a power of two > items) must stay addressable by int32
_MAX_ITEMS = 2**30 - 1
_KERNEL_NAMES = (
    "insert_corners",
    "insert_sides",
    "count_firsts",
    "scan_counts",
    "emit_corners",
    "emit_sides",
    "gather_ids",
)


def first_occurrence_ids(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Number equal keys by first occurrence.

    Returns ``ids`` (N,) int32 with ``ids[i] == ids[j]`` iff ``keys[i] == keys[j]``, numbered 0, 1, … in the order
    the distinct keys first appear, and ``first`` (K,) int64, the index of each id's first occurrence.
    """
    n = keys.shape[0]
    if n == 0:
        return np.zeros(0, np.int32), np.zeros(0, np.int64)
    order = np.argsort(keys, kind="stable")
    sk = keys[order]
    start = np.empty(n, dtype=bool)
    start[0] = True
    np.not_equal(sk[1:], sk[:-1], out=start[1:])
    group = np.cumsum(start) - 1
    firsts = order[start]  # stable sort: the smallest index of each group
    rank = np.empty(firsts.size, dtype=np.int64)
    by_first = np.argsort(firsts)
    rank[by_first] = np.arange(firsts.size)
    ids = np.empty(n, dtype=np.int32)
    ids[order] = rank[group]
    return ids, firsts[by_first]


def weld_numpy(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ids (N,) int32 and first corners (V,) int64 of bit-identical corners (the host weld of ``mesh.py``)."""
    corners = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 3)
    bits = corners.view(np.uint32).astype(np.uint64)
    # a 64-bit mix of the three 32-bit patterns; equal patterns give equal keys, collisions are checked below
    key = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
    key ^= (bits[:, 1] + np.uint64(0x632BE59BD9B4E019)) * np.uint64(0xBF58476D1CE4E5B9)
    key ^= (bits[:, 2] + np.uint64(0x8CB92BA72F3D8DD7)) * np.uint64(0x94D049BB133111EB)
    ids, first = first_occurrence_ids(key)
    if not np.array_equal(corners[first][ids].view(np.uint32), corners.view(np.uint32)):
        exact = corners.view(np.dtype((np.void, 12))).reshape(-1)
        ids, first = first_occurrence_ids(exact)
    return ids, first


def edge_ids_numpy(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Edge id of each facet side (F, 3) int32 (side k joins corners k and k + 1) and each edge's (min, max) vertex
    ids (E, 2) int32, numbered by first occurrence (the host path of ``mesh.py``)."""
    faces = np.asarray(faces).reshape(-1, 3)
    a = faces.reshape(-1).astype(np.int64)
    b = np.roll(faces, -1, axis=1).reshape(-1).astype(np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    eid, efirst = first_occurrence_ids(lo * np.int64(n_vertices) + hi)
    edge_vertices = np.stack([lo[efirst], hi[efirst]], axis=1).astype(np.int32)
    return eid.reshape(-1, 3).astype(np.int32), edge_vertices


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
        k = {name: cl.Kernel(prg, f"weld_{name}") for name in _KERNEL_NAMES}
        self._insert = {"corners": k["insert_corners"], "sides": k["insert_sides"]}
        self._emit = {"corners": k["emit_corners"], "sides": k["emit_sides"]}
        self._count, self._scan, self._gather = k["count_firsts"], k["scan_counts"], k["gather_ids"]

    def _number(self, kind: str, d_keys, n: int) -> tuple[int, object, object]:
        """The passes on n > 0 items of ``kind`` ("corners" or "sides"): (number of ids, ids buffer, per-id buffer).

        The per-id buffer holds ``first`` (int64) for corners and ``edge_vertices`` (2 x int32) for sides.
        """
        import pyopencl as cl

        if n > _MAX_ITEMS:
            raise ValueError(f"{n} items: more than the device weld handles ({_MAX_ITEMS})")
        q = self.device.queue
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
        self._insert[kind](q, *items, d_keys, n_, d_slots, np.uint32(size - 1), self._hash_and, d_slot_of)
        self._count(q, *chunks, d_slots, d_slot_of, n_, chunk, nc, d_flags, d_counts)
        self._scan(q, *self._grid(1), d_counts, nc, d_offsets, d_total)
        extra = (d_keys,) if kind == "sides" else ()
        self._emit[kind](q, *chunks, d_slots, d_slot_of, n_, chunk, nc, d_flags, d_offsets, *extra, d_per_id)
        self._gather(q, *items, d_slots, d_slot_of, n_, d_ids)
        total = np.empty(1, dtype=np.int32)
        cl.enqueue_copy(q, total, d_total, is_blocking=True)
        return int(total[0]), d_ids, d_per_id

    def weld(self, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(vid, first)`` of (N, 3) float32 corners: the same arrays as :func:`weld_numpy`."""
        import pyopencl as cl

        corners = np.ascontiguousarray(corners, dtype=np.float32).reshape(-1, 3)
        n = corners.shape[0]
        if n == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.int64)
        q = self.device.queue
        n_ids, d_ids, d_first = self._number("corners", self._put("corners", corners), n)
        vid = np.empty(n, dtype=np.int32)
        first = np.empty(n_ids, dtype=np.int64)
        cl.enqueue_copy(q, vid, d_ids, is_blocking=False)
        cl.enqueue_copy(q, first, d_first, is_blocking=True)
        return vid, first

    def edge_ids(self, faces: np.ndarray, n_vertices: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(face_edges, edge_vertices)`` of (F, 3) vertex ids: the same arrays as :func:`edge_ids_numpy`.

        The ids are only used as keys; ``n_vertices`` (optional) is checked: every id must lie in [0, n_vertices).
        """
        import pyopencl as cl

        faces = np.ascontiguousarray(faces, dtype=np.int32).reshape(-1, 3)
        n = faces.size
        if n == 0:
            return np.zeros((0, 3), np.int32), np.zeros((0, 2), np.int32)
        if n_vertices is not None and (faces.min() < 0 or faces.max() >= n_vertices):
            raise ValueError(f"face vertex ids outside [0, {n_vertices})")
        q = self.device.queue
        n_ids, d_ids, d_ev = self._number("sides", self._put("faces", faces), n)
        face_edges = np.empty((n // 3, 3), dtype=np.int32)
        edge_vertices = np.empty((n_ids, 2), dtype=np.int32)
        cl.enqueue_copy(q, face_edges, d_ids, is_blocking=False)
        cl.enqueue_copy(q, edge_vertices, d_ev, is_blocking=True)
        return face_edges, edge_vertices


def weld_device(corners: np.ndarray, device) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ids (N,) int32 and first corners (V,) int64 of bit-identical corners, on ``device``."""
    return WeldKernel.of(device).weld(corners)


def edge_ids_device(faces: np.ndarray, n_vertices: int, device) -> tuple[np.ndarray, np.ndarray]:
    """Edge ids (F, 3) int32 of the facet sides and each edge's (min, max) vertex ids (E, 2) int32, on ``device``."""
    return WeldKernel.of(device).edge_ids(faces, n_vertices)
