"""``.dxf``: one DXF layer per slice, every loop an ``LWPOLYLINE``, units mm; written with ``ezdxf`` (the
``formats`` extra: ``pip install 'gpuslice[formats]'``). Output bytes are a pure function of the result (ezdxf's
fixed metadata: no creation date, constant GUIDs)."""

from __future__ import annotations

import os
from collections import OrderedDict
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import MeshFileError, ParameterError
from ..io.atomic import atomic_path
from .numbers import MAX_ABS, result_arrays

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


def write_dxf(result: SliceResult, path: PathLike, *, version: str = "R2010") -> None:
    """Write ``result`` as a DXF drawing, atomically.

    Layout:

    * Units mm (``$INSUNITS`` 4, ``$MEASUREMENT`` 1, metric); drawing x, y are the bed's x, y (no flip).
    * One DXF layer per slice, named by :func:`dxf_layer_name` (``SLICE_00012``), in layer order, with the
      slice's z, thickness and area in the layer's description (``z=… thickness=… area=…``, mm, mm²).
    * Every loop one ``LWPOLYLINE`` on its slice's layer, in the result's order, with ``elevation`` = the cutting
      plane z: closed loops with the closed flag (the first point not repeated), outer loops counter-clockwise
      and holes clockwise as in the result, holes on the same layer as their outer loop; open chains (broken
      meshes only) as open polylines. Coordinates are the float32 values exactly (DXF stores doubles). Loops of
      fewer than 2 points are skipped.

    Parameters
    ----------
    version : the DXF version ezdxf writes (``"R2010"`` default; ``"R2000"`` or later have ``LWPOLYLINE``).

    Raises
    ------
    ParameterError
        ezdxf is not installed, or the result is malformed (inconsistent offsets, coordinates beyond 1e9 mm).
    """
    ezdxf = _ezdxf()
    points, loop_offsets, layer_offsets = result_arrays(result)
    if points.size and np.abs(points).max() > MAX_ABS:
        raise ParameterError("result coordinates are too large to write (beyond 1e9 mm)")
    closed = np.asarray(result.loop_closed, dtype=bool).tolist()
    z = np.asarray(result.z, dtype=np.float64).tolist()
    thickness = np.asarray(result.thickness, dtype=np.float64).tolist()
    area = np.asarray(result.area, dtype=np.float64).tolist()
    saved = ezdxf.options.write_fixed_meta_data_for_testing
    try:
        ezdxf.options.write_fixed_meta_data_for_testing = True  # reproducible bytes: fixed dates and GUIDs
        doc = ezdxf.new(version, setup=False, units=ezdxf.units.MM)
        doc.header["$MEASUREMENT"] = 1
        msp = doc.modelspace()
        offsets = loop_offsets.tolist()
        for i in range(len(z)):
            name = dxf_layer_name(i)
            layer = doc.layers.add(name)
            layer.description = f"z={z[i]!r} thickness={thickness[i]!r} area={area[i]!r}"
            attribs = {"layer": name, "elevation": z[i]}
            for r in range(int(layer_offsets[i]), int(layer_offsets[i + 1])):
                a, b = offsets[r], offsets[r + 1]
                if b - a < 2:
                    continue
                msp.add_lwpolyline(points[a:b].astype(np.float64), format="xy", close=closed[r], dxfattribs=attribs)
        # the CLASSES section: ezdxf adds a class for each entity type in use when saving, iterating a set (an order
        # that changes with Python's hash seed, so the bytes changed from run to run); added here first, sorted
        doc.classes.add_required_classes(doc.dxfversion)
        doc.classes.classes = OrderedDict(sorted(doc.classes.classes.items()))
        with atomic_path(path) as tmp:
            doc.saveas(tmp)
    finally:
        ezdxf.options.write_fixed_meta_data_for_testing = saved


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
