"""Read ASCII OFF files (Geomview's Object File Format) into vertices and triangles, strictly.

The layout (Geomview's ``OFF`` manual page): an optional keyword line ``[ST][C][N]OFF``; a counts line ``NV NF
[NE]`` (on the keyword's line or the next); ``NV`` vertex lines ``x y z`` (then, per the keyword, a normal, a
colour, a texture coordinate: ignored); ``NF`` face lines ``n i_1 ... i_n`` (vertex indices counted from 0, then
an optional colour: ignored). ``#`` starts a comment anywhere; blank lines are skipped. Faces are returned as
polygons (vertex counts and their indices); :mod:`gpuslice.io.polygons` cuts those of n > 3 vertices into n − 2
triangles (a fan where it is exact, a concave face inside its outline).

trimesh's OFF reader (5.x) let broken files through silently: a comment line after the counts line dropped a
face, a face line short of an index dropped that face, a face colour dropped every face. Here each is refused with
one line naming the file and the line, or read as the specification says (a colour is ignored).
"""

from __future__ import annotations

import re

import numpy as np

from ..errors import MeshFileError, flatten
from .rawmesh import plain_text

__all__ = ["read_off"]

_KEYWORD = re.compile(rb"(?:ST)?C?N?(4?)(n?)OFF")
_INTEGER = re.compile(rb"[+-]?[0-9]+")  # (Python's int() also takes "1_000" and other digits: not OFF's)


def _content_lines(data: bytes) -> list[bytes]:
    """The file's lines without comments, blank ones left out (a UTF-8 byte-order mark dropped; CR, CRLF or LF line
    ends)."""
    return [line for line in plain_text(data).split(b"\n") if line.strip()]


def read_off(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` float64 (file units), the faces' vertex counts ``(F,)`` int64 (each >= 3) and their
    vertex indices (flat, face after face, int64, not yet checked against the vertex count) of the ASCII OFF file
    ``data``; a :class:`MeshFileError` naming ``name``
    for a binary OFF, a 4-D or n-D one, a bad counts line, a vertex or face line that is short or not numbers, a
    face of fewer than 3 vertices, or other than as many lines as the counts declare."""

    def fail(reason: str) -> MeshFileError:
        return MeshFileError(f"{name}: cannot read OFF file: {flatten(reason, 300)}")  # (escaped)

    lines = _content_lines(data)
    if not lines:
        raise fail("no OFF header (the file holds nothing but comments or blank lines)")
    tokens = lines[0].split()
    head = 1  # (content lines before the vertices)
    keyword = _KEYWORD.fullmatch(tokens[0])
    if keyword is not None:
        if keyword.group(1) or keyword.group(2):
            raise fail(f"a {tokens[0].decode()} file holds points of other than 3 dimensions")
        if b"BINARY" in tokens[1:]:
            raise fail("a binary OFF file (save it as ASCII OFF)")
        tokens = tokens[1:]
        if not tokens:  # (the counts on the next line, as usual)
            if len(lines) < 2:
                raise fail("no counts line after the OFF keyword")
            tokens, head = lines[1].split(), 2
    elif tokens[0].upper().endswith(b"OFF"):
        raise fail(f"unknown keyword {tokens[0].decode(errors='replace')!r}")
    counts = [int(t) for t in tokens[:3]] if all(_INTEGER.fullmatch(t) for t in tokens[:3]) else []
    if len(counts) < 2 or min(counts) < 0:
        raise fail(f"the counts line {b' '.join(tokens).decode(errors='replace')!r} is not vertex, face "
                   "(and edge) counts")
    nv, nf = counts[0], counts[1]
    body = lines[head:]
    if len(body) != nv + nf:  # (more: a face the count leaves out would be dropped, the mesh left open)
        raise MeshFileError(f"{name}: the OFF header declares {nv} vertices and {nf} faces, the file holds "
                            f"{len(body)} lines after it ({'cut short?' if len(body) < nv + nf else 'a wrong count?'})")
    vertices = _numbers(body[:nv], float, 3, "vertex", fail)
    rows = body[nv:]
    try:  # (the usual file: every face a triangle; anything after its three indices is a colour)
        first = np.loadtxt(rows, dtype=np.int64, usecols=(0, 1, 2, 3), ndmin=2) if nf else np.zeros((0, 4), int)
    except (ValueError, OverflowError):  # (an index past int64: found by the line below)
        first = None
    if first is not None and (first[:, 0] == 3).all():
        return vertices, first[:, 0].copy(), first[:, 1:].reshape(-1)
    return (vertices, *_polygons(rows, fail))


def _numbers(rows: list[bytes], dtype, n: int, what: str, fail) -> np.ndarray:
    """The first ``n`` numbers of each line in ``rows`` (the ``what`` lines, counted from 1 in messages)."""
    if not rows:
        return np.zeros((0, n), dtype)
    try:
        return np.loadtxt(rows, dtype=dtype, usecols=tuple(range(n)), ndmin=2)
    except (ValueError, OverflowError):
        for k, row in enumerate(rows):  # (only on failure: find the line to name)
            parts = row.split()
            try:
                [dtype(p) for p in parts[:n]]
            except ValueError:
                parts = []
            if len(parts) < n:
                raise fail(f"{what} line {k + 1} ({row.strip().decode(errors='replace')[:40]!r}) does not start "
                           f"with {n} numbers") from None
        raise fail(f"unreadable {what} lines") from None


def _polygons(rows: list[bytes], fail) -> tuple[np.ndarray, np.ndarray]:
    """Vertex counts and flat indices of face lines ``n i_1 ... i_n [colour]``: one pass in Python, only for files
    whose faces are not all triangles or whose lines are not all well formed."""
    counts: list[int] = []
    flat: list[int] = []
    for k, row in enumerate(rows):
        parts = row.split()
        n = int(parts[0]) if _INTEGER.fullmatch(parts[0]) else -1
        if n >= 0 and not all(_INTEGER.fullmatch(p) for p in parts[1 : n + 1]):
            n = -1
        idx = [int(p) for p in parts[1 : n + 1]] if n >= 0 else []
        text = row.strip().decode(errors="replace")[:40]
        if n < 0 or len(idx) < n:
            raise fail(f"face line {k + 1} ({text!r}) lists fewer vertex indices than its count {parts[0].decode()}"
                       if n >= 0 else f"face line {k + 1} ({text!r}) is not a count and vertex indices")
        if n < 3:
            raise fail(f"face line {k + 1} ({text!r}) has {n} vertices (a face needs 3)")
        if any(abs(i) >= 1 << 62 for i in idx):
            raise fail(f"face line {k + 1} ({text!r}) names a vertex index out of range")
        counts.append(n)
        flat.extend(idx)
    return np.asarray(counts, np.int64), np.asarray(flat, np.int64)
