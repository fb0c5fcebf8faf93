"""The slicing options, declared once (:mod:`gpuslice.options`): :class:`SliceParams`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ..errors import ParameterError
from ..options import check_flag, is_real, option, parse_floats, python_number
from ..schedule.adaptive import ADAPTIVE_MODES
from .nest import FILL_RULES

__all__ = ["SliceParams", "BACKENDS", "Z_MODES"]

#: the slicing backends: the OpenCL kernels, or their numpy reference twins
BACKENDS = ("opencl", "numpy")
#: where a uniform layer is cut: the middle of its slab, or the paper's Z_i = i*h
Z_MODES = ("mid", "paper")


@dataclass(frozen=True)
class SliceParams:
    """Every slicing option in one place (lengths in mm); each field's help is its documentation.

    thickness : uniform layer thickness h (ignored when a schedule or z values are given).
    first_layer : thickness of the first layer (default: h).
    z_mode : ``"mid"`` (planes at the middle of each slab, z_i = (i + 0.5)·h) or ``"paper"`` (Z_i = i·h).
    fill_rule : ``"nonzero"``, ``"evenodd"`` or ``"positive"``.
    max_gap : open chain ends closer than this are joined (PrusaSlicer's default: 2 mm); 0 disables.
    join_edges : open mesh edges are joined to a nearby open edge whose corners lie within this distance (mm) and a
        quarter of the edge's length, before slicing (:mod:`gpuslice.mesh.seams`); 0 disables.
    fill_holes : the loops of open edges left are closed by fans of facets before slicing
        (:mod:`gpuslice.mesh.holes`); False leaves them open (their layers' chains are joined across gaps up to
        ``max_gap``, and a chain left open is not filled).
    backend : ``"opencl"`` (default) or ``"numpy"`` (the reference implementation of every kernel).
    device : OpenCL device spec (see :mod:`gpuslice.device`); None for the default.
    max_segments_per_batch : layers are processed in batches of at most about this many segments.
    adaptive : None (uniform), ``"roi"``, ``"cusp"`` or ``"area"``: an adaptive schedule
        (:mod:`gpuslice.schedule.adaptive`).
    max_cusp : cusp mode: the largest cusp height t·|n_z|, mm. max_area : area mode: the largest staircase error
        area per unit length, mm². min_height, max_height : cusp/area modes: thickness clamp, mm. smooth : cusp/area
        modes: the thickness changes by at most this many mm per mm of height, give or take one bin of the grid
        the layer tops lie on (``min_height / 10``) (0: no smoothing).
    roi_ladder : roi mode: thicknesses, coarse to fine, mm. roi_threshold : roi mode: points per layer (one value,
        or one per refinement step); None: the ``roi_quantile`` of each level's signal. roi_windows : windows kept per
        level (0: all).
    """

    thickness: float = option(0.1, "Layer thickness", unit="mm", flags=("-t", "--thickness"))
    first_layer: float | None = option(None, "First layer thickness (default: -t)", unit="mm")
    z_mode: str = option("mid", "mid: cut at the middle of each layer, z=(i+0.5)h; paper: at its top, z=(i+1)h "
                         "(the paper's Z_i = i*h, counted from 1)", choices=Z_MODES)
    fill_rule: str = option("nonzero", "Which loops bound material (positive: only where the mesh's winding is "
                            "positive, so an inside-out shell is empty)", choices=FILL_RULES)
    max_gap: float = option(2.0, "Join open chain ends closer than this (0: never); chains left open are not filled",
                            unit="mm")
    join_edges: float = option(0.01, "Before slicing, join each open mesh edge to one whose corners lie closer than "
                               "this (0: never) and within a quarter of the edge's length: a triangle soup's edges, "
                               "edges an exporter did not weld", unit="mm")
    fill_holes: bool = option(True, "Before slicing, close each loop of open mesh edges (a hole: an open scan's, a "
                              "missing facet) with a fan of facets, as PrusaSlicer's loader does", negatable=True)
    backend: str = option("opencl", "The OpenCL kernels, or their numpy reference twins", choices=BACKENDS)
    device: str | None = option(None, "OpenCL device: 'P:D' index or a name piece (env GPUSLICE_DEVICE)")
    max_segments_per_batch: int = option(2_000_000, "Layers are sliced in batches of at most about this many "
                                         "segments (bounds memory)", flags=())
    adaptive: str | None = option(None, "Adaptive layers: roi (the paper's ladder), cusp (t*|n_z| <= --max-cusp), "
                                  "area (error area)", choices=ADAPTIVE_MODES)
    max_cusp: float = option(0.05, "cusp: largest cusp height", unit="mm")
    max_area: float = option(0.0025, "area: largest staircase error area per mm of surface", unit="mm^2")
    min_height: float = option(0.05, "cusp/area: thinnest layer", unit="mm")
    max_height: float = option(0.3, "cusp/area: thickest layer", unit="mm")
    smooth: float = option(0.0, "cusp/area: thickness may change by at most this many mm per mm of height, to "
                                "within min-height/10 (the grid of layer tops; 0: off)")
    roi_ladder: tuple[float, ...] = option((1.0, 0.5, 0.1), "roi: thicknesses, coarse to fine", unit="mm",
                                           parse=parse_floats)
    roi_threshold: tuple[float, ...] | None = option(
        None, "roi: points per layer marking the region of interest (one value, or one per step)", parse=parse_floats)
    roi_quantile: float = option(0.75, "roi: without --roi-threshold, this quantile of each level's points per layer")
    roi_windows: int = option(1, "roi: windows kept per level (0: all)")

    #: the options that shape one kind of schedule, and the modes (``adaptive``; None: uniform) each is for; the
    #: others ignore them (the command line refuses one given without its mode: :meth:`not_for_mode`)
    FOR_MODES: ClassVar[dict[str, tuple[str | None, ...]]] = {
        "thickness": (None,), "max_cusp": ("cusp",), "max_area": ("area",), "min_height": ("cusp", "area"),
        "max_height": ("cusp", "area"),
        "smooth": ("cusp", "area"), "roi_ladder": ("roi",), "roi_threshold": ("roi",), "roi_quantile": ("roi",),
        "roi_windows": ("roi",),
    }

    def not_for_mode(self, names) -> list[tuple[str, tuple[str | None, ...]]]:
        """Of the option ``names`` (those a user gave), the ones this schedule ignores, with the modes they are
        for: ``max_cusp`` without ``adaptive="cusp"``, ``roi_ladder`` without ``"roi"``, ..."""
        return [(n, self.FOR_MODES[n]) for n in names if n in self.FOR_MODES and self.adaptive not in self.FOR_MODES[n]]

    def __post_init__(self) -> None:
        # types first (a string or a bool where a number goes fails here, named, not deep in a stage); ranges are
        # checked where each value is used (uniform, adaptive_schedule), as the command line's messages expect
        for name in ("thickness", "first_layer", "max_gap", "join_edges", "max_cusp", "max_area", "min_height",
                     "max_height", "smooth", "roi_quantile", "max_segments_per_batch", "roi_windows"):
            v = getattr(self, name)
            if getattr(v, "ndim", None) == 0 and getattr(getattr(v, "dtype", None), "kind", "") in ("i", "u", "f"):
                v = v.item()  # (a 0-d array, np.array(0.5): one number)
            if not (is_real(v) or (v is None and name == "first_layer")):
                raise ParameterError(f"{name} must be a number, got {v!r}", param=name)
            object.__setattr__(self, name, python_number(v))
        for name in ("max_segments_per_batch", "roi_windows"):
            v = getattr(self, name)
            if not (float(v).is_integer()):
                raise ParameterError(f"{name} must be a whole number, got {v!r}", param=name)
        for name in ("roi_ladder", "roi_threshold"):
            v = getattr(self, name)
            if name == "roi_threshold" and (v is None or is_real(v)):  # none, or one threshold for every step
                object.__setattr__(self, name, python_number(v))
                continue
            if not (isinstance(v, tuple | list) and all(is_real(x) for x in v)):
                raise ParameterError(f"{name} must be a tuple of numbers, got {v!r}", param=name)
            # a tuple (hashable, as the frozen dataclass is) of Python numbers (the report's JSON takes no numpy)
            object.__setattr__(self, name, tuple(python_number(x) for x in v))
        if self.z_mode not in Z_MODES:
            raise ParameterError(f"unknown z_mode {self.z_mode!r} (use {' or '.join(map(repr, Z_MODES))})",
                                 param="z_mode")
        if self.device is not None and not isinstance(self.device, str):
            raise ParameterError(f"device must be a device spec string ('P:D' or a name piece) or None, got "
                                 f"{type(self.device).__name__}; pass a Device object to slice_mesh's device=",
                                 param="device")
        if self.adaptive not in (None, *ADAPTIVE_MODES):
            raise ParameterError(f"unknown adaptive mode '{self.adaptive}' (use roi, cusp or area)")
        if self.adaptive is not None and self.first_layer is not None:  # (they were ignored, silently)
            raise ParameterError(f"first_layer applies to uniform layers, not to adaptive ones ({self.adaptive})",
                                 param="first_layer")
        if self.adaptive is not None and self.z_mode != "mid":  # (adaptive layers are cut at their slab's middle)
            raise ParameterError(f"z_mode '{self.z_mode}' applies to uniform layers, not to adaptive ones "
                                 f"({self.adaptive}: each cut at its slab's middle)", param="z_mode")
        if self.fill_rule not in FILL_RULES:
            raise ParameterError(f"unknown fill rule '{self.fill_rule}' (use {', '.join(FILL_RULES)})",
                                 param="fill_rule")
        if self.backend not in BACKENDS:
            raise ParameterError(f"unknown backend '{self.backend}' (use opencl or numpy)")
        if not (self.max_gap >= 0):
            raise ParameterError(f"max_gap must be >= 0 mm, got {self.max_gap}", param="max_gap")
        object.__setattr__(self, "fill_holes", check_flag(self.fill_holes, "fill_holes"))
        if not (0 <= self.join_edges < float("inf")):
            raise ParameterError(f"join_edges must be >= 0 mm and finite, got {self.join_edges}", param="join_edges")
        if self.max_segments_per_batch < 1:
            raise ParameterError("max_segments_per_batch must be positive", param="max_segments_per_batch")

