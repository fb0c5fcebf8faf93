"""The options of a batch, composed of the pipeline's own (:class:`SliceParams`, :class:`Placement`, the resin
output's :class:`RasterSpec` and :class:`ResinOptions`), never copied from them."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

from ..errors import ParameterError
from ..formats import CONTOUR_FORMATS, format_names
from ..mesh.mesh import Placement
from ..options import option, options_of, parse_value
from ..slicing.params import SliceParams

__all__ = ["BatchOptions", "check_path", "raster_option_fields", "typed_raster_options", "same_options"]

#: what ends the name of a model's check report, next to its output (``--check``)
CHECK_SUFFIX = ".check.json"


def check_path(target: str | Path) -> Path:
    """Where a model's check report goes: its output's path + ``.check.json`` (``part.goo`` → ``part.goo.check.json``;
    a PNG stack folder ``part`` → ``part.check.json``)."""
    target = Path(target)
    return target.with_name(target.name + CHECK_SUFFIX)


def write_check_report(report, path: str | Path) -> None:
    """Write ``report`` (:class:`gpuslice.checks.CheckReport`) as JSON to ``path``, atomically, without its timings:
    the file's bytes depend only on the model and the options, as the batch's outputs do."""
    from ..io.report import write_report

    data = report.to_json()
    data.pop("timings_s", None)
    write_report(data, path)

#: the SliceParams fields of an adaptive schedule (recorded in the manifest only when one is asked for)
_SCHEDULE_FIELDS = ("adaptive", "max_cusp", "max_area", "min_height", "max_height", "smooth", "roi_ladder",
                    "roi_threshold", "roi_quantile", "roi_windows")


def _resin_names() -> tuple[str, ...]:
    from ..raster.outputs import resin_format_names

    return tuple(resin_format_names())


def raster_option_fields() -> dict[str, Any]:
    """``--raster-opt`` keys → their :class:`~gpuslice.options.OptionInfo`: the fields of
    :class:`~gpuslice.raster.spec.RasterSpec` and :class:`~gpuslice.raster.spec.ResinOptions`."""
    from ..raster.settings import PrintSettings
    from ..raster.spec import RasterSpec, ResinOptions

    return {i.name: i for cls in (RasterSpec, ResinOptions, PrintSettings) for i in options_of(cls)}


def typed_raster_options(pairs: dict[str, Any] | tuple[tuple[str, Any], ...]) -> tuple[tuple[str, Any], ...]:
    """``(key, value)`` pairs with text values typed by their fields (``resolution=3840x2400`` → (3840, 2400),
    ``pixel=0.05`` → 0.05, ``mirror_x=true`` → True); :class:`ParameterError` for an unknown key."""
    known = raster_option_fields()
    out = []
    for key, value in (pairs.items() if isinstance(pairs, dict) else pairs):
        key = key.strip().replace("-", "_")
        if key not in known:
            raise ParameterError(f"unknown raster option {key} (use {', '.join(known)})")
        try:
            out.append((key, parse_value(known[key], value)))
        except ParameterError as exc:
            raise ParameterError(f"{key}: {exc}", param=key) from None
    return tuple(out)


def _as_recorded(value: Any) -> Any:
    """A ``--raster-opt`` value as the manifest records it: text as it reads (an int, else a float, else true/false,
    else the text: what 8c0d960 wrote, so its output folders stay valid); other values as JSON has them."""
    if isinstance(value, str):
        for cast in (int, float):
            try:
                return cast(value)
            except ValueError:
                pass
        return {"true": True, "false": False}.get(value.lower(), value)
    return list(value) if isinstance(value, tuple) else value


@dataclass(frozen=True)
class BatchOptions:
    """The options every model of a batch is sliced with, picklable for the workers.

    params, placement : the slicing options and the scaling, as for ``gpuslice slice``.
    fmt : the contour output format (a :mod:`gpuslice.formats` name: ``npz``, ``svg``, ``cli``).
    raster : a resin output (:mod:`gpuslice.raster.outputs` name: ``sl1``, ``png``) instead of contours, with
        ``raster_options``: (name, value) pairs of :class:`~gpuslice.raster.spec.RasterSpec` and
        :class:`~gpuslice.raster.spec.ResinOptions` fields (``printer``, ``resolution``, ``gamma``, …); values may
        be the command line's text (``"3840x2400"``), typed by the fields when used.
    check : also run the pre-print checks (:mod:`gpuslice.checks`, default options) on every model and write its
        report next to its output (:func:`check_path`): on the display's pixels with a resin output (as
        ``raster --check``), else on the contours (as ``gpuslice check``); either way on the batch's own layers.
    date : the date resin archives state (:attr:`gpuslice.pipeline.Job.date`); None (with ``raster``): the
        ``SOURCE_DATE_EPOCH`` of the process that makes the options, so that every worker, a Dask one too, writes
        the date the client's environment gives (else each archive its time of writing).
    """

    params: SliceParams = SliceParams()
    placement: Placement = Placement()
    fmt: str = option("npz", "Result format of each model", flags=("--format",), choices=format_names)
    raster: str | None = option(None, "Rasterise each model to a resin output instead (a file, or a folder for png)",
                                choices=_resin_names)
    raster_options: tuple[tuple[str, Any], ...] = ()
    check: bool = option(False, "Also run the pre-print checks on every model (islands, unsupported area, resin "
                         "traps, suction cups, print time, resin: as `gpuslice check`, on the printer's pixels with "
                         "--raster) and write each report next to its output as <output>.check.json; they check the "
                         "batch's layers (-t: 0.1 mm by default, 0.05 with --raster, where `gpuslice check` slices "
                         "at 0.05)")
    date: Any = field(default=None, compare=False)
    #: (text as given, Printer) of a ``printer=`` preset file, read where the options are made: a worker elsewhere
    #: (Dask) needs neither the file nor the same working folder (keyed by the text: options remade with another
    #: ``printer=`` never take it)
    preset_files: tuple = field(default=(), compare=False)

    def __post_init__(self) -> None:
        from ..schedule.validate import check_schedule_params

        check_schedule_params(self.params)  # layer settings refused now, not once per model
        if self.fmt not in CONTOUR_FORMATS:
            raise ParameterError(f"unknown output format '{self.fmt}' (use {', '.join(format_names())})", param="fmt")
        if self.raster is not None:
            if self.raster not in _resin_names():
                raise ParameterError(f"unknown raster output '{self.raster}' (use {', '.join(_resin_names())})",
                                     param="raster")
            preset = dict(self.raster_options).get("printer")
            if not self.preset_files and isinstance(preset, str) and Path(preset).is_file():
                from ..raster.printers import find_printer

                object.__setattr__(self, "preset_files", ((preset, find_printer(preset)),))
            self.resin()  # validates the display and resin options now, before any model is sliced
            if self.date is None:  # (here, where the batch is run; the workers get it with the options)
                from ..raster.outputs import source_date

                object.__setattr__(self, "date", source_date())
        elif self.raster_options:
            raise ParameterError("raster_options need a raster output", param=("raster_options", "raster"))

    def resin(self):
        """(:class:`RasterSpec`, :class:`ResinOptions`, :class:`PrintSettings`) of ``raster_options``."""
        from ..raster.settings import PrintSettings
        from ..raster.spec import RasterSpec, ResinOptions

        given = dict(typed_raster_options(self.raster_options))
        resin_keys = {f.name for f in fields(ResinOptions)}
        read = dict(self.preset_files).get(given.get("printer"))  # (on a worker: the file as the client read it)
        ropts = ResinOptions(**{k: v for k, v in given.items() if k in resin_keys}, preset_read=read)
        ropts.check_format(self.raster)
        display = {f.name: given.get(f.name) for f in fields(RasterSpec)}
        spec = ropts.spec(**display)
        ropts.check_display(self.raster, spec)
        settings = ropts.settings(**{f.name: given.get(f.name) for f in fields(PrintSettings)})
        from ..raster.outputs import RESIN_FORMATS

        RESIN_FORMATS[self.raster].check_settings(f"--raster {self.raster}", ropts, settings, spec)
        return spec, ropts, settings

    @property
    def suffix(self) -> str:
        """The suffix of each model's output (``""`` for a folder output such as a PNG stack)."""
        if self.raster is not None:
            from ..raster.outputs import RESIN_FORMATS

            return RESIN_FORMATS[self.raster].suffix
        return CONTOUR_FORMATS[self.fmt].suffix

    def job(self, source: str, target: Path, *, name: str, label: str, data: bytes | None = None,
            workers: int | None = None):
        """The :class:`~gpuslice.pipeline.Job` of one model: read ``source`` (or ``data``), write ``target``;
        portable (no device or backend in the output)."""
        from dataclasses import replace
        from functools import partial

        from ..pipeline import CheckOutput, Job, ResinOutput

        resin = checks = None
        if self.raster is not None:
            spec, ropts, settings = self.resin()
            resin = ResinOutput(str(target), self.raster, spec, replace(ropts, workers=ropts.workers or workers),
                                settings)
        if self.check:
            pixels = (resin.spec, resin.settings) if resin is not None else (None, None)
            checks = CheckOutput(*pixels, on_report=partial(write_check_report, path=check_path(target)))
        return Job(source=source, name=name, label=label, data=data, placement=self.placement, params=self.params,
                   contours=None if resin is not None else str(target), resin=resin, checks=checks, portable=True,
                   date=self.date)

    def shaping(self) -> dict[str, Any]:
        """The options that shape output bytes (not the backend or device: both give bit-identical results), as the
        output folder's manifest records them."""
        p = self.params
        d: dict[str, Any] = {k: getattr(p, k) for k in ("thickness", "first_layer", "z_mode", "fill_rule", "max_gap")}
        d.update(asdict(self.placement))
        if d.pop("center"):  # recorded only when set: folders made before --center keep their fingerprint
            d["center"] = True
        d.update(fmt=self.fmt, raster=self.raster,
                 raster_options=[[k, _as_recorded(v)] for k, v in self.raster_options])
        d["schedule"] = {k: list(v) if isinstance(v, tuple) else v for k, v in
                         ((k, getattr(p, k)) for k in _SCHEDULE_FIELDS)} if p.adaptive else {}
        if self.check:  # only then: folders made without --check keep their fingerprint
            d["check"] = True
        preset = dict(self.raster_options).get("printer")
        if preset is not None and Path(str(preset)).is_file():  # a user's preset file: what it says, not its name
            d["printer_file_sha256"] = hashlib.sha256(Path(str(preset)).read_bytes()).hexdigest()[:16]
        return d

    def fingerprint(self) -> str:
        return hashlib.sha256(json.dumps(self.shaping(), sort_keys=True).encode()).hexdigest()[:16]


def same_options(a: Any, b: Any) -> bool:
    """Whether two manifests' ``options`` (:meth:`BatchOptions.shaping`) are the same, whatever order their
    ``--raster-opt`` pairs were given in (each key's last value counts) and whatever path a preset file was given
    by (its contents' digest counts)."""
    return _canonical(a) == _canonical(b)


def _canonical(options: Any) -> Any:
    """A manifest's ``options`` with its ``raster_options`` pairs as each key's last value, by key: two batches
    whose --raster-opt were given in another order made the same outputs."""
    if not isinstance(options, dict) or not isinstance(options.get("raster_options"), list):
        return options
    try:
        pairs = sorted(dict((k, v) for k, v in options["raster_options"]).items())
    except (TypeError, ValueError):  # (an unreadable manifest's: compared as it is)
        return options
    if "printer_file_sha256" in options:  # a preset file counts by its contents, not by the path it was given as
        pairs = [p for p in pairs if p[0] != "printer"]
    return {**options, "raster_options": [list(p) for p in pairs]}
