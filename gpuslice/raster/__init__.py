"""Resin layers: rasterising the nested polygons onto a printer's display and writing the archives resin printers
read.

``spec.py`` (the display, resin options), ``printers.py`` (presets), ``settings.py`` (print settings per layer),
``edges.py`` (the layers' edges in pixels, for every rasteriser), ``coverage.py`` + ``kernels/raster.cl`` (exact area
coverage; numpy twin), ``runs.py`` + ``kernels/runs.cl`` (run-length runs), ``layers.py`` (a layer in flight),
``gl.py`` (the moderngl pass), ``outputs.py`` (the resin-output registry), ``png.py`` and ``deflate_runs.py`` (PNG
encoders), ``sl1.py`` and ``pngstack.py`` (the outputs)."""

from .coverage import RasterKernel, Tile, choose_backend, coverage_numpy, iter_masks, iter_tiles, masks
from .edges import LayerEdges, check_fits, layer_edges, result_bounds
from .printers import Printer, find_printer
from .settings import PrintSettings
from .spec import BACKENDS, PRINTERS, RasterSpec, ResinOptions, gamma_lut, with_printer

__all__ = [
    "BACKENDS",
    "LayerEdges",
    "PRINTERS",
    "PrintSettings",
    "Printer",
    "RasterKernel",
    "RasterSpec",
    "ResinOptions",
    "Tile",
    "check_fits",
    "choose_backend",
    "coverage_numpy",
    "find_printer",
    "gamma_lut",
    "iter_masks",
    "iter_tiles",
    "layer_edges",
    "masks",
    "result_bounds",
    "with_printer",
]
