"""Layer schedules: where each layer is cut and how thick it is.

A :class:`Schedule` is two float64 arrays of equal length: ``z``, the height of each layer's cutting plane in mm
above the bed (the mesh's lowest point is at z = 0), and ``thickness``, each layer's thickness in mm. Layers tile the
object from the bed up: layer i spans ``[bottom[i], bottom[i] + thickness[i]]`` with ``bottom`` the running sum of
the earlier thicknesses (explicit planes that such slabs would not hold get their own: :func:`slab_bottoms`). The
slicer only looks at ``z``; ``thickness`` is carried through to the result (areas times
thicknesses give volumes, exports write layer tops).

Uniform schedules (:func:`uniform`) follow Slic3r and CuraEngine: the plane of layer i is the middle of its slab,
``z_i = (i + 0.5)·h`` (with a first layer of its own thickness ``h0``, ``z_0 = h0/2`` and
``z_i = h0 + (i - 0.5)·h``), and a layer is kept while its cutting plane is below the top of the object. The
``paper`` mode cuts at the paper's planes ``Z_i = Z_min + i·h`` (i ≥ 1), keeping planes below the top.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError
from ..io.rawmesh import MAX_COORDINATE
from ..options import is_finite, shown
from .validate import check_uniform

__all__ = ["Schedule", "uniform", "from_z", "slab_bottoms"]



def _reals(value, what: str) -> np.ndarray:
    """``value`` (a number or an array of at most one dimension) as a 1-D float64 array; :class:`ParameterError`
    naming ``what`` for text, complex or bool values and for arrays of two or more dimensions."""
    try:
        a = np.asarray(value)
        if a.dtype.kind == "O":
            a = a.astype(np.float64)
    except (TypeError, ValueError):
        raise ParameterError(f"schedule: {what} must be numbers (mm), got {type(value).__name__}") from None
    if a.dtype.kind not in "iuf":
        raise ParameterError(f"schedule: {what} must be numbers (mm), got dtype {a.dtype}")
    if a.ndim > 1:
        raise ParameterError(f"schedule: {what} must be one number per layer (1-D), got shape {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float64).reshape(-1)


def _check_planes(z: np.ndarray, what: str) -> None:
    """:class:`ParameterError` unless every value of ``z`` is finite and within a mesh's coordinates' bound
    (:data:`~gpuslice.io.rawmesh.MAX_COORDINATE`, which a saved result's loader holds too; NaN fails)."""
    if z.size and not (-MAX_COORDINATE <= float(z.min()) and float(z.max()) <= MAX_COORDINATE):
        bad = float(z[~(np.abs(z) <= MAX_COORDINATE)][0])
        raise ParameterError(f"schedule: cutting planes must lie within 1e18 mm of the bed, got {what} up to {bad:g}")


@dataclass(frozen=True)
class Schedule:
    """Cutting planes ``z`` (L,) and thicknesses ``thickness`` (L,), float64, mm; ``z`` strictly increasing."""

    z: np.ndarray
    thickness: np.ndarray
    mode: str = "custom"

    def __post_init__(self) -> None:
        z = _reals(self.z, "z values")
        t = _reals(self.thickness, "thicknesses")
        if t.shape != z.shape:
            raise ParameterError(f"schedule: {z.size} z values but {t.size} thicknesses")
        _check_planes(z, "z values")
        if not np.all(np.isfinite(t)):
            raise ParameterError("schedule: z values and thicknesses must be finite")
        if z.size > 1 and not np.all(np.diff(z) > 0):
            raise ParameterError("schedule: z values must be strictly increasing")
        if np.any(t <= 0):
            raise ParameterError("schedule: thicknesses must be positive")
        if np.any(t > MAX_COORDINATE):  # (1e308 was sliced: its result's volume overflowed, its .npz did not load)
            raise ParameterError(f"schedule: thicknesses must be at most {MAX_COORDINATE:g} mm")
        object.__setattr__(self, "z", z)
        object.__setattr__(self, "thickness", t)

    def __len__(self) -> int:
        return int(self.z.size)

    @property
    def bottom(self) -> np.ndarray:
        """(L,) float64: the bottom of each layer's slab, mm (:func:`slab_bottoms`)."""
        return slab_bottoms(self.z, self.thickness)

    @property
    def top(self) -> np.ndarray:
        """(L,) float64: the top of each layer's slab, mm."""
        return self.bottom + self.thickness


def slab_bottoms(z: np.ndarray, thickness: np.ndarray) -> np.ndarray:
    """(L,) float64: the bottom of each layer's slab, mm. The layers tile the part from the bed up (bottom_i =
    t_0 + … + t_(i−1)) wherever each plane then lies in its own slab, as in every uniform and adaptive schedule (or
    from half the first layer below its plane, as :func:`from_z` tiles planes that start at or below the bed);
    explicit planes that do not (``z=[1, 2, 3]`` with 0.1 mm layers, a plane below the bed) each get a slab centred
    on it (z_i − t_i / 2), the one placement their planes and thicknesses give, so that exports state where each
    layer really is. A plane on its slab's bottom edge is not in that slab: a section is the limit from below (the
    on-plane rule), the layer under it (``from_z`` planes from 0 tiled from the bed left layer 0 empty)."""
    z = np.asarray(z, np.float64)
    t = np.asarray(thickness, np.float64)
    if z.size == 0:
        return np.zeros(0)
    eps = 1e-9 * max(1.0, float(np.max(np.abs(z))))
    # from the bed, else from below the first plane (from_z's own slabs of a plane at or below the bed)
    for base in (0.0, float(z[0] - t[0] / 2)):
        tiled = base + np.concatenate(([0.0], np.cumsum(t)[:-1]))
        if np.all(z > tiled + eps) and np.all(z <= tiled + t + eps):
            return tiled
    return z - t / 2


def uniform(
    height: float, thickness: float, *, first_layer: float | None = None, z_mode: str = "mid"
) -> Schedule:
    """A uniform schedule for an object ``height`` mm tall standing on the bed (its lowest point at z = 0).

    Parameters
    ----------
    height : float
        The object's height, mm (its top is at z = height).
    thickness : float
        Layer thickness h, mm.
    first_layer : float, optional
        Thickness of the first layer h0, mm (default h). Mode ``mid`` only.
    z_mode : {"mid", "paper"}
        ``mid``: cut each layer at the middle of its slab, ``z_i = (i + 0.5)·h`` (Slic3r, CuraEngine), keeping
        layers whose plane is below the top (compared in float32, as the planes are cut: a plane that rounds onto
        the top is not kept). ``paper``: the paper's ``Z_i = i·h`` for i = 1, 2, … below the top;
        layer i then spans ``[(i - 1)·h, i·h]`` and is cut at its top.

    Examples
    --------
    >>> uniform(1.0, 0.25).z
    array([0.125, 0.375, 0.625, 0.875])
    >>> uniform(1.0, 0.25, z_mode="paper").z
    array([0.25, 0.5 , 0.75])
    """
    check_uniform(thickness, first_layer, z_mode)
    if not (is_finite(height) and float(height) >= 0):
        raise ParameterError(f"object height must be finite and non-negative, got {shown(height)}")
    thickness = float(thickness)  # (an int gave an int array below, which cut a first layer of 1.5 mm to 1)
    h0 = thickness if first_layer is None else float(first_layer)
    if height / thickness > 5e7:
        raise ParameterError(f"{height:g} mm at {thickness:g} mm would make more than 5e7 layers")
    if z_mode == "mid":
        n = int(np.ceil((height - h0 / 2) / thickness)) + 2 if height > h0 / 2 else 1
        z = np.concatenate(([h0 / 2], h0 + (np.arange(1, n) - 0.5) * thickness))
        t = np.full(z.size, thickness)
        t[0] = h0
    else:  # "paper" (check_uniform refused the others)
        n = int(np.ceil(height / thickness)) + 1
        z = np.arange(1, n + 1) * thickness
        t = np.full(z.size, thickness)
    # below the top as the kernels cut: the float32 plane against the float32 top (a mesh's height is float32);
    # in float64 a plane that rounds onto the top was kept or dropped by how i·h happened to round (paper mode:
    # a 0.4 and a 0.5 mm box both gave 4 layers)
    with np.errstate(over="ignore"):  # (a plane beyond float32, -t 1e300's, is inf there: above any top)
        keep = z.astype(np.float32) < np.float32(height)
    return Schedule(z[keep], t[keep], mode=f"uniform-{z_mode}")


def from_z(z: np.ndarray, thickness: np.ndarray | float | None = None) -> Schedule:
    """A schedule from explicit cutting planes ``z`` (mm, strictly increasing).

    ``thickness`` may be an array, one number for every layer, or None: then each layer reaches from the middle
    between its plane and the one below (0 for the first) to the middle between its plane and the one above
    (the last layer is as thick above its plane as below).
    """
    z = _reals(z, "z values")
    _check_planes(z, "z values")  # (before the planes' midpoints: inf and 1e308 made numpy warn there)
    if thickness is None:
        if z.size == 0:
            t = np.zeros(0)
        else:
            edges = np.concatenate(([min(0.0, z[0])], (z[1:] + z[:-1]) / 2, [0.0]))
            if z[0] <= 0:  # a plane at or below the bed: give it the spacing above it (or 1 mm alone)
                edges[0] = z[0] - ((edges[1] - z[0]) if z.size > 1 else 0.5)
            edges[-1] = z[-1] + (z[-1] - edges[-2])
            t = np.diff(edges)
    else:
        t = _reals(thickness, "thicknesses")
        if t.size not in (1, z.size):
            raise ParameterError(f"schedule: thickness must be one number or one per z value ({z.size}), got "
                                 f"{t.size} values")
        t = np.broadcast_to(t, z.shape)
    return Schedule(z, t, mode="custom")
