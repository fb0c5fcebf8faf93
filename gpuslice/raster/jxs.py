"""UniFormation GKone ``.jxs`` archives: a zip of RGB-packed layer PNGs, ``config.ini`` and ``control.json``.

Facts from UVtools' ``JXSFile.cs`` (its reader; its writer since 4.3 puts the wrong object in ``control.json``, so the
reader is the reference) and its G-code builder, gathered in ``docs/research/UNIFORMATION.md`` section 2; our own code.
No file UniFormation's slicer wrote was found, and nothing is verified on a printer (section 5 there lists what is
not known: whether the firmware reads ``config.ini`` at all, its G-code dialect, whether it takes greys).

* ``00000.png`` … (zero-based, five digits, at the root): each layer an 8-bit **RGB** PNG a third as wide as the
  display, every PNG pixel three display pixels side by side (R the first, G the second, B the third), each a full
  8-bit grey: exact. Our greyscale PNG rows (filter 0 on every row) are byte for byte that RGB image's rows, so a
  layer is the PNG stack's PNG (made from the runs, on the device where there is one) with its header changed. The
  GKone's display only (4920x2880; the format has no resolution field), mirrored in y as its preset says.
* ``config.ini``, ``key=value`` lines in the reader's order: ``Action=print``, ``FirstLayerTime`` and ``LayerTime``
  (bottom and normal exposure, ms), ``NumFade`` 0 (meaning unknown: UVtools never sets it; the ramp is in the program),
  ``NumLayers``, ``UsedMaterial`` (ml), ``layerHeight`` (mm), ``nJobName``, ``NumBottomLayers``, ``LiftDistance1``,
  ``LiftFeedrate1`` (the lift and its speed, mm and mm/min), ``LiftDistance2``, ``LiftFeedrate2`` (the second stage),
  ``BottomLiftFeedrate``, ``RetractFeedrate``, ``ZMoveTimeCompensation`` and ``ZMoveTimeCompensationBottom`` (the
  waits before the exposure, ms), ``OnLightCode``/``OffLightCode`` (``M106 S<pwm>``/``M106 S0``), ``GcodeHeader``,
  ``GcodeFooter`` (the program's last move), ``ApplicationName``.
* ``control.json``: ``total_time`` (s), ``total_slices``, ``used_material`` (ml) and ``action_list``, the print as
  ``[kind, value]`` steps: ``gcode`` lines, ``slice`` (``{PWD}/00000.png`` shows a layer, ``<BLANK>`` blanks the
  screen), ``delay`` (ms) and ``layerno`` (1-based, before its layer's image). The program is the one UVtools' G-code
  builder lays out for this format, in relative positioning: ``G21``, ``G91``, ``M106 S0``, blank, ``M17``,
  ``G28 Z0``; per layer its number and image, the lift (``G0 Z<rise to the layer's top + lift> F<mm/min>``, the
  second stage), a delay for the move, the wait after the lift, the retract (fast stage, then the slow one, both
  down), a delay for it, the wait before the exposure, ``M106 S<pwm>``, the exposure as a delay, ``M106 S0``, blank,
  the wait after the exposure; at the end the light off, a lift of at least 4 mm and a rise to the top, ``M18``.
  The firmware does not wait for a move before the next step, so each move is followed by a delay: its duration at
  the programmed speed plus 0.75 s a stage and 0.75 s more (UVtools' converter's margin). Moves are whole
  micrometres between the layers' tops rounded to 1 µm, so they add up to each layer's top exactly. Every layer's
  own values (the exposure ramp, the bottom layers' motion and waits, the PWM) are in the program; zero delays are
  left out. ``total_time`` is the program's delays without the layers' rises and the final rise
  (:func:`stated_print_time`): the time the command line states.
"""

from __future__ import annotations

import json
import os
import struct
import zipfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from .coverage import Tile
from .layers import RUNS_LEVEL, RunLayer, encode_png, run_groups
from .png import PngEncoder, encode_all, png_chunk
from .png_runs import png_group
from .settings import header_layer_height, layer_table, resin_ml

__all__ = ["RESOLUTION", "program", "program_seconds", "refuse_settings", "stated_print_time", "rgb_packed",
           "write_jxs", "write_target"]

RESOLUTION = (4920, 2880)  #: the GKone's display, the only one the format is for (columns, rows)
MOVE_MARGIN_S = 0.75  #: added to each motion stage's duration in the delay that follows it
HEADER = "G21|G91|M17|M106 S0"
_SIG = b"\x89PNG\r\n\x1a\n"


def rgb_packed(png: bytes, width: int, height: int) -> bytes:
    """A greyscale 8-bit PNG ``width`` x ``height`` (filter 0 on every row) as the RGB PNG of ``width / 3`` pixels
    per row holding the same bytes: only its header changes."""
    if png[:8] != _SIG or png[12:16] != b"IHDR" or png[24:26] != b"\x08\x00" or width % 3:
        raise ValueError("not a greyscale PNG whose width is a multiple of 3")
    return _SIG + png_chunk(b"IHDR", struct.pack(">IIBBBBB", width // 3, height, 8, 2, 0, 0, 0)) + png[33:]


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """``.jxs``'s check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`), before any work: the format
    has no resolution field and is read as the GKone's 4920x2880 display."""
    if spec is not None and tuple(spec.png_size) != RESOLUTION:
        cols, rows = spec.png_size
        raise ParameterError(f"{path}: a .jxs file is for the UniFormation GKone's {RESOLUTION[0]}x{RESOLUTION[1]} "
                             f"display, not {cols}x{rows} (give --printer uniformation-gkone)")


def _num(v: float) -> str:
    """A G-code or ini number: up to 3 decimals, no trailing zeros."""
    text = f"{round(float(v), 3):.3f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _ms(seconds: float) -> int:
    return int(round(float(seconds) * 1000.0))


def _move_ms(stages: list[tuple[int, float]]) -> int:
    """The delay after a move of ``stages`` (distance µm, speed mm/min): each stage's time plus the margin, and
    the margin once more (UVtools' converter's rule)."""
    return _ms(MOVE_MARGIN_S + sum(abs(d) / 1000.0 / (v / 60.0) + MOVE_MARGIN_S for d, v in stages))


def _max_speed(settings) -> float:
    """The fastest motion speed the settings use (mm/min): the final rise's."""
    return max(float(g[k]) for g in (settings.group(True), settings.group(False))
               for k in ("lift_speed", "lift_speed2", "retract_speed", "retract_speed2"))


def program(settings, top: np.ndarray, machine_z: float) -> list[list]:
    """The ``action_list`` (module docstring) of layers whose tops are ``top`` (mm, from the plate), for a machine
    of ``machine_z`` mm of travel. Moves are whole micrometres between the layers' tops rounded to 1 µm, each
    layer's lift and retract equal, so the relative moves add up to every layer's top exactly."""
    n = top.size
    t = layer_table(settings, n)
    um = np.round(np.asarray(top, np.float64) * 1000.0).astype(np.int64)
    rise = np.diff(um, prepend=0)
    lift, lift2, back2 = (np.round(t[k] * 1000.0).astype(np.int64) for k in ("lift_height", "lift_height2",
                                                                            "retract_height2"))
    back2 = np.minimum(back2, lift + lift2)
    acts: list[list] = [["gcode", "G21"], ["gcode", "G91"], ["gcode", "M106 S0"], ["slice", "<BLANK>"],
                        ["gcode", "M17"], ["gcode", "G28 Z0"]]

    def delay(ms: int) -> None:
        if ms > 0:
            acts.append(["delay", int(ms)])

    def moves(stages: list[tuple[int, float]]) -> None:
        stages = [(int(d), float(v)) for d, v in stages if d != 0 and v > 0]
        for d, v in stages:
            acts.append(["gcode", f"G0 Z{_num(d / 1000.0)} F{_num(v)}"])
        if stages:
            delay(_move_ms(stages))

    for i in range(n):
        acts.append(["layerno", i + 1])
        acts.append(["slice", f"{{PWD}}/{i:05d}.png"])
        if lift[i] > 0:  # (as UVtools' builder: the rise in the first stage, or in the second when there is no first)
            moves([(rise[i] + lift[i], t["lift_speed"][i]), (lift2[i], t["lift_speed2"][i])])
        elif lift2[i] > 0:
            moves([(rise[i] + lift2[i], t["lift_speed2"][i])])
        if lift[i] + lift2[i] > 0:
            delay(_ms(t["wait_after_lift"][i]))
            moves([(-(lift[i] + lift2[i] - back2[i]), t["retract_speed"][i]), (-back2[i], t["retract_speed2"][i])])
        else:
            moves([(rise[i], t["lift_speed"][i])])
        delay(_ms(t["wait_before_cure"][i]))
        acts += [["gcode", f"M106 S{int(t['light_pwm'][i])}"]]
        delay(_ms(t["exposure"][i]))
        acts += [["gcode", "M106 S0"], ["slice", "<BLANK>"]]
        delay(_ms(t["wait_after_cure"][i]))
    acts += [["gcode", "M106 S0"], ["slice", "<BLANK>"]]
    last, top_um = (int(um[-1]) if n else 0), int(round(machine_z * 1000.0))
    if n and last < top_um:
        end = min(last + max(4000, int(lift[-1])), top_um)  # (a lift of at least 4 mm, then up to the top)
        moves([(end - last, t["lift_speed"][-1])])
        moves([(top_um - end, _max_speed(settings))])
    acts.append(["gcode", "M18"])
    return acts


def program_seconds(actions: list[list]) -> float:
    """The time a program's delays take (moves and waits each have one), s."""
    return sum(a[1] for a in actions if a[0] == "delay") / 1000.0


def stated_print_time(settings, n_layers: int) -> float:
    """The print time a ``.jxs`` states (``total_time``; the registry's ``print_time``, so the command line, the
    report and the checks state it too), s: the program's delays for ``n_layers`` layers less the layers' own rises
    and the final rise (a few hundredths of a second a layer, and the trip up), which depend on the layer heights
    and the machine."""
    return program_seconds(program(settings, np.zeros(n_layers), 0.0))


def _config(settings, n: int, ml: float, layer_height: float, name: str, footer: str) -> bytes:
    from .. import __version__

    s = settings
    b = s.group(True)
    rows = [("Action", "print"), ("FirstLayerTime", _ms(s.bottom_exposure)), ("LayerTime", _ms(s.exposure)),
            ("NumFade", 0), ("NumLayers", n), ("UsedMaterial", _num(ml)), ("layerHeight", _num(layer_height)),
            ("nJobName", name), ("NumBottomLayers", min(s.bottom_layers, n)), ("LiftDistance1", _num(s.lift_height)),
            ("LiftFeedrate1", _num(s.lift_speed)), ("LiftDistance2", _num(s.lift_height2)),
            ("LiftFeedrate2", _num(s.lift_speed2 if s.lift_speed2 > 0 else s.lift_speed)),
            ("BottomLiftFeedrate", _num(b["lift_speed"])),
            ("RetractFeedrate", _num(s.retract_speed)), ("ZMoveTimeCompensation", _ms(s.wait_before_cure)),
            ("ZMoveTimeCompensationBottom", _ms(b["wait_before_cure"])), ("OnLightCode", f"M106 S{s.light_pwm}"),
            ("OffLightCode", "M106 S0"), ("GcodeHeader", HEADER), ("GcodeFooter", footer),
            ("ApplicationName", f"gpuslice {__version__}")]
    return "".join(f"{k}={v}\n" for k, v in rows).encode("utf-8")


def write_jxs(layers: Iterable[Tile | RunLayer], target, *, machine_z: float) -> dict[str, Any]:
    """Write ``target.result``'s layers (tiles or runs, in order) as a ``.jxs`` archive at ``target.path``,
    atomically (module docstring); ``machine_z``: the printer's Z travel (mm). Layers are encoded on
    ``target.workers`` threads (PNGs on ``target.device`` where it has the runs) and streamed into the zip.
    Returns the layer count, ``png_bytes``, ``print_time_s`` and ``resin_ml``."""
    from .sl1 import _zip_time

    path = Path(os.fspath(target.path))
    spec, res, s = target.spec, target.result, target.settings
    n = target.layer_count()
    cols, rows = spec.png_size
    th = np.asarray(res.thickness, np.float64)
    layer_height = header_layer_height(th)  # (the program moves by each layer's own)
    top = np.cumsum(th)
    ml = resin_ml(res.area, th)
    level = target.options.png_level
    enc = PngEncoder(cols, rows, level, target.deflater)
    device = target.device if level == RUNS_LEVEL else None
    actions = program(s, top, float(machine_z))
    seconds = stated_print_time(s, n)
    footer = next((a[1] for a in reversed(actions) if a[0] == "gcode" and a[1].startswith("G0")), "")

    def encode(item: Tile | RunLayer) -> bytes:  # on a worker thread
        return rgb_packed(encode_png(item, enc), cols, rows)

    def encode_group(group: list[Tile | RunLayer]) -> list[bytes]:  # on a worker thread
        pngs = png_group(device, group, cols, rows)
        if pngs is None:
            return [encode(item) for item in group]
        return [rgb_packed(p, cols, rows) for p in pngs]

    with atomic_path(path) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as fh, \
            zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as z:
        when = _zip_time(target.now)

        def sink(k: int, data: bytes) -> None:  # (PNGs are deflated already: stored as they are)
            z.writestr(zipfile.ZipInfo(f"{k:05d}.png", when), data)

        stats = encode_all(layers, encode, sink, target.workers, progress=target.progress, many=encode_group,
                           chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{path}: expected {n} layers, got {stats['layers']}")
        for member, data in (("config.ini", _config(s, n, ml, layer_height, target.name, footer)),
                             ("control.json", json.dumps({"total_time": round(seconds, 3), "total_slices": n,
                                                          "used_material": round(ml, 4), "action_list": actions},
                                                         indent=2).encode())):
            info = zipfile.ZipInfo(member, when)
            info.compress_type = zipfile.ZIP_DEFLATED
            z.writestr(info, data)
    return {**stats, "print_time_s": seconds, "resin_ml": ml}


def write_target(layers: Iterable[Tile | RunLayer], target) -> dict[str, Any]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): a ``.jxs`` archive for the GKone."""
    refuse_settings(target.path, "jxs", target.options, target.settings, target.spec)
    preset = target.options.preset
    z_travel = float(preset.build_height) if preset is not None else float(np.sum(target.result.thickness)) + 10.0
    return write_jxs(layers, target, machine_z=z_travel)
