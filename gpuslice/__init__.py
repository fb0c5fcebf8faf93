"""gpuslice: slice triangle meshes into closed, nested layer contours on any OpenCL device.

Importing the package is cheap: pyopencl, trimesh and moderngl are imported only when a function needs them.
"""

from .errors import (
    DeviceError,
    EmptyMeshError,
    GpusliceError,
    InvalidGeometryError,
    MeshFileError,
    ParameterError,
)
from .mesh.defects import MESH_REPAIR_KINDS, mesh_repairs
from .mesh.mesh import Mesh, Placement, load_mesh, mesh_from_arrays, mesh_from_triangles
from .schedule.adaptive import AdaptiveSchedule, adaptive_schedule, cusp_schedule
from .schedule.uniform import Schedule, from_z, uniform
from .slicing.params import SliceParams
from .slicing.result import LayerView, SliceResult
from .slicing.slicer import roi_schedule, slice_mesh

__version__ = "0.1.0"

__all__ = [
    "AdaptiveSchedule",
    "BatchOptions",
    "DeviceError",
    "EmptyMeshError",
    "GpusliceError",
    "InvalidGeometryError",
    "LayerView",
    "MESH_REPAIR_KINDS",
    "Mesh",
    "Placement",
    "MeshFileError",
    "ParameterError",
    "Schedule",
    "SliceParams",
    "SliceResult",
    "__version__",
    "adaptive_schedule",
    "cusp_schedule",
    "cusp_summary",
    "from_z",
    "load_mesh",
    "mesh_from_arrays",
    "mesh_from_triangles",
    "mesh_repairs",
    "roi_schedule",
    "run_batch",
    "schedule_quality",
    "slice_mesh",
    "uniform",
    "volume_deviation",
]

# heavier modules, imported on first use (the bench ones pull in bench/runner.py, statistics, csv: not needed by
# `gpuslice slice`)
_LAZY = {
    "BatchOptions": "batch.options",
    "run_batch": "batch.runner",
    "cusp_summary": "bench.quality",
    "schedule_quality": "bench.quality",
    "volume_deviation": "bench.quality",
}


#: sub-packages reachable as attributes (``gpuslice.formats.export(...)``), imported on first use
_SUBPACKAGES = ("batch", "bench", "formats", "io", "pipeline", "raster", "view")


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'gpuslice' has no attribute {name!r}")
