"""Stages 4-6: crossings (``crossings.py`` + ``kernels/crossings.cl``), chaining (``chain.py``, ``walk.py`` +
``kernels/walk.cl``), nesting (``nest.py``), wired by ``slicer.py`` into a :class:`SliceResult` (``result.py``)."""

from .params import SliceParams
from .result import LayerView, SliceResult
from .slicer import roi_schedule, slice_mesh

__all__ = ["LayerView", "SliceParams", "SliceResult", "roi_schedule", "slice_mesh"]
