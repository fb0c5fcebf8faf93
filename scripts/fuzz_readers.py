"""Fuzz gpuslice's own mesh readers (OBJ, PLY, OFF, 3MF): exact round trips of random meshes, and mutated files.

Each case takes the next format (obj, ply-ascii, ply-le, ply-be, off, 3mf) and is, half the time each:

1. a round trip: a random mesh (3..2000 vertices, magnitudes 1e-250..1e15, negative, integer, repeated; triangles,
   some degenerate, and simple planar polygons of 4..13 vertices in random or axis-aligned planes: convex, star-shaped
   concave, rectilinear with a point mid-edge) written by this script's writers in a random valid layout (OBJ: v,
   v/vt, v/vt/vn, v//vn, negative references, fo, groups, comments, CRLF or CR, continuations, tabs, a BOM; PLY: any
   property order and types, float32 and integer coordinates, extra properties and elements, list count types, face
   before vertex; OFF: keyword variants, counts on the keyword line, colours, comments; 3MF: attribute orders, quotes,
   a namespace prefix, nested components with transforms incl. mirrors, p:path parts, units, the .rels start part),
   read by ``read_mesh_source(path, data)`` (a quarter by path, the suffix in any case). Passing: each triangle as
   written, bit for bit (3MF: transforms and unit applied, within 1e-12 of the magnitudes, a mirrored instance
   reversed); each polygon of n vertices as n - 2 triangles of its own vertices, none turned against its Newell
   normal beyond 1e-9 (rounding's slivers, under 1e-12 of its area, exempt), areas summing to its own within 1e-9 and
   edges cancelling to its outline: covered exactly once (computed in exact rational arithmetic);
2. a mutation of such a file (3MF: of a member, zipped again with a member maybe twice, or of the zip) by 1-3 edits:
   bit flips, format tokens inserted or put in place of a token, numbers made extreme, truncation, lines duplicated
   (up to 1000 times, 1 MiB), deleted or swapped, random bytes. Passing: a mesh, or a ``GpusliceError`` whose
   message is one line (no control character) starting with the file's name.

Always: no other exception, no warning (numpy's default error handling, every warning recorded: a RuntimeWarning
escaping the readers' errstate is a finding), nothing on stderr, no case past ``--slow`` s of CPU time (``--timeout``
stops one). ``--cli-cases``: mutated files also run as ``gpuslice info FILE``: exit 0 with an empty stderr, or exit 2
with one stderr line ``gpuslice: error: FILE...``. Cases follow from ``--seed``; failing inputs are kept under
``--keep``; the summary is printed (and written to ``--json``); ``--replay FILE...`` reads files again and prints
what came back (and the CPU time).

    python scripts/fuzz_readers.py --seed 1 --time-limit 720 --cli-cases 300 --json fuzz.json   # a long run
    python scripts/fuzz_readers.py --cases 300 --cli-cases 20                                    # a quick look
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import random
import re
import resource
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import warnings
import zipfile
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from fractions import Fraction
from pathlib import Path

import numpy as np

FORMATS = ("obj", "ply-ascii", "ply-le", "ply-be", "off", "3mf")
PLY = {"ply-ascii": ("ascii", ""), "ply-le": ("binary_little_endian", "<"), "ply-be": ("binary_big_endian", ">")}
PLY_NAMES = {"i1": ["char", "int8"], "u1": ["uchar", "uint8"], "i2": ["short", "int16"], "u2": ["ushort", "uint16"],
             "i4": ["int", "int32"], "u4": ["uint", "uint32"], "f4": ["float", "float32"], "f8": ["double", "float64"]}
UNITS = {"micron": 0.001, "millimeter": 1.0, "centimeter": 10.0, "inch": 25.4, "foot": 304.8, "meter": 1000.0}
CORE, PROD = ("http://schemas.microsoft.com/3dmanufacturing/core/2015/02",
              "http://schemas.microsoft.com/3dmanufacturing/production/2015/06")
RELS = ('<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships"><Relationship Target="{}" '
        'Id="r0" Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/></Relationships>')
TYPES = ('<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types"><Default Extension="model" '
         'ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/></Types>')
EXTREME = (b"1e308 -1e308 1e309 nan -inf 4294967296 -1 0 18446744073709551616 1e-320 -0 2147483648 65536 256 -129 "
           b"3.5 1e18 1.0000001e18 1e-300").split() + [b"9" * 400]
CONTROL = [b"\r", b"\n", b"\t", b"\x00", b"\xff", b"\xef\xbb\xbf", b"\x1b[2J", b"\x0b", b"\x0c", b" "]
TOKENS = {
    "obj": b"v f fo vt vn / // surf \\ # g l + - 1/2/3 0x10 1_0 -0".split() + [b"\\\n"],
    "ply": (b"ply format ascii binary_little_endian binary_big_endian 1.0 element property list uchar int float double "
            b"vertex face vertex_indices vertex_index end_header comment obj_info x + -").split(),
    "off": b"OFF COFF NOFF 4OFF nOFF STOFF BINARY # 3 4 + - 1_0".split(),
    "3mf": (b'<|>|/>|"|\'|&amp;|&#0;|&#x31;|<!--|-->|<![CDATA[|]]>|<!DOCTYPE x>|<mesh>|</mesh>|<vertex x="1" y="2" z='
            b'"3"/>|<triangle v1="0" v2="1" v3="9"/>|<component objectid="1"/>|<item objectid="1"/>|transform="-1 0 0 '
            b'0 1 0 0 0 1 0 0 0"|p:path="/3D/3dmodel.model"|unit="foot"|unit="parsec"|xmlns="urn:x"|gpuslice-mesh:0|1.|'
            b'.5|1e|objectid="99"|id="1"|<?xml version="1.0" encoding="latin-9"?>').split(b"|"),
}
GPUSLICE = str(Path(sys.executable).with_name("gpuslice")) if Path(sys.executable).with_name("gpuslice").is_file() \
    else (shutil.which("gpuslice") or "gpuslice")


class CaseTimeout(BaseException):
    """A case ran past its time cap (not an Exception, not an OSError: no reader's handler takes it)."""


# ---- random meshes and writers ----------------------------------------------------------------------------------


def num(rng: random.Random, x: float) -> str:
    """``x`` as text that reads back exactly, in a random style (integer, exponent, fixed point, plus sign)."""
    x = float(x)
    if x.is_integer() and abs(x) < 1e15 and rng.random() < 0.5:
        s = str(int(x)) + rng.choice(["", "", ".", ".0", ".000"])
    else:
        s = rng.choice([repr(x), f"{x:.17g}", f"{x:.16e}", f"{x:.16E}", f"{x:.20f}" if 1e-3 < abs(x) < 1e3 else ""])
        s = s or repr(x)
    return "+" + s if s[0] != "-" and rng.random() < 0.1 else s


def _outline(rng: random.Random) -> np.ndarray:
    """(n, 2) a simple polygon in [-1, 1]^2: convex (on a circle), star-shaped concave, or rectilinear (steps)."""
    if (kind := rng.randrange(3)) < 2:
        w = np.array([rng.uniform(0.5, 1) for _ in range(rng.randint(4, 13))])
        t = np.cumsum(w) / w.sum() * 2 * math.pi + rng.uniform(0, 7)
        r = np.ones(w.size) if kind == 0 else np.array([rng.uniform(0.3, 1) for _ in w])
        pts = np.column_stack([r * np.cos(t), r * np.sin(t)])
    else:
        k = rng.randint(1, 5)
        xs, hs = sorted(rng.sample(range(32), k + 1)), [rng.randint(1, 31)]
        for _ in range(k - 1):
            hs.append(rng.choice([h for h in range(1, 32) if h != hs[-1]]))
        pts = [(xs[0], 0)] + [((xs[0] + xs[-1]) / 2, 0)] * (rng.random() < 0.4) + [(xs[-1], 0)]
        pts = np.array(pts + [p for i in range(k - 1, -1, -1) for p in ((xs[i + 1], hs[i]), (xs[i], hs[i]))]) / 16 - 1
    return np.roll(pts[::-1] if rng.random() < 0.5 else pts, rng.randrange(len(pts)), axis=0)


def random_mesh(rng: random.Random, kinds=("f8",) * 3, big=False, polygons=True, top=15) -> tuple[np.ndarray, list]:
    """Vertices (V, 3), as stored (each axis ``kinds``: f8, f4 rounded to float32, int), and faces (vertex index
    lists, file order) of a random mesh; coordinates below ``10 ** top``."""
    import shapely

    g = np.random.default_rng(rng.getrandbits(63))

    def snap(p: np.ndarray) -> np.ndarray:
        p = np.array(p, np.float64)
        for k, kind in enumerate(kinds):
            p[..., k] = p[..., k].astype(np.float32) if kind == "f4" else np.round(p[..., k]) if kind == "int" else p[
                ..., k]
        return p

    ints, f4, tiny = "int" in kinds, "f4" in kinds, rng.random() < 0.03
    scale = 10 ** (rng.uniform(1.7, 4) if ints else rng.uniform(-6, 9) if f4 else rng.uniform(-250, -20) if tiny
                   else rng.uniform(-9, top - 3))
    off = np.round(g.uniform(-1, 1, 3) * 10 ** g.uniform(0, 2.5, 3) * (g.random(3) < 0.7) * scale)
    off = off if ints else off + g.uniform(-1, 1, 3) * scale
    nv = rng.randint(3, 2000 if big else 60)
    pts = off + scale * g.uniform(-1, 1, (nv, 3))
    pts[whole] = np.round(pts[whole := g.random(nv) < 0.15])
    pts[g.random((nv, 3)) < 0.03] = 0.0
    verts = list(snap(pts))
    faces = [[rng.randrange(nv) for _ in range(3)] for _ in range(rng.randint(1, 1500 if big else 40))]
    for _ in range(rng.randint(0, 4)):  # a vertex written twice
        verts.append(verts[rng.randrange(nv)])
        faces.append([len(verts) - 1, rng.randrange(nv), rng.randrange(nv)])
    for _ in range(rng.randint(0, 300 if big else 8) if polygons else 0):
        for _try in range(10):
            if rng.random() < 0.3:  # an axis-aligned plane: exact coordinates, points exactly on a line
                u, v, (a, b) = np.zeros(3), np.zeros(3), rng.sample(range(3), 2)
                u[a], v[b] = rng.choice([-1, 1]), rng.choice([-1, 1])
            else:
                u, v = np.linalg.qr(g.normal(size=(3, 3)))[0][:, :2].T
            uv, s = _outline(rng), scale * 2.0 ** rng.randint(-4 if not ints else 0, 0)
            p = snap(off + np.round(g.uniform(-1, 1, 3) * 64) / 64 * scale + s * (uv[:, :1] * u + uv[:, 1:] * v))
            normal = np.cross(p - p[0], np.roll(p, -1, 0) - p[0]).sum(0)
            flat = shapely.Polygon(np.delete(p, np.abs(normal).argmax(), 1))  # (a simple polygon, distinct points)
            if len(np.unique(p, axis=0)) == len(p) and flat.is_valid:
                faces.append(list(range(len(verts), len(verts) + len(p))))
                verts += list(p)
                break
    perm = g.permutation(len(verts))  # (vertex k written at position where[k])
    where = np.argsort(perm)
    rng.shuffle(faces)
    return np.array(verts)[perm], [[int(where[i]) for i in f] for f in faces]


def _sp(rng: random.Random) -> str:
    return rng.choice([" ", " ", " ", "  ", "\t", " \t "])


def write_obj(rng: random.Random, V: np.ndarray, faces: list) -> bytes:
    nl, style, lines, written = rng.choice(["\n", "\n", "\r\n", "\r"]), rng.randrange(5), [], 0
    extras = ["g part", "o thing one", "s 1", "s off", "usemtl red", "mtllib a.mtl", "vt 0.5 0.25", "vn 0 0 1",
              "vp 0.5", "# a comment", "", "g", "l 1 2", "p 1", "vt 1 1 0"]

    def flush(upto: int) -> None:
        nonlocal written
        while written < upto:
            tail = rng.choice(["", "", _sp(rng) + "1", _sp(rng) + " ".join(num(rng, rng.random()) for _ in range(3))])
            lines.append("v" + "".join(_sp(rng) + num(rng, c) for c in V[written]) + tail)
            written += 1
            lines.extend([rng.choice(extras)] * (rng.random() < 0.05))

    for f in faces:
        if rng.random() < 0.9:
            flush(max(f) + 1 if rng.random() < 0.7 else rng.randint(max(f) + 1, len(V)))
        refs = [(str(i + 1) if i >= written or rng.random() < 0.5 else str(i - written))
                + ["", "/3", "/2/1", "//4"][style if style < 4 else rng.randrange(4)] for i in f]
        lines += [rng.choice(["f", "f", "fo"]) + _sp(rng) + _sp(rng).join(refs)] + [rng.choice(extras)] * (
            rng.random() < 0.1)
    flush(len(V))
    for k, line in enumerate(lines):
        r, tokens = rng.random(), line.split(" ")
        if r < 0.05 and len(tokens) > 2:  # a line continued with a backslash
            cut = rng.randrange(1, len(tokens))
            line = " ".join(tokens[:cut]) + rng.choice([" \\", "\\", "\\ "]) + nl + " ".join(tokens[cut:])
        lines[k] = rng.choice(" \t") * (r > 0.95) + line + " # note" * (0.9 < r < 0.93)
    return b"\xef\xbb\xbf" * (rng.random() < 0.1) + (nl.join(lines) + rng.choice([nl, ""])).encode()


def write_ply(rng: random.Random, V: np.ndarray, faces: list, fmt: str, kinds: tuple[str, ...]) -> bytes:
    def fits(a) -> list[str]:
        return [t for t in ("i1", "u1", "i2", "u2", "i4", "u4") if np.iinfo(t).min <= min(a) <= max(a) <= np.iinfo(
            t).max]

    codes = [rng.choice(fits(V[:, k])) if kind == "int" else kind for k, kind in enumerate(kinds)]
    vprops = [(a, c, None) for a, c in zip("xyz", codes, strict=True)] + rng.sample(
        [("nx", "f4", None), ("red", "u1", None), ("quality", "f8", None), ("flags", "i4", None), ("adj", "i4", "u1")],
        rng.randint(0, 3))
    flat = [i for f in faces for i in f]
    fprops = [(rng.choice(["vertex_indices", "vertex_index"]), rng.choice(fits(flat)), rng.choice(fits([3, 13])))]
    fprops += rng.sample([("red", "u1", None), ("uv", "f4", "u1"), ("quality", "f8", None), ("tag", "i2", "u2")],
                         rng.randint(0, 2))
    rng.shuffle(vprops) if rng.random() < 0.6 else None
    rng.shuffle(fprops)
    elements = [("vertex", len(V), vprops), ("face", len(faces), fprops)][:: rng.choice([1, 1, 1, -1])]
    for el in rng.sample([("material", rng.randint(0, 3), [("power", "f4", None), ("ambient", "u1", None)]),
                          ("edge", rng.randint(0, 5), [("vertex1", "i4", None), ("vertex2", "i4", None)]),
                          ("range", rng.randint(0, 3), [("ids", "i4", "u1")])], rng.randint(0, 3)):
        elements.insert(rng.randint(0, len(elements)), el)
    nl, (name, end) = rng.choice(["\n", "\r\n", "\r"] if fmt == "ply-ascii" else ["\n", "\n", "\r\n"]), PLY[fmt]
    head = ["ply", f"format {name} 1.0"] + ["comment made by fuzz_readers", "obj_info x"] * (rng.random() < 0.3)
    for el, n, props in elements:
        head += [f"element {el} {n}"] + [f"property {rng.choice(PLY_NAMES[c])} {p}" if lc is None else
                                         f"property list {rng.choice(PLY_NAMES[lc])} {rng.choice(PLY_NAMES[c])} {p}"
                                         for p, c, lc in props]
    out = [(nl.join(head + ["end_header"]) + nl).encode()]
    for el, n, props in elements:
        for r in range(n):
            vals = []  # (type, value) of the record's numbers
            for p, c, lc in props:
                items = list(faces[r]) if el == "face" and p.startswith("vertex_ind") else [V[r, "xyz".index(p)]] if \
                    el == "vertex" and p in "xyz" else [rng.randint(0, 100) if c[0] != "f" else float(
                        np.float32(rng.uniform(-99, 99))) for _ in range(rng.randint(0, 4) if lc else 1)]
                vals += [(lc, len(items))] * bool(lc) + [(c, v if c[0] == "f" else int(v)) for v in items]
            if end:
                out.append(struct.pack(end + "".join(np.dtype(c).char for c, _ in vals), *(v for _, v in vals)))
            else:
                text = (_sp(rng) if rng.random() < 0.1 else " ").join(num(rng, v) if c[0] == "f" else str(v)
                                                                      for c, v in vals)
                out.append((text + " " * (rng.random() < 0.05) + nl + nl * (rng.random() < 0.02)).encode())
    return b"\xef\xbb\xbf" * (rng.random() < 0.05) + b"".join(out)


def write_off(rng: random.Random, V: np.ndarray, faces: list) -> bytes:
    nl, kw = rng.choice(["\n", "\n", "\r\n", "\r"]), rng.choice(["OFF", "OFF", "COFF", "NOFF", "CNOFF", "STOFF", ""])
    count = f"{len(V)}{_sp(rng)}{len(faces)}" + rng.choice(["", " 0", f" {sum(len(f) for f in faces)}"])
    lines = [f"{kw} {count}"] if kw and rng.random() < 0.3 else [kw] * bool(kw) + [count]
    for p in V:
        extra = ["1 0 0"] * ("N" in kw) + [rng.choice(["255 0 0", "0.5 0.5 0.5 1"])] * ("C" in kw) + ["0 1"] * (
            "ST" in kw)
        lines.append(_sp(rng).join([num(rng, c) for c in p] + extra))
    lines += [" ".join(map(str, [len(f), *f])) + rng.choice(["", "", " 255 0 0", " 0.2 0.3 0.4 1", " 7"])
              for f in faces]
    for _ in range(rng.randint(0, 3)):
        lines.insert(rng.randint(0, len(lines)), rng.choice(["# a comment", "", "  ", "#"]))
    lines = [line + " # c" * (rng.random() < 0.03) for line in lines]
    return b"\xef\xbb\xbf" * (rng.random() < 0.05) + (nl.join(lines) + rng.choice([nl, ""])).encode()


def write_3mf(rng: random.Random, big: bool = False) -> tuple[dict[str, bytes], list]:
    """The zip members of a random 3MF and its expected faces [(corners, tolerance)], in millimetres."""
    q, pre, unit, nl = rng.choice("\"'"), rng.choice(["", "", "m:"]), rng.choice([None, *UNITS]), rng.choice(
        ["\n", "\r\n", "", "\n  "])
    eq, g = rng.choice(["=", "=", " = "]), np.random.default_rng(rng.getrandbits(63))

    def tag(name: str, attrs: list, close: str = "/>") -> str:
        rng.shuffle(attrs) if rng.random() < 0.3 else None
        return f"<{pre}{name}" + "".join(f" {k}{eq}{q}{v}{q}" for k, v in attrs) + " " * (rng.random() < 0.1) + close

    def ref(part: str) -> tuple[list, tuple]:  # an item's or a component's attributes, and (object, transform)
        key = rng.choice([k for k in objects if k[0] == part or part == "root"])
        m = None if rng.random() < 0.4 else np.vstack([(np.linalg.qr(g.normal(size=(3, 3)))[0] if rng.random() < 0.7
                                                       else np.eye(3)[g.permutation(3)]) * 10 ** g.uniform(-1, 1, 3) *
                                                      np.where(g.random(3) < 0.25, -1, 1), g.uniform(-1, 1, 3) * 10 **
                                                      rng.uniform(-3, 5)])  # rotation, scales, mirrors; translation
        attrs = [("objectid", key[1])] + ([("transform", " ".join(num(rng, x) for x in m.ravel()))] if m is not None
                                          else [])
        return attrs + [("p:path", "/" + key[0])] * (key[0] != part), (key, m)

    objects: dict[tuple[str, str], tuple] = {}  # (part, id): ("mesh", V, T) | ("comp", [((part, id), matrix)])
    parts = {"root": [], **{f"3D/Objects/obj_{k}.model": [] for k in range(rng.randint(0, 2))}}
    ids = {p: rng.randint(1, 20) if p == "root" else 1 for p in parts}
    for k in range(rng.randint(1, 4) + rng.randint(0, 3)):
        part = rng.choice(list(parts)) if rng.random() < 0.4 else "root"
        oid, ids[part] = str(ids[part]), ids[part] + rng.randint(1, 3)
        if k and rng.random() < 0.4 and any(o[0] == "mesh" for (p, _), o in objects.items() if p == part):
            refs = [ref(part) for _ in range(rng.randint(1, 3))]  # components of objects defined above
            objects[part, oid] = ("comp", [r for _, r in refs])
            parts[part].append(tag("object", [("id", oid)], ">") + f"<{pre}components>" + "".join(
                tag("component", a) for a, _ in refs) + f"</{pre}components></{pre}object>")
            continue
        V, faces = random_mesh(rng, big=big, polygons=False, top=8)
        objects[part, oid] = ("mesh", V, np.array(faces))
        body = "".join(tag("vertex", [(k, num(rng, x)) for k, x in zip("xyz", p, strict=True)]) + nl for p in V)
        tris = "".join(tag("triangle", [("v1", a), ("v2", b), ("v3", c)] + [("p1", 0)] * (rng.random() < 0.1)) + nl
                       for a, b, c in faces)
        parts[part].append(tag("object", [("id", oid), ("type", "model")], ">") + f"<{pre}mesh>{nl}<{pre}vertices>"
                           f"{nl}{body}</{pre}vertices>{'<!-- c -->' * (rng.random() < 0.05)}<{pre}triangles>{tris}"
                           f"</{pre}triangles></{pre}mesh></{pre}object>")
    items, scale, expected = [ref("root") for _ in range(rng.randint(1, 3))], UNITS[unit or "millimeter"], []

    def expand(key: tuple, chain: list) -> None:
        if (obj := objects[key])[0] == "comp":
            for k, m in obj[1]:
                expand(k, [m, *chain])
            return
        c, mag = obj[1][obj[2]], np.abs(obj[1][obj[2]])
        for m in (m for m in chain if m is not None):
            c, mag = c @ m[:3] + m[3], mag @ np.abs(m[:3]) + np.abs(m[3])
        flip = np.prod([np.linalg.det(m[:3]) for m in chain if m is not None]) < 0
        expected.extend(((t[::-1] if flip else t) * scale, 1e-12 * mt.max() * scale)
                        for t, mt in zip(c, mag, strict=True))

    for _, (key, m) in items:
        expand(key, [m])
    ns = f'xmlns{":m" if pre else ""}={q}{CORE}{q} xmlns:p={q}{PROD}{q}' + f" requiredextensions={q}p{q}" * (
        len(parts) > 1)
    members, decl = {}, '<?xml version="1.0" encoding="UTF-8"?>\n' * (rng.random() < 0.8)
    for part, objs in parts.items():
        u = f" unit={q}{unit if part == 'root' else rng.choice(list(UNITS))}{q}" if part != "root" or unit else ""
        build = "".join(tag("item", a) for a, _ in items) if part == "root" else ""
        members[part] = (f"{decl}<{pre}model{u} xml:lang={q}en-US{q} {ns}>{nl}<{pre}metadata name={q}Title{q}>fuzz"
                         f"</{pre}metadata><{pre}resources>{nl}{nl.join(objs)}{nl}</{pre}resources>{nl}<{pre}build>"
                         f"{build}</{pre}build>{nl}</{pre}model>{nl}").encode()
    root = rng.choice(["3D/3dmodel.model", "3D/3dmodel.model", "3D/3DModel.model", "3D/Model_1.model"])
    members[root], members["[Content_Types].xml"] = members.pop("root"), TYPES.encode()
    if root != "3D/3dmodel.model" or rng.random() < 0.8:  # (else found by its conventional name)
        target = rng.choice(["/3D/3dmodel.model", "3D/3dmodel.model", "/3D/../3D/3dmodel.model"])
        members["_rels/.rels"] = RELS.format("/" + root if root == "3D/Model_1.model" else target).encode()
    return members, expected


def zip_members(rng: random.Random, members: dict[str, bytes], twice: str | None = None) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # ("Duplicate name")
        for name in sorted(members, key=lambda n: (n != "[Content_Types].xml", rng.random())) + [twice] * bool(twice):
            zf.writestr(name, members[name], compress_type=rng.choice([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))
    return out.getvalue()


def make_file(rng: random.Random, fmt: str, big: bool) -> tuple[bytes, list, dict | None]:
    """(file bytes, expected faces [(corners, tolerance or None)], 3MF members or None) of a random valid file."""
    if fmt == "3mf":
        members, expected = write_3mf(rng, big)
        return zip_members(rng, members), expected, members
    mode = rng.choice(["f8", "f4", "mixed", "int"]) if fmt.startswith("ply") else "f8"
    kinds = tuple(rng.choice(["f4", "f8"]) if mode == "mixed" else mode for _ in range(3))
    V, faces = random_mesh(rng, kinds, big)
    data = write_obj(rng, V, faces) if fmt == "obj" else write_off(rng, V, faces) if fmt == "off" else write_ply(
        rng, V, faces, fmt, kinds)
    return data, [(V[f], None) for f in faces], None


# ---- checks -----------------------------------------------------------------------------------------------------


def _cover(poly: np.ndarray, tris: np.ndarray) -> str:
    """'' where ``tris`` cover the polygon ``poly`` exactly once (see the module docstring), else why not."""
    pos = {tuple(p): k for k, p in enumerate(poly.tolist())}
    ids = [[pos.get(tuple(c)) for c in t] for t in tris.tolist()]
    if any(None in t for t in ids):
        return "a triangle corner that is not one of the face's vertices"
    P = [[Fraction(x) for x in p] for p in poly.tolist()]

    def cross(a, b, c):
        u, v = [b[i] - a[i] for i in range(3)], [c[i] - a[i] for i in range(3)]
        return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

    normal = [sum(t) for t in zip(*(cross(P[0], P[k], P[k + 1]) for k in range(1, len(P) - 1)), strict=True)]
    nn, total, chain = sum(x * x for x in normal), Fraction(0), Counter()
    for a, b in [(k, (k + 1) % len(P)) for k in range(len(P))]:
        chain[min(a, b), max(a, b)] += 1 if a < b else -1
    for a, b, c in ids:
        t = cross(P[a], P[b], P[c])
        d, tt = sum(x * y for x, y in zip(t, normal, strict=True)), float(sum(x * x for x in t))
        if float(d) < -1e-9 * math.sqrt(tt * float(nn)) and tt > 1e-24 * float(nn):  # (not a sliver of rounding)
            return f"triangle {(a, b, c)} turned against the face"
        total += abs(d)
        for e, f in ((a, b), (b, c), (c, a)):
            chain[min(e, f), max(e, f)] -= 1 if e < f else -1
    if abs(float((total - nn) / nn)) > 1e-9:
        return f"triangle areas add up to {float(total / nn)} of the face's"
    return "" if not any(chain.values()) else "the triangles' edges are not the face's outline"


def compare(got: np.ndarray, expected: list) -> str:
    """'' where triangles ``got`` are the faces ``expected`` [(corners (n, 3), tolerance or None)], else how not."""
    at = 0
    for k, (c, tol) in enumerate(expected):
        if len(part := got[at : at + len(c) - 2]) < len(c) - 2:
            return f"{len(got)} triangles for {len(expected)} faces: face {k + 1} missing"
        if len(c) == 3 and tol is None and not np.array_equal(part[0], c):
            return f"face {k + 1}: triangle {part[0].tolist()} read, {c.tolist()} written"
        if tol is not None and not any(np.abs(part[0] - np.roll(c, s, 0)).max() <= tol for s in range(3)):
            return f"face {k + 1}: triangle {part[0].tolist()} read, {c.tolist()} expected (tolerance {tol:.3g})"
        if len(c) > 3 and (why := _cover(c, part)):
            return f"face {k + 1} of {len(c)} vertices: {why}: {c.tolist()} read as {part.tolist()}"
        at += len(c) - 2
    return "" if at == len(got) else f"{len(got)} triangles read, {at} expected"


def read(path: Path, data: bytes | None, timeout: float) -> tuple[str, object]:
    """(outcome, triangles or a detail): outcome 'ok', an error class name, or 'FAIL:...'."""
    from gpuslice.errors import GpusliceError
    from gpuslice.io.meshfile import read_mesh_source

    def alarm(signum, frame):
        raise CaseTimeout

    old, err = signal.signal(signal.SIGALRM, alarm), io.StringIO()
    signal.setitimer(signal.ITIMER_REAL, timeout)
    try:
        with warnings.catch_warnings(record=True) as seen, contextlib.redirect_stderr(err):
            warnings.simplefilter("always")
            try:
                out = "ok", read_mesh_source(path, data).triangles
            except GpusliceError as exc:
                msg = str(exc)
                bad = len(msg.splitlines()) != 1 or any(ord(ch) < 32 and ch != "\t" or ch == "\x7f" for ch in msg)
                out = ("FAIL:multi-line message or control character" if bad else type(exc).__name__ if
                       msg.startswith(str(path)) else "FAIL:message not starting with the file name"), msg
    except CaseTimeout:
        out = "FAIL:timeout", f"> {timeout} s"
    except Exception as exc:  # noqa: BLE001 - the point of the fuzzer
        out = f"FAIL:{type(exc).__name__}", " ".join(str(exc).split())[:300]
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    if seen:
        return f"FAIL:warning {seen[0].category.__name__}", f"{seen[0].filename}:{seen[0].lineno}: {seen[0].message}"
    return ("FAIL:stderr output", err.getvalue()[:300]) if err.getvalue() else out


# ---- mutations --------------------------------------------------------------------------------------------------


def mutate(rng: random.Random, data: bytes, tokens: list[bytes]) -> tuple[bytes, str]:
    """``data`` with one random edit, and what it was."""
    b, kind = bytearray(data), rng.choice("flip insert replace number truncate dup delete swap splice replace number "
                                          "dup".split())
    lines, at = b.split(b"\n"), rng.randrange(len(b) + 1)
    spans = [(m.start(), m.end()) for m in re.finditer(rb"[^ \t\r\n\"'<>=]+", bytes(b))]
    if kind == "flip":
        for _ in range(rng.choice([1, 1, 2, 8]) * bool(b)):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
    elif kind == "insert":
        b[at:at] = rng.choice(tokens + CONTROL)
    elif kind in ("replace", "number") and spans:
        s, e = rng.choice([sp for sp in spans if kind == "replace" or b[sp[0]] in b"+-.0123456789"] or spans)
        b[s:e] = rng.choice(tokens + CONTROL if kind == "replace" else EXTREME)
    elif kind == "truncate":
        del b[rng.choice([at, rng.randrange(min(len(b), 200) + 1), max(0, len(b) - rng.randrange(1, 40))]):]
    elif kind in ("dup", "delete", "swap"):
        i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
        if kind == "dup":
            lines[i:i] = [lines[j]] * min(rng.choice([1, 1, 2, 10, 1000]), 1 + (1 << 20) // (1 + len(lines[j])))
        elif kind == "delete":
            del lines[i]
        else:
            lines[i], lines[j] = lines[j], lines[i]
        b = bytearray(b"\n".join(lines))
    else:
        b[at:at] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64)))
    return bytes(b), kind


def mutate_file(rng: random.Random, fmt: str, data: bytes, members: dict | None) -> tuple[bytes, str]:
    """A mutated copy of a file (3MF: of its zip, or of members then zipped again, a member maybe twice)."""
    steps = []
    for _ in range(rng.choice([1, 1, 2, 3])):
        if members is None or rng.random() < 0.1:
            data, what = mutate(rng, data, TOKENS[fmt.split("-")[0]] if members is None else [b"PK\x03\x04"])
            members, steps = None, steps + [what]
        else:
            name = rng.choice([n for n in members if n.endswith(".model")] * 6 + list(members))
            members[name], what = mutate(rng, members[name], TOKENS["3mf"])
            steps.append(f"{what} in {name}")
            twice = rng.choice(list(members)) if rng.random() < 0.03 else None
            data = zip_members(rng, members, twice)
            steps += [f"{twice} twice"] * bool(twice)
    return data, "+".join(steps)


def run_cli(data: bytes, ext: str, timeout: float) -> tuple[str, str]:
    """Run ``gpuslice info`` on ``data`` in a fresh folder: (outcome, detail)."""
    with tempfile.TemporaryDirectory(prefix="fuzzr-cli-") as tmp:
        (model := Path(tmp) / f"case.{ext}").write_bytes(data)
        try:
            proc = subprocess.run([GPUSLICE, "info", str(model)], capture_output=True, text=True, timeout=timeout,
                                  errors="replace")
        except subprocess.TimeoutExpired:
            return "FAIL:timeout", f"> {timeout} s"
    if "Traceback" in (err := proc.stderr.strip("\n")):
        return "FAIL:traceback", err[-300:]
    if proc.returncode == 0:
        return ("ok", "") if not err else ("FAIL:stderr on success", err[:300])
    if proc.returncode == 2:
        one = len(err.splitlines()) == 1 and err.startswith(f"gpuslice: error: {model}")
        return ("exit 2", err) if one else ("FAIL:not one error line naming the file", err[:300])
    return f"FAIL:exit {proc.returncode}", err[:300]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=1_000_000, help="cases at most (default: until --time-limit)")
    ap.add_argument("--time-limit", type=float, default=0.0, help="stop after this many seconds (0: no limit)")
    ap.add_argument("--cli-cases", type=int, default=0, help="mutated files run through `gpuslice info` too")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--slow", type=float, default=3.0, help="a case read slower than this (CPU s) is a finding")
    ap.add_argument("--timeout", type=float, default=60.0, help="cap per case, s (default 60)")
    ap.add_argument("--jobs", type=int, default=1, help="CLI subprocesses at once (default 1)")
    ap.add_argument("--max-memory", type=float, default=6.0, help="address-space limit, GiB (0: none)")
    ap.add_argument("--keep", type=Path, default=Path("fuzz-failures"), help="folder for failing inputs")
    ap.add_argument("--json", type=Path, default=None, help="write the summary here")
    ap.add_argument("--replay", type=Path, nargs="+", help="read these files, print what came back, and stop")
    args = ap.parse_args(argv)
    if args.max_memory:  # (a reader allocating by a count the file declares: a MemoryError, a finding)
        resource.setrlimit(resource.RLIMIT_AS, (int(args.max_memory * 2**30),) * 2)
    for path in args.replay or ():
        t0, (outcome, got) = time.process_time(), read(path, path.read_bytes(), args.timeout)
        print(f"{path}: {outcome} ({time.process_time() - t0:.2f} s CPU): " + (
            f"{len(got)} triangles" if outcome == "ok" else str(got)))
    if args.replay:
        return 0
    rng, t_start, pool = random.Random(args.seed), time.perf_counter(), ThreadPoolExecutor(max(1, args.jobs))
    outcomes: dict[str, Counter[str]] = {f"{fmt} {kind}": Counter() for fmt in FORMATS for kind in ("round", "mut")}
    failures, times, cli_jobs, cli_outcomes = [], [], [], Counter()
    args.keep.mkdir(parents=True, exist_ok=True)

    def record(where: str, i: int, fmt: str, ext: str, what: str, data: bytes, outcome: str, detail: str) -> None:
        (name := args.keep / f"s{args.seed}-case{i:06d}-{fmt}-{where}.{ext}").write_bytes(data)
        failures.append({"case": i, "where": where, "format": fmt, "mutation": what, "outcome": outcome,
                         "detail": detail[:2000], "file": str(name)})
        print(f"  FAIL {where} case {i} ({fmt}: {what}): {outcome}: {detail[:300]}", flush=True)

    with tempfile.TemporaryDirectory(prefix="fuzzr-") as tmp:
        read(Path(tmp) / "warm.obj", b"v 0 0 0\nv 2 0 0\nv 1 1 0\nv 1 2 0\nv 0 2 0\nf 1 2 3 4 5\n", args.timeout)
        for i in range(args.cases):
            if args.time_limit and time.perf_counter() - t_start > args.time_limit:
                break
            fmt, mut = FORMATS[i % len(FORMATS)], rng.random() < 0.5
            ext, big = fmt.split("-")[0], rng.random() < (0.02 if mut else 0.08)
            data, expected, members = make_file(rng, fmt, big)
            data, what = mutate_file(rng, fmt, data, members) if mut else (data, "valid file")
            path = Path(tmp) / f"case.{ext if rng.random() < 0.9 else ext.upper()}"
            if by_path := not mut and rng.random() < 0.25:
                path.write_bytes(data)
            t0 = time.process_time()  # (CPU time: the machine may be busy)
            outcome, got = read(path, None if by_path else data, args.timeout)
            times.append(wall := time.process_time() - t0)
            if not mut and outcome == "ok" and (why := compare(got, expected)):
                outcome, got = "FAIL:wrong round trip", why
            elif not mut and outcome != "ok" and not outcome.startswith("FAIL"):
                outcome = f"FAIL:valid file refused ({outcome})"
            outcomes[f"{fmt} {'mut' if mut else 'round'}"][outcome] += 1
            if outcome.startswith("FAIL") or wall > args.slow:
                record("lib", i, fmt, path.suffix[1:], what, data, outcome if outcome.startswith("FAIL") else
                       "FAIL:slow", f"{wall:.2f} s CPU, {len(data)} bytes: {got if isinstance(got, str) else 'read'}")
            if mut and len(cli_jobs) < args.cli_cases and rng.random() < 0.1:
                cli_jobs.append((i, fmt, ext, what, data, pool.submit(run_cli, data, ext, args.timeout)))
            if (i + 1) % 1000 == 0:
                print(f"{i + 1} cases, {time.perf_counter() - t_start:.0f} s, {len(failures)} failures", flush=True)
    for i, fmt, ext, what, data, fut in cli_jobs:
        cli_outcomes[(res := fut.result())[0]] += 1
        if res[0].startswith("FAIL"):
            record("cli", i, fmt, ext, what, data, *res)
    pool.shutdown()
    summary = {"command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
               "seed": args.seed, "cases": sum(sum(c.values()) for c in outcomes.values()),
               "outcomes": {k: dict(c.most_common()) for k, c in outcomes.items()},
               "case_cpu_s": {"median": float(np.median(times)) if times else None, "max": max(times, default=None)},
               "cli_cases": len(cli_jobs), "cli_outcomes": dict(cli_outcomes.most_common()), "failures": failures,
               "wall_s": time.perf_counter() - t_start}
    print(text := json.dumps(summary, indent=1))
    if args.json:
        args.json.write_text(text + "\n")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
