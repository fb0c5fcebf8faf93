"""Batch slicing: many models, the same options, on local worker processes or an existing Dask cluster.

The engine behind ``gpuslice batch`` (the command line is ``cli_batch.py``). Four pieces, in the order a batch
uses them:

1. **Discovery** (:func:`discover`): folders (recursive, filtered by a glob), list files (``.txt``/``.list``: one
   path a line, ``#`` comments, relative to the list file) and single paths become :class:`Model` s. Outputs mirror
   the input tree under the output folder: a model's relative path is taken from the deepest folder holding every
   input (a single folder argument is that folder), and its suffix is replaced by the output's (``.npz`` by default).
2. **The task** (:func:`run_model`): read, weld, slice and write one model; never raises, returns a JSON-able
   record (status ``done`` or ``failed`` with a one-line ``error``, facets, layers, per-stage timings in s). Outputs
   are written through :func:`gpuslice.export.atomic_path`, and their bytes depend only on the model and the
   options (no timings, device names or paths of the machine in the file), so a task can be re-run anywhere, any
   number of times: tasks are idempotent.
3. **Execution** (:class:`BatchRunner`): in this process (``workers=0``), on local worker processes (one OpenCL
   context and one kernel build per worker; a failed model is retried once on another worker; a worker that dies
   is replaced and its unfinished models re-run) or on a Dask ``distributed.Client`` (the scheduler re-runs a lost
   worker's tasks itself; failed models are retried once on another worker).
4. **The report** (:meth:`BatchRunner.report`): per model status, facets, layers, timings and error, plus totals.

Skipping: a model whose output exists is skipped (``force`` redoes it); outputs are only ever renamed into place
complete, so existing means complete. The output folder holds a small manifest (``.gpuslice-batch.json``) with the
options that shape the outputs; a batch with other options into the same folder is refused unless ``force`` is
given, so a re-run never skips a model whose output was made with different options.
"""

from __future__ import annotations

import collections
import contextlib
import hashlib
import json
import multiprocessing
import os
import re
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..errors import GpusliceError

__all__ = [
    "BatchError",
    "BatchOptions",
    "BatchRunner",
    "check_raster",
    "connect",
    "format_summary",
    "Model",
    "MESH_SUFFIXES",
    "MANIFEST_NAME",
    "default_workers",
    "discover",
    "pocl_thread_env",
    "run_batch",
    "run_model",
]

#: suffixes a folder search picks up when no glob is given (any case)
MESH_SUFFIXES = (".stl", ".3mf", ".obj", ".ply", ".off")
#: list files: one model path a line
LIST_SUFFIXES = (".txt", ".list", ".lst")
FORMATS = ("npz", "svg", "cli")
RASTER_KINDS = ("sl1", "png")
#: the manifest in the output folder: the options that shape the outputs
MANIFEST_NAME = ".gpuslice-batch.json"
#: tasks submitted ahead per local worker (hides the round trip between two models)
PREFETCH = 2
#: a model whose worker died this many times is reported failed instead of re-run again
MAX_LOST = 2


class BatchError(GpusliceError):
    """A batch cannot start: no models found, clashing outputs, options differing from the output folder's."""


# ---------------------------------------------------------------------------------------------------------
# options and models
# ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BatchOptions:
    """The options every model of a batch is sliced with (lengths in mm), picklable for the workers.

    The slicing fields mean what they mean in :class:`~gpuslice.slicer.SliceParams`; ``scale``/``fit`` as in
    :func:`~gpuslice.mesh.mesh_from_triangles`. ``fmt`` is the output format (``npz``, ``svg`` or ``cli``);
    ``raster`` (``sl1`` or ``png``) rasterises each model instead, with ``raster_options`` (name, value) pairs
    passed to the rasteriser. ``schedule``: further ``SliceParams`` fields as (name, value) pairs, e.g. an adaptive
    schedule's (``adaptive``, ``max_cusp``, ...); empty for uniform layers.
    """

    thickness: float = 0.1
    first_layer: float | None = None
    z_mode: str = "mid"
    fill_rule: str = "nonzero"
    max_gap: float = 2.0
    backend: str = "opencl"
    device: str | None = None
    scale: float | None = None
    fit: float | None = None
    fmt: str = "npz"
    raster: str | None = None
    raster_options: tuple[tuple[str, Any], ...] = ()
    schedule: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        from ..errors import ParameterError

        if self.fmt not in FORMATS:
            raise ParameterError(f"unknown output format '{self.fmt}' (use {', '.join(FORMATS)})")
        if self.raster is not None and self.raster not in RASTER_KINDS:
            raise ParameterError(f"unknown raster output '{self.raster}' (use {', '.join(RASTER_KINDS)})")
        if not (self.thickness > 0):
            raise ParameterError(f"-t/--thickness must be > 0 mm, got {self.thickness}")
        if self.scale is not None and self.fit is not None:
            raise ParameterError("give --scale or --fit, not both")
        self.params()  # validates the slicing options

    def params(self):
        """The :class:`~gpuslice.slicer.SliceParams` of these options."""
        from ..slicing.slicer import SliceParams

        return SliceParams(thickness=self.thickness, first_layer=self.first_layer, z_mode=self.z_mode,
                           fill_rule=self.fill_rule, max_gap=self.max_gap, backend=self.backend, device=self.device,
                           **dict(self.schedule))

    @property
    def suffix(self) -> str:
        """The suffix of each model's output (``""`` for a PNG-stack folder)."""
        if self.raster == "sl1":
            return ".sl1"
        if self.raster == "png":
            return ""
        return "." + self.fmt

    def shaping(self) -> dict[str, Any]:
        """The options that shape output bytes (not the backend or device: both give bit-identical results)."""
        d = asdict(self)
        for k in ("backend", "device"):
            d.pop(k)
        d["raster_options"] = [list(kv) for kv in self.raster_options]
        d["schedule"] = {k: list(v) if isinstance(v, tuple) else v for k, v in self.schedule}
        return d

    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.shaping(), sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Model:
    """One model of a batch: ``src`` the file as found (named so in messages), ``rel`` its path relative to the
    batch's base folder (POSIX), ``out`` its output path relative to the output folder (POSIX), ``path`` the absolute
    path workers read (``src`` when not given)."""

    src: str
    rel: str
    out: str
    path: str = ""

    @property
    def location(self) -> str:
        return self.path or self.src


def _glob_regex(pattern: str) -> re.Pattern:
    """A case-insensitive regex for a glob over relative POSIX paths: ``**/`` any folders (or none), ``*`` and
    ``?`` within one name, ``[...]`` a character class; a pattern without ``/`` matches the file name only."""
    if "/" not in pattern:
        pattern = "**/" + pattern
    out, i = [], 0
    while i < len(pattern):
        c = pattern[i]
        if pattern.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
            continue
        if pattern.startswith("**", i):
            out.append(".*")
            i += 2
            continue
        if c == "*":
            out.append("[^/]*")
        elif c == "?":
            out.append("[^/]")
        elif c == "[":
            j = pattern.find("]", i + 1)
            if j < 0:
                out.append(re.escape(c))
            else:
                body = pattern[i + 1 : j]
                out.append("[" + ("^" + body[1:] if body.startswith("!") else body) + "]")
                i = j
        else:
            out.append(re.escape(c))
        i += 1
    return re.compile("".join(out) + r"\Z", re.IGNORECASE)


def _walk(folder: Path, pattern: str | None) -> list[Path]:
    rx = _glob_regex(pattern) if pattern else None
    found = []
    for root, dirs, files in os.walk(folder, followlinks=True):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.startswith("."):
                continue
            p = Path(root) / name
            rel = p.relative_to(folder).as_posix()
            if (rx.match(rel) if rx else name.lower().endswith(MESH_SUFFIXES)):
                found.append(p)
    return found


def _read_list(path: Path) -> list[Path]:
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise BatchError(f"{path}: cannot read the list file ({exc.strerror or exc})") from None
    out = []
    for n, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        p = Path(line)
        p = p if p.is_absolute() else path.parent / p
        if not p.is_file():
            raise BatchError(f"{path}:{n}: {line}: no such model file")
        out.append(p)
    return out


def discover(inputs: Sequence[str | os.PathLike], glob: str | None = None, suffix: str = ".npz") -> list[Model]:
    """The models named by ``inputs`` (folders searched recursively, list files, model files), in sorted order.

    Parameters
    ----------
    inputs : folders, list files (``.txt``, ``.list``, ``.lst``) or model files.
    glob : in folders, keep the files whose path relative to the folder matches this pattern (case-insensitive;
        ``**/`` spans folders; a pattern without ``/`` matches names at any depth). Default: every file ending in
        one of :data:`MESH_SUFFIXES`. Hidden files and folders (names starting with ``.``) are skipped.
    suffix : the output suffix that replaces each model's suffix (``""``: none, e.g. a PNG-stack folder).

    Raises
    ------
    BatchError
        An input does not exist, nothing was found, or two models would write the same output.
    """
    if not inputs:
        raise BatchError("no inputs given")
    files: list[Path] = []
    roots: list[Path] = []
    for item in inputs:
        p = Path(os.fspath(item))
        if p.is_dir():
            roots.append(p.resolve())
            files += _walk(p, glob)
        elif p.is_file() and p.suffix.lower() in LIST_SUFFIXES:
            listed = _read_list(p)
            files += listed
            roots += [q.resolve().parent for q in listed]
        elif p.is_file():
            files.append(p)
            roots.append(p.resolve().parent)
        else:
            raise BatchError(f"{p}: no such file or folder")
    if not files:
        what = f"matching '{glob}'" if glob else f"ending in {', '.join(MESH_SUFFIXES)}"
        raise BatchError(f"{', '.join(map(str, inputs))}: no model files {what}")
    base = Path(os.path.commonpath([str(r) for r in roots]))
    models: dict[str, Model] = {}
    outputs: dict[str, str] = {}
    for f in files:
        resolved = f.resolve()
        rel = resolved.relative_to(base).as_posix() if resolved.is_relative_to(base) else resolved.name
        if rel in models:
            continue  # the same file named twice
        stem = rel[: -len(Path(rel).suffix)] if Path(rel).suffix else rel
        out = stem + suffix
        if out.lower() in outputs:
            raise BatchError(f"{f}: its output {out} clashes with that of {outputs[out.lower()]}")
        outputs[out.lower()] = str(f)
        models[rel] = Model(src=str(f), rel=rel, out=out, path=str(resolved))
    return [models[k] for k in sorted(models)]


# ---------------------------------------------------------------------------------------------------------
# the task: one model
# ---------------------------------------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def pocl_thread_env(threads: int) -> dict[str, str]:
    """Environment that limits PoCL's CPU driver to ``threads`` threads in a process (PoCL 3 reads
    ``POCL_MAX_PTHREAD_COUNT``; PoCL 4+ ``POCL_CPU_MAX_CU_COUNT``; both are set)."""
    n = str(max(1, int(threads)))
    return {"POCL_MAX_PTHREAD_COUNT": n, "POCL_CPU_MAX_CU_COUNT": n}


def _worker_device(spec: str | None):
    """The OpenCL device of this process with every kernel built, made once per process; (device, seconds)."""
    key = ("device", spec)
    if key not in _WORKER:
        from ..device import get_device

        t = time.perf_counter()
        dev = get_device(spec)
        dev.program("crossings.cl")  # builds every kernels/*.cl (one program)
        _WORKER[key] = dev
        _WORKER["init_s"] = _WORKER.get("init_s", 0.0) + time.perf_counter() - t
    return _WORKER[key]


def init_worker(env: dict[str, str] | None = None, device: str | None = None, backend: str = "opencl") -> None:
    """Initializer of a local worker process: PoCL threads, signals, the OpenCL device and kernels (built once).

    Ctrl-C goes to the whole process group; the workers ignore it (the driver stops them), and SIGTERM unwinds
    the worker (``SystemExit``) so a half-written temporary output is removed.
    """
    os.environ.update(env or {})
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    t = time.perf_counter()
    if backend == "opencl":
        with contextlib.suppress(GpusliceError):  # reported by the first task instead
            _worker_device(device)
    _WORKER["started"] = time.perf_counter() - t


def _raster_modules():
    """``gpuslice.raster`` and ``gpuslice.sl1`` (the one place the batch touches the raster stage)."""
    try:
        from ..raster import coverage as raster
        from ..raster import sl1
    except ImportError as exc:
        raise BatchError(f"--raster: gpuslice.raster/gpuslice.sl1 are not available here ({exc})") from None
    return raster, sl1


def check_raster(kind: str, options: Sequence[tuple[str, Any]] = ()) -> None:
    """Raise now (before any model is sliced) if ``--raster kind`` with these options cannot work here."""
    _raster_modules()
    _raster_spec(dict(options))


_SPEC_KEYS = ("resolution", "pixel", "pixel_y", "mirror_x", "mirror_y", "portrait", "keep_xy", "gamma")
_OTHER_KEYS = ("printer", "raster_backend", "supersample", "png_level", "exposure", "exposure_first")


def _raster_spec(options: dict[str, Any]):
    from ..errors import ParameterError

    raster, _ = _raster_modules()
    unknown = sorted(set(options) - set(_SPEC_KEYS) - set(_OTHER_KEYS))
    if unknown:
        raise ParameterError(f"unknown --raster-opt {', '.join(unknown)} (use {', '.join(_SPEC_KEYS + _OTHER_KEYS)})")
    kw: dict[str, Any] = {}
    if "printer" in options:
        if options["printer"] not in raster.PRINTERS:
            raise ParameterError(f"unknown printer '{options['printer']}' (use {', '.join(sorted(raster.PRINTERS))})")
        kw.update(raster.PRINTERS[options["printer"]])
    kw.update({k: v for k, v in options.items() if k in _SPEC_KEYS})
    if isinstance(kw.get("resolution"), str):
        try:
            kw["resolution"] = tuple(int(v) for v in kw["resolution"].lower().split("x"))
        except ValueError:
            raise ParameterError(f"resolution: expected NXxNY pixels, got '{kw['resolution']}'") from None
    return raster.RasterSpec(**kw)


def rasterise(result, mesh, path: Path, kind: str, options: dict[str, Any], device=None) -> None:
    """Rasterise ``result`` (sliced from ``mesh``) into an SL1 archive (``kind="sl1"``) or a PNG-stack folder
    (``"png"``) at ``path``, as ``gpuslice raster`` does; ``options`` are its option names (``printer``,
    ``resolution``, ``pixel``, ``gamma``, ``raster_backend``, ``png_level``, ``exposure``, ...). The SL1 date is
    ``SOURCE_DATE_EPOCH`` when set (reproducible archives), else now."""
    import datetime as dt

    raster, sl1 = _raster_modules()
    spec = _raster_spec(options)
    b = mesh.bounds
    bounds = (b[0, 0], b[0, 1], b[1, 0], b[1, 1])
    raster.check_fits(result, spec, bounds, name=mesh.name)
    backend = raster.choose_backend(options.get("raster_backend", "auto"))
    extra = {"supersample": int(options["supersample"])} if "supersample" in options else {}  # else raster's own
    tiles = raster.iter_tiles(result, spec, backend=backend, device=device, bounds=bounds, **extra)
    threads = int(os.environ.get("POCL_MAX_PTHREAD_COUNT", "0")) or None  # this worker's share of the cores
    level = int(options.get("png_level", 1))
    name = Path(mesh.name).stem
    if kind == "png":
        sl1.write_png_stack(tiles, spec, path, prefix=name, level=level, workers=threads)
        return
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    now = dt.datetime.fromtimestamp(int(epoch), dt.timezone.utc).replace(tzinfo=None) if epoch else None
    info = sl1.info_from(result, name, {"exposure_time": float(options.get("exposure", 10.0)),
                                        "initial_exposure_time": float(options.get("exposure_first", 15.0))})
    sl1.write_sl1(tiles, spec, path, info, result.n_layers, level=level, workers=threads, now=now)


def connect(address: str):
    """A ``distributed.Client`` for the Dask scheduler at ``address``; one-line :class:`BatchError` otherwise."""
    try:
        from distributed import Client
    except ImportError:
        raise BatchError("--scheduler needs Dask: pip install 'gpuslice[batch]'") from None
    try:
        return Client(address, timeout="10s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise BatchError(f"{address}: cannot reach the Dask scheduler ({_one_line(exc)})") from None


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) if str(exc).strip() else ""
    if isinstance(exc, GpusliceError):
        return text or type(exc).__name__
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _read_raw(model: Model, data: bytes | None):
    from ..io.meshfile import read_mesh_file, read_stl_bytes

    if data is None:
        try:
            return read_mesh_file(model.location)
        except GpusliceError as exc:  # name the file as the user gave it
            raise type(exc)(str(exc).replace(model.location, model.src)) from None
    suffix = Path(model.src).suffix.lower()
    if suffix in (".obj", ".ply", ".off", ".3mf"):
        with tempfile.TemporaryDirectory(prefix="gpuslice-batch-") as tmp:
            p = Path(tmp) / ("model" + suffix)
            p.write_bytes(data)
            try:
                return read_mesh_file(p)
            except GpusliceError as exc:
                raise type(exc)(str(exc).replace(str(p), model.src)) from None
    return read_stl_bytes(data, model.src)


def _write_output(result, mesh, target: Path, opts: BatchOptions, device) -> None:
    from ..formats import export

    if opts.raster is not None:
        rasterise(result, mesh, target, opts.raster, dict(opts.raster_options), device)
    elif opts.fmt == "npz":
        result.save(target)  # deterministic: fixed zip dates (zipfile's default), meta without timings
    else:
        export(result, target)


def _mesh_repairs(mesh) -> dict[str, int]:
    try:
        from ..mesh.defects import mesh_repairs
    except ImportError:  # pragma: no cover - older checkouts
        return {}
    return mesh_repairs(mesh)


def _collect(path: Path) -> bytes | dict[str, bytes]:
    if path.is_dir():
        return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}
    return path.read_bytes()


def run_model(model: Model, opts: BatchOptions, out_root: str | None, data: bytes | None = None) -> dict[str, Any]:
    """Slice one model and write its output; never raises.

    Parameters
    ----------
    model : the model (``src`` is read unless ``data`` is given).
    opts : the batch options.
    out_root : the output folder, reachable from this process (a shared file system); ``None``: the output is
        returned as bytes in the record's ``"payload"`` (a dict of relative path → bytes for a folder output).
    data : the model file's bytes, when the inputs travel as bytes instead of through a shared file system.

    Returns
    -------
    dict
        ``model``, ``output``, ``status`` (``"done"`` or ``"failed"``), ``error`` (one line naming the file, or
        None), ``facets``, ``layers``, ``loops``, ``points``, ``open_chains``, ``device``, ``pid``, ``host``,
        ``timings_s`` (``load``, ``topology``, ``device``, ``schedule``, ``crossings``, ``chaining``, ``nesting``,
        ``write``, ``total``; s), ``worker_init_s`` (the worker's one-off device and kernel set-up, on the first
        task a worker runs, else 0).
    """
    t0 = time.perf_counter()
    rec: dict[str, Any] = {"model": model.rel, "output": model.out, "status": "failed", "error": None,
                           "pid": os.getpid(), "host": socket.gethostname()}
    timings: dict[str, float] = {}
    try:
        from ..mesh.mesh import mesh_from_triangles
        from ..slicing.slicer import slice_mesh

        dev = None
        if opts.backend == "opencl":
            t = time.perf_counter()
            dev = _worker_device(opts.device)
            timings["device"] = time.perf_counter() - t
        t = time.perf_counter()
        raw = _read_raw(model, data)
        timings["load"] = time.perf_counter() - t
        t = time.perf_counter()
        mesh = mesh_from_triangles(raw.triangles, raw.normals, scale=opts.scale, fit=opts.fit, name=model.rel,
                                   source_format=raw.source_format, solids=raw.solids, device=dev)
        timings["topology"] = time.perf_counter() - t
        result = slice_mesh(mesh, opts.params())
        meta = result.meta
        t = time.perf_counter()
        meta["repairs"] = {**_mesh_repairs(mesh), **meta["repairs"]}  # as `gpuslice slice` reports them
        timings["mesh_check"] = time.perf_counter() - t
        for k, v in meta.pop("timings_s", {}).items():
            if k != "device":
                timings[k] = v
        rec.update(facets=meta["facets"], layers=meta["layers"], loops=meta["loops"], points=meta["points"],
                   open_chains=meta["open_chains"], device=meta.pop("device"))
        # output bytes depend on the model and the options only: no timings, device name or machine paths
        meta["params"] = {k: v for k, v in meta["params"].items() if k not in ("backend", "device")}
        meta.pop("backend", None)
        t = time.perf_counter()
        if out_root is not None:
            target = Path(out_root) / model.out
            target.parent.mkdir(parents=True, exist_ok=True)
            _write_output(result, mesh, target, opts, dev)
        else:
            with tempfile.TemporaryDirectory(prefix="gpuslice-batch-") as tmp:
                target = Path(tmp) / (Path(model.out).name or "out")
                _write_output(result, mesh, target, opts, dev)
                rec["payload"] = _collect(target)
        timings["write"] = time.perf_counter() - t
        rec["status"] = "done"
    except Exception as exc:  # a failing model must not stop the batch: one line in its record
        msg = _one_line(exc)
        rec["error"] = msg if model.src in msg or model.rel in msg else f"{model.src}: {msg}"
    timings["total"] = time.perf_counter() - t0
    rec["timings_s"] = timings
    if "distributed" in sys.modules:  # on a Dask worker: its address, so a retry can avoid it
        with contextlib.suppress(Exception):
            from distributed import get_worker

            rec["worker"] = get_worker().address
    rec["worker_init_s"] = _WORKER.pop("init_s", 0.0)
    return rec


# ---------------------------------------------------------------------------------------------------------
# execution
# ---------------------------------------------------------------------------------------------------------
def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def default_workers(n_models: int, device: str | None = None, backend: str = "opencl") -> tuple[int, int]:
    """The default (worker processes, PoCL threads per worker) for ``n_models`` models on this machine.

    On a CPU device (PoCL) one worker per core, each with ``cores // workers`` PoCL threads: the cores are
    shared out instead of every process starting one thread per core (oversubscription). Fewer models than cores
    get fewer workers with more threads each. On a GPU, ``min(cores, 4)`` workers share the GPU (the host-side
    stages of one model overlap the kernels of another); PoCL's thread count does not matter there.
    """
    cores = _cores()
    n = max(1, min(cores, n_models))
    if backend == "opencl":
        with contextlib.suppress(Exception):
            from ..device import resolve

            if "GPU" in resolve(device)["type"]:
                n = max(1, min(4, cores, n_models))
    return n, max(1, cores // n)


_PRELOAD = ["gpuslice.batch.runner", "gpuslice.slicing.slicer", "gpuslice.io.meshfile", "gpuslice.formats",
            "gpuslice.io.atomic", "gpuslice.mesh.defects", "shapely"]


def _mp_context():
    methods = multiprocessing.get_all_start_methods()
    if "forkserver" in methods:  # pyopencl contexts do not survive fork; forkserver forks a clean process
        ctx = multiprocessing.get_context("forkserver")
        # imported once in the forkserver, inherited by every worker (no OpenCL there: contexts come after the fork)
        ctx.set_forkserver_preload(_PRELOAD)
        return ctx
    return multiprocessing.get_context("spawn")


@dataclass
class _Task:
    index: int
    attempt: int = 1
    lost: int = 0
    avoid: str | None = None  # the worker a failed first attempt ran on
    errors: list[str] = field(default_factory=list)
    workers: list[str] = field(default_factory=list)  # the workers of earlier attempts


@dataclass
class _Slot:
    """One local worker: a single-process executor, so a retry can be sent to another worker and a dead worker
    breaks only its own executor."""

    name: str
    executor: ProcessPoolExecutor
    inflight: dict[Future, _Task] = field(default_factory=dict)


class BatchRunner:
    """Run one batch: ``BatchRunner(models, opts, out_dir).run(workers=…)`` or ``.run(client=…)``.

    ``progress`` is called with each finished model's record (in the driver process). After ``run`` (or after it
    was interrupted), :meth:`report` gives the batch report.
    """

    def __init__(self, models: Sequence[Model], opts: BatchOptions, out_dir: str | os.PathLike, *,
                 force: bool = False, progress: Callable[[dict], None] | None = None,
                 inputs: Sequence[str] = ()) -> None:
        self.models = list(models)
        self.opts = opts
        self.out_dir = Path(os.fspath(out_dir))
        self.force = force
        self.progress = progress
        self.inputs = [str(i) for i in inputs]
        self.records: dict[int, dict] = {}
        self.info: dict[str, Any] = {"workers_lost": 0, "retries": 0, "worker_init_s": []}
        self.wall_s = 0.0
        self.interrupted = False

    # ---- the output folder --------------------------------------------------------------------------------
    def _prepare_output(self) -> list[_Task]:
        out = self.out_dir
        if out.exists() and not out.is_dir():
            raise BatchError(f"{out}: exists and is not a folder")
        out.mkdir(parents=True, exist_ok=True)
        manifest = out / MANIFEST_NAME
        want = {"fingerprint": self.opts.fingerprint(), "options": self.opts.shaping()}
        if manifest.exists():
            try:
                have = json.loads(manifest.read_text())
            except (OSError, ValueError):
                have = {}
            if have.get("fingerprint") != want["fingerprint"] and not self.force:
                old = have.get("options", {})
                diff = ", ".join(f"{k} {old.get(k)!r} -> {v!r}" for k, v in want["options"].items()
                                 if old.get(k) != v) or "unreadable manifest"
                raise BatchError(f"{out}: holds outputs made with other options ({diff}); use --force to redo "
                                 "them, or another output folder")
        from ..io.atomic import atomic_write_text

        atomic_write_text(manifest, json.dumps(want, indent=1, sort_keys=True) + "\n")
        tasks = []
        for i, m in enumerate(self.models):
            target = out / m.out
            if not self.force and target.exists():
                self._finish(i, {"model": m.rel, "output": m.out, "status": "skipped", "error": None}, None)
            else:
                tasks.append(_Task(i))
        return tasks

    def _cleanup_temporaries(self) -> None:
        """Remove temporaries left by killed workers beside this batch's outputs (``.NAME.tmp-…``): one listing
        per output folder, so 10,000 models in one folder cost one scan, not 10,000."""
        from ..io.atomic import remove_path

        by_dir: dict[Path, set[str]] = collections.defaultdict(set)
        for m in self.models:
            target = self.out_dir / m.out
            by_dir[target.parent].add(target.name)
        for folder, names in by_dir.items():
            with contextlib.suppress(OSError):
                for entry in os.scandir(folder):
                    name = entry.name
                    k = name.find(".tmp-")
                    if name.startswith(".") and k > 1 and name[1:k] in names:
                        remove_path(Path(entry.path))

    def _finish(self, index: int, rec: dict, task: _Task | None) -> None:
        m = self.models[index]
        rec["input"] = m.src
        if task is not None:
            rec["attempts"] = task.attempt
            rec["workers"] = [*task.workers, rec.get("worker")]
            if task.errors and rec["status"] == "done":
                rec["earlier_errors"] = list(task.errors)
        self.records[index] = rec
        if self.progress is not None:
            self.progress(rec)

    def _outcome(self, task: _Task, rec: dict, worker: str, n_workers: int) -> _Task | None:
        """Record a task's result; returns the retry task for a first failure."""
        rec["worker"] = worker
        if rec.get("worker_init_s"):
            self.info["worker_init_s"].append(rec["worker_init_s"])
        if rec["status"] == "failed" and task.attempt == 1:
            self.info["retries"] += 1
            return _Task(task.index, 2, task.lost, worker if n_workers > 1 else None, [rec["error"]], [worker])
        self._finish(task.index, rec, task)
        return None

    def _lost(self, task: _Task, worker: str) -> _Task | None:
        task.lost += 1
        if task.lost >= MAX_LOST:
            m = self.models[task.index]
            self._finish(task.index, {"model": m.rel, "output": m.out, "status": "failed", "worker": worker,
                                      "error": f"{m.src}: its worker process died {task.lost} times while "
                                               "slicing it"}, task)
            return None
        return task

    # ---- in this process ---------------------------------------------------------------------------------
    def _run_serial(self, tasks: list[_Task]) -> None:
        queue = collections.deque(tasks)
        while queue:
            task = queue.popleft()
            rec = run_model(self.models[task.index], self.opts, str(self.out_dir))
            retry = self._outcome(task, rec, "main", 1)
            if retry is not None:
                queue.appendleft(retry)

    # ---- local worker processes --------------------------------------------------------------------------
    def _run_local(self, tasks: list[_Task], workers: int, threads: int) -> None:
        ctx = _mp_context()
        # the whole environment: a forkserver started earlier carries the environment of that moment
        env = {**os.environ, **pocl_thread_env(threads)}
        init_args = (env, self.opts.device, self.opts.backend)

        def new_executor():
            return ProcessPoolExecutor(1, mp_context=ctx, initializer=init_worker, initargs=init_args)

        slots = [_Slot(f"local-{k}", new_executor()) for k in range(workers)]
        self._slots = slots
        queue: collections.deque[_Task] = collections.deque(tasks)
        out_root = str(self.out_dir)

        def take(slot: _Slot) -> _Task | None:
            for k, t in enumerate(queue):
                if t.avoid != slot.name:
                    del queue[k]
                    return t
            return None

        try:
            while queue or any(s.inflight for s in slots):
                for depth in range(1, PREFETCH + 1):  # round-robin: every worker gets a task before any a second
                    for slot in slots:
                        if len(slot.inflight) >= depth or not queue:
                            continue
                        task = take(slot)
                        if task is None:
                            continue
                        try:
                            fut = slot.executor.submit(run_model, self.models[task.index], self.opts, out_root)
                        except BrokenProcessPool:
                            queue.appendleft(task)
                            continue
                        slot.inflight[fut] = task
                # a retry that avoids the one idle worker while the others are gone would wait forever
                if queue and not any(s.inflight for s in slots):
                    for t in queue:
                        t.avoid = None
                    continue
                every = [f for s in slots for f in s.inflight]
                done, _ = wait(every, timeout=0.5, return_when=FIRST_COMPLETED)
                for slot in slots:
                    finished = [f for f in slot.inflight if f in done]
                    broken = False
                    for fut in finished:
                        task = slot.inflight.pop(fut)
                        try:
                            rec = fut.result()
                        except BrokenProcessPool:
                            broken = True
                            again = self._lost(task, slot.name)
                            if again is not None:
                                queue.appendleft(again)
                            continue
                        except Exception as exc:  # pickling trouble and the like: the model's failure
                            m = self.models[task.index]
                            rec = {"model": m.rel, "output": m.out, "status": "failed",
                                   "error": f"{m.src}: {_one_line(exc)}"}
                        retry = self._outcome(task, rec, slot.name, workers)
                        if retry is not None:
                            queue.appendleft(retry)
                    if broken:
                        # the worker died: the rest of its tasks are lost too; replace it and re-run them
                        self.info["workers_lost"] += 1
                        for task in list(slot.inflight.values()):
                            again = self._lost(task, slot.name)
                            if again is not None:
                                queue.appendleft(again)
                        slot.inflight.clear()
                        slot.executor.shutdown(wait=False, cancel_futures=True)
                        slot.executor = new_executor()
        except BaseException:
            _stop_slots(slots)
            raise
        for slot in slots:
            slot.executor.shutdown(wait=True)

    def worker_pids(self) -> list[int]:
        """PIDs of the local worker processes now running (for tests and monitoring)."""
        pids = []
        for slot in getattr(self, "_slots", []):
            procs = getattr(slot.executor, "_processes", None) or {}
            pids += [p.pid for p in procs.values() if p.is_alive()]
        return pids

    # ---- Dask --------------------------------------------------------------------------------------------
    def _run_dask(self, tasks: list[_Task], client, transfer: str) -> None:
        from distributed import as_completed

        client.register_plugin(_device_plugin(self.opts.device, self.opts.backend), name="gpuslice-device")
        n_workers = max(1, len(client.scheduler_info(n_workers=-1).get("workers", {})))
        window = 4 * n_workers  # bounded: 10,000 models never sit in the client's memory at once
        queue = collections.deque(tasks)
        by_future: dict[Any, _Task] = {}
        out_root = str(self.out_dir.resolve()) if transfer == "shared" else None
        ac = as_completed()

        def submit(task: _Task) -> None:
            m = self.models[task.index]
            data = Path(m.location).read_bytes() if transfer == "bytes" else None
            kwargs: dict[str, Any] = {}
            if task.avoid is not None:
                others = [w for w in client.scheduler_info(n_workers=-1)["workers"] if w != task.avoid]
                if others:
                    kwargs = {"workers": others, "allow_other_workers": True}
            fut = client.submit(run_model, m, self.opts, out_root, data, pure=False, retries=0,
                                key=f"gpuslice-{task.index}-{task.attempt}-{task.lost}-{os.getpid()}-{time.time_ns()}",
                                **kwargs)
            by_future[fut] = task
            ac.add(fut)

        try:
            while queue and len(by_future) < window:
                submit(queue.popleft())
            for fut in ac:
                task = by_future.pop(fut)
                m = self.models[task.index]
                try:
                    rec = fut.result()
                    worker = rec.get("worker") or f"{rec.get('host')}:{rec.get('pid')}"
                except Exception as exc:  # KilledWorker (the task killed its workers), a lost connection
                    rec = {"model": m.rel, "output": m.out, "status": "failed",
                           "error": f"{m.src}: {_one_line(exc)}"}
                    worker = "?"
                fut.release()
                if rec["status"] == "done" and "payload" in rec:
                    _write_payload(self.out_dir / m.out, rec.pop("payload"))
                retry = self._outcome(task, rec, worker, n_workers)
                if retry is not None:
                    queue.appendleft(retry)
                while queue and len(by_future) < window:
                    submit(queue.popleft())
        except BaseException:
            for fut in list(by_future):
                fut.cancel()
            raise

    # ---- entry -------------------------------------------------------------------------------------------
    def run(self, workers: int | None = None, *, threads: int | None = None, client=None,
            transfer: str = "bytes") -> dict[str, Any]:
        """Run the batch and return its report.

        workers : local worker processes; 0 slices in this process; None: :func:`default_workers`.
        threads : PoCL threads per local worker (default: cores // workers).
        client : a ``distributed.Client``: run the tasks on its cluster instead (``workers`` is ignored).
        transfer : with a client, ``"bytes"`` (model bytes go to the workers and output bytes come back to this
            process, which writes them; the default) or ``"shared"`` (workers read the models and write the outputs
            by their absolute paths: a shared file system mounted alike everywhere).
        """
        if transfer not in ("shared", "bytes"):
            raise BatchError(f"unknown transfer '{transfer}' (use shared or bytes)")
        t0 = time.perf_counter()
        tasks = self._prepare_output()
        mode = "dask" if client is not None else "serial" if workers == 0 else "local"
        self.info.update(mode=mode, transfer=transfer if client is not None else "shared")
        try:
            if client is not None:
                self.info["scheduler"] = getattr(client.scheduler, "address", None)
                self.info["workers"] = len(client.scheduler_info(n_workers=-1).get("workers", {}))
                if tasks:
                    self._run_dask(tasks, client, transfer)
            elif workers == 0:
                self.info["workers"] = 0
                self._run_serial(tasks)
            else:
                auto_n, _ = default_workers(len(tasks), self.opts.device, self.opts.backend)
                n = auto_n if workers is None else max(1, workers)
                n = max(1, min(n, len(tasks))) if tasks else n
                t = threads or max(1, _cores() // n)
                self.info.update(workers=n, pocl_threads_per_worker=t)
                if tasks:
                    self._run_local(tasks, n, t)
        except KeyboardInterrupt:
            self.interrupted = True
            raise
        finally:
            self._cleanup_temporaries()
            self.wall_s = time.perf_counter() - t0
        return self.report()

    def report(self) -> dict[str, Any]:
        """The batch report: ``options``, ``models`` (one record per model, sorted by path; unfinished models
        have status ``"not run"`` after an interrupt) and ``summary`` (counts, wall time, models per second)."""
        records = []
        for i, m in enumerate(self.models):
            rec = self.records.get(i) or {"model": m.rel, "input": m.src, "output": m.out, "status": "not run",
                                          "error": None}
            records.append({k: v for k, v in rec.items() if k != "payload"})
        counts = collections.Counter(r["status"] for r in records)
        done = [r for r in records if r["status"] == "done"]
        info = dict(self.info)
        init = info.pop("worker_init_s")
        summary = {
            "models": len(records),
            "done": counts.get("done", 0),
            "skipped": counts.get("skipped", 0),
            "failed": counts.get("failed", 0),
            "not_run": counts.get("not run", 0),
            "interrupted": self.interrupted,
            "wall_s": self.wall_s,
            "models_per_s": len(done) / self.wall_s if self.wall_s > 0 else 0.0,
            "facets": sum(r.get("facets", 0) for r in done),
            "layers": sum(r.get("layers", 0) for r in done),
            "task_s": sum(r["timings_s"]["total"] for r in done if "timings_s" in r),
            "worker_init_s": init,
            **info,
        }
        return {
            "gpuslice_batch": 1,
            "inputs": self.inputs,
            "output_dir": str(self.out_dir),
            "options": self.opts.shaping() | {"backend": self.opts.backend, "device": self.opts.device},
            "fingerprint": self.opts.fingerprint(),
            "models": records,
            "summary": summary,
        }


def _write_payload(target: Path, payload: bytes | dict[str, bytes]) -> None:
    from ..io.atomic import atomic_path, atomic_write_bytes

    target.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(payload, bytes):
        atomic_write_bytes(target, payload)
        return
    with atomic_path(target) as tmp:
        tmp.mkdir()
        for rel, data in payload.items():
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp / rel).write_bytes(data)


def _stop_slots(slots: Iterable[_Slot]) -> None:
    """Cancel what is queued and stop every worker now (Ctrl-C): SIGTERM (the worker removes its temporary
    output), then SIGKILL for any still running a second later."""
    procs = []
    for slot in slots:
        for fut in slot.inflight:
            fut.cancel()
        procs += list((getattr(slot.executor, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = time.monotonic() + 1.0
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()
                p.join(1.0)
    for slot in slots:
        with contextlib.suppress(Exception):
            slot.executor.shutdown(wait=False, cancel_futures=True)


def _device_plugin(device: str | None, backend: str):
    """A Dask worker plugin that makes the OpenCL device and builds the kernels once, when a worker starts or
    joins (defined here so that ``distributed`` is imported only for Dask batches; Dask pickles it by value)."""
    from distributed import WorkerPlugin

    class GpusliceDevicePlugin(WorkerPlugin):
        idempotent = True

        def setup(self, worker) -> None:
            if backend == "opencl":
                with contextlib.suppress(Exception):  # reported by the first task instead
                    _worker_device(device)

    return GpusliceDevicePlugin()


def run_batch(inputs: Sequence[str | os.PathLike], out_dir: str | os.PathLike, opts: BatchOptions | None = None, *,
              glob: str | None = None, workers: int | None = None, client=None, transfer: str = "bytes",
              force: bool = False, progress: Callable[[dict], None] | None = None) -> dict[str, Any]:
    """Slice every model found in ``inputs`` into ``out_dir`` (mirroring the input tree); returns the report.

    See :func:`discover` for ``inputs`` and ``glob``, :meth:`BatchRunner.run` for ``workers``, ``client`` and
    ``transfer``. A model whose output exists is skipped unless ``force``.
    """
    opts = opts or BatchOptions()
    models = discover(inputs, glob, opts.suffix)
    runner = BatchRunner(models, opts, out_dir, force=force, progress=progress, inputs=[str(i) for i in inputs])
    return runner.run(workers, client=client, transfer=transfer)


def format_summary(report: dict[str, Any], max_rows: int = 40) -> str:
    """A plain-text summary table of a batch report: one row per model (failed ones first; at most
    ``max_rows``), then the totals."""
    rows = sorted(report["models"], key=lambda r: (r["status"] != "failed", r["model"]))
    width = min(60, max([len(r["model"]) for r in rows] + [5]))
    lines = [f"{'model':{width}s} {'status':8s} {'facets':>9s} {'layers':>7s} {'time s':>8s}  error"]
    for r in rows[:max_rows]:
        t = r.get("timings_s", {}).get("total")
        name = r["model"] if len(r["model"]) <= width else "…" + r["model"][-width + 1:]
        lines.append(f"{name:{width}s} {r['status']:8s} {r.get('facets', ''):>9} {r.get('layers', ''):>7} "
                     f"{'' if t is None else f'{t:.3f}':>8s}  {r.get('error') or ''}")
    if len(rows) > max_rows:
        lines.append(f"… {len(rows) - max_rows} more in the JSON report")
    s = report["summary"]
    rate = s["models_per_s"]
    lines.append(
        f"{s['models']} models: {s['done']} done, {s['skipped']} skipped, {s['failed']} failed"
        + (f", {s['not_run']} not run" if s["not_run"] else "")
        + f"; {s['wall_s']:.2f} s wall, {rate:.2f} models/s ({s['mode']}, {s.get('workers', 0)} workers"
        + (f", {s['workers_lost']} lost" if s["workers_lost"] else "")
        + (f", {s['retries']} retries" if s["retries"] else "") + ")"
    )
    return "\n".join(lines)

