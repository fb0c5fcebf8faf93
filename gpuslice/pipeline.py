"""One pipeline: a :class:`Job` (what to read, placement, schedule and slicing parameters, outputs) and the one
function that runs it, :func:`run_job`. ``gpuslice slice``, ``raster``, ``view``, ``bench`` and the batch workers
all run jobs through here, with the same stage names and timings:

``device`` (OpenCL context and kernels) → ``load`` (read the file) → ``topology`` (weld, edge ids, placement) →
``schedule``, ``crossings``, ``chaining``, ``nesting`` (the slicer's own) → ``mesh_check`` (defect counts, counted
on a thread beside the slicing: its time is what the job then waited for them) →
``write`` (the contour file) → ``cusp`` (schedule quality, for the report) → ``checks`` (pre-print checks) →
``raster`` (masks, encoding and the archive) → ``view`` (the viewer page; ``masks`` when it shows resin masks).

Timings are seconds, in :attr:`JobResult.timings`; nothing else of a run depends on the machine unless asked
(``Job.portable`` leaves the device and backend out of the result's meta, so outputs are the same anywhere).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ParameterError
from .mesh.mesh import Placement
from .slicing.params import SliceParams

if TYPE_CHECKING:
    from collections.abc import Callable

    from .mesh.mesh import Mesh
    from .raster.settings import PrintSettings
    from .raster.spec import RasterSpec, ResinOptions
    from .slicing.result import SliceResult

__all__ = ["CheckOutput", "Job", "JobResult", "ResinOutput", "ViewOutput", "prepare_device", "load_job_mesh", "run_job"]


@dataclass(frozen=True)
class ResinOutput:
    """Rasterise the layers onto ``spec``'s display and write them to ``path`` as the resin output ``format``
    (a name of :data:`gpuslice.raster.outputs.RESIN_FORMATS`), with ``options`` and the print ``settings`` (None:
    ``options.settings()``, the preset's or the defaults)."""

    path: str
    format: str
    spec: RasterSpec
    options: ResinOptions
    settings: PrintSettings | None = None

    def __post_init__(self) -> None:
        try:
            self.options.check_format(self.format, self.spec)  # a printer that cannot read it, or another display
        except ParameterError as exc:
            raise ParameterError(f"{self.path}: {exc}") from None
        from .raster.outputs import RESIN_FORMATS

        if self.format not in RESIN_FORMATS:
            raise ParameterError(f"{self.path}: unknown resin format '{self.format}' (use "
                                 f"{', '.join(RESIN_FORMATS)})")
        RESIN_FORMATS[self.format].check_settings(self.path, self.options, self.settings or self.options.settings(),
                                                  self.spec)


@dataclass(frozen=True)
class ViewOutput:
    """Write the HTML layer viewer to ``path``; ``masks``: also draw each ``mask_every``-th layer's resin mask on
    this display; ``title`` (default: the model's file name)."""

    path: str
    title: str | None = None
    masks: RasterSpec | None = None
    mask_every: int = 1


@dataclass(frozen=True)
class CheckOutput:
    """Run the pre-print checks (:func:`gpuslice.checks.run_checks`, stage ``checks``) after slicing, before any
    resin or view output: on ``spec``'s pixels (a printer's display, placed as the archive places it; None:
    contour-exact), with the print ``settings`` (None: the defaults) and ``options``
    (:class:`gpuslice.checks.CheckOptions`; None: the defaults); ``path``: also write the JSON report there;
    ``on_report(report)``: called as soon as the report is made (``raster --check`` prints it before writing);
    ``printer``: the preset whose display ``spec`` is (a model taller than its build height is refused before
    slicing, as ``raster`` refuses it). The report goes to ``JobResult.stats["checks"]``."""

    spec: RasterSpec | None = None
    settings: PrintSettings | None = None
    options: Any = None
    path: str | None = None
    on_report: Callable[[Any], None] | None = field(default=None, compare=False)
    printer: Any = None


@dataclass(frozen=True)
class Job:
    """What to slice and what to write (lengths in mm).

    source : the model file; for ``view``, a saved ``.npz`` result may stand in for a mesh (no slicing then).
    name : how outputs and the result's meta name the model (default: ``source``); label : how messages name the
        file (default: ``source``).
    data : the file's bytes, when they travel instead of a path (batch over Dask); ``source`` still names it.
    placement, params : :class:`~gpuslice.mesh.mesh.Placement` and :class:`~gpuslice.slicing.params.SliceParams`.
    contours : a contour file to write (format by suffix, :mod:`gpuslice.formats`), or None; ``contours_format``:
        a format name that overrides the suffix (``slice --format``).
    resin, view : a :class:`ResinOutput` / :class:`ViewOutput`, or None.
    checks : a :class:`CheckOutput` (the pre-print checks), or None.
    mesh_check : count the mesh's defects into ``meta["repairs"]`` (:func:`gpuslice.mesh.defects.mesh_repairs`).
    cusp : add the schedule's cusp heights to the meta (:func:`gpuslice.bench.quality.cusp_summary`).
    portable : leave the device and backend out of the meta, so output bytes do not depend on the machine.
    saved_result : a ``.npz`` source is a saved result, loaded instead of sliced (``view``); elsewhere it is read as
        a mesh file (and refused as one).
    date : the date a resin archive states (a naive UTC ``datetime``); None: ``SOURCE_DATE_EPOCH``'s, else the time
        of writing (a batch's Dask workers get their client's, whatever their own environment holds).
    """

    source: str
    name: str | None = None
    label: str | None = None
    data: bytes | None = field(default=None, repr=False)
    placement: Placement = Placement()
    params: SliceParams = SliceParams()
    contours: str | None = None
    contours_format: str | None = None
    resin: ResinOutput | None = None
    view: ViewOutput | None = None
    checks: CheckOutput | None = None
    mesh_check: bool = True
    cusp: bool = False
    portable: bool = False
    saved_result: bool = False
    date: Any = None

    def __post_init__(self) -> None:
        if self.placement.center and any(getattr(o.spec, "keep_xy", False) for o in (self.resin, self.checks) if o):
            raise ParameterError("--center moves the model's X/Y to the origin, and --keep-xy places it on the display "
                                 "by its own X/Y: give one of them", param=("center", "keep_xy"))

    @property
    def model_name(self) -> str:
        return self.name if self.name is not None else str(self.source)

    @property
    def is_saved_result(self) -> bool:
        return self.saved_result and self.data is None and Path(self.source).suffix.lower() == ".npz"


@dataclass
class JobResult:
    """What a job made: the ``mesh`` (None for a saved result), the ``result``, the OpenCL ``device`` used (None on
    the numpy backend), per-stage ``timings`` (s) and output ``stats`` (e.g. ``png_bytes``, ``view_bytes``)."""

    mesh: Mesh | None
    result: SliceResult
    device: Any
    timings: dict[str, float]
    stats: dict[str, Any] = field(default_factory=dict)


def prepare_device(params: SliceParams, device=None, timings: dict[str, float] | None = None):
    """The OpenCL device of ``params`` with every kernel built (one program), or ``device`` when given; None on the
    numpy backend. Its time goes to ``timings["device"]``."""
    if params.backend != "opencl" or device is not None:
        return device
    from .device import get_device

    t = time.perf_counter()
    dev = get_device(params.device)
    dev.program("crossings.cl")  # builds every kernels/*.cl (one program)
    if timings is not None:
        timings["device"] = timings.get("device", 0.0) + time.perf_counter() - t
    return dev


def load_job_mesh(job: Job, device=None, timings: dict[str, float] | None = None, reading=None) -> Mesh:
    """Read the job's file (or wait for ``reading``: its read, started) and build the mesh (``load``, ``topology``)."""
    from .io.meshfile import read_mesh_source
    from .mesh.mesh import mesh_from_triangles

    timings = timings if timings is not None else {}
    t = time.perf_counter()
    raw = read_mesh_source(job.source, job.data, job.label) if reading is None else reading.result()
    timings["load"] = time.perf_counter() - t
    t = time.perf_counter()
    # a resin job centres the part on the display anyway (unless --keep-xy): a far one is centred in float64 first
    auto = job.resin is not None and not job.resin.spec.keep_xy
    mesh = mesh_from_triangles(raw.triangles, raw.normals, scale=job.placement.scale, fit=job.placement.fit,
                               name=job.model_name, source_format=raw.source_format, solids=raw.solids, device=device,
                               center=True if job.placement.center else None if auto else False)
    timings["topology"] = time.perf_counter() - t
    return mesh


def _too_thin(mesh: Mesh | None, job: Job) -> str:
    """Why a job has no layers, for its error: the model's height against the layer, and a hint at the units when
    the model is under a millimetre across and was not scaled (a file drawn in metres)."""
    if mesh is None or mesh.n_faces == 0:
        return "(the model is thinner than one layer)"
    size = float(np.max(mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)))
    why = f"(the model is {float(mesh.height):.3g} mm tall: no cutting plane lies below its top"
    if size < 1.0 and job.placement.scale is None and job.placement.fit is None:
        why += f"; it is {size:.3g} units across: if they are metres, give --scale 1000"
    return why + ")"


def _archive_name(job: Job) -> str:
    """The name a resin output states (its job name, a PNG stack's file prefix): ``--job-name`` or the model's stem
    (a file name's bytes that are not UTF-8, kept by Python as surrogates, become U+FFFD)."""
    from .io.atomic import utf8

    return utf8(job.resin.options.job_name or Path(job.model_name).stem).decode("utf-8")


def _check_resin_early(job: Job) -> None:
    """Before slicing: a PNG stack's folder holding other files, and settings the format cannot store for layers
    the options make uniform (``.cxdlpv4``'s bottom values; adaptive layers are checked by the writer)."""
    from .raster.outputs import RESIN_FORMATS

    r, p = job.resin, job.params
    if r.format == "png":
        from .raster.pngstack import check_stack_folder

        check_stack_folder(Path(r.path.rstrip("/\\") or "."), _archive_name(job))
    if p.adaptive is None:
        RESIN_FORMATS[r.format].check_layers(r.path, r.settings or r.options.settings(),
                                             np.array([p.first_layer or p.thickness, p.thickness]))


def run_job(job: Job, *, device=None, progress: Callable[[int, int], None] | None = None) -> JobResult:
    """Run ``job``: the device, the mesh, the slices, then every output it names (see the module docstring).

    ``device``: an OpenCL device already made (batch workers keep one); ``progress(k, n)``: called as resin layers
    are written (k of n). Raises :class:`~gpuslice.errors.GpusliceError` subclasses with one-line messages naming
    the file.
    """
    timings: dict[str, float] = {}
    stats: dict[str, Any] = {}
    now = job.date
    if job.resin is not None and now is None:  # a bad SOURCE_DATE_EPOCH fails here, before any work
        from .raster.outputs import source_date

        now = source_date()
    stream = None  # the contour file written while the layers are sliced (an .npz), when its format can be
    try:
        if job.is_saved_result:
            from .slicing.result import SliceResult

            t = time.perf_counter()
            result = SliceResult.load(job.source)
            timings["load"] = time.perf_counter() - t
            mesh, dev = None, None
        else:
            if job.resin is not None:  # (first: the encoder processes start while pyopencl is imported)
                _prestart_encoders(job.resin)
            reading = None
            if job.params.backend == "opencl" and device is None:  # the file read while PyOpenCL is imported
                from .io.meshfile import read_mesh_source
                from .prefetch import beside

                reading = beside(read_mesh_source, job.source, job.data, job.label, name="gpuslice-read")
            try:
                dev = prepare_device(job.params, device, timings)
            except Exception:
                _ = reading and reading.exception()  # (the read ends before the device's error goes up; not Ctrl-C)
                raise
            mesh = load_job_mesh(job, dev, timings, reading)
            if job.resin is not None:  # before slicing: a model larger than the printer is refused now
                from .raster.edges import check_printer_fits  # (not for contours: the raster modules cost 10 ms)

                check_printer_fits(job.model_name, mesh, job.resin.spec, job.resin.options.preset, _bounds(mesh))
                _check_resin_early(job)
            elif job.checks is not None and job.checks.printer is not None:
                from .raster.edges import check_printer_fits

                check_printer_fits(job.model_name, mesh, job.checks.spec, job.checks.printer, _bounds(mesh))
            stream = _open_contour_stream(job)
            result = _slice(job, mesh, dev, timings, stream)
            if job.resin is not None:  # the slicer's scratch memory back before the layers' (peak RSS: issue 18)
                from .device import release_scratch

                release_scratch(dev)
        out = JobResult(mesh, result, dev, timings, stats)
        if result.n_layers == 0:  # (also with no output: a summary or a report of no layers, exit 0, hid it)
            raise ParameterError(f"{job.model_name}: no layers to write {_too_thin(mesh, job)}")
        if job.contours is not None:
            t = time.perf_counter()
            if stream is not None:
                stream.commit(result)
                timings["write"] = stream.seconds  # (its points were written as the slicer nested them)
            else:
                from .formats import export

                export(result, job.contours, job.contours_format)
                timings["write"] = time.perf_counter() - t
    except BaseException:
        if stream is not None:  # (its temporary file goes; nothing is left under the output's name)
            stream.abort()
        raise
    if job.cusp and mesh is not None:  # the schedule's cusp heights, for the report (not in the written file)
        from .bench.quality import cusp_summary

        t = time.perf_counter()
        result.meta.update(cusp_summary(mesh, result, dev))
        timings["cusp"] = time.perf_counter() - t
    if job.checks is not None:
        _run_checks(job, out)
    if job.resin is not None:
        _write_resin(job, out, progress, now)
    if job.view is not None:
        _write_view(job, out)
    return out


def _prestart_encoders(r: ResinOutput) -> None:
    """PNG-layer outputs: start the PNG encoder processes now, so their imports overlap the slicing; only where the
    layers' PNGs are made in them: with the OpenCL rasteriser (runs) they are made on its device (``kernels/png.cl``,
    :mod:`gpuslice.raster.png_runs`) unless ``GPUSLICE_PNG_PROCESSES=1`` asks for the processes."""
    from .raster.coverage import choose_backend
    from .raster.outputs import RESIN_FORMATS

    runs = choose_backend(r.options.raster_backend) == "opencl"  # layers as runs, PNGs straight from them
    if RESIN_FORMATS[r.format].png and r.options.png_level == 1 and runs and _png_processes():
        from .raster.png_procs import prestart

        prestart(r.options.workers or os.cpu_count())


def _open_contour_stream(job: Job):
    """The contour output's stream (:func:`gpuslice.formats.open_stream`: the ``.npz`` written while the layers are
    sliced, its points never held twice), or None: no contour output, a format written at the end, or Windows
    (where a file mapped into memory, as the stream's points are, cannot be renamed)."""
    if job.contours is None or os.name == "nt":
        return None
    from .formats import open_stream

    return open_stream(job.contours, job.contours_format)


def _slice(job: Job, mesh: Mesh, dev, timings: dict[str, float], stream=None) -> SliceResult:
    from .slicing.slicer import slice_mesh

    repairs = None
    if job.mesh_check:  # what the mesh needed: flipped facets, non-manifold edges, ... (mesh/defects.py), counted
        # on a second core while the layers are sliced (its union-find on a queue of its own: mesh/weld.py)
        from .mesh.defects import mesh_repairs
        from .prefetch import beside

        repairs = beside(mesh_repairs, mesh, name="gpuslice-mesh-check")
    try:
        result = slice_mesh(mesh, job.params, points_sink=stream)
    except Exception:
        if repairs is not None:  # (the mesh is not left to a thread still reading it; an interrupt does not wait)
            repairs.exception()
        raise
    meta = result.meta
    for key, value in meta.pop("timings_s", {}).items():
        timings[key] = timings.get(key, 0.0) + value
    if repairs is not None:
        t = time.perf_counter()
        counts = repairs.result()  # (waits; its error is the job's)
        timings["mesh_check"] = time.perf_counter() - t
        meta["repairs"] = {**counts, **meta["repairs"]}
    if job.portable:  # output bytes depend on the model and the options only
        meta.pop("device", None)
        meta.pop("backend", None)
        meta["params"] = {k: v for k, v in meta["params"].items() if k not in ("backend", "device")}
    meta["timings_s"] = timings
    return result


def _bounds(mesh: Mesh | None) -> tuple[float, float, float, float] | None:
    """(xmin, ymin, xmax, ymax) of the mesh, mm: what is centred on a resin display."""
    if mesh is None:
        return None
    b = mesh.bounds
    return float(b[0, 0]), float(b[0, 1]), float(b[1, 0]), float(b[1, 1])


def _write_resin(job: Job, out: JobResult, progress, now) -> None:
    from .raster.coverage import choose_backend, iter_tiles
    from .raster.edges import check_fits
    from .raster.outputs import RESIN_FORMATS, ResinTarget

    r = job.resin
    t = time.perf_counter()
    k = r.options.z_samples
    backend = choose_backend(r.options.raster_backend)
    dev = out.device
    if dev is None and backend == "opencl":  # numpy slicing, OpenCL rasterising
        from .device import get_device

        dev = get_device(job.params.device)
    bounds = _bounds(out.mesh)
    if out.result.n_layers == 0:
        raise ParameterError(f"{job.model_name}: no layers to write {_too_thin(out.mesh, job)}")
    check_fits(out.result, r.spec, bounds, name=job.model_name)
    from .raster.settings import MAX_PRINT_TIME_S, print_time_s

    settings = r.settings if r.settings is not None else r.options.settings()
    t_print = print_time_s(settings, out.result.n_layers)
    if t_print > MAX_PRINT_TIME_S:
        raise ParameterError(f"{r.path}: {out.result.n_layers} layers at these settings would print for "
                             f"{t_print / 3.156e7:.0f} years, more than an archive's print time holds")
    if k > 1 and backend != "opencl":
        raise ParameterError(f"z_samples needs the OpenCL rasteriser, not {backend}", param="z_samples")
    if backend == "opencl":  # runs all the way to the PNGs (raster/layers.py: tiles only for another --png-level)
        from .raster.layers import iter_run_layers

        if k > 1:  # anti-aliasing in Z: k sub-planes per layer, sliced a chunk of layers at a time
            from .raster.z_sampled import z_sampled_layers

            layers = z_sampled_layers(out.mesh, out.result, job.params, r.spec, dev, bounds, k, sliced_on=out.device,
                                      timings=out.timings, stats=out.stats)
        else:
            layers = iter_run_layers(out.result, r.spec, device=dev, bounds=bounds, clip=True)  # (checked above)
    else:
        layers = iter_tiles(out.result, r.spec, backend=backend, device=dev, bounds=bounds,
                            supersample=r.options.supersample, clip=True)
    name = _archive_name(job)
    n = out.result.n_layers
    tick = (lambda k: progress(k, n)) if progress is not None else None
    png_by_numpy = RESIN_FORMATS[r.format].png and _png_processes()  # (GPUSLICE_PNG_PROCESSES=1)
    target = ResinTarget(Path(r.path.rstrip("/\\") or "."), r.spec, r.options, out.result, name, now,
                         r.options.workers, tick, settings, bounds=bounds,
                         device=dev if backend == "opencl" and not png_by_numpy else None, format=r.format)
    try:
        out.stats.update(RESIN_FORMATS[r.format].load()(layers, target))
    finally:  # a writer that failed: its layers' producer threads stop now
        close = getattr(layers, "close", None)
        if close is not None:
            close()
    out.stats["raster_backend"] = backend
    if backend == "gl":  # say which renderer drew it: Mesa's software one where no GPU is (50-135x slower)
        from .raster.gl import gl_info

        info = gl_info() or {}
        if info.get("software"):
            out.stats["gl_renderer"] = f"software: {info.get('renderer', '').split(' (')[0] or 'Mesa'}"
    t_sub = out.timings.get("z_samples", 0.0)
    out.timings["raster"] = time.perf_counter() - t - t_sub  # the z sub-slices have their own line


def _png_processes() -> bool:
    """``GPUSLICE_PNG_PROCESSES=1``: PNG layers from runs made by numpy in processes (the numpy twin of the PNG
    kernel, as before it), not on the device; for comparisons and for devices where the kernel is slow."""
    return os.environ.get("GPUSLICE_PNG_PROCESSES", "").strip().lower() in ("1", "yes", "true", "on")


def _run_checks(job: Job, out: JobResult) -> None:
    """The pre-print checks (stage ``checks``): islands, unsupported area, traps and suction cups, peel, time and
    resin (:mod:`gpuslice.checks`), on the display's pixels placed as the archive places them."""
    from .checks import run_checks

    c = job.checks
    t = time.perf_counter()
    backend = "numpy" if job.params.backend == "numpy" else "auto"
    report = run_checks(out.result, c.spec, c.settings, options=c.options, bounds=_bounds(out.mesh), backend=backend,
                        device=out.device, name=job.model_name)
    fmt = job.resin.format if job.resin is not None else getattr(c.printer, "native_format", None)
    from .raster.outputs import RESIN_FORMATS

    if fmt in RESIN_FORMATS and RESIN_FORMATS[fmt].print_time is not None:  # the archive's own (the SL1s tilt)
        from .raster.settings import PrintSettings

        report.print_time_s = RESIN_FORMATS[fmt].print_time_s(c.settings or PrintSettings(), out.result.n_layers)
    out.stats["checks"] = report
    out.timings["checks"] = time.perf_counter() - t
    if c.path is not None:
        from .io.report import write_report

        write_report(report.to_json(), c.path)
    if c.on_report is not None:
        c.on_report(report)


def _write_view(job: Job, out: JobResult) -> None:
    from .view.page import raster_masks, write_view

    v = job.view
    t = time.perf_counter()
    masks = None
    if v.masks is not None:
        backend = "numpy" if job.params.backend == "numpy" else "auto"
        masks = raster_masks(out.result, v.masks, every=v.mask_every, bounds=_bounds(out.mesh), backend=backend,
                             device=out.device, name=job.model_name)
        out.timings["masks"] = time.perf_counter() - t
        out.stats["masks"] = masks
    src = Path(job.source)
    if v.title is not None:
        title = v.title
    elif job.is_saved_result:
        sliced = out.result.meta.get("file")
        title = f"{Path(str(sliced)).name} ({src.name})" if sliced else src.name
    else:
        title = src.name
    t = time.perf_counter()
    out.stats["view_bytes"] = write_view(out.result, v.path, title=title, masks=masks,
                                         checks=out.stats.get("checks"))
    out.timings["view"] = time.perf_counter() - t

