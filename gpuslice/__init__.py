"""gpuslice: slice triangle meshes into closed, nested layer contours on any OpenCL device.

Importing the package is cheap: pyopencl, trimesh and moderngl are imported only when a function needs them.
"""

from typing import TYPE_CHECKING

from .errors import (
    DeviceError,
    EmptyMeshError,
    GpusliceError,
    InvalidGeometryError,
    MeshFileError,
    ParameterError,
)

if TYPE_CHECKING:  # imported on first use (below): `import gpuslice` does not import numpy
    from .batch.options import BatchOptions
    from .batch.runner import run_batch
    from .bench.quality import cusp_summary, schedule_quality, volume_deviation
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

# every public name but the errors lives in a module imported on first use: the package itself imports no numpy,
# so the command line can configure the process before numpy loads (gpuslice.cli.main.entry); the bench ones pull
# in bench/runner.py, statistics, csv: not needed by `gpuslice slice`
_LAZY = {
    "MESH_REPAIR_KINDS": "mesh.defects",
    "mesh_repairs": "mesh.defects",
    "Mesh": "mesh.mesh",
    "Placement": "mesh.mesh",
    "load_mesh": "mesh.mesh",
    "mesh_from_arrays": "mesh.mesh",
    "mesh_from_triangles": "mesh.mesh",
    "AdaptiveSchedule": "schedule.adaptive",
    "adaptive_schedule": "schedule.adaptive",
    "cusp_schedule": "schedule.adaptive",
    "Schedule": "schedule.uniform",
    "from_z": "schedule.uniform",
    "uniform": "schedule.uniform",
    "SliceParams": "slicing.params",
    "LayerView": "slicing.result",
    "SliceResult": "slicing.result",
    "roi_schedule": "slicing.slicer",
    "slice_mesh": "slicing.slicer",
    "BatchOptions": "batch.options",
    "run_batch": "batch.runner",
    "cusp_summary": "bench.quality",
    "schedule_quality": "bench.quality",
    "volume_deviation": "bench.quality",
}


#: sub-packages and modules reachable as attributes (``gpuslice.formats.export(...)``), imported on first use
_SUBPACKAGES = ("batch", "bench", "checks", "device", "formats", "io", "mesh", "options", "pipeline", "prefetch",
                "ragged", "raster", "schedule", "slicing", "view")


def __getattr__(name: str):
    if name in _SUBPACKAGES:
        import importlib

        return importlib.import_module(f".{name}", __name__)
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value  # later lookups skip this function
        return value
    raise AttributeError(f"module 'gpuslice' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__) | set(_SUBPACKAGES))
