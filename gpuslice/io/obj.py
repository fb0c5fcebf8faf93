"""Read Wavefront OBJ files (their polygonal geometry) into vertices and polygon faces, strictly.

What is read (the OBJ specification, Wavefront's "Object Files (.obj)", Appendix B1 of the Advanced Visualizer
manual): vertex lines ``v x y z`` (a fourth weight, or the common extension's colour ``r g b`` after them, is
ignored) and face lines ``f v1 v2 v3 …`` (``fo``, the old keyword, too) whose references are ``v``, ``v/vt``,
``v/vt/vn`` or ``v//vn``: the vertex index counts from 1 over the whole file, a negative one counts back from
the last vertex defined before the face line (-1 is that vertex). Faces of every object and group make one mesh
(as trimesh merges them). ``#`` starts a comment; a line ending in a backslash continues on the next; CR, CRLF and
LF line ends and a UTF-8 byte-order mark are taken. Everything else is skipped: texture coordinates and normals
(``vt``, ``vn``), groups, objects, smoothing groups, materials, and points and lines (``p``, ``l``: no surface).
Faces are returned as polygons (vertex counts and their indices): :mod:`gpuslice.io.polygons` cuts those of more
than three vertices into triangles (a concave face inside its outline; trimesh cut it into a fan that folds over
itself).

Refused, with one line naming the file and the line: a vertex line without three numbers, a face line with fewer
than three references or one that is not a number, vertex 0 (OBJ counts from 1: trimesh took it as vertex 1), a
vertex past the file's last, a negative reference counting back past the first vertex, and free-form surfaces
(``surf``: gpuslice reads polygons only). Columnar: numpy parses the vertex and face lines in bulk (2x trimesh's
reader, without its import); a Python pass over single lines runs only to name the line of an error.
"""

from __future__ import annotations

import re
import warnings

import numpy as np

from ..errors import MeshFileError, flatten
from .rawmesh import plain_text

__all__ = ["read_obj"]

_REFERENCE_TAIL = re.compile(rb"/[^ \t\n]*")  # "/vt/vn" after a face's vertex index
_INTEGER = re.compile(rb"[+-]?[0-9]+")
_BLANKS = bytes.maketrans(b"\x0b\x0c", b"  ")


def _lines(data: bytes) -> list[bytes]:
    """The file's lines (LF), comments gone, leading blanks stripped where there are any; a statement continued
    over lines (a backslash at the end) is joined on its last line, the lines before it left blank (so that each
    line keeps its number)."""
    data = plain_text(data)
    if b"\x0b" in data or b"\x0c" in data:  # (vertical tab, form feed: blanks to Python's split, not to numpy's)
        data = data.translate(_BLANKS)
    lines = data.split(b"\n")
    if data[:1] in (b" ", b"\t") or b"\n " in data or b"\n\t" in data:
        lines = [line.lstrip() for line in lines]
    if b"\\" in data and re.search(rb"\\[ \t]*(\n|\Z)", data):  # (rare: one pass in Python)
        carry = b""
        for k, line in enumerate(lines):
            body = line.rstrip()
            if body.endswith(b"\\"):
                carry, lines[k] = carry + body[:-1] + b" ", b""
            elif carry:
                carry, lines[k] = b"", carry + line
        if carry:  # (the file ends in a backslash: the statement is what was there)
            lines[-1] = carry
    return lines


def _kinds(lines: list[bytes]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Booleans over ``lines``: vertex lines (``v``), face lines (``f``, ``fo``), free-form surface lines."""
    c = np.array(lines, dtype="S5").view(np.uint8).reshape(-1, 5)  # (each line's first 5 bytes)
    ends = [(c[:, k] == 32) | (c[:, k] == 9) | (c[:, k] == 0) for k in range(5)]  # a keyword ends at k
    v, f = c[:, 0] == ord("v"), c[:, 0] == ord("f")
    surf = (c[:, :4] == np.frombuffer(b"surf", np.uint8)).all(axis=1) & ends[4]
    return v & ends[1], f & (ends[1] | ((c[:, 1] == ord("o")) & ends[2])), surf


def read_obj(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` float64 (file units), the faces' vertex counts ``(F,)`` int64 (each >= 3) and their
    vertex indices (flat, face after face, int64, counted from 0, negative references resolved; not yet checked
    against the vertex count) of the OBJ file ``data`` (see the module docstring for what is read and refused;
    a :class:`MeshFileError` naming ``name``)."""

    def fail(line: int, reason: str) -> MeshFileError:
        return MeshFileError(f"{name}: line {line}: {flatten(reason, 300)}")  # (a line's text: escaped)

    lines = _lines(data)
    is_v, is_f, is_surf = _kinds(lines)
    if is_surf.any():
        raise fail(int(np.argmax(is_surf)) + 1, "a free-form surface (surf): gpuslice reads polygons; export the "
                                                "model as a polygon mesh")
    v_at, f_at = np.flatnonzero(is_v), np.flatnonzero(is_f)
    vertices = _vertices([lines[i] for i in v_at.tolist()], v_at, fail)
    if f_at.size == 0:
        return vertices, np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows = [lines[i] for i in f_at.tolist()]
    counts, values = _references(rows, f_at, fail)
    face = np.repeat(np.arange(counts.size), counts)
    if (values == 0).any():
        raise fail(int(f_at[face[np.argmax(values == 0)]]) + 1,
                   "an OBJ face names vertex 0 (OBJ counts vertices from 1)")
    before = np.cumsum(is_v)[f_at][face]  # the vertices defined above each face line
    back = values < 0
    if (values[back] + before[back] < 0).any():
        k = int(face[np.flatnonzero(back)[np.argmax(values[back] + before[back] < 0)]])
        raise fail(int(f_at[k]) + 1, f"a face counts back past the first vertex ({_text(rows[k])!r}: "
                                     f"{int(np.cumsum(is_v)[f_at[k]])} vertices above it)")
    past = values > len(vertices)
    if past.any():  # (in OBJ's numbers, as the user wrote them: meshfile's own check would count from 0)
        k = int(face[np.argmax(past)])
        raise fail(int(f_at[k]) + 1, f"a face names vertex {int(values[np.argmax(past)])}, but the file has "
                                     f"{len(vertices)} vertices ({_text(rows[k])!r}; OBJ counts them from 1)")
    return vertices, counts, np.where(back, values + before, values - 1)


def _references(rows: list[bytes], at: np.ndarray, fail) -> tuple[np.ndarray, np.ndarray]:
    """(F,) vertex counts and the flat vertex references (as written: from 1, or negative) of face lines ``rows``
    (at line indices ``at``): the lines joined, their keywords and "/vt/vn" tails blanked, every number parsed in
    one call, the numbers of each line counted by its token starts."""
    block = b"\n".join(rows)
    if b"/" in block:
        block = _REFERENCE_TAIL.sub(b"", block)
    text = np.frombuffer(block, np.uint8).copy()
    newline = text == 10
    start = np.concatenate([[0], np.flatnonzero(newline) + 1])
    text[start] = 32  # the keyword: "f" or "fo"
    two = start[start + 1 < text.size]
    text[two[text[two + 1] == ord("o")] + 1] = 32
    blank = newline | (text == 32) | (text == 9)
    first = ~blank
    first[1:] &= blank[:-1]
    sign = (text == 43) | (text == 45)
    lone = bool((sign[:-1] & blank[1:]).any() or sign[-1:].any())  # (a bare sign: numpy reads it as 0)
    counts = np.bincount(np.cumsum(newline)[first], minlength=len(rows)).astype(np.int64)
    if (counts < 3).any():
        k = int(np.argmax(counts < 3))
        raise fail(int(at[k]) + 1, f"a face of {int(counts[k])} vertices ({_text(rows[k])!r}; a face needs 3)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # (numpy warns, then stops, at the first thing that is not a number)
            values = np.fromstring(text.tobytes(), dtype=np.int64, sep=" ")
    except (ValueError, DeprecationWarning):
        values = np.zeros(0, np.int64)
    if lone or values.size != int(counts.sum()) or not (np.abs(values) < 1 << 62).all():
        for k, row in enumerate(rows):  # (only on failure: find the line to name)
            refs = _REFERENCE_TAIL.sub(b"", row).split()[1:]
            if not all(_INTEGER.fullmatch(t) for t in refs):
                raise fail(int(at[k]) + 1, f"a face reference that is not a vertex number ({_text(row)!r})")
            if any(abs(int(t)) >= 1 << 62 for t in refs):
                raise fail(int(at[k]) + 1, f"a face names a vertex index out of range ({_text(row)!r})")
        raise fail(int(at[0]) + 1, "unreadable face lines")  # pragma: no cover - numpy and the check disagree
    return counts, values


def _vertices(rows: list[bytes], at: np.ndarray, fail) -> np.ndarray:
    """The ``x y z`` of vertex lines ``rows`` (at line indices ``at``)."""
    if not rows:
        return np.zeros((0, 3))
    try:
        return np.loadtxt(rows, dtype=np.float64, usecols=(1, 2, 3), ndmin=2, comments=None)
    except (ValueError, OverflowError):
        for k, row in enumerate(rows):  # (only on failure: find the line to name)
            parts = row.split()
            try:
                if len(parts) < 4:
                    raise ValueError
                [float(p) for p in parts[1:4]]
            except ValueError:
                raise fail(int(at[k]) + 1, f"a vertex line that does not hold x y z ({_text(row)!r})") from None
        raise fail(int(at[0]) + 1, "unreadable vertex lines") from None


def _text(row: bytes) -> str:
    return row.strip().decode(errors="replace")[:40]
