"""gpuslice: slice triangle meshes into closed, nested layer contours on any OpenCL device.

Importing the package is cheap: pyopencl, trimesh and moderngl are imported only when a function needs them.
"""

from .adaptive import AdaptiveSchedule, adaptive_schedule, cusp_schedule, roi_schedule
from .defects import MESH_REPAIR_KINDS, mesh_repairs
from .errors import (
    DeviceError,
    EmptyMeshError,
    GpusliceError,
    InvalidGeometryError,
    MeshFileError,
    ParameterError,
)
from .mesh import Mesh, load_mesh, mesh_from_arrays, mesh_from_triangles
from .quality import cusp_summary, schedule_quality, volume_deviation
from .result import LayerView, SliceResult
from .schedule import Schedule, from_z, uniform
from .slicer import SliceParams, slice_mesh

__version__ = "0.1.0"

__all__ = [
    "AdaptiveSchedule",
    "DeviceError",
    "EmptyMeshError",
    "GpusliceError",
    "InvalidGeometryError",
    "LayerView",
    "MESH_REPAIR_KINDS",
    "Mesh",
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
    "schedule_quality",
    "slice_mesh",
    "uniform",
    "volume_deviation",
]
