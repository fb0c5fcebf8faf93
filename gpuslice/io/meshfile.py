"""Read mesh files into a raw triangle array (:class:`~gpuslice.io.rawmesh.RawMesh`), with strict validation.

The slicer works on a triangle soup: an ``(F, 3, 3)`` float32 array holding the three corners of every facet in file
order and file units (STL, OBJ, PLY and OFF have no units; for 3D printing they are millimetres by convention),
except a 3MF, whose model declares its unit (micron to meter): it is read in millimetres (:data:`UNITS_3MF_MM`).
Files named ``.obj``, ``.ply``, ``.off`` and ``.3mf`` are read by gpuslice's own readers (:mod:`gpuslice.io.obj`,
:mod:`gpuslice.io.ply`, :mod:`gpuslice.io.off`, :mod:`gpuslice.io.threemf`; polygon faces cut into triangles by
:mod:`gpuslice.io.polygons`; trimesh, which read them before, is not imported); every other file is parsed as STL,
binary or ASCII (:mod:`gpuslice.io.stl`).
:func:`read_mesh_source` also reads a file's bytes sent elsewhere (a batch worker). Every problem a user can cause
raises a :class:`~gpuslice.errors.MeshFileError` (or a subclass) whose message is one line naming the file and the
problem.
"""

from __future__ import annotations

import io
import os
import re
import stat
import zipfile
from pathlib import Path

import numpy as np

from ..errors import EmptyMeshError, GpusliceError, MeshFileError, flatten
from .obj import read_obj
from .off import read_off
from .ply import read_ply
from .rawmesh import BINARY_STL_RECORD, MAX_COORDINATE, NON_STL_EXTENSIONS, ZIP_ERRORS, RawMesh, check_coordinates
from .stl import _os_reason, read_stl_bytes

__all__ = [
    "read_mesh_source",
    "RawMesh",
    "read_mesh_file",
    "read_stl_bytes",
    "BINARY_STL_RECORD",
    "MAX_COORDINATE",
    "NON_STL_EXTENSIONS",
    "ZIP_MAX_INFLATED",
    "ZIP_MAX_RATIO",
    "ZIP_RATIO_FLOOR",
    "inflate_3mf",
    "zip_inflate_limit",
]

#: Zipped inputs (3MF) are refused when their members inflate to more than ``zip_inflate_limit(file size)`` bytes:
#: at most ``ZIP_MAX_INFLATED`` (1 GiB) and at most ``ZIP_MAX_RATIO`` (200) times the zip's own size, though
#: ``ZIP_RATIO_FLOOR`` (64 MiB) is always allowed. Checked first on the sizes the members declare
#: (``ZipInfo.file_size``), then as a hard cap on the bytes actually inflated.
ZIP_MAX_INFLATED = 1 << 30
#: millimetres in each unit a 3MF model may declare (``<model unit="...">``, 3MF core specification 1.3, 3.4.1)
UNITS_3MF_MM = {"micron": 0.001, "millimeter": 1.0, "centimeter": 10.0, "inch": 25.4, "foot": 304.8, "meter": 1000.0}
ZIP_MAX_RATIO = 200
ZIP_RATIO_FLOOR = 64 << 20
_INFLATE_CHUNK = 1 << 20
#: the formats read from the file by name (3MF: inflated from the zip under its limits); the others from its bytes
_BY_NAME = ("3mf",)
#: gpuslice's own readers: vertices, face vertex counts and flat indices (polygons) from a file's bytes
_OWN = {"obj": read_obj, "ply": read_ply, "off": read_off}


def read_mesh_file(path: str | os.PathLike[str]) -> RawMesh:
    """Read a mesh file into a :class:`RawMesh`.

    Files named ``.obj``, ``.ply``, ``.off`` or ``.3mf`` (any case) are read with
    :func:`gpuslice.io.obj.read_obj`, :func:`gpuslice.io.ply.read_ply`, :func:`gpuslice.io.off.read_off` and
    :func:`gpuslice.io.threemf.read_3mf` (all objects of a file merged, vertices not merged, nothing repaired);
    every other name, ``.stl`` or not, goes through :func:`read_stl_bytes`, which tells binary from ASCII STL and
    recognises common non-STL files.

    Parameters
    ----------
    path : str or os.PathLike
        The file to read. Messages name it exactly as given.

    Returns
    -------
    RawMesh
        At least one facet, all coordinates finite and within :data:`MAX_COORDINATE`.

    Raises
    ------
    MeshFileError
        The path is missing, a directory or unreadable; the file is not a mesh of its type, is truncated or
        malformed (see :func:`read_stl_bytes` and the readers above).
    EmptyMeshError
        The file is well formed but holds no facets.
    InvalidGeometryError
        A vertex coordinate is NaN, infinite, or larger in magnitude than :data:`MAX_COORDINATE`.
    """
    name = os.fspath(path)
    if isinstance(name, bytes):  # os.PathLike[bytes]
        name = os.fsdecode(name)
    if "\0" in name:  # os.stat would raise a bare ValueError
        raise MeshFileError(f"{name!r}: not a valid path (it holds a NUL character)")
    try:
        mode = os.stat(name).st_mode
        if stat.S_ISDIR(mode):
            raise IsADirectoryError
        if not (stat.S_ISREG(mode) or stat.S_ISFIFO(mode)):  # /dev/zero would be read until memory runs out
            raise MeshFileError(f"{name}: not a regular file (a device or a socket)")
        ext = os.path.splitext(name)[1].lower()
        if NON_STL_EXTENSIONS.get(ext) in _BY_NAME and not stat.S_ISFIFO(mode):  # (the zip opened by name)
            return _read_non_stl(name, NON_STL_EXTENSIONS[ext])
        with open(name, "rb") as fh:  # (a FIFO's bytes read here: a zip is read by name only from a regular file)
            data = fh.read()
    except OSError as exc:
        raise _file_error(name, exc) from None
    if ext in NON_STL_EXTENSIONS:
        return _read_non_stl(name, NON_STL_EXTENSIONS[ext], data)
    return read_stl_bytes(data, name)


def read_mesh_source(path: str | os.PathLike[str], data: bytes | None = None, label: str | None = None) -> RawMesh:
    """Read a mesh from ``path``, or from ``data`` (the file's bytes, e.g. sent to a batch worker) with ``path``'s
    suffix telling the format; messages name the file ``label`` (default: ``path``)."""
    where = os.fspath(path)
    label = label or where
    if data is None:
        try:
            return read_mesh_file(where)
        except GpusliceError as exc:  # name the file as the user gave it
            if label == where:
                raise
            named = type(exc)(str(exc).replace(where, label))
            named.__dict__.update(exc.__dict__)  # (os_error: where it was read, not what it holds)
            raise named from None
    suffix = Path(where).suffix.lower()
    if suffix in NON_STL_EXTENSIONS:  # from memory, no temporary file (a 3MF inflated under its limits)
        return _read_non_stl(label, NON_STL_EXTENSIONS[suffix], bytes(data))
    return read_stl_bytes(data, label)


def _file_error(name: str, exc: OSError) -> MeshFileError:
    """The one-line error for an OS error met while opening or reading ``name``; marked ``os_error`` (where the file
    is read, not what it holds: a batch tries such a model again on another worker, which may see the file)."""
    if isinstance(exc, IsADirectoryError):
        err = MeshFileError(f"{name}: is a directory")
    elif isinstance(exc, FileNotFoundError):
        err = MeshFileError(f"{name}: no such file")
    elif isinstance(exc, NotADirectoryError):
        err = MeshFileError(f"{name}: no such file (a parent is not a directory)")
    else:
        err = MeshFileError(f"{name}: cannot read: {_os_reason(exc)}")
    err.os_error = True
    return err


def zip_inflate_limit(zip_size: int) -> int:
    """Most bytes a zip of ``zip_size`` bytes may inflate to: ``min(ZIP_MAX_INFLATED, max(ZIP_RATIO_FLOOR,
    ZIP_MAX_RATIO * zip_size))``."""
    return int(min(ZIP_MAX_INFLATED, max(ZIP_RATIO_FLOOR, ZIP_MAX_RATIO * zip_size)))


#: the 3MF slice extension's mark of an object whose mesh is not for fabrication (gpuslice's own 3MF slice stacks
#: carry their bounding box so): a reader would read that box as the part
_LOWRES = re.compile(rb"meshresolution\s*=\s*[\"']lowres[\"']")


def inflate_3mf(name: str, data: bytes | None = None) -> io.BytesIO:
    """Inflate the 3MF (a zip) ``data`` (or the file ``name``) under :func:`zip_inflate_limit`, into an in-memory
    zip of stored (uncompressed) members for :func:`gpuslice.io.threemf.read_3mf` to read.

    Raises :class:`MeshFileError` (one line naming ``name``) when the members' declared sizes add up to more than
    the limit, when inflating goes past it anyway (sizes that lie), or when the zip is broken.
    """
    try:
        size = len(data) if data is not None else os.path.getsize(name)
        limit = zip_inflate_limit(size)
        with zipfile.ZipFile(io.BytesIO(data) if data is not None else name) as zf:
            infos = [i for i in zf.infolist() if not i.is_dir()]
            seen: set[str] = set()
            for info in infos:  # (OPC part names are unique, case aside; zipfile read the last copy, with a warning)
                key = info.filename.lower().lstrip("/")  # (as the reader matches part names)
                if key in seen:
                    raise MeshFileError(f"{name}: not a valid 3MF file: it holds two members named "
                                        f"{flatten(info.filename, 80)!r}")
                seen.add(key)
            declared = sum(i.file_size for i in infos)
            if declared > limit:
                raise MeshFileError(f"{name}: 3MF members declare {declared} bytes inflated, over the limit of "
                                    f"{limit} bytes for a file of {size} bytes")
            out = io.BytesIO()
            total = 0
            with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as dst:
                for info in infos:
                    chunks = []
                    with zf.open(info) as src:
                        while chunk := src.read(_INFLATE_CHUNK):
                            total += len(chunk)
                            if total > limit:
                                raise MeshFileError(f"{name}: 3MF inflates past the limit of {limit} bytes")
                            chunks.append(chunk)
                    dst.writestr(info.filename, b"".join(chunks))
    except ZIP_ERRORS as exc:
        reason = flatten(str(exc), 200) or type(exc).__name__
        raise MeshFileError(f"{name}: cannot read 3MF file: {type(exc).__name__}: {reason}") from None
    except OSError as exc:
        raise _file_error(name, exc) from None
    out.seek(0)
    return out


def _triangles(name: str, kind: str, vertices: np.ndarray, faces: np.ndarray,
               counts: np.ndarray | None = None) -> np.ndarray:
    """(F, 3, 3) float64 corners of the faces read, or a one-line :class:`MeshFileError` for what a reader let
    through: vertices without three coordinates, a face naming a vertex that is not there (a negative index: numpy
    would take another vertex).

    ``faces``: (F, 3) triangles (3MF's), or with ``counts`` (vertices per face) the polygons' flat
    vertex indices (gpuslice's readers), cut into triangles by :func:`gpuslice.io.polygons.triangulate` (a concave
    face inside its outline)."""
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshFileError(f"{name}: {kind} vertices with {vertices.shape[-1] if vertices.ndim == 2 else '?'} "
                            "coordinates, not x y z (a vertex line short of a number?)")
    faces = np.asarray(faces, np.int64).reshape(-1 if counts is not None else (-1, 3))
    bad = (faces < 0) | (faces >= len(vertices))
    if bad.any():
        raise MeshFileError(f"{name}: a {kind} face names vertex {int(faces[bad][0])}, but the file has "
                            f"{len(vertices)} vertices (counted from 0; an index out of range)")
    if counts is not None:
        from .polygons import triangulate

        faces = triangulate(vertices, counts, faces)[0]
    return vertices[faces]


def _read_non_stl(name: str, file_type: str, data: bytes | None = None) -> RawMesh:
    """Read OBJ, PLY, OFF (:data:`_OWN`'s readers) and 3MF (:func:`gpuslice.io.threemf.read_3mf`, after
    :func:`inflate_3mf` under :func:`zip_inflate_limit` and the slice-stack check) from the file's bytes ``data``
    (or the file ``name``: a 3MF by name, :data:`_BY_NAME`)."""
    if file_type in _OWN:  # (not trimesh's readers: they dropped faces silently, folded concave ones, cost 1 s)
        # (a number past float32 is infinite, NaN or infinite coordinates are refused by _raw_mesh: without numpy's
        # warnings from the reading and the triangles on the way)
        with np.errstate(all="ignore"):
            vertices, counts, faces = _OWN[file_type](data, name)
            triangles = _triangles(name, file_type.upper(), vertices, faces, counts)
        return _raw_mesh(name, file_type, triangles)
    from .threemf import read_3mf

    source = inflate_3mf(name, data)
    with zipfile.ZipFile(source) as zf:  # (no model part at all: read_3mf's own one-line error)
        parts = [n for n in zf.namelist() if n.lower().endswith(".model")]
        if any(_LOWRES.search(zf.read(n)) for n in parts):  # (stored members: read without inflating again)
            raise MeshFileError(f"{name}: a 3MF slice stack (its mesh is a low-resolution stand-in, "
                                's:meshresolution="lowres", not the part): slice the model it was made from')
    with np.errstate(all="ignore"):
        vertices, faces = read_3mf(source.getvalue(), name, units=UNITS_3MF_MM)  # (millimetres: its unit applied)
        triangles = _triangles(name, "3MF", vertices, faces)
    return _raw_mesh(name, file_type, triangles)


def _raw_mesh(name: str, file_type: str, triangles: np.ndarray) -> RawMesh:
    """The :class:`RawMesh` of a non-STL file's ``triangles`` (a 3MF's already in millimetres); refuses a file
    without facets and coordinates out of range."""
    if len(triangles) == 0:
        raise EmptyMeshError(f"{name}: no facets ({file_type.upper()} file)")
    check_coordinates(triangles, name)
    # float64 as read: the mesh is placed on the bed before its one rounding to float32 (mesh.mesh_from_triangles)
    return RawMesh(triangles=np.ascontiguousarray(triangles, dtype=np.float64), normals=None,
                   source_format=file_type, solids=1, header=b"", path=name)
