"""Resin outputs, behind one registry: ``suffix → archive writer``.

Each output is one module of :mod:`gpuslice.raster` with a function ``write_target(layers, target) -> stats`` that
encodes the layers (in order; each a tile or runs, :mod:`gpuslice.raster.layers`) into ``target.path`` atomically,
and one :class:`ResinFormat` entry in
:data:`RESIN_FORMATS` below. ``gpuslice raster -o`` (suffix dispatch), ``batch --raster``, the messages and the docs
read this registry; writer modules are imported only when used.

Adding an archive format (say ``.goo``): write ``gpuslice/raster/goo.py`` with ``write_target(tiles, target)``, then
add ``ResinFormat("goo", (".goo",), "goo:write_target", "…")`` to ``RESIN_FORMATS``.
"""

from __future__ import annotations

import datetime as dt
import importlib
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ParameterError
from .settings import PrintSettings
from .spec import RasterSpec, ResinOptions

if TYPE_CHECKING:
    from ..slicing.result import SliceResult
    from .coverage import Tile

__all__ = ["RESIN_FORMATS", "ResinFormat", "ResinTarget", "resin_format_for", "resin_format_names", "resin_usage",
           "source_date"]


@dataclass(frozen=True)
class ResinTarget:
    """Everything an archive writer needs besides the tiles: where (``path``), the display (``spec``), the job's
    options, the sliced ``result`` (layer heights, areas for the resin volume, count), the job ``name`` (SL1 jobDir,
    PNG prefix), the archive date ``now`` (None: the current time; given: a reproducible build, see
    :attr:`deflater`), encoder ``workers``, a ``progress(k)`` callback and the print ``settings``
    (:class:`~gpuslice.raster.settings.PrintSettings`: exposures, lifts, per layer via ``layer_table``); ``bounds``:
    the (xmin, ymin, xmax, ymax) mm box the layers were centred by (None: the result's own, as ``masks()``), for
    writers that place the contours themselves (``sl1svg``); ``device``: the OpenCL device of the runs, for writers
    that encode on it (GOO)."""

    path: Path
    spec: RasterSpec
    options: ResinOptions
    result: SliceResult
    name: str
    now: dt.datetime | None = None
    workers: int | None = None
    progress: Callable[[int], None] | None = None
    settings: PrintSettings = PrintSettings()
    bounds: tuple[float, float, float, float] | None = None
    #: the OpenCL device the layers' runs were made on: writers with encoding kernels use it (None: numpy)
    device: object | None = None
    #: the registry name of the output (``raster --format``); None: the one ``path``'s suffix names
    format: str | None = None

    @property
    def deflater(self) -> str:
        """``"zlib"`` for a reproducible build (``now`` given, from ``SOURCE_DATE_EPOCH``), else ``"auto"`` (ISA-L
        where installed). ISA-L's deflate is not byte-deterministic from run to run (the same pixels, other LZ77
        matches now and then: ``scripts/compare_outputs.py`` found it), zlib's is."""
        return "zlib" if self.now is not None else "auto"

    def layer_count(self) -> int:
        """The result's layer count; a :class:`ParameterError` naming ``path`` when there is none to write."""
        n = int(self.result.n_layers)
        if n == 0:
            raise ParameterError(f"{self.path}: no layers to write")
        return n


@dataclass(frozen=True)
class ResinFormat:
    """One resin output: ``name`` (``--raster`` value), ``suffixes`` (lower case; empty for a folder output),
    ``writer`` as ``"module:function"`` inside :mod:`gpuslice.raster`, ``help``, ``title`` (its name in messages),
    ``folder`` (the output is a directory, named ``DIR/`` on the command line) and ``png`` (its layers are PNGs:
    the pipeline starts the PNG encoder processes of :mod:`gpuslice.raster.png_procs` before slicing)."""

    name: str
    suffixes: tuple[str, ...]
    writer: str
    help: str
    title: str
    folder: bool = False
    png: bool = False
    #: ``"module:function"`` that refuses, before any work, print settings or a display the format cannot store (a
    #: one-line :class:`~gpuslice.errors.ParameterError`; called as ``f(path, name, options, settings, spec)``);
    #: None: it stores all
    settings_check: str | None = None
    #: ``"module:function"`` that refuses settings the format cannot store for layers of these thicknesses (mm):
    #: ``f(path, settings, thickness_mm)``; called before slicing where the options fix them (uniform layers) and
    #: by the writer. None: none
    layers_check: str | None = None
    #: ``"module:function"`` giving the print time (s) the archive itself states, where its printer moves otherwise
    #: than :func:`~gpuslice.raster.settings.print_time_s`'s lifts and retracts (the SL1 family tilts its vat):
    #: ``f(settings, n_layers)``; the pre-print checks then state the same time. None: the settings' own
    print_time: str | None = None

    def print_time_s(self, settings, n_layers: int) -> float:
        """The print time (s) of ``n_layers`` at ``settings`` as this format's archive states it."""
        if self.print_time is None:
            from .settings import print_time_s

            return print_time_s(settings, n_layers)
        module, func = self.print_time.split(":")
        return float(getattr(importlib.import_module(f"{__package__}.{module}"), func)(settings, n_layers))

    def check_settings(self, path, options, settings, spec) -> None:
        """Refuse ``settings`` (:class:`~gpuslice.raster.settings.PrintSettings`) or a display ``spec`` this format
        cannot store for ``options`` (its preset: the format's version), naming ``path``; nothing to refuse:
        returns."""
        if self.settings_check is not None:
            module, func = self.settings_check.split(":")
            getattr(importlib.import_module(f"{__package__}.{module}"), func)(path, self.name, options, settings, spec)

    def check_layers(self, path, settings, thickness_mm) -> None:
        """Refuse ``settings`` this format cannot store for layers of ``thickness_mm`` (mm), naming ``path``."""
        if self.layers_check is not None:
            module, func = self.layers_check.split(":")
            getattr(importlib.import_module(f"{__package__}.{module}"), func)(path, settings, thickness_mm)

    @property
    def suffix(self) -> str:
        """What batch appends to a model's output name (``""`` for a folder)."""
        return self.suffixes[0] if self.suffixes else ""

    def load(self) -> Callable[[Iterable[Tile], ResinTarget], dict[str, Any]]:
        module, func = self.writer.split(":")
        return getattr(importlib.import_module(f"{__package__}.{module}"), func)


#: Photon Workshop suffixes and the Anycubic printer each names (gpuslice/raster/photon_machines.py's MACHINES)
_PHOTON = (("pwmo", "Photon Mono"), ("pwms", "Photon Mono SE"), ("pwma", "Photon Mono 4K"), ("pwmx", "Photon Mono X"),
           ("pmsq", "Photon Mono SQ"), ("pm3", "Photon M3"), ("pm3m", "Photon M3 Max"), ("pm3n", "Photon Mono 2"),
           ("pm4n", "Photon Mono 4"), ("pwmb", "Photon Mono X 6K / M3 Plus"), ("pmx2", "Photon Mono X2"),
           ("pm3r", "Photon M3 Premium"), ("px6s", "Photon Mono X 6Ks"), ("pm5", "Photon Mono M5"),
           ("pm5s", "Photon Mono M5s"), ("m5sp", "Photon Mono M5s Pro"))

#: Anycubic's zip archives (gpuslice/raster/anycubic_zip.py's ZIP_MACHINES)
_ANYCUBIC_ZIP = (("pm7", "Photon Mono M7"), ("pm7m", "Photon Mono M7 Max"), ("pwsz", "Photon Mono M7 Pro"))

#: the registry, in the order the help lists them
RESIN_FORMATS: dict[str, ResinFormat] = {
    f.name: f
    for f in (
        ResinFormat("sl1", (".sl1",), "sl1:write_target", "Prusa SL1 archive (PNG layers, config.ini, thumbnails)",
                    "SL1 archive", png=True, settings_check="sl1:refuse_settings", print_time="sl1:tilt_print_time"),
        ResinFormat("sl1s", (".sl1s",), "sl1s:write_target", "Prusa SL1S Speed archive (the SL1 archive for the "
                    "SL1S: 1620x2560 PNGs of 0.05 mm, printerModel SL1S)", "SL1S archive", png=True,
                    settings_check="sl1:refuse_settings", print_time="sl1s:tilt_print_time"),
        ResinFormat("sl1svg", (".sl1_svg",), "sl1svg:write_target", "PrusaSlicer's vector SL1 archive (one SVG of "
                    "the contours per layer, config.ini, thumbnails)", "SL1 SVG archive",
                    settings_check="sl1svg:refuse_settings", print_time="sl1:tilt_print_time"),
        ResinFormat("nanodlp", (".nanodlp",), "nanodlp:write_target", "NanoDLP plate (1.png upward, "
                    "meta/plate/profile/options/info json, 3d.png)", "NanoDLP plate", png=True,
                    settings_check="nanodlp:refuse_settings"),
        ResinFormat("goo", (".goo",), "goo:write_target", "Elegoo GOO file (8-bit RLE layers, print settings, "
                    "RGB565 previews)", "GOO file"),
        ResinFormat("prz", (".prz",), "goo:write_target", "Phrozen PRZ file (the GOO layout, no grey-difference "
                    "chunks)", "PRZ file"),
        ResinFormat("ctb", (".ctb",), "ctb:write_target", "Chitubox CTB file, unencrypted, v3 unless the printer "
                    "preset asks for v2 or v4 (7-bit RLE layers, print settings, RGB15 previews)", "CTB file",
                    settings_check="ctb:refuse_settings"),
        *(ResinFormat(s, (f".{s}",), "photon:write_target", f"Anycubic {t} file (Photon Workshop: 4-bit PW0 "
                      "layers, settings, preview)", f"Photon Workshop file ({t})",
                      settings_check="photon_machines:refuse_settings") for s, t in _PHOTON),
        *(ResinFormat(s, (f".{s}",), "anycubic_zip:write_target", f"Anycubic {t} archive (the M7 generation's "
                      "zip: 4-bit PW0 layers, JSON settings, PNG previews)", f"Anycubic zip archive ({t})",
                      settings_check="anycubic_zip:refuse_settings") for s, t in _ANYCUBIC_ZIP),
        ResinFormat("cxdlp", (".cxdlp",), "cxdlp:write_target", "Creality Halot CXDLP file, v3 (v2 where the "
                    "preset asks): vertical line runs of 8-bit greys, print settings, RGB565 previews", "CXDLP file",
                    settings_check="cxdlp:refuse_settings"),
        ResinFormat("cxdlpv4", (".cxdlpv4",), "cxdlpv4:write_target", "Creality Halot Mage CXDLP v4 file (another "
                    "layout than .cxdlp: 7-bit RLE layers with their own settings, RGB15 previews)", "CXDLP v4 file",
                    settings_check="cxdlpv4:refuse_settings", layers_check="cxdlpv4:refuse_layers"),
        ResinFormat("jxs", (".jxs",), "jxs:write_target", "UniFormation GKone JXS archive (RGB-packed PNG layers, "
                    "config.ini, control.json with the print program)", "JXS archive",
                    settings_check="jxs:refuse_settings", print_time="jxs:stated_print_time"),
        ResinFormat("png", (), "pngstack:write_target", "a folder of 8-bit PNGs, one per layer", "PNG stack",
                    folder=True, png=True),
    )
}


def resin_format_names() -> list[str]:
    return list(RESIN_FORMATS)


def _usage() -> str:
    files = [f"FILE{s}" for f in RESIN_FORMATS.values() for s in f.suffixes]
    folders = [f"DIR/ for a {f.title}" for f in RESIN_FORMATS.values() if f.folder]
    return ", ".join(files) + (", or " + ", ".join(folders) if folders else "")


def resin_usage() -> str:
    """How ``-o`` names each resin output: ``FILE.sl1, or DIR/ for a PNG stack``."""
    return _usage()


def resin_format_for(path: str | os.PathLike, name: str | None = None) -> ResinFormat:
    """The resin output that ``path`` names: a registered suffix (any case), or a folder (``DIR/`` or an existing
    directory) for the folder output; :class:`ParameterError` naming ``path`` otherwise. ``name``: a registry name
    that overrides the suffix (``raster --format``): any path then, except that a one-file format refuses a path
    naming a folder, and a suffix another format owns is refused (``--format goo -o part.ctb``)."""
    text = os.fspath(path)
    p = Path(text)
    names_folder = text.endswith(("/", "\\")) or p.is_dir()
    if name is not None:
        fmt = RESIN_FORMATS.get(name)
        if fmt is None:
            raise ParameterError(f"{text}: unknown resin format '{name}' (use {', '.join(RESIN_FORMATS)})")
        if names_folder and not fmt.folder:
            raise ParameterError(f"{text}: names a folder, but a {fmt.title} is one file (e.g. part{fmt.suffix})")
        kind = p.suffix.lower()
        owner = next((f for f in RESIN_FORMATS.values() if kind and kind in f.suffixes), None)
        # (`--format goo -o part.ctb`: GOO bytes in a file named .ctb; `-o out.goo/` names a folder, not a file)
        if owner is not None and owner is not fmt and not (names_folder and fmt.folder):
            name_it = f"name it part{fmt.suffix}" if fmt.suffix else "name a folder DIR/"
            raise ParameterError(f"{text}: a {kind} file is a {owner.title}, not the {fmt.title} --format {name} "
                                 f"writes ({name_it}, or leave --format out)")
        return fmt
    kind = p.suffix.lower()
    if names_folder:
        one_file = next((f for f in RESIN_FORMATS.values() if kind and kind in f.suffixes and not f.folder), None)
        if one_file is not None and not text.endswith(("/", "\\")):  # (an existing folder named like an archive)
            raise ParameterError(f"{text}: is a folder, but a {one_file.title} is one file; name the file to write")
        for f in RESIN_FORMATS.values():
            if f.folder:
                return f
    for f in RESIN_FORMATS.values():
        if kind and kind in f.suffixes:
            return f
    raise ParameterError(f"{text}: unknown output format '{p.suffix}' (use {_usage()}, or --format NAME)")


def source_date() -> dt.datetime | None:
    """``SOURCE_DATE_EPOCH`` (reproducible builds) as a naive UTC datetime, or None when unset: archive dates."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if not epoch:
        return None
    try:
        when = dt.datetime.fromtimestamp(int(epoch), dt.timezone.utc).replace(tzinfo=None)
    except (ValueError, OverflowError, OSError):
        raise ParameterError(f"SOURCE_DATE_EPOCH must be an integer number of seconds, got '{epoch}'") from None
    if not 1980 <= when.year <= 2107:  # what a zip entry can hold
        raise ParameterError(f"SOURCE_DATE_EPOCH must be a date from 1980 to 2107, got '{epoch}' ({when.year})")
    return when
