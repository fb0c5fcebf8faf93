"""Run the peer slicers (Slic3r 1.3, CuraEngine 4.13) and two mesh libraries (manifold3d, trimesh) as
independent references for gpuslice's tests and benchmarks.

Conventions used by every function here:

* Units are millimetres (lengths, z) and mm^2 (areas); wall times are seconds (``time.perf_counter``).
* Feed every peer the *same* scaled STL made by :func:`write_scaled_stl`: uniformly scaled, and translated so
  that its minimum z is 0 (x, y are left as they are after scaling).  Then all z values below are heights
  above the mesh's lowest point, in the same frame for all peers.
* With a uniform layer height ``h`` and first layer height ``h``, layer ``i`` spans ``[i*h, (i+1)*h]`` and
  both Slic3r and CuraEngine cut it at its middle plane ``z_i = (i + 0.5) * h`` (checked against exact
  sections, see :func:`slic3r_layers`).  gpuslice's tests use the same mid-layer planes, so the per-layer
  areas of Slic3r, manifold3d and trimesh at ``z_i`` are directly comparable; ``sum(area_i) * h`` is the
  midpoint-rule volume.

The peers are installed by ``/work/shared/peers/setup-peers.sh`` (Debian packages ``slic3r``,
``prusa-slicer``, ``cura-engine``; Cura's printer definitions are extracted from the ``cura`` package into
``${GPUSLICE_PEERS_DIR:-~/.cache/gpuslice-peers}/cura-defs``).

Run ``python scripts/peers.py`` for a volume cross-check of all four references on the cow mesh.
"""

from __future__ import annotations

import csv
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = [
    "STL_DTYPE",
    "CuraLoop",
    "Slic3rLayer",
    "Slic3rLayers",
    "cura_definitions",
    "cura_slice",
    "find_peer",
    "load_stl",
    "manifold_from_arrays",
    "manifold_slices",
    "mid_layer_planes",
    "parse_cura_gcode",
    "parse_slic3r_svg",
    "peers_dir",
    "read_stl_triangles",
    "slic3r_layers",
    "slice_manifold",
    "trimesh_sections",
    "write_scaled_stl",
]

SETUP_HINT = "run ../shared/peers/setup-peers.sh"

# Executable names per peer; the Debian package ``cura-engine`` installs the binary ``CuraEngine``.
_PEER_EXECUTABLES = {
    "slic3r": ("slic3r",),
    "prusa-slicer": ("prusa-slicer", "PrusaSlicer"),
    "CuraEngine": ("CuraEngine", "cura-engine"),
}

# One binary STL facet record: normal, 3 vertices (float32 little endian), attribute byte count.
STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attr", "<u2")])
assert STL_DTYPE.itemsize == 50

SLIC3R_NS = "http://slic3r.org/namespaces/slic3r"
SVG_NS = "http://www.w3.org/2000/svg"
# Slic3r 1.3 writes slic3r:z as (z in mm) * SCALING_FACTOR (1e-6), i.e. 1e6 too small.
SLIC3R_Z_FACTOR = 1e6
# Slic3r clamps every layer above the first to at most the nozzle diameter (default 0.5 mm).
SLIC3R_DEFAULT_NOZZLE = 0.5


# ----------------------------------------------------------------------------------------------------------
# Locating the peers
# ----------------------------------------------------------------------------------------------------------


def find_peer(name: str) -> str | None:
    """Absolute path of a peer slicer's executable, or None if it is not on PATH.

    ``name`` is one of ``"slic3r"``, ``"prusa-slicer"``, ``"CuraEngine"`` (``"cura-engine"`` is accepted as an
    alias of ``"CuraEngine"``).  Any other name is looked up on PATH as given.
    """
    if name == "cura-engine":
        name = "CuraEngine"
    for exe in _PEER_EXECUTABLES.get(name, (name,)):
        path = shutil.which(exe)
        if path:
            return path
    return None


def peers_dir() -> Path:
    """The cache folder setup-peers.sh uses: ``$GPUSLICE_PEERS_DIR``, else ``${XDG_CACHE_HOME:-~/.cache}/
    gpuslice-peers``."""
    env = os.environ.get("GPUSLICE_PEERS_DIR")
    if env:
        return Path(env).expanduser()
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(cache).expanduser() / "gpuslice-peers"


def cura_definitions() -> Path | None:
    """Folder holding Cura's ``fdmprinter.def.json`` *and* ``fdmextruder.def.json``, or None.

    Looks in ``peers_dir() / "cura-defs"`` (where setup-peers.sh puts them; it prints that folder on its last
    stdout line), and also accepts ``$GPUSLICE_PEERS_DIR`` itself holding the files.  Does not run the setup
    script.  Both files are required: CuraEngine resolves fdmprinter's extruder train ``fdmextruder`` from the
    same folder and exits with status 2 ("Couldn't find definition file with ID: fdmextruder") without it.
    """
    candidates = [peers_dir() / "cura-defs"]
    env = os.environ.get("GPUSLICE_PEERS_DIR")
    if env:
        candidates.append(Path(env).expanduser())
    candidates.append(Path.home() / ".cache" / "gpuslice-peers" / "cura-defs")
    for folder in candidates:
        if (folder / "fdmprinter.def.json").is_file() and (folder / "fdmextruder.def.json").is_file():
            return folder
    return None


# ----------------------------------------------------------------------------------------------------------
# Binary STL in / out
# ----------------------------------------------------------------------------------------------------------


def _read_stl_records(path: str | os.PathLike) -> np.ndarray:
    data = Path(path).read_bytes()
    if len(data) < 84:
        raise ValueError(f"{path}: too short for a binary STL ({len(data)} bytes)")
    n = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    if len(data) != 84 + 50 * n:
        # A 'solid' header alone does not mean ASCII (rear_case.stl is binary with a 'solid' header); the size
        # check is what decides.
        raise ValueError(
            f"{path}: not a binary STL (size {len(data)} != 84 + 50 * {n}); ASCII STL is not supported here"
        )
    return np.frombuffer(data, dtype=STL_DTYPE, count=n, offset=84)


def read_stl_triangles(path: str | os.PathLike) -> np.ndarray:
    """Triangles of a binary STL as a float32 array of shape (n, 3, 3), in the file's own units."""
    return _read_stl_records(path)["vertices"].copy()


def load_stl(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Binary STL -> (vertices float64 (m, 3), faces int64 (n, 3)), welding bit-identical vertices only.

    Units are the file's (mm for the output of :func:`write_scaled_stl`).
    """
    tri = read_stl_triangles(path).reshape(-1, 3)
    vertices, inverse = np.unique(tri, axis=0, return_inverse=True)
    return vertices.astype(np.float64), inverse.reshape(-1, 3).astype(np.int64)


def write_scaled_stl(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    *,
    fit: float | None = None,
    scale: float | None = None,
) -> tuple[float, np.ndarray]:
    """Write a uniformly scaled copy of binary STL ``src`` to ``dst`` (binary STL), with its minimum z at 0.

    Exactly one of ``fit`` (the longest bounding-box side becomes ``fit`` mm) or ``scale`` (a positive factor
    applied to the file's coordinates) must be given.  After scaling, the mesh is translated along z only so
    that its minimum z is exactly 0; x and y are kept as they are after scaling.  Normals are unchanged (a
    positive uniform scale does not change directions); the attribute bytes are kept.  Arithmetic is float64,
    the written coordinates float32 (as STL requires).

    Returns ``(scale_used, offset)``: a point ``p`` of ``src`` lands at ``p * scale_used + offset`` in ``dst``
    (``offset`` = ``(0, 0, -scale_used * zmin)`` in mm, a float64 array of shape (3,)).
    """
    if (fit is None) == (scale is None):
        raise ValueError("give exactly one of fit= or scale=")
    rec = _read_stl_records(src)
    tri = rec["vertices"].astype(np.float64)
    if tri.size == 0:
        raise ValueError(f"{src}: empty STL")
    lo = tri.reshape(-1, 3).min(axis=0)
    hi = tri.reshape(-1, 3).max(axis=0)
    if fit is not None:
        longest = float((hi - lo).max())
        if not (fit > 0 and longest > 0):
            raise ValueError(f"cannot fit: fit={fit}, longest side={longest}")
        s = float(fit) / longest
    else:
        s = float(scale)  # type: ignore[arg-type]
        if not s > 0:
            raise ValueError(f"scale must be positive, got {scale}")
    offset = np.array([0.0, 0.0, -lo[2] * s])
    out = np.empty(len(rec), dtype=STL_DTYPE)
    out["normal"] = rec["normal"]
    out["vertices"] = (tri * s + offset).astype(np.float32)
    out["attr"] = rec["attr"]
    header = f"gpuslice peers: {Path(src).name} scaled x{s:.9g}, min z = 0".encode()[:80].ljust(80, b" ")
    with open(dst, "wb") as f:
        f.write(header)
        f.write(np.uint32(len(out)).astype("<u4").tobytes())
        f.write(out.tobytes())
    return s, offset


def mid_layer_planes(height: float, h: float) -> np.ndarray:
    """Mid-layer cutting planes ``z_i = (i + 0.5) * h`` (mm) for ``i = 0 .. round(height / h) - 1``.

    ``height`` is the mesh's z extent (min z = 0).  This is the set of planes Slic3r 1.3 cuts with first layer
    height = layer height = ``h`` (it keeps a layer while its middle plane is below the top, i.e.
    ``round(height / h)`` layers; e.g. 20 mm at 0.3 mm -> 67 layers, at 0.15 mm -> 133).  Planes at or above
    the top simply give empty sections, so for volume sums any count >= this is fine.
    """
    n = max(int(round(height / h)), 0)
    return (np.arange(n, dtype=np.float64) + 0.5) * h


# ----------------------------------------------------------------------------------------------------------
# Slic3r
# ----------------------------------------------------------------------------------------------------------


def _polygon_area(points: np.ndarray) -> float:
    """Absolute shoelace area (float64) of a closed polygon given without the repeated first point."""
    x = points[:, 0]
    y = points[:, 1]
    return abs(0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


class Slic3rLayer(NamedTuple):
    """One Slic3r layer.

    ``z``: the cutting plane in mm above the mesh's minimum z (the mid-layer plane ``(i + 0.5) * h``; Slic3r's
    ``slic3r:z`` attribute times 1e6).  ``area``: sum of contour areas minus sum of hole areas, mm^2.
    ``polygons``: ``[(kind, points), ...]`` with ``kind`` ``"contour"`` or ``"hole"`` and ``points`` a float64
    (n, 2) array in the SVG's frame, i.e. shifted in XY so that the *mesh's* bounding-box minimum is (0, 0)
    (add :attr:`Slic3rLayers.xy_origin` to get the STL's coordinates).  Contours are counter-clockwise, holes
    clockwise (y up); the first point is not repeated.
    """

    z: float
    area: float
    polygons: list[tuple[str, np.ndarray]]


class Slic3rLayers(list):
    """A list of :class:`Slic3rLayer` (bottom to top), plus run information as attributes.

    ``wall_s``: wall time of the slic3r subprocess (s).  ``xy_origin``: (2,) the STL's bounding-box minimum in
    x, y (mm) = the shift Slic3r removed.  ``h``: layer height asked for.  ``command``: the argv run.
    ``log``: slic3r's stdout + stderr.
    """

    wall_s: float
    xy_origin: np.ndarray
    h: float
    command: list[str]
    log: str


def _parse_points(text: str) -> np.ndarray:
    vals = np.array(text.replace(",", " ").split(), dtype=np.float64)
    return vals.reshape(-1, 2)


def parse_slic3r_svg(path: str | os.PathLike) -> list[Slic3rLayer]:
    """Parse a ``slic3r --export-svg`` file into layers (see :class:`Slic3rLayer`)."""
    root = ET.parse(path).getroot()
    layers: list[Slic3rLayer] = []
    for g in root.iter(f"{{{SVG_NS}}}g"):
        zattr = g.get(f"{{{SLIC3R_NS}}}z")
        if zattr is None:
            continue
        polys: list[tuple[str, np.ndarray]] = []
        area = 0.0
        for poly in g.iter(f"{{{SVG_NS}}}polygon"):
            kind = poly.get(f"{{{SLIC3R_NS}}}type", "contour")
            pts = _parse_points(poly.get("points", ""))
            if len(pts) < 3:
                continue
            a = _polygon_area(pts)
            area += -a if kind == "hole" else a
            polys.append((kind, pts))
        layers.append(Slic3rLayer(float(zattr) * SLIC3R_Z_FACTOR, area, polys))
    return layers


def slic3r_layers(stl: str | os.PathLike, h: float, *, timeout: float = 600.0) -> Slic3rLayers:
    """Slice ``stl`` with Slic3r 1.3 at layer height = first layer height = ``h`` mm; parse its SVG export.

    Runs ``slic3r --no-gui --export-svg --layer-height H --first-layer-height H -o out.svg model.stl`` in a
    temporary folder (``--nozzle-diameter H`` is added when ``h > 0.5``: Slic3r clamps layers above the first
    to the nozzle diameter, 0.5 mm by default, so h = 1 would otherwise give z = 0.5, 1.25, 1.75, ...).

    What the SVG holds (Slic3r 1.3.0, checked on real files):

    * one ``<g id="layerN" slic3r:z="...">`` per layer, bottom to top;
    * ``slic3r:z`` is the layer's *cutting plane* in mm times 1e-6 (Slic3r multiplies the unscaled z by its
      SCALING_FACTOR); the plane is the middle of the layer: for h = 0.2 the first z is 1e-07 -> 0.1 mm, then
      0.3, 0.5, ...  Areas of a cone's layers match exact sections at that z to ~1e-7 relative (the point
      coordinates are Slic3r's 1e-6 mm integers printed with 6 decimals).  z is measured from the mesh's
      minimum z (Slic3r drops the object onto z = 0).  The z values are running sums, so they carry ~1e-14 mm
      float noise (e.g. 19.9750000000002).
    * the number of layers is ``round(height / h)`` (a layer is kept while its middle is below the top);
    * each region is ``<polygon slic3r:type="contour" points="x,y x,y ..." style="fill: white"/>`` followed by
      its holes as ``<polygon slic3r:type="hole" ... style="fill: black"/>``;
    * XY is shifted so that the mesh's bounding-box minimum is (0, 0) (Slic3r aligns the mesh to the origin
      before slicing); y is not flipped.  The polygons are returned in that shifted frame; adding
      ``xy_origin`` (the STL's x, y minimum) gives STL coordinates (cow at 80 mm: every layer matches
      manifold3d's section to < 0.18 mm^2 of symmetric difference).

    Returns a :class:`Slic3rLayers` list of ``(z_mm, area_mm2, polygons)`` with ``.wall_s`` etc.
    Raises RuntimeError if slic3r is missing or fails.
    """
    exe = find_peer("slic3r")
    if exe is None:
        raise RuntimeError(f"slic3r not installed: {SETUP_HINT}")
    stl = Path(stl).resolve()
    tri = read_stl_triangles(stl).reshape(-1, 3)
    with tempfile.TemporaryDirectory(prefix="peers-slic3r-") as tmp:
        model = Path(tmp) / "model.stl"
        shutil.copyfile(stl, model)
        cmd = [exe, "--no-gui", "--export-svg", "--layer-height", f"{h:g}", "--first-layer-height", f"{h:g}"]
        if h > SLIC3R_DEFAULT_NOZZLE:
            cmd += ["--nozzle-diameter", f"{h:g}"]
        cmd += ["-o", "out.svg", "model.stl"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True, timeout=timeout)
        wall = time.perf_counter() - t0
        svg = Path(tmp) / "out.svg"
        if proc.returncode != 0 or not svg.is_file():
            raise RuntimeError(
                f"slic3r failed (rc={proc.returncode}): {' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}"
            )
        layers = Slic3rLayers(parse_slic3r_svg(svg))
    layers.wall_s = wall
    layers.xy_origin = tri.min(axis=0)[:2].astype(np.float64)
    layers.h = h
    layers.command = cmd
    layers.log = proc.stdout + proc.stderr
    return layers


# ----------------------------------------------------------------------------------------------------------
# CuraEngine
# ----------------------------------------------------------------------------------------------------------


class CuraLoop(NamedTuple):
    """One extruded path of a Cura layer: ``points`` (n, 2) float64 mm in the STL's x, y (Cura keeps them with
    machine_center_is_zero=true), ``closed`` whether last point == first point (within 1e-3 mm)."""

    points: np.ndarray
    closed: bool


_GCODE_WORD = re.compile(r"([GXYZEF])(-?\d*\.?\d+(?:[eE][-+]?\d+)?)")

# stderr lines CuraEngine 4.13 always prints with this setup: its JSON loader does not know polygon-valued
# settings of fdmprinter.def.json, and it logs the effective settings as one '[WARNING]  -s key="value" ...'
# line (that line spans several text lines because start/end gcode values contain newlines).
_CURA_BENIGN_WARNINGS = ("Unrecognized data type in JSON setting ", "-s ")


def _cura_benign(line: str) -> bool:
    rest = line.removeprefix("[WARNING]").lstrip()
    return line.startswith("[WARNING]") and rest.startswith(_CURA_BENIGN_WARNINGS)


def parse_cura_gcode(text: str) -> dict:
    """Parse CuraEngine gcode into per-layer extruded loops.

    Returns ``dict(layer_count_header, layers, z_top, loops)``: ``layers`` counts ``;LAYER:`` lines, ``z_top``
    is each layer's gcode Z at its first extruding move (the layer's *top*, mm above the mesh minimum,
    (i + 1) * h; NaN for a layer without extrusion; Cura moves to the next layer's Z before its ``;LAYER:``
    line and may z-hop on travels, so the first Z word of a layer is not it), ``loops`` a list
    per layer of :class:`CuraLoop`.  A loop is a maximal run of ``G1`` moves that extrude (have X/Y and E),
    starting at the position before the run.
    """
    layer_count_header = None
    z_tops: list[float] = []
    loops: list[list[CuraLoop]] = []
    x = y = z = 0.0
    run: list[tuple[float, float]] | None = None

    def close_run() -> None:
        nonlocal run
        if run is not None and loops and len(run) >= 2:
            pts = np.array(run, dtype=np.float64)
            closed = bool(np.hypot(*(pts[-1] - pts[0])) < 1e-3)
            loops[-1].append(CuraLoop(pts[:-1] if closed else pts, closed))
        run = None

    in_layer = False
    for line in text.splitlines():
        if line.startswith(";"):
            if line.startswith(";LAYER:"):
                close_run()
                loops.append([])
                z_tops.append(math.nan)
                in_layer = True
            elif line.startswith(";LAYER_COUNT:"):
                layer_count_header = int(line.split(":", 1)[1])
            continue
        code = line.split(";", 1)[0].strip()
        if not code or code[0] != "G":
            continue
        words = dict(_GCODE_WORD.findall(code))
        g = words.get("G")
        if g not in ("0", "1"):
            continue
        nx = float(words["X"]) if "X" in words else x
        ny = float(words["Y"]) if "Y" in words else y
        if "Z" in words:
            z = float(words["Z"])
        moves_xy = "X" in words or "Y" in words
        extrudes = g == "1" and "E" in words and moves_xy
        if extrudes:
            if in_layer and math.isnan(z_tops[-1]):
                z_tops[-1] = z
            if run is None:
                run = [(x, y)]
            run.append((nx, ny))
        elif moves_xy or "E" in words:
            close_run()
        x, y = nx, ny
    close_run()
    return {"layer_count_header": layer_count_header, "layers": len(loops), "z_top": z_tops, "loops": loops}


def cura_slice(
    stl: str | os.PathLike,
    h: float,
    *,
    threads: int | None = None,
    settings: dict[str, object] | None = None,
    timeout: float = 600.0,
) -> dict:
    """Slice ``stl`` with CuraEngine 4.13 in surface mode at layer height = initial layer height = ``h`` mm.

    Runs, in a temporary folder::

        CuraEngine slice [-m<threads>] -j DEFS/fdmprinter.def.json -s layer_height=H -s layer_height_0=H
            -s magic_mesh_surface_mode=surface -s adhesion_type=none -s machine_center_is_zero=true
            -s machine_width=1000 -s machine_depth=1000 -s machine_height=1000 [-s key=value ...]
            -l model.stl -o out.gcode

    No extruder (``-e0``) settings are needed: fdmprinter.def.json pulls in fdmextruder.def.json from the same
    folder (see :func:`cura_definitions`).  Cura keeps the STL's x, y with machine_center_is_zero=true, drops
    the mesh onto z = 0, cuts layer i at its middle (``slicing_tolerance`` = middle) and writes the layer's
    top, ``(i + 1) * h``, as gcode Z.  In surface mode each extruded loop is a slice polygon, simplified
    (meshfix_maximum_resolution 0.5 mm), so its areas are only approximate.

    ``threads`` adds ``-m<threads>`` (CuraEngine's default is used otherwise; on a 2-CPU machine ``-m8`` was
    5x slower on the cow, ``-m1`` 1.5x slower than the default).

    Returns a dict:

    * ``wall_s``: wall time of the subprocess (s), including gcode writing;
    * ``layers``: number of ``;LAYER:`` lines; ``layer_count_header``: Cura's ``;LAYER_COUNT:``;
    * ``z_top``: per-layer gcode Z (mm); ``polygons_per_layer``, ``points_per_layer``: loops and points;
    * ``open_paths``: number of extruded paths that do not close;
    * ``area_per_layer``: per layer, sum of the loops' signed shoelace areas (mm^2; Cura writes outer loops
      and holes with opposite orientation, so the sum is the net area -- up to its simplification);
    * ``loops``: per layer, the :class:`CuraLoop` list;
    * ``returncode``, ``command``, ``warnings`` (stderr ``[WARNING]``/``[ERROR]`` lines, each cut to 300
      characters), ``unexpected_warnings`` (those not in the always-present benign set).

    Raises RuntimeError if CuraEngine or its definitions are missing, or it fails.
    """
    exe = find_peer("CuraEngine")
    if exe is None:
        raise RuntimeError(f"CuraEngine not installed: {SETUP_HINT}")
    defs = cura_definitions()
    if defs is None:
        raise RuntimeError(
            f"Cura definitions (fdmprinter.def.json) not found under {peers_dir()}: {SETUP_HINT}"
        )
    stl = Path(stl).resolve()
    opts: dict[str, object] = {
        "layer_height": f"{h:g}",
        "layer_height_0": f"{h:g}",
        "magic_mesh_surface_mode": "surface",
        "adhesion_type": "none",
        "machine_center_is_zero": "true",
        "machine_width": 1000,
        "machine_depth": 1000,
        "machine_height": 1000,
    }
    opts.update(settings or {})
    with tempfile.TemporaryDirectory(prefix="peers-cura-") as tmp:
        model = Path(tmp) / "model.stl"
        shutil.copyfile(stl, model)
        cmd = [exe, "slice"]
        if threads:
            cmd.append(f"-m{int(threads)}")
        cmd += ["-j", str(defs / "fdmprinter.def.json")]
        for key, val in opts.items():
            cmd += ["-s", f"{key}={val}"]
        cmd += ["-l", "model.stl", "-o", "out.gcode"]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True, timeout=timeout)
        wall = time.perf_counter() - t0
        gcode = Path(tmp) / "out.gcode"
        text = gcode.read_text() if gcode.is_file() else ""
    warnings = [
        ln[:300] for ln in proc.stderr.splitlines() if ln.startswith("[WARNING]") or ln.startswith("[ERROR]")
    ]
    if proc.returncode != 0 or not text:
        raise RuntimeError(
            f"CuraEngine failed (rc={proc.returncode}): {' '.join(cmd)}\n" + "\n".join(warnings)
        )
    parsed = parse_cura_gcode(text)
    loops = parsed["loops"]
    areas = []
    for layer in loops:
        a = 0.0
        for lp in layer:
            if lp.closed and len(lp.points) >= 3:
                px, py = lp.points[:, 0], lp.points[:, 1]
                a += 0.5 * float(np.dot(px, np.roll(py, -1)) - np.dot(py, np.roll(px, -1)))
        areas.append(a)
    return {
        "wall_s": wall,
        "layers": parsed["layers"],
        "layer_count_header": parsed["layer_count_header"],
        "z_top": parsed["z_top"],
        "polygons_per_layer": [sum(lp.closed for lp in layer) for layer in loops],
        "points_per_layer": [sum(len(lp.points) for lp in layer) for layer in loops],
        "open_paths": sum(not lp.closed for layer in loops for lp in layer),
        "area_per_layer": areas,
        "loops": loops,
        "returncode": proc.returncode,
        "command": cmd,
        "warnings": warnings,
        "unexpected_warnings": [w for w in warnings if not _cura_benign(w)],
    }


# ----------------------------------------------------------------------------------------------------------
# manifold3d and trimesh
# ----------------------------------------------------------------------------------------------------------


def _welded(vertices: np.ndarray, faces: np.ndarray):
    import trimesh

    # process=True merges duplicate vertices (and drops NaN/inf); validate=False keeps every face.
    return trimesh.Trimesh(
        vertices=np.asarray(vertices, dtype=np.float64), faces=np.asarray(faces), process=True
    )


def manifold_from_arrays(vertices: np.ndarray, faces: np.ndarray, *, weld: bool = True):
    """Build a ``manifold3d.Manifold`` from vertices (m, 3) mm and faces (n, 3).

    manifold3d needs a closed, welded (edge-manifold) mesh; with ``weld=True`` duplicate vertices are merged
    with trimesh first (time that step separately by passing ``weld=False`` with already welded arrays).
    Uses float64 ``Mesh64`` when available.  Raises ValueError if manifold3d rejects the mesh (its status is
    in the message).
    """
    import manifold3d

    if weld:
        tm = _welded(vertices, faces)
        vertices, faces = tm.vertices, tm.faces
    tri = np.ascontiguousarray(faces, dtype=np.uint32)
    mesh_cls = getattr(manifold3d, "Mesh64", None)
    if mesh_cls is not None:
        mesh = mesh_cls(vert_properties=np.ascontiguousarray(vertices, dtype=np.float64), tri_verts=tri)
    else:
        mesh = manifold3d.Mesh(
            vert_properties=np.ascontiguousarray(vertices, dtype=np.float32), tri_verts=tri
        )
    m = manifold3d.Manifold(mesh)
    status = m.status()
    if status != manifold3d.Error.NoError:
        raise ValueError(f"manifold3d rejected the mesh: {status}")
    return m


def slice_manifold(m, zs) -> list[tuple[float, int]]:
    """``(area mm^2, number of points)`` of ``m.slice(z)`` for each z (mm) in ``zs``.

    The point count includes every mesh edge the plane crosses, collinear ones too (manifold3d does not
    simplify): a cube triangulated with one diagonal per side face gives 8 points per section, not 4.
    """
    out = []
    for z in np.asarray(zs, dtype=np.float64):
        cs = m.slice(float(z))
        out.append((float(cs.area()), int(sum(len(p) for p in cs.to_polygons()))))
    return out


def manifold_slices(vertices: np.ndarray, faces: np.ndarray, zs) -> list[tuple[float, int]]:
    """Sections of a mesh at planes ``zs`` (mm, same frame as ``vertices``) by manifold3d.

    Welds with trimesh, builds the Manifold (:func:`manifold_from_arrays`) and returns per z ``(area mm^2,
    n_points)`` (net area: holes subtracted; points summed over all polygons of ``to_polygons()``).
    """
    return slice_manifold(manifold_from_arrays(vertices, faces), zs)


def trimesh_sections(vertices: np.ndarray, faces: np.ndarray, zs, *, loop_holes: bool = False) -> list[float]:
    """Net section area (mm^2) at each plane ``z`` in ``zs`` (mm, same frame as ``vertices``) by trimesh's
    ``section_multiplane``; the mesh is welded first (``process=True``); planes that miss the mesh give 0.

    By default this is trimesh's own ``Path2D.area``: the closed loops' *exteriors* nested even-odd (outer,
    hole, island, ...).  Where a section loop touches itself (the cow has 82 self-intersecting facets),
    trimesh's loop repair turns the pinched-off pockets into interiors of that loop's polygon and
    ``Path2D.area`` ignores them, so it reads high there: cow at 80 mm, z = 12.3 mm: 1699.35 mm^2 vs 1684.81
    from manifold3d and Slic3r.  ``loop_holes=True`` keeps those interiors (even-odd area of the full
    ``polygons_closed``), which agrees with manifold3d on the cow.

    ``Path2D.area`` needs the optional ``rtree`` package as soon as a section has two or more loops; without
    it the same even-odd nesting of the loops' exteriors is computed here with shapely (same result).
    """
    tm = _welded(vertices, faces)
    zs = np.asarray(zs, dtype=np.float64)
    paths = tm.section_multiplane(plane_origin=[0.0, 0.0, 0.0], plane_normal=[0.0, 0.0, 1.0], heights=zs)
    return [_path2d_area(p, loop_holes) for p in paths]


def _even_odd_area(polys) -> float:
    import shapely

    polys = [p for p in polys if p is not None and not p.is_empty]
    if not polys:
        return 0.0
    region = polys[0]
    for p in polys[1:]:
        region = shapely.symmetric_difference(region, p)
    return float(region.area)


def _path2d_area(path, loop_holes: bool) -> float:
    if path is None:
        return 0.0
    if loop_holes:
        return _even_odd_area(path.polygons_closed)
    try:
        return float(path.area)
    except ImportError:  # rtree missing
        import shapely

        return _even_odd_area([shapely.Polygon(p.exterior) for p in path.polygons_closed if p is not None])


# ----------------------------------------------------------------------------------------------------------
# Cross-check
# ----------------------------------------------------------------------------------------------------------


def _catalog_row(mesh: Path) -> dict | None:
    cat = mesh.parent / "catalog.csv"
    if not cat.is_file():
        return None
    with open(cat, newline="") as f:
        for row in csv.DictReader(f):
            if row.get("file") == mesh.name:
                return row
    return None


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(
        description="Cross-check the peer references on one mesh (volume via sum(area)*h)."
    )
    ap.add_argument("--mesh", default="/work/shared/meshes/cow.stl")
    ap.add_argument("--fit", type=float, default=80.0, help="longest bbox side, mm")
    ap.add_argument("--h", type=float, default=0.2, help="layer height, mm")
    args = ap.parse_args(argv)

    mesh = Path(args.mesh)
    h = args.h
    row = _catalog_row(mesh)
    with tempfile.TemporaryDirectory(prefix="peers-main-") as tmp:
        stl = Path(tmp) / f"{mesh.stem}_{args.fit:g}mm.stl"
        s, offset = write_scaled_stl(mesh, stl, fit=args.fit)
        vertices, faces = load_stl(stl)
        height = float(vertices[:, 2].max())
        zs = mid_layer_planes(height, h)
        print(
            f"{mesh.name}: scale {s:.6g} (longest side {args.fit:g} mm), offset {offset.tolist()}, "
            f"height {height:.4f} mm, h {h:g} mm, {len(zs)} mid-layer planes"
        )
        results: dict[str, float] = {}
        if row and row.get("volume"):
            ref = float(row["volume"]) * s**3
            results["catalog"] = ref
            print(f"catalog volume {row['volume']} x scale^3 = {ref:.3f} mm^3")
        else:
            ref = None

        if find_peer("slic3r"):
            sl = slic3r_layers(stl, h)
            z = np.array([L.z for L in sl])
            vol = sum(L.area for L in sl) * h
            results["slic3r"] = vol
            dz = np.abs(z - zs[: len(z)]).max() if len(z) <= len(zs) else math.nan
            print(
                f"slic3r   : {sl.wall_s:.3f} s, {len(sl)} layers, z {z.min():.4f} .. {z.max():.4f} mm "
                f"(max |z - (i+0.5)h| = {dz:.2e}), xy origin {sl.xy_origin.round(4).tolist()}, "
                f"sum(area)*h = {vol:.3f} mm^3"
            )
        else:
            print(f"slic3r   : not installed ({SETUP_HINT})")

        if find_peer("CuraEngine") and cura_definitions():
            cu = cura_slice(stl, h)
            vol = sum(cu["area_per_layer"]) * h
            results["cura (simplified loops)"] = vol
            print(
                f"CuraEngine: {cu['wall_s']:.3f} s, {cu['layers']} layers "
                f"(;LAYER_COUNT {cu['layer_count_header']}), "
                f"{sum(cu['polygons_per_layer'])} loops, {cu['open_paths']} open paths, "
                f"sum(area)*h = {vol:.3f} mm^3, unexpected warnings: {len(cu['unexpected_warnings'])}"
            )
            for w in cu["unexpected_warnings"][:5]:
                print("    ", w[:200])
        else:
            print(f"CuraEngine: not installed or no definitions ({SETUP_HINT})")

        t0 = time.perf_counter()
        man = manifold_from_arrays(vertices, faces)
        t1 = time.perf_counter()
        ms = slice_manifold(man, zs)
        t2 = time.perf_counter()
        vol = sum(a for a, _ in ms) * h
        results["manifold3d"] = vol
        print(
            f"manifold3d: build {t1 - t0:.3f} s, {len(zs)} slices {t2 - t1:.3f} s, "
            f"{sum(n for _, n in ms)} points, sum(area)*h = {vol:.3f} mm^3 (mesh volume {man.volume():.3f})"
        )

        t0 = time.perf_counter()
        ta = trimesh_sections(vertices, faces, zs)
        t1 = time.perf_counter()
        vol = sum(ta) * h
        results["trimesh"] = vol
        vol2 = sum(trimesh_sections(vertices, faces, zs, loop_holes=True)) * h
        results["trimesh (loop_holes)"] = vol2
        print(
            f"trimesh   : {t1 - t0:.3f} s, sum(area)*h = {vol:.3f} mm^3 (Path2D.area), "
            f"{vol2:.3f} mm^3 (loop_holes=True)"
        )

    if ref:
        worst = 0.0
        for name, vol in results.items():
            rel = (vol - ref) / ref
            if name != "catalog":
                worst = max(worst, abs(rel))
            print(f"  {name:24s} {vol:12.3f} mm^3  {100 * rel:+.3f} %")
        print(
            f"worst deviation from catalog: {100 * worst:.3f} %  ({'OK' if worst <= 0.005 else 'over 0.5 %'})"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
