"""Drawing layers with matplotlib (the ``plot`` extra; imported only when a plot is drawn).

Each layer is one ``PathPatch`` over a compound path: every closed loop a closed sub-path (``MOVETO``,
``LINETO``…, ``CLOSEPOLY``), built from the flat arrays without a loop per point. Holes run opposite to their
outer loops (clockwise against counter-clockwise), so under matplotlib's nonzero fill they are drawn as holes.
Open chains (broken meshes only) are drawn as red lines, never filled. Axes are in mm with equal aspect.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..ragged import expand_ranges
from .geometry import Contours

__all__ = ["plot_layers"]


def _closed_path(result: Contours, loops: np.ndarray):
    """A matplotlib ``Path`` of the closed ``loops`` (each with ≥ 2 points), or ``None`` if there are none."""
    from matplotlib.path import Path

    offsets = np.asarray(result.loop_offsets)
    counts = offsets[loops + 1] - offsets[loops]
    keep = counts >= 2
    loops, counts = loops[keep], counts[keep]
    if loops.size == 0:
        return None
    _, idx = expand_ranges(offsets[loops], counts)
    n = int(counts.sum()) + loops.size  # each loop gets one CLOSEPOLY vertex
    ends = np.cumsum(counts + 1) - 1  # index of each loop's CLOSEPOLY
    starts = ends - counts
    is_point = np.ones(n, dtype=bool)
    is_point[ends] = False
    verts = np.empty((n, 2), dtype=np.float64)
    verts[is_point] = result.points[idx]
    verts[ends] = verts[starts]
    codes = np.full(n, Path.LINETO, dtype=Path.code_type)
    codes[starts] = Path.MOVETO
    codes[ends] = Path.CLOSEPOLY
    return Path(verts, codes)


def plot_layers(
    result: Contours,
    layers: int | Iterable[int] | None = None,
    ax: Any = None,
    *,
    color: Any = None,
    alpha: float | None = None,
    edgecolor: Any = "k",
    linewidth: float = 0.5,
) -> Any:
    """Draw ``layers`` of ``result`` on matplotlib axes ``ax`` (new axes when ``None``) and return the axes.

    ``layers``: one layer index, a sequence of them, or ``None`` for every layer; several layers are overlaid, each
    coloured by its z (viridis) unless ``color`` is given, with ``alpha`` 0.35 (1 for a single layer) unless given.
    Holes are drawn as holes (a compound path per layer); open chains as red lines. Coordinates in mm, equal aspect.
    """
    try:
        import matplotlib.pyplot as plt
        from matplotlib.collections import LineCollection
        from matplotlib.patches import PathPatch
    except ImportError as exc:  # pragma: no cover - the plot extra
        raise ParameterError(f"plotting needs matplotlib (pip install 'gpuslice[plot]'): {exc}") from None
    if layers is None:
        index = list(range(result.n_layers))
    elif isinstance(layers, int | np.integer):
        index = [int(layers)]
    else:
        index = [int(i) for i in layers]
    for i in index:
        if not -result.n_layers <= i < result.n_layers:
            raise IndexError(f"layer {i} out of range for {result.n_layers} layers")
    index = [i % result.n_layers for i in index] if result.n_layers else []
    if ax is None:
        _, ax = plt.subplots()
    if alpha is None:
        alpha = 1.0 if len(index) == 1 else 0.35
    cmap = plt.get_cmap("viridis")
    z = np.asarray(result.z, dtype=np.float64)
    z_lo, z_span = (float(z.min()), float(np.ptp(z)) or 1.0) if z.size else (0.0, 1.0)
    closed = np.asarray(result.loop_closed, dtype=bool)
    lo_off = np.asarray(result.layer_offsets)
    offsets = np.asarray(result.loop_offsets)
    segments = []
    for i in index:  # one patch per layer: the loop over layers is not a loop over points
        loops = np.arange(lo_off[i], lo_off[i + 1])
        fill = color if color is not None else (cmap((z[i] - z_lo) / z_span) if len(index) > 1 else "#3b7dd8")
        path = _closed_path(result, loops[closed[loops]])
        if path is not None:
            ax.add_patch(PathPatch(path, facecolor=fill, edgecolor=edgecolor, linewidth=linewidth, alpha=alpha))
        segments.extend(
            np.asarray(result.points[offsets[r] : offsets[r + 1]], dtype=np.float64) for r in loops[~closed[loops]]
        )
    if segments:
        ax.add_collection(LineCollection(segments, colors="#d62728", linewidths=linewidth * 2))
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    if len(index) == 1:
        ax.set_title(f"layer {index[0]}, z = {z[index[0]]:.4g} mm")
    return ax
