"""Every kind of mesh source :func:`gpuslice.load_mesh` and :func:`gpuslice.slice_mesh` take, turned into a raw
triangle soup without a temporary file.

Sources (besides a path, read by :func:`gpuslice.io.meshfile.read_mesh_file`):

* a ``trimesh.Trimesh``: its ``vertices[faces]`` (float64); one whose values are float32 values (loaded from an
  STL) gives the same result as slicing its binary STL, finer ones are placed on the bed before they are rounded to
  float32 (:func:`gpuslice.mesh.mesh.mesh_from_triangles`); a ``trimesh.Scene``: its geometry with the scene graph's
  transforms applied, concatenated into one mesh (``Scene.to_mesh()``);
* ``(vertices, faces)``: (V, 3) coordinates and (F, 3) vertex indices, counter-clockwise seen from outside;
  any other object with ``vertices`` and ``faces`` attributes is read the same way;
* ``bytes`` (or ``bytearray``/``memoryview``) of a mesh file, or a binary file object (anything with ``read()``
  giving bytes). The format comes from ``name``'s suffix (for a file object, default its ``name`` attribute);
  without one, a zip (``PK\\x03\\x04``) is read as 3MF and everything else as STL (binary or ASCII). OBJ, PLY, OFF
  and 3MF go to trimesh from memory; a 3MF is inflated under the limits of :func:`gpuslice.io.meshfile.inflate_3mf`.

Coordinates are in the source's units (mm by convention); ``load_mesh``'s ``scale``/``fit`` convert them.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import EmptyMeshError, ParameterError, flatten

__all__ = ["SourceTriangles", "read_source", "real_array"]


@dataclass
class SourceTriangles:
    """A source's triangles: (F, 3, 3) corners (file units), stored normals or ``None``, and how to name it."""

    triangles: np.ndarray
    normals: np.ndarray | None
    name: str
    source_format: str
    solids: int = 1


def _trimesh_types() -> tuple[type, type] | None:
    """``(Trimesh, Scene)`` when trimesh is already imported (a caller holding one has imported it), else None."""
    tm = sys.modules.get("trimesh")
    if tm is None:
        return None
    return tm.Trimesh, tm.Scene


def real_array(value: Any, what: str, name: str) -> np.ndarray:
    """``value`` as a numpy array of real numbers, its integer or float dtype kept (an object array of numbers
    becomes float64); :class:`ParameterError` naming ``name`` and ``what`` for anything else: strings, complex or
    bool values, ragged nested lists."""
    try:
        a = np.asarray(value)
        if a.dtype.kind == "O":
            a = a.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name}: {what} must be a numeric array ({flatten(str(exc), 120)})") from None
    if a.dtype.kind not in "iuf":
        raise ParameterError(f"{name}: {what} must be real numbers, got dtype {a.dtype}")
    return a


def _arrays(vertices: Any, faces: Any, name: str) -> np.ndarray:
    """(F, 3, 3) float64 corners of indexed arrays, checked (one-line :class:`ParameterError` naming ``name``)."""
    v = real_array(vertices, "vertices", name).astype(np.float64, copy=False)
    try:
        f = np.asarray(faces)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name}: faces must be a numeric array ({flatten(str(exc), 120)})") from None
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ParameterError(f"{name}: vertices must be (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        raise ParameterError(f"{name}: faces must be integer vertex indices, got {f.dtype}")
    if f.size == 0:
        raise EmptyMeshError(f"{name}: no facets")
    if f.min() < 0 or f.max() >= len(v):
        raise ParameterError(f"{name}: face indices out of range for {len(v)} vertices")
    return v[f]


def _from_trimesh(mesh: Any, name: str | None) -> SourceTriangles:
    label = name or str((getattr(mesh, "metadata", None) or {}).get("file_name") or "<trimesh>")
    return SourceTriangles(_arrays(mesh.vertices, mesh.faces, label), None, label, "trimesh")


def _from_bytes(data: bytes, name: str | None, default: str = "<bytes>") -> SourceTriangles:
    from ..io.meshfile import _read_non_stl, read_stl_bytes
    from ..io.rawmesh import NON_STL_EXTENSIONS

    label = name or default
    suffix = os.path.splitext(label)[1].lower()
    if suffix in NON_STL_EXTENSIONS:
        raw = _read_non_stl(label, NON_STL_EXTENSIONS[suffix], data=data)
    elif suffix != ".stl" and data[:4] == b"PK\x03\x04":  # an unnamed zip: a 3MF
        raw = _read_non_stl(label, "3mf", data=data)
    else:
        raw = read_stl_bytes(data, label)
    return SourceTriangles(raw.triangles, raw.normals, label, raw.source_format, raw.solids)


def read_source(source: Any, name: str | None = None) -> SourceTriangles:
    """The triangles of any non-path mesh ``source`` (see the module docstring), named ``name`` in messages.

    Raises
    ------
    ParameterError
        A source of no known kind, malformed arrays, a text-mode file object.
    MeshFileError, EmptyMeshError, InvalidGeometryError
        Bytes that are not a readable mesh (one line naming ``name``).
    """
    types = _trimesh_types()
    if types is not None and isinstance(source, types[0]):
        return _from_trimesh(source, name)
    if types is not None and isinstance(source, types[1]):
        label = name or "<trimesh scene>"
        if not source.geometry:
            raise EmptyMeshError(f"{label}: the scene holds no geometry")
        to_mesh = getattr(source, "to_mesh", None)
        merged = to_mesh() if to_mesh is not None else source.dump(concatenate=True)
        return _from_trimesh(merged, label)
    if isinstance(source, bytes | bytearray | memoryview):
        return _from_bytes(bytes(source), name)
    if callable(getattr(source, "read", None)):
        data = source.read()
        if not isinstance(data, bytes | bytearray | memoryview):
            raise ParameterError(f"{name or '<file object>'}: open the mesh file in binary mode ('rb')")
        file_name = getattr(source, "name", None)
        return _from_bytes(bytes(data), name or (file_name if isinstance(file_name, str) else None), "<file>")
    if isinstance(source, tuple | list) and len(source) == 2:
        label = name or "<arrays>"
        return SourceTriangles(_arrays(source[0], source[1], label), None, label, "arrays")
    if hasattr(source, "vertices") and hasattr(source, "faces"):
        label = name or f"<{type(source).__name__}>"
        return SourceTriangles(_arrays(source.vertices, source.faces, label), None, label, "arrays")
    hint = ""
    shape = getattr(source, "shape", None)
    if isinstance(shape, tuple) and shape[-2:] == (3, 3):  # (an (F, 3, 3) array of corners: its own constructor)
        hint = "; an (F, 3, 3) array of triangle corners goes to gpuslice.mesh_from_triangles"
    raise ParameterError(
        f"cannot load a mesh from a {type(source).__name__}: give a path, bytes, a binary file object, a "
        f"trimesh.Trimesh or Scene, a gpuslice Mesh or (vertices, faces) arrays{hint}"
    )
