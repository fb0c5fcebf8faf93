"""Stage 2, the mesh: welding, edge ids and placement (``mesh.py``, ``weld.py`` + ``kernels/weld.cl``), the mesh
check (``defects.py``), connected components of graphs (``graph.py``) and built-in test solids (``shapes.py``)."""

from .defects import MESH_REPAIR_KINDS, mesh_repairs
from .mesh import Mesh, Placement, load_mesh, mesh_from_arrays, mesh_from_triangles

__all__ = ["MESH_REPAIR_KINDS", "Mesh",
    "Placement", "load_mesh", "mesh_from_arrays", "mesh_from_triangles", "mesh_repairs"]
