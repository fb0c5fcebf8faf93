"""Connected components of graphs given as edge lists (numpy; the device's union-find or scipy where they pay).

Used by the mesh check (shells), ``count_bodies``, nesting (loops that share a face) and the pre-print checks
(holes and cavities). Kept apart from :mod:`gpuslice.mesh.defects` so that a caller needs neither the mesh check
nor scipy: scipy's ``connected_components`` is imported only for graphs of :data:`SCIPY_NODES` nodes or more (its
import, ~0.16 s, is most of a small command's start-up).
"""

from __future__ import annotations

import numpy as np

__all__ = ["connected_labels", "components", "SCIPY_NODES"]

#: graphs with at least this many nodes go to scipy on the host (linear; the numpy pointer jumping is not)
SCIPY_NODES = 200_000


def connected_labels(n: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of the graph on nodes ``0 .. n - 1`` with edges ``a[i] -- b[i]``: (n,) int64 labels,
    each node labelled with the smallest node of its component.

    Min-label hooking with full pointer jumping (numpy only: no scipy import on the command line's path); the number
    of rounds grows with the logarithm of the component sizes.
    """
    label = np.arange(n, dtype=np.int64)
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    while a.size:
        la, lb = label[a], label[b]
        differ = la != lb
        if not differ.any():
            break
        a, b, la, lb = a[differ], b[differ], la[differ], lb[differ]  # edges inside a finished tree are done
        low = np.minimum(la, lb)
        np.minimum.at(label, np.maximum(la, lb), low)  # hook the larger root under the smaller
        while True:  # pointer jumping until every node points at its root
            up = label[label]
            if np.array_equal(up, label):
                break
            label = up
    return label


def components(n: int, a: np.ndarray, b: np.ndarray, device=None) -> np.ndarray:
    """:func:`connected_labels` (labels: the smallest node of each component) in linear time: on ``device`` (the
    union-find of ``kernels/weld.cl``), else with scipy's ``connected_components`` for large graphs (its import,
    ~0.2 s, pays off), else :func:`connected_labels`. Returns (n,) int32 or int64 labels."""
    if device is not None:  # (on a queue and with buffers of its own: not waiting for a slicer holding the device)
        from .weld import COMPONENTS_LANE, ComponentsKernel

        return ComponentsKernel.of(device.lane(COMPONENTS_LANE)).components(n, a, b)
    if n < SCIPY_NODES:
        return connected_labels(n, a, b)
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    graph = csr_matrix((np.ones(a.size, dtype=np.int8), (a, b)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    del graph
    smallest = np.empty(int(comp.max()) + 1 if n else 0, dtype=np.int64)
    nodes = np.arange(n, dtype=np.int64)
    smallest[comp[::-1]] = nodes[::-1]  # the last write wins: each component's smallest node
    return smallest[comp]
