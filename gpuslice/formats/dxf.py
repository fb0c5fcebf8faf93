"""``.dxf``: one DXF layer per slice, every loop an ``LWPOLYLINE``, units mm; the drawing made with ``ezdxf`` (the
``formats`` extra: ``pip install 'gpuslice[formats]'``) and its polylines streamed into the file a run of layers at
a time, so memory is bounded by the run, not the model. Output bytes are a pure function of the result (ezdxf's
fixed metadata: no creation date, constant GUIDs), the bytes ezdxf writes for the same drawing built entity by
entity."""

from __future__ import annotations

import io
import os
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import MeshFileError, ParameterError
from ..io.atomic import atomic_path
from .numbers import CHUNK_POINTS as NUMBERS_CHUNK_POINTS
from .numbers import MAX_ABS, layer_chunks, result_arrays

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

PathLike = str | os.PathLike

__all__ = ["write_dxf", "read_dxf", "dxf_layer_name"]


def dxf_layer_name(index: int) -> str:
    """The DXF layer of slice ``index``: ``SLICE_00000``, ``SLICE_00001``, … (zero-padded, so they sort)."""
    return f"SLICE_{index:05d}"


def _ezdxf() -> Any:
    try:
        import ezdxf
    except ImportError:
        raise ParameterError("DXF output needs ezdxf: pip install 'gpuslice[formats]' (or pip install ezdxf)") from None
    return ezdxf


#: Points (all the loops of a run of layers, at least one layer) whose LWPOLYLINE text is built at once: bounds the
#: writer's memory (about 150 bytes a point: the Python floats, the format string and its text), 32k points.
CHUNK_POINTS = NUMBERS_CHUNK_POINTS // 16
#: What ezdxf writes for the ENTITIES section's start; the streamed LWPOLYLINE s go right after it.
_ENTITIES = "  0\nSECTION\n  2\nENTITIES\n"
#: One vertex, as ezdxf writes it: group codes 10 and 20, each value as ``"%s" % float`` (its shortest repr).
_VERTEX = " 10\n%r\n 20\n%r\n"


def write_dxf(result: SliceResult, path: PathLike, *, version: str = "R2010") -> None:
    """Write ``result`` as a DXF drawing, atomically, streaming the contours: memory is bounded by a run of layers.

    Layout:

    * Units mm (``$INSUNITS`` 4, ``$MEASUREMENT`` 1, metric); drawing x, y are the bed's x, y (no flip).
    * One DXF layer per slice, named by :func:`dxf_layer_name` (``SLICE_00012``), in layer order, with the
      slice's z, thickness and area in the layer's description (``z=… thickness=… area=…``, mm, mm²).
    * Every loop one ``LWPOLYLINE`` on its slice's layer, in the result's order, with ``elevation`` = the cutting
      plane z: closed loops with the closed flag (the first point not repeated), outer loops counter-clockwise
      and holes clockwise as in the result, holes on the same layer as their outer loop; open chains (broken
      meshes only) as open polylines. Coordinates are the float32 values exactly (DXF stores doubles). Loops of
      fewer than 2 points are skipped.

    How: ezdxf builds the drawing without its entities (the header, the tables with every slice's LAYER, the
    blocks, the objects), its handle counter stepped over the handles the polylines take, layer by layer, as if
    they had been added in between; that skeleton is written up to its ENTITIES section, then the ``LWPOLYLINE``
    s are formatted here, a run of layers (about ``CHUNK_POINTS`` points) at a time, exactly as ezdxf writes them
    (same handles, group codes and float text), then the rest of the skeleton. The bytes are those of the same
    drawing built and saved by ezdxf entity by entity, without holding an entity object per loop.

    Parameters
    ----------
    version : the DXF version ezdxf writes (``"R2010"`` default; ``"R2000"`` or later have ``LWPOLYLINE``).

    Raises
    ------
    ParameterError
        ezdxf is not installed, or the result is malformed (inconsistent offsets, coordinates beyond 1e9 mm).
    ezdxf.DXFVersionError
        ``version`` is before R2000 and the result has a loop to write (as ezdxf's ``add_lwpolyline``).
    """
    ezdxf = _ezdxf()
    points, loop_offsets, layer_offsets = result_arrays(result)
    if points.size and np.abs(points).max() > MAX_ABS:
        raise ParameterError("result coordinates are too large to write (beyond 1e9 mm)")
    closed = np.asarray(result.loop_closed, dtype=bool)
    z = np.asarray(result.z, dtype=np.float64).tolist()
    thickness = np.asarray(result.thickness, dtype=np.float64).tolist()
    area = np.asarray(result.area, dtype=np.float64).tolist()
    per_layer = _loops_written(loop_offsets, layer_offsets)
    saved = ezdxf.options.write_fixed_meta_data_for_testing
    try:
        ezdxf.options.write_fixed_meta_data_for_testing = True  # reproducible bytes: fixed dates and GUIDs
        doc = ezdxf.new(version, setup=False, units=ezdxf.units.MM)
        if doc.dxfversion < ezdxf.const.DXF2000 and per_layer.any():
            raise ezdxf.DXFVersionError("LWPOLYLINE requires DXF R2000")
        doc.header["$MEASUREMENT"] = 1
        owner = doc.modelspace().block_record_handle
        handles = doc.entitydb.handles
        first = np.zeros(len(z), dtype=np.int64)  # the handle of each layer's first polyline
        for i, count in enumerate(per_layer.tolist()):
            layer = doc.layers.add(dxf_layer_name(i))
            layer.description = f"z={z[i]!r} thickness={thickness[i]!r} area={area[i]!r}"
            # ezdxf gives handles in creation order: the layer's polylines take the next ``count``, then the next
            # layer (and at saving, the objects ezdxf adds) those after them
            first[i] = h = int(str(handles), 16)
            if count:
                handles.reset(f"{h + count:X}")
        # the CLASSES section: ezdxf adds a class for each entity type in use when saving, iterating a set (an order
        # that changes with Python's hash seed, so the bytes changed from run to run); added here first, sorted
        doc.classes.add_required_classes(doc.dxfversion)
        doc.classes.classes = OrderedDict(sorted(doc.classes.classes.items()))
        encoding = doc.output_encoding
        skeleton = io.StringIO()
        doc.write(skeleton)  # what doc.saveas writes, less the entities
    finally:
        ezdxf.options.write_fixed_meta_data_for_testing = saved
    del doc
    text = skeleton.getvalue()
    del skeleton
    cut = text.find(_ENTITIES)
    if cut < 0 or text.find(_ENTITIES, cut + 1) >= 0 or not text.startswith("  0\nENDSEC\n", cut + len(_ENTITIES)):
        raise RuntimeError("unexpected DXF layout from ezdxf: no single empty ENTITIES section")  # pragma: no cover
    cut += len(_ENTITIES)
    layer_points = loop_offsets[layer_offsets]  # points before each layer
    # the file the way ezdxf's saveas opens it (text mode: the same newline translation and encoding)
    with atomic_path(path) as tmp, open(tmp, "w", encoding=encoding, errors="dxfreplace") as fp:
        fp.write(text[:cut])
        for a, b in layer_chunks(layer_points, CHUNK_POINTS):
            fp.write(_polylines(points, loop_offsets, layer_offsets, closed, z, first, owner, a, b))
        fp.write(text[cut:])


def _loops_written(loop_offsets: np.ndarray, layer_offsets: np.ndarray) -> np.ndarray:
    """(L,) int64: the loops of each layer with at least 2 points (those written), counted a run of layers at a
    time."""
    out = np.zeros(layer_offsets.size - 1, dtype=np.int64)
    for a, b in layer_chunks(layer_offsets, 1 << 20):  # runs of about a million loops
        r0, r1 = int(layer_offsets[a]), int(layer_offsets[b])
        kept = np.zeros(r1 - r0 + 1, dtype=np.int64)
        np.cumsum(np.diff(loop_offsets[r0 : r1 + 1]) >= 2, out=kept[1:])
        out[a:b] = np.diff(kept[layer_offsets[a : b + 1] - r0])
    return out


def _polylines(
    points: np.ndarray,
    loop_offsets: np.ndarray,
    layer_offsets: np.ndarray,
    closed: np.ndarray,
    z: list[float],
    first: np.ndarray,
    owner: str,
    a: int,
    b: int,
) -> str:
    """The ``LWPOLYLINE`` s of layers ``[a, b)`` as ezdxf writes them: handle, owner (the modelspace's block
    record), layer, count, closed flag, elevation unless 0 (an optional attribute at its default), vertices."""
    r0, r1 = int(layer_offsets[a]), int(layer_offsets[b])
    lo = loop_offsets[r0 : r1 + 1]
    counts = np.diff(lo)
    kept = counts >= 2
    loop_layer = np.repeat(np.arange(a, b), np.diff(layer_offsets[a : b + 1]))[kept]
    # a layer's polylines take consecutive handles from its first: rank among the kept loops of the run, less
    # the rank of the layer's first kept loop
    rank = np.arange(loop_layer.size)
    start = np.searchsorted(loop_layer, loop_layer, side="left")
    handle = (first[loop_layer] + rank - start).tolist()
    elevation = {i: (f" 38\n{z[i]!r}\n" if z[i] != 0 else "") for i in range(a, b)}
    names = {i: dxf_layer_name(i) for i in range(a, b)}
    fmt = "".join(
        f"  0\nLWPOLYLINE\n  5\n{h:X}\n330\n{owner}\n100\nAcDbEntity\n  8\n{names[i]}\n100\nAcDbPolyline\n"
        f" 90\n{n}\n 70\n{int(c)}\n{elevation[i]}" + _VERTEX * n
        for h, i, n, c in zip(handle, loop_layer.tolist(), counts[kept].tolist(), closed[r0:r1][kept].tolist(),
                              strict=True)
    )
    pts = points[lo[0] : lo[-1]]
    if not kept.all():
        pts = pts[np.repeat(kept, counts)]
    return fmt % tuple(pts.astype(np.float64).ravel().tolist())


def read_dxf(path: PathLike) -> dict[str, list[tuple[np.ndarray, bool, float]]]:
    """Read the ``LWPOLYLINE`` s of a DXF: ``{layer name: [(points (n, 2) float64 mm, closed, elevation), ...]}`` in
    file order (the reader :func:`write_dxf`'s tests use). One-line :class:`MeshFileError` on an unreadable file."""
    ezdxf = _ezdxf()
    try:
        doc = ezdxf.readfile(os.fspath(path))
    except (OSError, ezdxf.DXFError) as exc:
        raise MeshFileError(f"{path}: not a readable DXF file ({exc})") from None
    out: dict[str, list[tuple[np.ndarray, bool, float]]] = {}
    for e in doc.modelspace().query("LWPOLYLINE"):
        pts = np.array([(x, y) for x, y in e.get_points("xy")], dtype=np.float64).reshape(-1, 2)
        out.setdefault(e.dxf.layer, []).append((pts, bool(e.closed), float(e.dxf.elevation)))
    return out
