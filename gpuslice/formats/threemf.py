"""``.3mf``: a 3MF package holding the layers as a slice stack of the 3MF Slice Extension 1.0 (namespace
``http://schemas.microsoft.com/3dmanufacturing/slice/2015/07``). Output bytes are a pure function of the result.

Package (OPC): ``[Content_Types].xml``, ``_rels/.rels`` (start part ``/3D/3dmodel.model``) and ``3D/3dmodel.model``
holding, in ``<resources>``, one ``<s:slicestack id="1" zbottom="…">`` with every slice inline, and one
``<object id="2" type="model" s:slicestackid="1" s:meshresolution="lowres">`` whose mesh is the stack's bounding
box (the core spec wants a mesh on every object; "lowres" says it is not for fabrication, and the model lists the
extension in ``requiredextensions``), built once by ``<build><item objectid="2"/>``.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
import zipfile
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MeshFileError
from ..io.atomic import atomic_path
from ..ragged import expand_ranges
from .numbers import (
    CHUNK_POINTS,
    checked_result,
    fmt_scalar,
    format_fixed,
    layer_chunks,
    point_bounds,
    stacked_slabs,
)

if TYPE_CHECKING:
    from ..slicing.result import SliceResult

PathLike = str | os.PathLike

__all__ = ["write_3mf_slices", "read_3mf_slices", "SLICE_NS", "CORE_NS"]

CORE_NS = "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"
SLICE_NS = "http://schemas.microsoft.com/3dmanufacturing/slice/2015/07"
_MODEL = "3D/3dmodel.model"
_CONTENT_TYPES = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">'
    '<Default Extension="rels" ContentType="application/vnd.openxmlformats-package.relationships+xml"/>'
    '<Default Extension="model" ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/>'
    "</Types>\n"
)
_RELS = (
    '<?xml version="1.0" encoding="UTF-8"?>\n'
    '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
    f'<Relationship Target="/{_MODEL}" Id="rel0" '
    'Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/>'
    "</Relationships>\n"
)
_DATE = (1980, 1, 1, 0, 0, 0)  # fixed member dates: identical results give identical bytes


def _member(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(name, date_time=_DATE)
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    return info


def _num(x: float) -> str:
    """A z value exactly (shortest repr of the float64), in the spec's ST_Number syntax."""
    return repr(float(x) + 0.0)


def write_3mf_slices(result: SliceResult, path: PathLike, *, decimals: int = 6) -> None:
    """Write ``result`` as a 3MF slice stack (3MF Slice Extension 1.0), atomically.

    Each layer is one ``<s:slice ztop="bottom + thickness">`` (mm; the stack's ``zbottom`` is the first layer's
    bottom), in layer order; an empty layer is a ``<s:slice>`` with only its ``ztop``, as the spec asks. A layer's
    closed loops are its ``<s:polygon>`` s, in the result's order: the loop's points are the slice's
    ``<s:vertex x y>`` s (one run per loop, not shared) and the polygon runs ``startv`` → its ``<s:segment v2>`` s
    back to ``startv`` (closed). Outer loops counter-clockwise and holes clockwise, so the spec's positive fill
    rule fills exactly the result's region. Open chains (broken meshes only) are left out, as are loops of fewer
    than 3 points: every polygon of a ``type="model"`` object must be closed. Coordinates have exactly
    ``decimals`` decimals (rounded half-to-even from float32), z values are exact.

    Raises
    ------
    ParameterError
        ``decimals`` out of 0..9, or a malformed result (inconsistent offsets, coordinates beyond 1e9 mm), or
        slabs that do not stack (:func:`~gpuslice.formats.numbers.stacked_slabs`).
    """
    decimals, points, loop_offsets, layer_offsets = checked_result(result, decimals)
    bottom, top = stacked_slabs(result, "a 3MF slice stack")
    z_bottom = float(bottom[0]) if bottom.size else 0.0
    cum = loop_offsets[layer_offsets]
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w") as zf:
        zf.writestr(_member("[Content_Types].xml"), _CONTENT_TYPES)
        zf.writestr(_member("_rels/.rels"), _RELS)
        with zf.open(_member(_MODEL), "w", force_zip64=True) as fh:
            fh.write(
                '<?xml version="1.0" encoding="UTF-8"?>\n'
                f'<model unit="millimeter" xml:lang="en-US" xmlns="{CORE_NS}" xmlns:s="{SLICE_NS}" '
                'requiredextensions="s">\n<resources>\n'
                f'<s:slicestack id="1" zbottom="{_num(z_bottom)}">\n'.encode()
            )
            for l0, l1 in layer_chunks(cum, CHUNK_POINTS // 8):  # (~60 bytes of XML a point, formatted twice)
                _write_chunk(fh, points, loop_offsets, layer_offsets, result.loop_closed, top, l0, l1, decimals)
            fh.write(b"</s:slicestack>\n")
            fh.write(_bbox_object(points, z_bottom, float(top[-1]) if top.size else 0.0).encode())
            fh.write(b'</resources>\n<build><item objectid="2"/></build>\n</model>\n')


def _write_chunk(fh, points, loop_offsets, layer_offsets, loop_closed, top, l0, l1, decimals) -> None:
    """The ``<s:slice>`` elements of layers ``l0 .. l1 - 1``: vertex and segment text formatted for the chunk at
    once (vectorised), then cut per layer."""
    r0, r1 = int(layer_offsets[l0]), int(layer_offsets[l1])
    counts = np.diff(loop_offsets[r0 : r1 + 1])
    kept = np.flatnonzero(np.asarray(loop_closed[r0:r1], dtype=bool) & (counts >= 3))
    counts = counts[kept]
    layer_of = np.searchsorted(layer_offsets, kept + r0, side="right") - 1  # each kept loop's layer
    bounds = np.searchsorted(layer_of, np.arange(l0, l1 + 1))  # kept loops of each layer
    if kept.size:
        _, idx = expand_ranges(loop_offsets[kept + r0], counts)
        values = points[idx].astype(np.float64).reshape(-1)
        n = idx.size
        sep = np.full(2 * n, ord('"'), dtype=np.uint8)
        vx, vy = format_fixed(values, decimals, sep,
                              [(np.arange(0, 2 * n, 2), b'<s:vertex x="'), (np.arange(1, 2 * n, 2), b' y="')],
                              [(np.arange(1, 2 * n, 2), b"/>")])
        v_at = vy[0 : 2 * n + 1 : 2].tolist()  # byte offset of each vertex (+ the end)
        # vertex indices restart at 0 in every slice: the index of a point is its rank within its layer
        loop_first = np.cumsum(counts) - counts  # first vertex of each kept loop, chunk-wide
        layer_first = np.concatenate((loop_first, [n]))[bounds]
        local = np.arange(n, dtype=np.int64) - np.repeat(layer_first[:-1], np.diff(layer_first))
        start_local = local[loop_first]
        v2 = np.roll(local, -1)  # each point's segment goes to the next point of its loop, the last to startv
        v2[loop_first + counts - 1] = start_local
        heads = [f'<s:polygon startv="{s}">'.encode() for s in start_local.tolist()]
        sx, sy = format_fixed(v2.astype(np.float64), 0, ord('"'),
                              [(loop_first, heads), (np.arange(n), b'<s:segment v2="')],
                              [(np.arange(n), b"/>"), (loop_first + counts - 1, b"</s:polygon>")])
        s_at = sy[np.concatenate((loop_first, [n]))].tolist()  # byte offset of each polygon (+ the end)
        v_mv, s_mv = memoryview(vx), memoryview(sx)
        lf = layer_first.tolist()
    bl = bounds.tolist()
    for i in range(l0, l1):
        ztop = _num(top[i])
        a, b = bl[i - l0], bl[i - l0 + 1]
        if b == a:
            fh.write(f'<s:slice ztop="{ztop}"/>\n'.encode())
            continue
        fh.write(f'<s:slice ztop="{ztop}">\n<s:vertices>'.encode())
        fh.write(v_mv[v_at[lf[i - l0]] : v_at[lf[i - l0 + 1]]])
        fh.write(b"</s:vertices>\n")
        fh.write(s_mv[s_at[a] : s_at[b]])
        fh.write(b"\n</s:slice>\n")


def _bbox_object(points: np.ndarray, z0: float, z1: float) -> str:
    """The low-resolution mesh of the sliced object: the stack's bounding box (12 triangles, outward)."""
    lo, hi = point_bounds(points) if points.size else (np.zeros(2), np.zeros(2))
    if z1 <= z0:
        z1 = z0 + 1e-3
    xs, ys, zs = (lo[0], hi[0]), (lo[1], hi[1]), (z0, z1)
    f = fmt_scalar
    verts = "".join(f'<vertex x="{f(xs[i & 1])}" y="{f(ys[(i >> 1) & 1])}" z="{f(zs[i >> 2])}"/>' for i in range(8))
    tris = ((0, 2, 1), (1, 2, 3), (4, 5, 6), (5, 7, 6), (0, 1, 4), (1, 5, 4),
            (2, 6, 3), (3, 6, 7), (0, 4, 2), (2, 4, 6), (1, 3, 5), (3, 7, 5))
    faces = "".join(f'<triangle v1="{a}" v2="{b}" v3="{c}"/>' for a, b, c in tris)
    return (
        '<object id="2" name="gpuslice slices" type="model" s:slicestackid="1" s:meshresolution="lowres">'
        f"<mesh><vertices>{verts}</vertices><triangles>{faces}</triangles></mesh></object>\n"
    )


def read_3mf_slices(path: PathLike) -> tuple[float, list[tuple[float, list[tuple[np.ndarray, bool]]]]]:
    """Read the first slice stack of a 3MF's ``3D/3dmodel.model`` (inline slices, as :func:`write_3mf_slices`
    writes them): ``(zbottom, [(ztop, [(points (n, 2) float64 mm, closed), ...]), ...])``. A polygon's points are
    ``startv`` then each segment's ``v2``, without the repeated ``startv`` when it is closed. One-line
    :class:`MeshFileError` when the file is not such a 3MF."""
    s = f"{{{SLICE_NS}}}"
    try:
        with zipfile.ZipFile(path) as zf, zf.open(_MODEL) as fh:
            z_bottom, slices = 0.0, []
            for _, el in ET.iterparse(fh, events=("end",)):
                if el.tag == f"{s}slice":
                    vs = el.find(f"{s}vertices")
                    xy = np.array([(float(v.get("x")), float(v.get("y"))) for v in vs.iter(f"{s}vertex")]
                                  if vs is not None else [], dtype=np.float64).reshape(-1, 2)
                    polys = []
                    for p in el.iter(f"{s}polygon"):
                        ids = [int(p.get("startv"))] + [int(g.get("v2")) for g in p.iter(f"{s}segment")]
                        closed = len(ids) > 1 and ids[-1] == ids[0]
                        polys.append((xy[ids[:-1] if closed else ids], closed))
                    slices.append((float(el.get("ztop")), polys))
                    el.clear()
                elif el.tag == f"{s}slicestack":
                    z_bottom = float(el.get("zbottom", "0"))
                    break
    except (OSError, KeyError, zipfile.BadZipFile, ET.ParseError, TypeError, ValueError, IndexError) as exc:
        raise MeshFileError(f"{path}: not a readable 3MF slice stack ({type(exc).__name__}: {exc})") from None
    return z_bottom, slices
