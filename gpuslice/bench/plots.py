"""Plots of the paper's figures (matplotlib, the optional ``plot`` extra; Agg backend, imported only when used).

Each function writes ``<stem>.png`` and ``<stem>.svg`` atomically and returns the paths:

* :func:`plot_points_per_layer`: points per layer against layer index, the uniform settings overlaid (Fig. 6), and
  against height for every setting with the roi windows shaded.
* :func:`plot_roi_levels`: the roi ladder's levels, one panel each, the chosen windows shaded (Fig. 11).
* :func:`plot_schedule`: layer thickness against height for every setting (uniform and adaptive).
* :func:`plot_layers`: chosen layers' contours (left) and their points (right) (Fig. 5 / Fig. 10).
* :func:`plot_stack`: a 3D stack of contours per setting (Fig. 8).

Dense artists (3D lines, point clouds) are rasterised inside the SVGs so the files stay small.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ParameterError
from ..slicing.result import SliceResult

__all__ = ["plot_points_per_layer", "plot_roi_levels", "plot_schedule", "plot_layers", "plot_stack", "plot_all",
           "default_layers"]


def _mpl():
    try:
        import matplotlib
    except ImportError:  # pragma: no cover
        raise ParameterError("plots need matplotlib: pip install 'gpuslice[plot]'") from None
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, stem: Path) -> list[Path]:
    from ..io.atomic import atomic_path

    out = []
    width_in = float(fig.get_size_inches()[0])
    for fmt, dpi in (("png", min(110.0, 1300.0 / width_in)), ("svg", 72)):
        path = stem.with_suffix(f".{fmt}")
        with atomic_path(path) as tmp:
            if fmt == "png":  # a 256-colour palette keeps line-art PNGs small (Pillow comes with matplotlib)
                import io

                from PIL import Image

                buf = io.BytesIO()
                fig.savefig(buf, format="png", dpi=dpi, facecolor="white")
                buf.seek(0)
                with Image.open(buf) as im:
                    im.convert("RGB").quantize(256).save(tmp, format="PNG", optimize=True)
            else:  # fixed element ids (matplotlib's are random unless salted): the same plot, the same bytes
                with _mpl().rc_context({"svg.hashsalt": "gpuslice"}):
                    fig.savefig(tmp, format=fmt, dpi=dpi, metadata={"Date": None})
        out.append(path)
    _mpl().close(fig)
    return out


def plot_points_per_layer(results: dict[str, SliceResult], stem: str | Path, title: str = "") -> list[Path]:
    """Points per layer (the paper's Fig. 6): against layer index for the uniform settings (top), and against height
    for every setting (bottom), with the roi windows of each level shaded."""
    plt = _mpl()
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6.4))
    shades = ["tab:orange", "tab:green", "tab:purple", "tab:red"]
    for label, r in results.items():
        info = r.meta.get("adaptive") or {}
        dense = r.n_layers > 1500  # long curves are rasterised inside the SVG (small files)
        if not info:
            top.plot(np.arange(r.n_layers), r.points_per_layer, lw=0.8, label=f"{label} ({r.n_layers} layers)",
                     rasterized=dense)
        bottom.plot(r.z, r.points_per_layer, lw=0.7, label=f"{label} ({r.n_layers} layers)", rasterized=dense)
        for lv in info.get("levels", []):
            for w in lv["windows"]:
                bottom.axvspan(*w["z_mm"], color=shades[lv["level"] % len(shades)], alpha=0.15,
                               label=f"roi window, level {lv['level']} ({lv['thickness_mm']:g} mm)")
    top.set_xlabel("layer index")
    bottom.set_xlabel("z (mm)")
    for ax in (top, bottom):
        ax.set_ylabel("points per layer")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    top.set_title(title or "points per layer", fontsize=10)
    fig.tight_layout()
    return _save(fig, Path(stem))


def plot_roi_levels(result: SliceResult, stem: str | Path, title: str = "") -> list[Path]:
    """The roi levels (Fig. 11): each level's points per layer (index within its region), windows shaded; the last
    panel is the finest level, taken from the final schedule's layers inside the deepest window."""
    plt = _mpl()
    info = result.meta.get("adaptive") or {}
    levels = info.get("levels", [])
    if not levels:
        raise ParameterError("plot_roi_levels: the result carries no roi levels (slice with --adaptive roi)")
    ladder = info.get("ladder_mm", [])
    panels = len(levels) + (1 if len(ladder) > len(levels) else 0)
    fig, axes = plt.subplots(panels, 1, figsize=(8, 2.4 * panels), squeeze=False)
    colors = ["tab:orange", "tab:green", "tab:purple", "tab:red"]
    for k, lv in enumerate(levels):
        ax = axes[k, 0]
        pts = np.asarray(lv["points"])
        ax.plot(np.arange(pts.size), pts, lw=0.9, color="tab:blue")
        ax.axhline(lv["threshold_points"], color="grey", lw=0.7, ls="--", label="threshold")
        for w in lv["windows"]:
            i0, i1 = w["layers"]
            ax.axvspan(i0, i1, color=colors[k % len(colors)], alpha=0.25,
                       label=f"window [{i0}, {i1}]: z {w['z_mm'][0]:.4g}..{w['z_mm'][1]:.4g} mm")
        ax.set_title(f"level {k}: {lv['thickness_mm']:g} mm over z {lv['region_mm'][0]:.4g}.."
                     f"{lv['region_mm'][1]:.4g} mm", fontsize=9)
        ax.set_ylabel("points")
        ax.legend(fontsize=7, loc="upper left")
        ax.grid(alpha=0.3)
    if panels > len(levels):
        ax = axes[-1, 0]
        last = levels[-1]
        for w in last["windows"]:
            a, b = w["z_mm"]
            sel = (result.z > a) & (result.z < b)
            pts = result.points_per_layer[sel]
            ax.plot(np.arange(pts.size), pts, lw=0.9, color="tab:blue")
        ax.set_title(f"level {len(levels)}: {ladder[len(levels)]:g} mm inside the window(s) of level "
                     f"{len(levels) - 1}", fontsize=9)
        ax.set_ylabel("points")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("layer index within the level's region")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, Path(stem))


def plot_schedule(results: dict[str, SliceResult], stem: str | Path, title: str = "") -> list[Path]:
    """Layer thickness against height (a step per layer) for every setting."""
    plt = _mpl()
    fig, ax = plt.subplots(figsize=(8, 3.6))
    for label, r in results.items():
        edges = np.concatenate(([0.0], np.cumsum(r.thickness)))
        ax.stairs(r.thickness, edges, baseline=None, label=f"{label} ({r.n_layers} layers)", lw=1.0)
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("layer thickness (mm)")
    ax.set_yscale("log")
    ax.set_title(title or "layer thickness")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    return _save(fig, Path(stem))


def default_layers(result: SliceResult) -> list[int]:
    """Layers worth drawing: the roi windows' end layers (Fig. 10), else the layers at 25 % and 75 % of the height."""
    info = result.meta.get("adaptive") or {}
    idx = []
    for lv in info.get("levels", [])[:2]:
        for w in lv["windows"][:1]:  # the first layer inside the window and the last one
            idx += [int(np.searchsorted(result.z, w["z_mm"][0])), int(np.searchsorted(result.z, w["z_mm"][1])) - 1]
    if not idx:
        top = float(result.bottom[-1] + result.thickness[-1]) if result.n_layers else 0.0
        idx = [int(i) for i in np.searchsorted(result.z, [0.25 * top, 0.75 * top])]
    return sorted(set(int(np.clip(i, 0, max(result.n_layers - 1, 0))) for i in idx))


def plot_layers(result: SliceResult, layers: list[int], stem: str | Path, title: str = "") -> list[Path]:
    """Each chosen layer's contours (left, lines) and points (right) (the paper's Fig. 5 / Fig. 10)."""
    plt = _mpl()
    if not layers:
        raise ParameterError("plot_layers: no layers chosen")
    fig, axes = plt.subplots(len(layers), 2, figsize=(7, 3.2 * len(layers)), squeeze=False)
    for row, i in enumerate(layers):
        lv = result.layer(i)
        for k in range(len(lv.loops)):
            p = lv.loop(k)
            closed = np.vstack((p, p[:1])) if result.loop_closed[lv.loops[k]] else p
            color = "tab:red" if result.loop_is_hole[lv.loops[k]] else "tab:blue"
            axes[row, 0].plot(closed[:, 0], closed[:, 1], lw=0.7, color=color)
        pts = result.points[result.loop_offsets[lv.loops.start]: result.loop_offsets[lv.loops.stop]]
        axes[row, 1].scatter(pts[:, 0], pts[:, 1], s=0.6, color="k", rasterized=True)
        axes[row, 0].set_title(f"layer #{i}, z = {lv.z:.4g} mm: contours", fontsize=9)
        axes[row, 1].set_title(f"layer #{i}: {lv.n_points} points", fontsize=9)
        for ax in axes[row]:
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, Path(stem))


def plot_stack(results: dict[str, SliceResult], stem: str | Path, max_layers: int = 60, max_points: int = 200,
               title: str = "") -> list[Path]:
    """A 3D stack of contours per setting (the paper's Fig. 8): at most ``max_layers`` layers per panel (evenly
    spaced) and ``max_points`` points per loop (decimated), drawn as rasterised lines."""
    plt = _mpl()
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    n = len(results)
    fig = plt.figure(figsize=(3.6 * n, 4.2))
    for k, (label, r) in enumerate(results.items()):
        ax = fig.add_subplot(1, n, k + 1, projection="3d")
        pick = np.unique(np.linspace(0, r.n_layers - 1, min(max_layers, r.n_layers)).astype(int)) if r.n_layers \
            else np.zeros(0, int)
        segs = []
        for i in pick:
            lv = r.layer(int(i))
            for j in range(len(lv.loops)):
                p = lv.loop(j)
                step = max(1, int(np.ceil(p.shape[0] / max_points)))
                q = np.vstack((p[::step], p[:1]))
                segs.append(np.column_stack((q, np.full(q.shape[0], lv.z))))
        if segs:
            ax.add_collection3d(Line3DCollection(segs, linewidths=0.5, colors="tab:blue", rasterized=True))
            allp = np.vstack(segs)
            lo, hi = allp.min(axis=0), allp.max(axis=0)
            flat = hi <= lo  # (one layer: its z alone, which matplotlib warned of and widened by itself)
            pad = 0.5 * float(np.max(r.thickness)) if r.n_layers else 0.5
            lo, hi = np.where(flat, lo - pad, lo), np.where(flat, hi + pad, hi)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_zlim(lo[2], hi[2])
            ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-9)))  # true proportions
        ax.set_title(f"{label}: {r.n_layers} layers", fontsize=9)
        ax.tick_params(labelsize=6)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, Path(stem))


def plot_all(results: dict[str, SliceResult], directory: str | Path, name: str = "model") -> list[Path]:
    """Every plot for these results into ``directory``: ``<name>_points``, ``_schedule``, ``_stack``, ``_layers``
    (of the roi result if any, else of the first), and ``_roi_levels`` when a roi result is present."""
    d = Path(directory)
    if not d.is_dir():
        raise ParameterError(f"{d}: plot directory does not exist")
    out = plot_points_per_layer(results, d / f"{name}_points", f"{name}: points per layer")
    out += plot_schedule(results, d / f"{name}_schedule", f"{name}: layer thickness")
    items = list(results.items())
    stack = dict(items if len(items) <= 4 else items[:2] + items[-2:])  # at most 4 panels: first two and last two
    out += plot_stack(stack, d / f"{name}_stack", title=f"{name}: contour stacks")
    roi = next((r for r in results.values() if (r.meta.get("adaptive") or {}).get("levels")), None)
    main = roi if roi is not None else next(iter(results.values()))
    out += plot_layers(main, default_layers(main), d / f"{name}_layers", f"{name}: chosen layers")
    if roi is not None:
        out += plot_roi_levels(roi, d / f"{name}_roi_levels", f"{name}: roi levels")
    return out
