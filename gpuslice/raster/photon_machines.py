"""Anycubic's Photon Workshop machines (:data:`MACHINES`: the printer each file suffix names, with its display, Z
travel and file version) and what a Photon Workshop file can store of a job's print settings and display
(:func:`refuse_settings`, the registry's settings check, before any work). The writer: :mod:`gpuslice.raster.photon`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import ParameterError

__all__ = ["MACHINES", "VERSIONS", "Machine", "machine_version", "refuse_display", "refuse_settings",
           "refuse_slow_retract", "wait_s"]

VERSIONS = (1, 515, 516, 517, 518)


@dataclass(frozen=True)
class Machine:
    """An Anycubic printer of the Photon Workshop family (lengths mm): ``suffix`` of its files, ``name`` as Photon
    Workshop writes it, display ``resolution`` and ``display`` size, Z travel ``height``, file ``version``."""

    suffix: str
    name: str
    resolution: tuple[int, int]
    display: tuple[float, float]
    height: float
    version: int


_M = Machine
#: by suffix. Names as Photon Workshop 2.x writes them in MACHINE (checked on its .pwmx/.pwma/.pm3 files); displays,
#: Z and versions from UVtools (AnycubicFile.cs: display mm, machine Z, versions each suffix accepts; its PrusaSlicer
#: printer profiles: resolution, FILEVERSION), the highest version UVtools accepts for the suffix, except where a
#: lower one is known to print: .pwmb 516 (UVtools' Mono X 6K profile; photonic-etcher's files). .pm3n 517, as UVtools
#: writes it (the only version it accepts for the suffix, and its Mono 2 profile's FILEVERSION_517; 516 was taken from
#: an unmerged photonic-etcher pull request, #20, while its issue #23 reports a converted .pm3 drawn wrong on a Mono 2).
#: .pm4n: no public source names its version; 516, the family's base, assumed.
MACHINES: dict[str, Machine] = {
    m.suffix: m
    for m in (
        _M("pwmo", "Anycubic Photon Mono", (1620, 2560), (82.62, 130.56), 165.0, 516),
        _M("pwms", "Anycubic Photon Mono SE", (1620, 2560), (82.62, 130.56), 160.0, 516),
        _M("pwma", "Anycubic Photon Mono 4K", (3840, 2400), (134.4, 84.0), 165.0, 516),
        _M("pwmx", "Anycubic Photon Mono X", (3840, 2400), (192.0, 120.0), 245.0, 516),
        _M("pmsq", "Anycubic Photon Mono SQ", (2400, 2560), (120.0, 128.0), 200.0, 516),
        _M("pm3", "Anycubic Photon M3", (4096, 2560), (163.84, 102.4), 180.0, 516),
        _M("pm3m", "Anycubic Photon M3 Max", (6480, 3600), (298.08, 165.6), 300.0, 516),
        _M("pm3n", "Anycubic Photon Mono 2", (4096, 2560), (143.36, 89.6), 165.0, 517),
        _M("pm4n", "Anycubic Photon Mono 4", (9024, 5120), (153.408, 87.04), 165.0, 516),
        _M("pwmb", "Anycubic Photon Mono X 6K", (5760, 3600), (198.15, 123.84), 245.0, 516),
        _M("pmx2", "Anycubic Photon Mono X2", (4096, 2560), (196.61, 122.88), 200.0, 517),
        _M("pm3r", "Anycubic Photon M3 Premium", (7680, 4320), (218.88, 123.12), 250.0, 517),
        _M("px6s", "Anycubic Photon Mono X 6Ks", (5760, 3600), (195.84, 122.4), 200.0, 517),
        _M("pm5", "Anycubic Photon Mono M5", (11520, 5120), (218.88, 122.88), 200.0, 517),
        _M("pm5s", "Anycubic Photon Mono M5s", (11520, 5120), (218.88, 122.88), 200.0, 518),
        _M("m5sp", "Anycubic Photon Mono M5s Pro", (13312, 5120), (223.6416, 126.976), 200.0, 518),
    )
}


def wait_s(s, path: Path) -> float:
    """The one rest the format stores (before each exposure, every layer), s: the normal layers' three waits folded
    together; :class:`ParameterError` when the bottom layers' waits differ (there is nowhere to put them)."""
    waits = [sum(s.group(b)[k] for k in ("wait_before_cure", "wait_after_cure", "wait_after_lift"))
             for b in (False, True)]
    if abs(waits[0] - waits[1]) > 1e-9:
        raise ParameterError(f"{path}: Photon Workshop files rest the same before every layer; the bottom layers' "
                             f"waits ({waits[1]:g} s) cannot differ from the others' ({waits[0]:g} s)")
    return waits[0]


def machine_version(name: str, options) -> tuple[Machine, int | None]:
    """The machine a suffix names, and the file version its preset asks for (None: the machine's)."""
    if name not in MACHINES:
        raise ParameterError(f"not a Photon Workshop suffix: .{name} (use .{', .'.join(MACHINES)})")
    preset = options.preset
    if preset is not None and preset.format_version is not None and preset.native_format == name:
        return MACHINES[name], int(preset.format_version)
    return MACHINES[name], None


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """Photon Workshop's settings check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`), before any
    work: where the file carries the suffix's machine name (no preset, or one without a ``machine``), the display
    ``spec`` must be that machine's (its firmware checks it: ``.pm5s`` is the M5s's 11520x5120 of 0.019 x 0.024
    mm); one rest for every layer (:func:`wait_s`); before version 516 one lift and one retract stage (as CTB v2/v3);
    from 516 two stages, whose slow retract is the first lift stage's height, so a ``retract_height2`` other than
    ``lift_height`` (or 0) is refused rather than changed (the module docstring's stage mapping)."""
    machine, version = machine_version(name, options)
    refuse_display(path, name, machine.name, machine.resolution, machine.display, options, spec)
    refuse_light_pwm(path, options, settings, "a Photon Workshop file")
    version = machine.version if version is None else version
    wait_s(settings, Path(os.fspath(path)))
    if version < 516:
        lost = settings.two_stages_lost()
        if lost:
            raise ParameterError(f"{path}: a Photon Workshop file of version {version} has one lift and one retract "
                                 f"stage; {lost} cannot be written")
        return
    refuse_slow_retract(path, settings, "a Photon Workshop file")


def refuse_display(path, suffix: str, machine: str, resolution: tuple[int, int], display: tuple[float, float],
                   options, spec) -> None:
    """Where the file carries the suffix's ``machine`` name (no preset, or one without a ``machine``), the display
    ``spec`` must be that machine's (``resolution`` px, ``display`` mm): its firmware checks it."""
    from .spec import RasterSpec, display_text, same_display

    if spec is None or (options.preset is not None and options.preset.machine):
        return
    want = RasterSpec(resolution=tuple(resolution), pixel=display[0] / resolution[0],
                      pixel_y=display[1] / resolution[1])
    if not same_display(spec, want):
        raise ParameterError(f"{path}: a .{suffix} file is for the {machine}, whose display is {display_text(want)}, "
                             f"not the {display_text(spec)} asked (give its --printer preset, or --resolution and "
                             "--pixel/--pixel-y of that display)")


def refuse_light_pwm(path, options, settings, what: str) -> None:
    """Anycubic's files have no light-intensity field: ``--light-pwm`` or ``--bottom-light-pwm`` given (beyond the
    preset's) is refused, not dropped."""
    from .settings import changed_settings

    pwm = changed_settings(settings, ("light_pwm",), base=options.settings() if options is not None else None)
    if pwm:
        raise ParameterError(f"{path}: {what} stores no light intensity (PWM): {', '.join(pwm)} cannot be written")


def refuse_slow_retract(path, settings, what: str) -> None:
    """Anycubic's two motion stages put the slow retract on the first lift stage's height (``photon``'s EXTRA, the
    zip's ``multi_state_paras``): a ``retract_height2`` other than ``lift_height`` (or 0) is refused, not changed."""
    for bottom in (False, True):
        g = settings.group(bottom)
        if g["retract_height2"] > 0 and abs(g["retract_height2"] - g["lift_height"]) > 1e-9:
            twin = "--bottom-" if bottom else "--"
            raise ParameterError(f"{path}: {what}'s slow retract is its first lift stage ({twin}lift-height "
                                 f"{g['lift_height']:g} mm); {twin}retract-height2 {g['retract_height2']:g} cannot "
                                 "be written (give it equal, or 0)")
