"""The columnar slicing result: every layer's loops in a few flat numpy arrays.

Layout (the GeoArrow / ragged-array layout, see ``docs/ARCHITECTURE.md``)::

    points        (P, 2) float32   x, y in mm, every loop's points one after another
    loop_offsets  (R + 1,) int64   loop r owns points[loop_offsets[r]:loop_offsets[r + 1]]
    layer_offsets (L + 1,) int64   layer i owns loops layer_offsets[i]:layer_offsets[i + 1]
    loop_layer    (R,) int32       the layer of each loop
    loop_is_hole  (R,) bool        True for holes (clockwise seen from +z), False for outer contours (CCW)
    loop_parent   (R,) int32       for a hole, the index of the outer loop it lies in; -1 for outer loops
    loop_closed   (R,) bool        False for chains left open after repair (broken meshes only)
    z             (L,) float64     the cutting plane of each layer, mm above the bed
    thickness     (L,) float64     each layer's thickness, mm; layer i spans [bottom[i], bottom[i] + thickness[i]]
    area          (L,) float64     filled area of each layer under the fill rule, mm^2
    repairs       dict[str, (L,) int32]   per-layer counts of each kind of repair

Within a layer, loops come polygon by polygon: an outer loop, then its holes. A closed loop does not repeat its
first point at the end. Outer loops are counter-clockwise and holes clockwise, seen from +z (looking down).
"""

from __future__ import annotations

import json
import operator
import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MeshFileError, ParameterError
from ..io.rawmesh import MAX_COORDINATE
from ..options import check_flag

__all__ = ["SliceResult", "LayerView", "LayerIndexError"]


class LayerIndexError(ParameterError, IndexError):
    """A layer or loop index out of range: a :class:`~gpuslice.errors.ParameterError` that is also the
    ``IndexError`` a Python sequence raises."""


def _index(i: Any, n: int, what: str) -> int:
    """``i`` (an integer, negative from the end as in Python) as an index into ``n`` items, or a one-line error."""
    if isinstance(i, bool | np.bool_):
        raise ParameterError(f"{what} index must be an integer, got {i!r}")
    try:
        k = operator.index(i)
    except TypeError:
        raise ParameterError(f"{what} index must be an integer, got {type(i).__name__} {i!r}") from None
    if not -n <= k < n:
        raise LayerIndexError(f"{what} {k} out of range for {n} {what}s")
    return k % n

_ARRAYS = (
    "points",
    "loop_offsets",
    "layer_offsets",
    "loop_layer",
    "loop_is_hole",
    "loop_parent",
    "loop_closed",
    "z",
    "thickness",
    "area",
)


@dataclass
class LayerView:
    """One layer of a :class:`SliceResult`, as views into the result's arrays (no copies).

    ``index``: the layer's number (from 0); ``z``: its cutting plane, mm above the bed; ``thickness``: mm; ``area``:
    its filled area, mm². ``loops`` are the loop indices of the layer; ``loop(i)`` returns the (n, 2) float32 points
    of the i-th loop of this layer, in mm.
    """

    index: int
    z: float
    thickness: float
    area: float
    result: SliceResult
    loops: range

    def loop(self, i: int) -> np.ndarray:
        r = self.loops[_index(i, len(self.loops), "loop")]
        o = self.result.loop_offsets
        return self.result.points[o[r] : o[r + 1]]

    def polygons(self) -> list[tuple[np.ndarray, list[np.ndarray]]]:
        """The layer's filled region as ``[(outer (n, 2), [hole (m, 2), ...]), ...]`` (closed loops only)."""
        res = self.result
        out: list[tuple[np.ndarray, list[np.ndarray]]] = []
        index_of: dict[int, int] = {}
        for k, r in enumerate(self.loops):
            if not res.loop_closed[r]:
                continue
            if not res.loop_is_hole[r]:
                index_of[r] = len(out)
                out.append((self.loop(k), []))
            else:
                parent = int(res.loop_parent[r])
                if parent in index_of:
                    out[index_of[parent]][1].append(self.loop(k))
        return out

    @property
    def n_points(self) -> int:
        o = self.result.loop_offsets
        return int(o[self.loops.stop] - o[self.loops.start])

    # ---- the Python geometry ecosystem (shapely, GeoJSON-like dicts, matplotlib) --------------------------
    def to_shapely(self, open_chains: bool = False) -> Any:
        """This layer as one shapely ``MultiPolygon`` (mm; holes as interiors, shells CCW, holes CW).

        With ``open_chains=True``, returns ``(multipolygon, multilinestring)``: the open chains (broken meshes
        only) as a ``MultiLineString``, empty when there are none. See :mod:`gpuslice.slicing.geometry`.
        """
        from .geometry import open_chains_shapely, polygons_shapely

        check_flag(open_chains, "open_chains")
        polys = polygons_shapely(self.result, self.index, self.index + 1)[0]
        if open_chains:
            return polys, open_chains_shapely(self.result, self.index, self.index + 1)[0]
        return polys

    @property
    def __geo_interface__(self) -> dict[str, Any]:
        """The layer's filled region as a GeoJSON-like ``{"type": "MultiPolygon", "coordinates": …}`` (mm; rings
        closed, first point repeated last; outer rings CCW, holes CW as RFC 7946 asks). Open chains are left out."""
        return self.to_shapely().__geo_interface__

    def plot(self, ax: Any = None, **style: Any) -> Any:
        """Draw the layer with matplotlib (holes as holes, open chains in red) on ``ax`` (new axes when ``None``);
        returns the axes. ``style``: ``color``, ``alpha``, ``edgecolor``, ``linewidth``."""
        from .plotting import plot_layers

        return plot_layers(self.result, self.index, ax, **style)


@dataclass
class SliceResult:
    """Nested contours of every layer of a sliced mesh; see the module docstring for the layout.

    All lengths are in mm. ``meta`` holds the run's report (device, timings, parameters, counts) as JSON-able
    values.
    """

    points: np.ndarray
    loop_offsets: np.ndarray
    layer_offsets: np.ndarray
    loop_layer: np.ndarray
    loop_is_hole: np.ndarray
    loop_parent: np.ndarray
    loop_closed: np.ndarray
    z: np.ndarray
    thickness: np.ndarray
    area: np.ndarray
    repairs: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)
    #: (L,) bool, or None where unknown (a loaded result): the layer's polygons have exactly the edges of its
    #: crossings' segments (nothing repaired, dropped, turned round or rebuilt); not saved
    #: (:mod:`gpuslice.raster.segment_edges`)
    segment_exact: np.ndarray | None = field(default=None, repr=False, compare=False)

    # ---- sizes and per-layer signals -------------------------------------------------------------------
    @property
    def n_layers(self) -> int:
        return int(self.z.shape[0])

    @property
    def n_loops(self) -> int:
        return int(self.loop_layer.shape[0])

    @property
    def bottom(self) -> np.ndarray:
        """(L,) float64: the bottom of each layer's slab, mm (layers tile the object from the bed up, unless explicit
        planes lie outside such slabs: :func:`gpuslice.schedule.uniform.slab_bottoms`)."""
        from ..schedule.uniform import slab_bottoms

        return slab_bottoms(self.z, self.thickness) if self.n_layers else np.zeros(0)

    @property
    def points_per_layer(self) -> np.ndarray:
        """(L,) int64: points in each layer, the paper's Fig. 11 signal."""
        return np.diff(self.loop_offsets[self.layer_offsets])

    @property
    def loops_per_layer(self) -> np.ndarray:
        return np.diff(self.layer_offsets)

    @property
    def open_chains_per_layer(self) -> np.ndarray:
        return np.bincount(self.loop_layer[~self.loop_closed], minlength=self.n_layers).astype(np.int64)

    @property
    def volume(self) -> float:
        """Σ area · thickness, mm^3."""
        return float(np.dot(self.area, self.thickness))

    def layer(self, i: int) -> LayerView:
        """Layer ``i`` (negative: from the top, as in Python) as a :class:`LayerView`; :class:`LayerIndexError`
        (a ``ParameterError`` and an ``IndexError``) when out of range."""
        i = _index(i, self.n_layers, "layer")
        a, b = int(self.layer_offsets[i]), int(self.layer_offsets[i + 1])
        return LayerView(i, float(self.z[i]), float(self.thickness[i]), float(self.area[i]), self, range(a, b))

    def __iter__(self):
        return (self.layer(i) for i in range(self.n_layers))

    # ---- the Python geometry ecosystem (shapely, matplotlib) ---------------------------------------------
    def to_shapely(self, open_chains: bool = False) -> Any:
        """Every layer as a shapely ``MultiPolygon``: a list, one per layer (empty ``MultiPolygon`` for an empty
        layer), coordinates in mm, holes as interiors (shells CCW, holes CW, as in the result).

        Built with shapely 2's vectorised constructors from the flat arrays, with no Python loop over points,
        loops or layers (``numpy.asarray`` of the list gives the shapely 2 array for ``shapely.area`` and co).
        Open chains (broken meshes only) are never part of the polygons: with ``open_chains=True`` the call
        returns ``(polygons, lines)``, ``lines`` a list of one ``MultiLineString`` per layer (empty where none);
        :meth:`open_chains_shapely` gives ``lines`` alone.
        """
        from .geometry import polygons_shapely

        check_flag(open_chains, "open_chains")
        polys = polygons_shapely(self).tolist()
        return (polys, self.open_chains_shapely()) if open_chains else polys

    def open_chains_shapely(self) -> list[Any]:
        """The open chains of every layer: a list of one shapely ``MultiLineString`` per layer (mm)."""
        from .geometry import open_chains_shapely

        return open_chains_shapely(self).tolist()

    def plot(self, layers: int | Any = None, ax: Any = None, **style: Any) -> Any:
        """Draw ``layers`` (an index, a sequence of indices, or ``None`` for all) with matplotlib, overlaid and
        coloured by z, holes as holes; returns the axes (new ones when ``ax`` is ``None``). ``style``: ``color``,
        ``alpha``, ``edgecolor``, ``linewidth``."""
        from .plotting import plot_layers

        if layers is not None:  # each an integer in range, or a one-line error naming it
            for i in [layers] if np.ndim(layers) == 0 else layers:
                _index(i, self.n_layers, "layer")
        return plot_layers(self, layers, ax, **style)

    def __len__(self) -> int:
        return self.n_layers

    # ---- persistence -----------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write a ``.npz`` (uncompressed, byte-identical for identical results), atomically."""
        from ..io.atomic import atomic_path

        arrays = self.npz_arrays()
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)

    def npz_arrays(self) -> dict[str, np.ndarray]:
        """The ``.npz`` file's members in its order (names without ``.npy``): the layout's arrays, ``points`` first,
        then ``repairs__KIND`` per repair kind (sorted) and ``meta_json`` (the meta as sorted JSON, without the
        timings, which differ run to run: byte-identical outputs)."""
        arrays = {name: getattr(self, name) for name in _ARRAYS}
        for kind, counts in sorted(self.repairs.items()):
            arrays[f"repairs__{kind}"] = counts
        meta = {k: v for k, v in self.meta.items() if k != "timings_s"}
        arrays["meta_json"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
        return arrays

    @classmethod
    def load(cls, path: str | os.PathLike) -> SliceResult:
        """Read a ``.npz`` written by :meth:`save`; :class:`~gpuslice.errors.MeshFileError` naming the file when it
        is not one (missing, truncated, another .npz, arrays that do not fit together)."""
        if not isinstance(path, str | os.PathLike):
            raise ParameterError(f"path must be a file path, got {type(path).__name__}")
        p = Path(path)
        if not p.exists():  # (as every reader says it, not "not a gpuslice result ([Errno 2] ...)")
            raise MeshFileError(f"{p}: no such file")
        try:
            with open(p, "rb") as f:  # (numpy reads any other bytes as a pickle and suggests allow_pickle)
                head = f.read(6)
            if not head.startswith((b"PK\x03\x04", b"PK\x05\x06", b"\x93NUMPY")):
                raise ValueError("not an .npz archive (no zip header)")
            data = np.load(p, allow_pickle=False)
            if not isinstance(data, np.lib.npyio.NpzFile):  # a .npy file
                raise ValueError("a single .npy array, not an .npz archive")
            with data:
                arrays = {name: data[name] for name in _ARRAYS}
                repairs = {k[len("repairs__") :]: data[k] for k in data.files if k.startswith("repairs__")}
                meta = json.loads(bytes(data["meta_json"]).decode()) if "meta_json" in data.files else {}
        except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
            raise MeshFileError(f"{p}: not a gpuslice result ({exc})") from None
        problem = _layout_problem(arrays, repairs, meta)
        if problem:
            raise MeshFileError(f"{p}: not a gpuslice result ({problem})")
        for name, dtype in _INDEX_DTYPES.items():  # (as the slicer makes them: values checked to fit above)
            arrays[name] = arrays[name].astype(dtype, copy=False)
        repairs = {k: v.astype(np.int32, copy=False) for k, v in repairs.items()}
        return cls(**arrays, repairs=repairs, meta=meta)


#: the index arrays' dtypes as the slicer makes them (a loaded file's integers of any width are checked and cast)
_INDEX_DTYPES = {"loop_offsets": np.int64, "layer_offsets": np.int64, "loop_layer": np.int32, "loop_parent": np.int32}

#: the dtype kinds of the 1-D arrays of the layout (numpy's ``dtype.kind``)
_KINDS = {"loop_offsets": "iu", "layer_offsets": "iu", "loop_layer": "iu", "loop_is_hole": "b", "loop_parent": "iu",
          "loop_closed": "b", "z": "fiu", "thickness": "fiu", "area": "fiu"}  # (an empty layer's area may be 0 int)


def _layout_problem(arrays: dict[str, np.ndarray], repairs: dict[str, np.ndarray], meta: Any) -> str | None:
    """What does not fit the layout (module docstring) in a loaded result's arrays, or None: shapes, dtypes,
    lengths, offsets' ends and order, index ranges, points and z finite and within a mesh's bound
    (:data:`~gpuslice.io.rawmesh.MAX_COORDINATE`: the raster's and the viewer's float64 arithmetic stays finite),
    thicknesses in (0, that], areas bounded, and the metadata gpuslice reads back (:func:`_meta_problem`)."""
    pts = arrays["points"]
    if pts.ndim != 2 or pts.shape[1] != 2 or pts.dtype != np.float32:
        return f"points must be (P, 2) float32, got shape {pts.shape} dtype {pts.dtype}"
    for name, kind in _KINDS.items():
        a = arrays[name]
        if a.ndim != 1 or a.dtype.kind not in kind:
            return f"{name} must be 1-D of dtype kind {kind!r}, got shape {a.shape} dtype {a.dtype}"
    for name in _INDEX_DTYPES:  # (uint64 beyond int64 would wrap when cast; numpy refuses to mix them)
        a = arrays[name]
        if a.dtype.kind == "u" and a.size and int(a.max()) > np.iinfo(np.int64).max:
            return f"{name} holds values beyond int64"
        arrays[name] = a.astype(np.int64, copy=False)
    n_loops, n_layers = arrays["loop_layer"].size, arrays["z"].size
    sizes = {"loop_offsets": n_loops + 1, "layer_offsets": n_layers + 1, "loop_is_hole": n_loops,
             "loop_parent": n_loops, "loop_closed": n_loops, "thickness": n_layers, "area": n_layers}
    for name, size in sizes.items():
        if arrays[name].size != size:
            return f"{name} holds {arrays[name].size} values, expected {size}"
    for kind, counts in repairs.items():
        if counts.shape != (n_layers,) or counts.dtype.kind not in "iu":
            return f"repairs__{kind} must be {n_layers} integers, got shape {counts.shape} dtype {counts.dtype}"
    for name, end in (("loop_offsets", pts.shape[0]), ("layer_offsets", n_loops)):
        o = arrays[name]
        if o[0] != 0 or o[-1] != end or np.any(o[1:] < o[:-1]):
            return f"{name} must rise from 0 to {end}"
    lay, par = arrays["loop_layer"], arrays["loop_parent"]
    if n_loops and (lay.min() < 0 or lay.max() >= n_layers or par.min() < -1 or par.max() >= n_loops):
        return "loop_layer or loop_parent out of range"
    lo = arrays["layer_offsets"]
    if n_loops and np.any(lay != np.repeat(np.arange(n_layers), np.diff(lo))):
        return "loop_layer disagrees with layer_offsets (a loop listed under another layer than its own)"
    if not all(np.isfinite(arrays[k]).all() for k in ("z", "thickness", "area")):
        return "z, thickness or area not finite"
    if np.any(np.diff(arrays["z"]) <= 0):
        return "z must be strictly increasing"
    z, th = arrays["z"], arrays["thickness"]
    if n_layers and not (-MAX_COORDINATE <= float(z.min()) and float(z.max()) <= MAX_COORDINATE):
        return "z must lie within 1e18 mm of the bed"
    if n_layers and not (float(th.min()) > 0 and float(th.max()) <= MAX_COORDINATE):
        return "thickness must be more than 0 and at most 1e18 mm"
    lo, hi = (float(pts.min()), float(pts.max())) if pts.size else (0.0, 0.0)
    if not (-MAX_COORDINATE <= lo and hi <= MAX_COORDINATE):  # (False for a NaN)
        return "points must be finite, within 1e18 mm of the origin"
    if not (np.abs(arrays["area"]) <= (2 * MAX_COORDINATE) ** 2).all():
        return "area beyond what points within 1e18 mm bound"
    return _meta_problem(meta)


def _meta_problem(meta: Any) -> str | None:
    """What is wrong with a loaded result's metadata, or None: it must be an object, and the entries gpuslice reads
    back (the viewer's summary, the fill rule, the checks' count of filled holes) must have their types."""
    if not isinstance(meta, dict):
        return f"meta_json must hold an object, got {type(meta).__name__}"
    facets, scale = meta.get("facets", 0), meta.get("scale", 1.0)
    if isinstance(facets, bool) or not isinstance(facets, int) or facets < 0:
        return f"meta_json's facets must be a whole number, got {facets!r:.40}"
    if isinstance(scale, bool) or not isinstance(scale, int | float) or not 0 < scale < float("inf"):
        return f"meta_json's scale must be a positive number, got {scale!r:.40}"
    for key in ("file", "schedule_mode", "device"):
        if not isinstance(meta.get(key, ""), str | type(None)):
            return f"meta_json's {key} must be text, got {type(meta[key]).__name__}"
    for key in ("params", "repairs"):
        if not isinstance(meta.get(key, {}), dict):
            return f"meta_json's {key} must be an object, got {type(meta[key]).__name__}"
    rule = meta.get("params", {}).get("fill_rule", "nonzero")
    if rule not in ("nonzero", "evenodd", "positive"):
        return f"meta_json's fill rule must be nonzero, evenodd or positive, got {rule!r:.40}"
    counts = meta.get("repairs", {}).values()
    if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in counts):
        return "meta_json's repairs must be counts (whole numbers)"
    return None
