"""``.npz``: the whole :class:`~gpuslice.slicing.result.SliceResult` (arrays and meta), byte-identical for identical
results; read back with :meth:`SliceResult.load <gpuslice.slicing.result.SliceResult.load>`."""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

__all__ = ["write_npz"]


def write_npz(result: SliceResult, path: str | os.PathLike) -> None:
    """Write ``result`` as ``.npz`` (uncompressed, fixed zip dates, meta without timings), atomically."""
    result.save(path)
