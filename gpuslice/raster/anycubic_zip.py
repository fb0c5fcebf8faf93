"""Anycubic's zip archives, the M7 generation's container: ``.pm7`` (Photon Mono M7), ``.pm7m`` (M7 Max) and
``.pwsz`` (M7 Pro).

Facts (member names, JSON keys, the two binaries' layouts) from public readers and writers, gathered in
``docs/research/ANYCUBIC-ZIP.md``: UVtools' ``AnycubicZipFile.cs`` and OpenVat's notes on Photon Workshop 4.2's own
files; our code. Unlike the Photon Workshop binary (:mod:`gpuslice.raster.photon`) this is a plain zip, every member
deflated (as Photon Workshop and UVtools write it), nothing signed or checksummed beyond the zip's CRCs:

* ``layer_images/layer_<i>.pw0Img`` (i from 0, no padding): each layer as PW0, the 4-bit run-length code of the
  binary format over the whole display (:func:`gpuslice.raster.photon.encode_pw0_batch`, on the device with the
  runs): grey g is stored as ``g >> 4`` and read back as ``17·(g >> 4)``; exact at ``--gamma 0``. Photon Workshop
  also has a vector layer (``.pwszImg``) for jobs without anti-aliasing; UVtools writes PW0 for every job, and so do
  we.
* ``anycubic_photon_resins.pwsp`` (JSON): the machine (name, suffix, resolution, pixel pitch µm in x and y, display
  and Z travel mm, anti-aliasing level: 1 when no layer holds a grey between black and white, else 16) and one resin
  whose ``slicepara`` / ``slice_extpara`` hold the print settings: bottom and normal exposures, bottom and transition
  layer counts, the three waits of the bottom and of the normal layers (before the cure, after it, after the lift:
  this format keeps each, unlike the binary's one rest), layer height, lift total and speeds (mm/s), and the two
  motion stages (``multi_state_paras``: height, lift and retract speed each, placed as the binary's EXTRA table:
  stage 0 = (``lift_height``, ``lift_speed``, the slow retract ``retract_speed2``, or ``retract_speed`` when
  ``retract_height2`` is 0), stage 1 = (``lift_height2``, ``lift_speed2``, ``retract_speed``), used when either
  second stage is set); the per-layer-settings switch (``use_indivi_layerpara``) is ``per_layer_settings``, off by
  default, and on whenever the layers' thicknesses vary (:func:`~gpuslice.raster.settings.per_layer_mode`).
* ``layers_controller.conf`` (JSON): per layer its exposure (with the transition ramp), index, bottom Z, thickness,
  lift total and first-stage speed. Readers take the layers' heights from here.
* ``print_info.json``, ``software_info.conf``, ``lcd_function.json`` (JSON): print time (s), resin volume (ml) and
  mass (g); the writing program; no Anycubic-side processing.
* ``preview_images/preview_0.png`` … ``_2.png``: the top view at 224×168, 336×252 and 800×600 (RGBA).
* ``scene.slice`` (binary, little endian): ``ANYCUBIC-PWSZ``, the program, the layer count and the part's box (mm
  from the display's centre), then 64 bytes a layer: top Z, area mm², its box, its polygon count and largest
  polygon's area. ``calc_layer_volumes.data`` (binary): the resin volume (mm³) of slabs of about 0.2 mm, which
  Photon Workshop's estimates read.

Members are written in this order: the layers as they are encoded (streamed to disk), then everything that sums
over them. Mirroring is the display's (``--mirror-x``; the M7 profiles mirror X, as for the binary format); nothing
is turned (OpenVat reports Photon Workshop turning the M7 Max's images by 180°, which UVtools does not do; unverified
on a printer). A preset (``--printer``) gives the machine name and Z travel; without one the suffix's machine is
written and the job's display must be its (:func:`refuse_settings`). **Unverified on a printer**: no M7-series
printer or Photon Workshop-written file was available; the layout is what two independent readers agree on.
"""

from __future__ import annotations

import io
import json
import os
import platform
import struct
import zipfile
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ParameterError
from ..io.atomic import WRITE_BUFFER, atomic_path
from .coverage import Tile
from .layers import RunLayer, pixel_runs, run_groups
from .photon import _stages, encode_pw0_batch, encode_pw0_runs
from .png import encode_all
from .settings import header_layer_height, layer_table, median, per_layer_mode, print_time_s, ramp_layers, resin_ml

__all__ = ["ZIP_MACHINES", "ZipMachine", "refuse_settings", "write_anycubic_zip", "write_target", "PREVIEWS",
           "SCENE_MAGIC", "VOLUMES_MAGIC"]

#: the three previews' sizes (width, height), ``preview_0.png`` … ``preview_2.png``
PREVIEWS = ((224, 168), (336, 252), (800, 600))
SCENE_MAGIC = b"ANYCUBIC-PWSZ"
SCENE_VERSION = 1  # (UVtools writes 1; OpenVat reports 3 from Photon Workshop 4.2)
VOLUMES_MAGIC = 0x20251024
VOLUME_SLAB_MM = 0.2
SCENE_LAYER = np.dtype([("z", "<f4"), ("area", "<f4"), ("box", "<f4", 4), ("objects", "<u4"), ("largest", "<f4"),
                        ("padding", "<u4", 8)])
VOLUME_ENTRY = np.dtype([("layer", "<u4"), ("z", "<f4"), ("thickness", "<f4"), ("padding", "<u4", 8),
                         ("volume", "<f4")])

#: the resin's default cure-depth curve: (temperature °C, x coefficient, y compensation), as UVtools writes it
PENETRATION = ((10, 184.27, 1675.8), (25, 197.78, 1803.2), (35, 161.19, 1417.3), (45, 167.31, 1480.9),
               (55, 166.76, 1474.1))
#: the motion model the firmware's own print-time estimate reads (``firmware_calc_print_time`` = 1), UVtools' values
FIRMWARE_TIME = {
    "version": "2", "MACHINE_AXIS_STEPS_PER_UNIT": [100, 100, 3200, 94], "MACHINE_BLOCK_BUFFER_SIZE": 32,
    "MACHINE_DEFAULT_ACCELERATION": 1000, "MACHINE_DEFAULT_MINSEGMENTTIME": 20000, "MACHINE_DEFAULT_XYJERK": 20,
    "MACHINE_DEFAULT_ZJERK": 0.2, "MACHINE_GENERATE_FRAME_TIME": 450,
    "MACHINE_MAX_ACCELERATION": [1000, 1000, 160, 1000], "MACHINE_MAX_FEEDRATE": [200, 200, 20, 45],
    "MACHINE_MAX_STEP_FREQUENCY": 256000,
    "MACHINE_MINIMUM_PLANNER_SPEED": 0.5, "MACHINE_NOR_LAYER_DOWN_HEIGHT_DIV": 0.25,
    "MACHINE_NOR_LAYER_DOWN_SPEED_DIV": 0.5, "MACHINE_NOR_LAYER_UP_HEIGHT_DIV": 0.25,
    "MACHINE_NOR_LAYER_UP_SPEED_DIV": 0.5, "MACHINE_STEP_MUL": 1, "MACHINE_TIME_COMPENSATE": 0,
    "MACHINE_TIM_PRES": 30, "MACHINE_TIM_RCC_CLK": 60, "FUNCTION": 1, "MACHINE_MODE_ACCELERATION": [0, 0, 0, 0],
    "LAYER_COMPENSATE": [0, 0, 0, 0], "HEIGHT_COMPENSATE": [0, 0, 0, 0], "TIMES_COMPENSATE": [0, 0, 0, 0]}
FIRMWARE_EXPOSURE = {"precision_range_branch": [0, 5, 25], "precision_per_volume": 5,
                     "precision_coeff_value": [0.024, 0.010, -0.2], "energy_coeff": 0, "machine_exposure_ton": 0.4}


@dataclass(frozen=True)
class ZipMachine:
    """An Anycubic printer of the zip family (lengths mm): ``suffix`` of its files, ``name`` as written, display
    ``resolution`` (columns, rows) and ``display`` size, Z travel ``height``."""

    suffix: str
    name: str
    resolution: tuple[int, int]
    display: tuple[float, float]
    height: float


#: by suffix; displays and Z from UVtools' Machine.cs and its PrusaSlicer profiles (docs/research/ANYCUBIC-ZIP.md)
ZIP_MACHINES: dict[str, ZipMachine] = {
    m.suffix: m
    for m in (
        ZipMachine("pm7", "Anycubic Photon Mono M7", (13312, 5120), (223.6416, 126.976), 230.0),
        ZipMachine("pm7m", "Anycubic Photon Mono M7 Max", (6480, 3600), (298.08, 165.6), 300.0),
        ZipMachine("pwsz", "Anycubic Photon Mono M7 Pro", (13312, 5120), (223.6416, 126.976), 230.0),
    )
}


def refuse_settings(path, name: str, options, settings, spec=None) -> None:
    """The registry's settings check (:meth:`gpuslice.raster.outputs.ResinFormat.check_settings`), before any work:
    where the archive carries the suffix's machine name (no preset, or one without a ``machine``), the display
    ``spec`` must be that machine's; the slow retract is the first lift stage (the module docstring), so a
    ``retract_height2`` other than ``lift_height`` (or 0) is refused rather than changed; it has no light-intensity
    field, so a PWM other than 255 is refused."""
    from .photon_machines import refuse_display, refuse_light_pwm, refuse_slow_retract

    machine = ZIP_MACHINES[name]
    refuse_display(path, name, machine.name, machine.resolution, machine.display, options, spec)
    refuse_light_pwm(path, options, settings, "an Anycubic zip archive")
    refuse_slow_retract(path, settings, "an Anycubic zip archive")


def _json(obj: Any) -> bytes:
    return (json.dumps(obj, indent=2, ensure_ascii=False) + "\n").encode("utf-8")


def _r(v: float, digits: int = 3) -> float:
    return round(float(v), digits)


def _stage(height: float, up: float, down: float) -> dict[str, float]:
    return {"height": _r(height), "up_speed": _r(up), "down_speed": _r(down)}


def _resin(s, layer_height: float, aa: int, density: float, per_layer: bool) -> dict[str, Any]:
    """The one resin of the archive, holding the print settings (speeds mm/s; ``per_layer``: the per-layer switch,
    :func:`~gpuslice.raster.settings.per_layer_mode`)."""
    two_b, bottom = _stages(s, True)
    two_n, normal = _stages(s, False)
    b = s.group(True)
    return {
        "version": "2",
        "property": {"version": "3", "code": "10", "currency": "", "price": 0, "type": "Standard resin",
                     "volume": 1000, "subfunc_code": 0, "density": _r(density), "target_temperature": 25,
                     "brand_name": "", "resin_name": "", "film_name": "", "setting_name": "gpuslice",
                     "name": "default_resin"},
        "depth_penetration_curve": {
            "zthick_min": 0.01, "zthick_max": 0.2, "light_intensity": 9000, "safety_coefficient": 1.6,
            "current_tempcurve_selector": 0,
            "temperature_coefficients": [{"temperature": t, "x_coefficient": x, "y_compensation": y}
                                         for t, x, y in PENETRATION]},
        "slice_extpara": {
            "version": "3", "multi_state_used": int(two_b or two_n),
            "transition_layercount": ramp_layers(s), "transition_type": 0,
            "multi_state_paras": {"bott_0": _stage(*bottom[:3]), "bott_1": _stage(*bottom[3:]),
                                  "normal_0": _stage(*normal[:3]), "normal_1": _stage(*normal[3:])},
            "exposure_compensate": 0, "intelli_mode": 0, "max_acceleration": 2.0,
            "separate_support_exposure_delayed": 0, "material_scale_coeffs": [], "material_scale_coeffs_mode": 0,
            "material_scale_xyz": {"x": 1, "y": 1, "z": 1}},
        "slicepara": {
            "anti_count": aa, "blur_level": 0, "bott_layers": int(s.bottom_layers),
            "bott_off_time": _r(b["wait_before_cure"], 2), "bott_time": _r(s.bottom_exposure, 2),
            "bott_time_dual": _r(s.bottom_exposure, 2), "bott_wait_before_lift": _r(b["wait_after_cure"], 2),
            "exposure_time": _r(s.exposure, 2), "wait_before_lift": _r(s.wait_after_cure, 2), "gray_level": 0,
            "off_time": _r(s.wait_before_cure, 2), "use_indivi_layerpara": float(per_layer),
            "use_random_erode": 0, "zthick": _r(layer_height, 4), "zup_height": _r(s.lift_height + s.lift_height2),
            "zup_speed": _r(s.lift_speed / 60), "zdown_speed": _r(s.retract_speed / 60),
            "bott_wait_after_lift": _r(b["wait_after_lift"], 2), "wait_after_lift": _r(s.wait_after_lift, 2)},
    }


def _pwsp(machine: ZipMachine, suffix: str, name: str, spec, z_travel: float, resin: dict, aa: int) -> dict:
    cols, rows = spec.png_size
    pw, ph = (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)
    mtype = {
        "version": "3", "name": name, "key_suffix": suffix, "key_image_format": "pw0Img", "res_x": cols,
        "res_y": rows, "xy_pixel": _r(pw * 1000), "xy_pixel_y": _r(ph * 1000), "rotate_z": 0, "max_samples": 16,
        "property": 119, "print_xsize": _r(cols * pw), "print_ysize": _r(rows * ph), "print_zsize": _r(z_travel),
        "max_file_version": 518, "prev_back_color": [0, 0.28, 0.39], "prev_model_color": [0.8, 0.8, 0.8],
        "prev_supports_color": [0.07, 0.93, 0.93], "prev_image_size": list(PREVIEWS[0]),
        "child_screen": [{"x": 0, "y": 0, "width": cols, "height": rows}],
        "prev2_back_color": [0.08, 0.11, 0.16], "prev2_image_size": list(PREVIEWS[1]),
        "raster_segments_capacity": 0, "raster_antialiasing": aa, "cloudprev_back_color": [0, 0.28, 0.39],
        "cloudprev_imag_size": list(PREVIEWS[2]), "print_platform_zheights": [0]}
    extern = {"version": "3", "alias": name, "picture": name.replace(" ", "") + ".png", "cloud_property": 0,
              "device_cn_code": "", "factory_resins": [resin], "user_resins": [resin],
              "active_resins": ["default_resin"], "firmware_calc_print_time": 1,
              "firmware_calc_print_time_paras": FIRMWARE_TIME, "firmware_calc_exp_time_paras": FIRMWARE_EXPOSURE}
    return {"version": "3", "machine_type": mtype, "machine_extern": extern}


def _scene(box_mm: np.ndarray, z_top: np.ndarray, area: np.ndarray, objects: np.ndarray, largest: np.ndarray,
           height: float) -> bytes:
    """``scene.slice``: the header, one 64-byte record a layer, the closing mark (module docstring)."""
    from .. import __version__

    n = z_top.size
    lit = box_mm[:, 0] <= box_mm[:, 2]
    part = (box_mm[lit, 0].min(), box_mm[lit, 1].min(), box_mm[lit, 2].max(), box_mm[lit, 3].max()) if lit.any() \
        else (0.0, 0.0, 0.0, 0.0)
    head = SCENE_MAGIC.ljust(16, b"\0") + f"gpuslice {__version__}".encode()[:63].ljust(64, b"\0")
    head += struct.pack("<4IfI6fI", 3, SCENE_VERSION, 0, 0, 1.0, n, part[0], part[1], 0.0, part[2], part[3], height, 0)
    head += bytes(256) + b"<---" + struct.pack("<I", n)
    rec = np.zeros(n, SCENE_LAYER)
    rec["z"], rec["area"], rec["objects"], rec["largest"] = z_top, np.round(area, 4), objects, largest
    rec["box"] = np.where(lit[:, None], box_mm, 0.0)
    return head + rec.tobytes() + b"--->"


def _volumes(thickness: np.ndarray, area: np.ndarray) -> bytes:
    """``calc_layer_volumes.data``: the resin volume (mm³) of each slab of about :data:`VOLUME_SLAB_MM`."""
    n = thickness.size
    layer_height = median(thickness) if n else VOLUME_SLAB_MM
    per = max(1, round(VOLUME_SLAB_MM / layer_height)) if layer_height > 0 else 1
    starts = np.arange(0, n, per)
    z = np.concatenate([[0.0], np.cumsum(thickness)])
    out = np.zeros(starts.size, VOLUME_ENTRY)
    out["layer"], out["z"], out["thickness"] = starts, z[starts], thickness[starts] if n else 0.0
    if n:
        out["volume"] = np.add.reduceat(area * thickness, starts)
    return struct.pack("<IfII", VOLUMES_MAGIC, VOLUME_SLAB_MM, 1, starts.size) + out.tobytes()


def write_anycubic_zip(layers: Iterable[Tile | RunLayer], target, *, machine: ZipMachine, suffix: str,
                       name: str | None = None, z_travel: float | None = None) -> dict[str, Any]:
    """Write ``target.result``'s layers (tiles or runs, in order) as an Anycubic zip archive of ``machine`` at
    ``target.path``, atomically (module docstring); ``suffix`` its key (``pm7``, ``pm7m``, ``pwsz``), ``name`` and
    ``z_travel`` (mm) override the machine's. Layers are encoded and deflated on ``target.workers`` threads and
    streamed into the zip; the members that sum over them follow. Returns the layer count, ``png_bytes`` (the
    layers' PW0 bytes before deflate), ``machine``, ``antialiasing`` and ``print_time_s``."""
    from .. import __version__
    from .nanodlp import polygon_areas
    from .sl1 import _Thumb, _write_deflated, _zip_time

    path = Path(os.fspath(target.path))
    spec, res, s = target.spec, target.result, target.settings
    n = res.n_layers
    cols, rows = spec.png_size
    pw, ph = (spec.py, spec.px) if spec.portrait else (spec.px, spec.py)
    n_pixels = cols * rows
    name = name or machine.name
    th = np.asarray(res.thickness, np.float64)
    area = np.asarray(res.area, np.float64)
    layer_height = header_layer_height(th)
    table = layer_table(s, n)
    boxes = np.full((n, 4), -1, np.int64)
    greys = False
    thumb = _Thumb(spec, n)
    device = target.device

    def finish(data: bytes, mid: bool, box) -> tuple:  # on a worker: the member's deflate stream too
        c = zlib.compressobj(1, zlib.DEFLATED, -15)
        return data, c.compress(data) + c.flush(), mid, box

    def encode(item: Tile | RunLayer) -> tuple:
        start, length, grey = pixel_runs(item, cols)
        data, _, mid, box = encode_pw0_batch(start, length, grey, np.array([0, start.size]), n_pixels, cols)
        return finish(data[0], bool(mid[0]), tuple(int(v) for v in box[0]))

    def encode_group(group: list[Tile | RunLayer]) -> list:
        if not isinstance(group[0], RunLayer):
            return [encode(item) for item in group]
        data, _, mid, box = encode_pw0_runs(group[0].runs, group[0].j, group[-1].j + 1, cols, n_pixels, device)
        return [finish(d, bool(m), tuple(int(v) for v in b)) for d, m, b in zip(data, mid, box, strict=True)]

    with atomic_path(path) as tmp, open(tmp, "wb", buffering=WRITE_BUFFER) as fh, \
            zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as z:
        stamp = _zip_time(target.now)

        def entry(member: str) -> zipfile.ZipInfo:
            zi = zipfile.ZipInfo(member, stamp)
            zi.compress_type = zipfile.ZIP_DEFLATED
            return zi

        def put(member: str, data: bytes) -> None:
            z.writestr(entry(member), data, compresslevel=6)

        def sink(k: int, item: tuple) -> None:
            nonlocal greys
            data, deflated, mid, box = item
            _write_deflated(z, entry(f"layer_images/layer_{k}.pw0Img"), data, deflated)
            boxes[k] = box
            greys |= mid

        stats = encode_all(layers, encode, sink, target.workers, on_tile=thumb.add, progress=target.progress,
                           many=encode_group, chunk=run_groups)
        if stats["layers"] != n:
            raise ParameterError(f"{path}: expected {n} layers, got {stats['layers']}")
        aa = 16 if greys else 1
        seconds = print_time_s(s, n)
        ml = resin_ml(area, th)
        resin = _resin(s, layer_height, aa, s.resin_density, per_layer_mode(s, th))
        put("anycubic_photon_resins.pwsp", _json(_pwsp(machine, suffix, name, spec,
                                                        machine.height if z_travel is None else z_travel, resin, aa)))
        put("print_info.json", _json({
            "model_layers_count": n, "cost": 0, "currency": "", "print_time": round(seconds, 2),
            "volume": _r(ml), "weight": _r(ml * s.resin_density),
            "sub_estimated_infos": [{"model_layers_count": n, "estimated_cost": 0, "estimated_cost_currency": "",
                                     "estimated_time": round(seconds, 2), "estimated_volume": _r(ml),
                                     "estimated_weight": _r(ml * s.resin_density)}]}))
        put("software_info.conf", _json({"mark": "gpuslice", "opengl": "", "os": platform.system().lower(),
                                         "Version": __version__}))
        for i, size in enumerate(PREVIEWS):
            buf = io.BytesIO()
            thumb.image(size).convert("RGBA").save(buf, format="PNG")
            put(f"preview_images/preview_{i}.png", buf.getvalue())
        bottom = np.concatenate([[0.0], np.cumsum(th)])[:n]
        put("layers_controller.conf", _json({"count": n, "paras": [
            {"exposure_time": _r(table["exposure"][i], 2), "layer_index": i, "layer_minheight": _r(bottom[i], 4),
             "layer_thickness": _r(th[i], 4), "zup_height": _r(table["lift_height"][i] + table["lift_height2"][i]),
             "zup_speed": _r(table["lift_speed"][i] / 60)} for i in range(n)]}))
        put("lcd_function.json", _json({
            "models_processed_info": {"models": [{"auto_support": 0, "hollow": 0, "makeronline_sourceid": -1,
                                                  "manual_support": 0, "name": target.name, "punch": 0,
                                                  "source_from": 0}],
                                      "scene_models_from": 0, "slice_paras_process": 0,
                                      "software_version": f"gpuslice {__version__}"},
            "rerf_function": {"enable": False, "model_name": "", "model_type": 1, "partition_exposure_array": [],
                              "partition_num": 0}}))
        put("calc_layer_volumes.data", _volumes(th, area))
        # the layers' lit boxes in mm from the display's centre, x right and y down the image (as MODEL's in .pwmx)
        lit = boxes[:, 0] >= 0
        box_mm = np.zeros((n, 4))
        box_mm[:, 0] = boxes[:, 1] * pw - cols * pw / 2
        box_mm[:, 1] = boxes[:, 0] * ph - rows * ph / 2
        box_mm[:, 2] = (boxes[:, 3] + 1) * pw - cols * pw / 2
        box_mm[:, 3] = (boxes[:, 2] + 1) * ph - rows * ph / 2
        box_mm[~lit] = (1.0, 1.0, 0.0, 0.0)  # (empty: min above max)
        poly_layer, poly_area = polygon_areas(res)
        objects = np.bincount(poly_layer, minlength=n)[:n].astype(np.uint32)
        largest = np.zeros(n)
        if poly_layer.size:
            np.maximum.at(largest, poly_layer, poly_area)
        put("scene.slice", _scene(box_mm, np.cumsum(th), area, objects, largest, float(th.sum())))
    return {**stats, "machine": name, "antialiasing": aa, "print_time_s": seconds}


def write_target(layers: Iterable[Tile | RunLayer], target) -> dict[str, Any]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): the format's name (``target.format``), else the suffix
    of ``target.path``, picks the machine (:data:`ZIP_MACHINES`); a printer preset gives its name and Z travel."""
    path = Path(os.fspath(target.path))
    suffix = target.format if target.format is not None else path.suffix.lower().lstrip(".")
    if suffix not in ZIP_MACHINES:
        raise ParameterError(f"{path}: not an Anycubic zip suffix (use .{', .'.join(ZIP_MACHINES)})")
    refuse_settings(path, suffix, target.options, target.settings)  # (the display: checked by the job, up front)
    preset = target.options.preset
    name = z_travel = None
    if preset is not None:
        name = preset.machine or None
        z_travel = float(preset.build_height) if preset.build_height > 0 else None
    return write_anycubic_zip(layers, target, machine=ZIP_MACHINES[suffix], suffix=suffix, name=name,
                              z_travel=z_travel)
