"""Prusa SL1S Speed archives (``.sl1s``): the SL1 archive of :mod:`gpuslice.raster.sl1` for the SL1S printer.

The members and their encoding are SL1's (``config.ini``, ``prusaslicer.ini``, ``<jobDir>00000.png`` upward, two
thumbnails); what differs, from PrusaSlicer 2.9's ``resources/profiles/PrusaResearchSLA.ini`` (printer "Original Prusa
SL1S SPEED") and the SL1S firmware's project loader (Prusa's ``sla-fw``, ``slafw/project/project.py``):

* ``config.ini``: ``printerModel = SL1S`` (the firmware refuses a project whose ``printerModel`` is not its own
  model), ``printerVariant = default`` (another variant: a warning), ``printerProfile`` the preset's title.
* The display: the firmware pastes every layer PNG into a 1620 x 2560 (width x height) greyscale buffer of 0.05 mm
  pixels; PrusaSlicer's profile says the same as ``display_pixels_x = 2560``, ``display_pixels_y = 1620``, 128 x 81 mm,
  ``display_orientation = portrait``, ``display_mirror_x = 1``. Other PNG sizes would be cropped or padded by the
  printer, so :func:`write_target` refuses them.
* One layer height: the firmware moves every layer by ``layerHeight`` (the first by its own default), so a schedule
  whose layers above the first differ in thickness (adaptive layers) is refused.
* ``printTime`` with the SL1S's fast tilt of 2.5 s a layer (SL1: 5 s); ``prusaslicer.ini`` also carries
  ``printer_model``, ``printer_variant``, ``printer_settings_id``, ``fast_tilt_time``, ``slow_tilt_time`` and
  ``sla_archive_format = SL1`` as PrusaSlicer writes them, so PrusaSlicer and UVtools recognise the printer.
* The suffix: the firmware lists the projects with its model's suffix, ``.sl1s``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

from ..errors import ParameterError
from .coverage import Tile
from .sl1 import check_one_layer_height, info_from, sl1_print_time, sl1_values, write_sl1
from .sl1 import tilt_print_time as sl1_tilt_print_time
from .spec import RasterSpec

__all__ = ["SL1S_PNG_SIZE", "SL1S_PIXEL_MM", "SL1S_FAST_TILT_S", "SL1S_SLOW_TILT_S", "check_sl1s_display",
           "write_target"]

#: (width, height) of the layer PNGs the SL1S firmware shows, pixels
SL1S_PNG_SIZE = (1620, 2560)
#: the SL1S display's pixel pitch, mm
SL1S_PIXEL_MM = 0.05
#: PrusaSlicer's SL1S tilt times, s per layer
SL1S_FAST_TILT_S = 2.5
SL1S_SLOW_TILT_S = 5.0


def tilt_print_time(settings, n_layers: int) -> float:
    """The SL1S archive's own print time (s): the SL1's, with the SL1S's fast tilt (``ResinFormat.print_time``)."""
    return sl1_tilt_print_time(settings, n_layers, SL1S_FAST_TILT_S)


def check_sl1s_display(spec: RasterSpec, path: Path) -> None:
    """:class:`ParameterError` unless ``spec`` makes 1620 x 2560 PNGs of 0.05 mm pixels, what the SL1S shows."""
    ok = spec.png_size == SL1S_PNG_SIZE and all(math.isclose(p, SL1S_PIXEL_MM, rel_tol=1e-9)
                                                 for p in (spec.px, spec.py))
    if not ok:
        w, h = spec.png_size
        raise ParameterError(f"{path}: an SL1S shows 1620x2560 PNGs of 0.05 mm pixels, this display makes {w}x{h} "
                             f"PNGs of {spec.px:g} x {spec.py:g} mm (PrusaSlicer's SL1S: --resolution 2560x1620 "
                             f"--pixel 0.05 --portrait --mirror-x)")


def write_target(tiles: Iterable[Tile], target) -> dict[str, float]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): an SL1S archive of ``target.result``'s layers."""
    path = Path(target.path)
    check_sl1s_display(target.spec, path)
    check_one_layer_height(target.result.thickness, path)
    o = target.options
    preset = o.preset
    model = preset.machine if preset is not None and preset.machine else "SL1S"
    profile = preset.title if preset is not None else ""
    extra = {"printer_model": model, "printer_variant": "default", "printer_settings_id": profile,
             "fast_tilt_time": SL1S_FAST_TILT_S, "slow_tilt_time": SL1S_SLOW_TILT_S, "sla_archive_format": "SL1"}
    values = {**sl1_values(target), "printer_model": model, "printer_variant": "default",
              "printer_profile": profile, "tilt_time": SL1S_FAST_TILT_S, "extra": extra}
    info = info_from(target.result, target.name, values)
    n = target.result.n_layers
    stats = write_sl1(tiles, target.spec, path, info, n, level=o.png_level, deflater=target.deflater,
                      workers=target.workers, progress=target.progress, now=target.now,
                      device=target.device)
    return {**stats, "print_time_s": sl1_print_time(info, n)}
