"""``--z-samples K``: every layer's runs averaged over K sub-planes of its slab, for the pipeline's resin stage
(:func:`gpuslice.pipeline.run_job`). The sub-planes of :data:`Z_SAMPLE_CHUNK` layers at a time are cut and
rasterised, then let go: straight from their segments to the runs where the segment-buffer shortcut holds
(:mod:`gpuslice.raster.segment_edges`), else sliced into polygons first."""

from __future__ import annotations

import time
from typing import Any

__all__ = ["Z_SAMPLE_CHUNK", "segment_shortcut", "z_sampled_layers"]

#: layers whose z sub-planes are sliced at once (memory: their K-fold sub-slice, not the whole model's)
Z_SAMPLE_CHUNK = 128


def z_sampled_layers(mesh, result, params, spec, dev, bounds, k: int, *, sliced_on=None,
                     timings: dict[str, float], stats: dict[str, Any]):
    """:class:`~gpuslice.raster.layers.RunLayer` of every layer of ``result`` (sliced from ``mesh`` with ``params``,
    on the device ``sliced_on``, None for numpy) averaged over ``k`` sub-planes of its slab, in order, on ``spec``'s
    display placed by ``bounds``, rasterised on ``dev``. The sub-planes' cutting is timed as ``timings["z_samples"]``;
    ``stats["z_samples_from"]`` says whether they went straight from their segments (and
    ``stats["z_samples_polygon_layers"]`` how many layers the shortcut still cut into polygons) or why not."""
    from ..slicing.slicer import slice_mesh
    from .edges import z_sample_planes
    from .layers import RunLayer, iter_run_layers

    z, th = z_sample_planes(result, k)
    refusal, kern = segment_shortcut(mesh, result, params, spec, dev, bounds, sliced_on=sliced_on)
    stats["z_samples_from"] = "segments" if refusal is None else f"polygons ({refusal})"

    def chunks():  # (first layer, its chunk's runs)
        if kern is not None:  # the sub-planes' segments straight to the runs (raster/segment_edges.py)
            from .segment_edges import iter_sub_plane_edges

            stats["z_samples_polygon_layers"] = 0
            cut = lambda sel: slice_mesh(mesh, params, z=z[sel], layer_thickness=th[sel])  # noqa: E731
            for a, merged, cut_layers in iter_sub_plane_edges(mesh, z, k, spec, bounds, dev, cut, Z_SAMPLE_CHUNK,
                                                              timings):
                stats["z_samples_polygon_layers"] += int(cut_layers.size)
                yield a, iter_run_layers(None, spec, device=dev, bounds=bounds, z_samples=k, merged=merged)
            return
        for a in range(0, result.n_layers, Z_SAMPLE_CHUNK):
            b = min(a + Z_SAMPLE_CHUNK, result.n_layers)
            t = time.perf_counter()
            sub = slice_mesh(mesh, params, z=z[a * k : b * k], layer_thickness=th[a * k : b * k])
            timings["z_samples"] = timings.get("z_samples", 0.0) + time.perf_counter() - t
            yield a, iter_run_layers(sub, spec, device=dev, bounds=bounds, z_samples=k, clip=True)  # (in the mesh's)

    for a, chunk in chunks():
        try:
            for item in chunk:
                yield RunLayer(a + item.index, item.runs, item.j)
        finally:
            chunk.close()


def segment_shortcut(mesh, result, params, spec, dev, bounds, *, sliced_on=None):
    """(why the z sub-planes go through chaining and nesting, or None; the driver that makes their edges from their
    segments instead, or None): :mod:`gpuslice.raster.segment_edges`."""
    from .segment_edges import SegmentEdgesKernel, shortcut_refusal

    if params.backend != "opencl" or sliced_on is None:
        return "the slices are made by numpy", None
    refusal = shortcut_refusal(mesh, result, params.fill_rule, spec, bounds)
    if refusal is not None:
        return refusal, None
    kern = SegmentEdgesKernel.of(dev)
    return (None, kern) if kern.available else ("the device has no doubles", None)
