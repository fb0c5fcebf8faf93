"""ASCII STL: a vectorised tokeniser (no Python loop per vertex on the normal path) and the one-line error that
names the first structural problem and its line."""

from __future__ import annotations

from typing import NoReturn

import numpy as np

from ..errors import EmptyMeshError, MeshFileError
from .rawmesh import (
    _FACET_TOKENS,
    _KEYWORD_COLUMNS,
    _KEYWORDS,
    _NORMAL_COLUMNS,
    _TOKEN_RE,
    _VERTEX_COLUMNS,
    RawMesh,
    check_coordinates,
)

__all__ = ["parse_ascii"]


def parse_ascii(data: bytes, name: str) -> RawMesh:
    """Parse an ASCII STL (``data`` is text starting with ``solid``)."""
    text = data
    if text.startswith(b"\xef\xbb\xbf"):
        text = text[3:]
    if b"\r" in text:
        text = text.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    lower = text.lower()

    blocks = _solid_blocks(lower, name)  # [(solid_line_start, body_start, body_end, endsolid_line_end)]
    first_line_end = lower.find(b"\n", blocks[0][0])
    header = text[blocks[0][0]: first_line_end if first_line_end >= 0 else len(text)].strip()

    tri_parts: list[np.ndarray] = []
    nrm_parts: list[np.ndarray] = []
    facets_before = 0
    for _start, body_start, body_end, _end in blocks:
        tri, nrm = _parse_ascii_body(lower, body_start, body_end, facets_before, name)
        facets_before += len(tri)
        tri_parts.append(tri)
        nrm_parts.append(nrm)

    if facets_before == 0:
        what = "its solid is" if len(blocks) == 1 else f"all {len(blocks)} solids are"
        raise EmptyMeshError(f"{name}: no facets (ASCII STL; {what} empty)")
    coords = tri_parts[0] if len(tri_parts) == 1 else np.concatenate(tri_parts)
    check_coordinates(coords, name)
    triangles = coords.astype(np.float32).reshape(-1, 3, 3)
    with np.errstate(over="ignore", invalid="ignore"):
        normals = (nrm_parts[0] if len(nrm_parts) == 1 else np.concatenate(nrm_parts)).astype(np.float32)
    return RawMesh(triangles=triangles, normals=normals, source_format="ASCII STL", solids=len(blocks),
                   header=header, path=name)


def _solid_blocks(lower: bytes, name: str) -> list[tuple[int, int, int, int]]:
    """Find the ``solid``/``endsolid`` lines of LF-normalised, lower-cased ASCII STL text.

    Returns ``(solid_line_start, body_start, body_end, endsolid_line_end)`` per block. A keyword counts only
    at the start of a line (after blanks); the rest of its line is the solid's name.
    """
    marks: list[tuple[bool, int, int]] = []  # (is_end, line_start, line_end)
    pos = 0
    while True:
        i = lower.find(b"solid", pos)
        if i < 0:
            break
        pos = i + 5
        is_end = lower[i - 3: i] == b"end" if i >= 3 else False
        kw_start = i - 3 if is_end else i
        after = lower[i + 5: i + 6]
        if after and not after.isspace():
            continue  # "solidworks", "solid_1": not the keyword
        line_start = lower.rfind(b"\n", 0, kw_start) + 1
        if lower[line_start:kw_start].strip():
            continue  # not at the start of its line: part of a name or junk
        line_end = lower.find(b"\n", i)
        line_end = len(lower) if line_end < 0 else line_end
        marks.append((is_end, line_start, line_end))
        pos = line_end

    blocks: list[tuple[int, int, int, int]] = []
    open_mark: tuple[bool, int, int] | None = None
    prev_end = 0
    for is_end, line_start, line_end in marks:
        if not is_end:
            if open_mark is not None:
                raise MeshFileError(
                    f"{name}: malformed ASCII STL: line {_line_of(lower, line_start)}: 'solid' before the "
                    f"'endsolid' of the solid opened on line {_line_of(lower, open_mark[1])}"
                )
            _check_blank(lower, prev_end, line_start, name)
            open_mark = (is_end, line_start, line_end)
        else:
            if open_mark is None:
                raise MeshFileError(
                    f"{name}: malformed ASCII STL: line {_line_of(lower, line_start)}: 'endsolid' without "
                    "'solid'"
                )
            blocks.append((open_mark[1], open_mark[2], line_start, line_end))
            open_mark = None
            prev_end = line_end
    if open_mark is not None:
        _truncated_ascii(lower, open_mark, name)
    if not blocks:  # cannot happen: the data starts with "solid"
        raise MeshFileError(f"{name}: not an STL file: no 'solid' line")
    _check_blank(lower, prev_end, len(lower), name)
    return blocks


def _truncated_ascii(lower: bytes, open_mark: tuple[bool, int, int], name: str) -> NoReturn:
    """Raise for a ``solid`` without ``endsolid``: garbage if no facet follows, else truncated."""
    body = lower[open_mark[2]:]
    tokens = body.split(None, 1)
    if not tokens or tokens[0] != b"facet":
        first = tokens[0][:20].decode("ascii", "replace") if tokens else ""
        where = f"'{first}'" if first else "nothing"
        raise MeshFileError(
            f"{name}: not an STL file: text starting with 'solid' followed by {where} instead of facets, and "
            "no 'endsolid'"
        )
    raise MeshFileError(
        f"{name}: truncated ASCII STL: the solid opened on line {_line_of(lower, open_mark[1])} has no "
        "'endsolid'"
    )


def _check_blank(lower: bytes, start: int, end: int, name: str) -> None:
    """Only whitespace may stand outside ``solid ... endsolid`` blocks."""
    m = _TOKEN_RE.search(lower, start, end) if start < end else None
    if m is not None:
        raise MeshFileError(
            f"{name}: malformed ASCII STL: line {_line_of(lower, m.start())}: unexpected text "
            f"{_show(m.group())} outside 'solid ... endsolid'"
        )


def _parse_ascii_body(lower: bytes, start: int, end: int, facets_before: int,
                      name: str) -> tuple[np.ndarray, np.ndarray]:
    """Parse the facets between a ``solid`` line and its ``endsolid`` line.

    Returns ``(coords, normals)``: ``(n, 9)`` float64 vertex coordinates and ``(n, 3)`` float64 normals.
    """
    tokens = lower[start:end].split()
    if not tokens:
        return np.empty((0, 9)), np.empty((0, 3))
    table = _facet_table(tokens)
    if table is None:
        # Slow path (non-standard files or errors): drop text after end tags, or find the first problem.
        tokens, _lines = _clean_tokens(lower, start, end)
        table = _facet_table(tokens)
        if table is None:
            _raise_structure_error(lower, start, end, facets_before, name)
    coords = _to_float(table[:, _VERTEX_COLUMNS])
    if coords is None:
        _raise_structure_error(lower, start, end, facets_before, name)
    normals = _to_float(table[:, _NORMAL_COLUMNS])
    if normals is None:  # junk normals are allowed: NaN where unparsable
        normals = np.array([[_float_or_nan(t) for t in row] for row in table[:, _NORMAL_COLUMNS]],
                           dtype=np.float64).reshape(-1, 3)
    return coords, normals


def _facet_table(tokens: list[bytes]) -> np.ndarray | None:
    """Tokens as an ``(n, 21)`` object array if they are exactly ``n`` well-formed facets, else ``None``."""
    if len(tokens) % _FACET_TOKENS:
        return None
    table = np.array(tokens, dtype=object).reshape(-1, _FACET_TOKENS)
    for col, keyword in _KEYWORD_COLUMNS.items():
        if not (table[:, col] == keyword).all():
            return None
    return table


def _to_float(cells: np.ndarray) -> np.ndarray | None:
    """Convert an object array of byte strings to float64, ``None`` if any cell is not a number."""
    try:
        return cells.astype(np.float64)
    except (ValueError, TypeError):
        return None


def _float_or_nan(token: bytes) -> float:
    try:
        return float(token)
    except ValueError:
        return float("nan")


def _is_number(token: bytes) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _token_spans(lower: bytes, start: int, end: int) -> tuple[list[bytes], np.ndarray]:
    """Tokens between ``start`` and ``end`` with their byte offsets in ``lower`` (slow path only)."""
    toks: list[bytes] = []
    offs: list[int] = []
    for m in _TOKEN_RE.finditer(lower, start, end):
        toks.append(m.group())
        offs.append(m.start())
    return toks, np.asarray(offs, dtype=np.int64)


def _clean_tokens(lower: bytes, start: int, end: int) -> tuple[list[bytes], np.ndarray]:
    """Tokens of a solid body and their 1-based line numbers, without the non-keyword text that follows
    ``endloop``/``endfacet`` on the same line (``endloop foo``). Slow path: non-standard files and errors."""
    toks, offs = _token_spans(lower, start, end)
    if not toks:
        return toks, np.zeros(0, dtype=np.int64)
    lines = _lines_of(lower, offs)
    is_kw = np.fromiter((t in _KEYWORDS for t in toks), dtype=bool, count=len(toks))
    is_end_tag = np.fromiter((t in (b"endloop", b"endfacet") for t in toks), dtype=bool, count=len(toks))
    idx = np.arange(len(toks))
    last_kw = np.maximum.accumulate(np.where(is_kw, idx, -1))
    has_kw = last_kw >= 0
    lk = np.where(has_kw, last_kw, 0)
    junk = ~is_kw & has_kw & is_end_tag[lk] & (lines[lk] == lines)
    kept = [t for t, j in zip(toks, junk, strict=True) if not j]
    return kept, lines[~junk]


def _lines_of(lower: bytes, offsets: np.ndarray) -> np.ndarray:
    """1-based line numbers of byte offsets in LF-normalised text."""
    newlines = np.flatnonzero(np.frombuffer(lower, dtype=np.uint8) == 0x0A)
    return np.searchsorted(newlines, offsets, side="right") + 1


def _line_of(lower: bytes, offset: int) -> int:
    return lower.count(b"\n", 0, offset) + 1


def _show(token: bytes) -> str:
    text = token[:24].decode("utf-8", "replace")
    return repr(text + ("..." if len(token) > 24 else ""))


def _raise_structure_error(lower: bytes, start: int, end: int, facets_before: int, name: str) -> NoReturn:
    """Walk the tokens of a solid body and raise a one-line error for the first deviation from the grammar
    (including a vertex coordinate that is not a number)."""
    toks, lines = _clean_tokens(lower, start, end)
    end_line = _line_of(lower, end)
    state = {"facet": 0, "complete": 0}

    def fail(i: int, problem: str, garbage: bool = False) -> NoReturn:
        line = int(lines[i]) if i < len(toks) else end_line
        if garbage:
            raise MeshFileError(f"{name}: not an STL file: line {line}: {problem}")
        raise MeshFileError(
            f"{name}: malformed ASCII STL: facet {facets_before + state['facet']} (line {line}): {problem}"
        )

    def expect(i: int, keyword: bytes) -> int:
        if i >= len(toks):
            fail(i, f"expected '{keyword.decode()}' but the solid ends (line {end_line})")
        if toks[i] != keyword:
            fail(i, f"expected '{keyword.decode()}' but found {_show(toks[i])}")
        return i + 1

    i = 0
    while i < len(toks):
        state["facet"] += 1
        if toks[i] != b"facet":
            # no facet anywhere before this point: text after "solid" that is not STL at all
            garbage = facets_before == 0 and state["complete"] == 0
            fail(i, f"expected 'facet' or 'endsolid' but found {_show(toks[i])}", garbage)
        facet_at = i
        i = expect(i + 1, b"normal")
        for k in range(3):
            if i >= len(toks) or toks[i] in _KEYWORDS:
                fail(facet_at, f"the facet normal has {k} values, expected 3")
            i += 1
        i = expect(i, b"outer")
        i = expect(i, b"loop")
        vertices = 0
        while i < len(toks) and toks[i] == b"vertex":
            vertices += 1
            vertex_at = i
            for k in range(3):
                i += 1
                if i >= len(toks) or toks[i] in _KEYWORDS:
                    fail(vertex_at, f"a vertex has {k} coordinates, expected 3")
                if not _is_number(toks[i]):
                    fail(i, f"cannot parse vertex coordinate {_show(toks[i])}")
            i += 1
            if i < len(toks) and toks[i] not in _KEYWORDS:
                fail(i, f"a vertex has more than 3 coordinates (extra {_show(toks[i])})")
        if vertices != 3:
            fail(facet_at, f"the outer loop has {vertices} vertices, expected 3")
        i = expect(i, b"endloop")
        i = expect(i, b"endfacet")
        state["complete"] += 1
    # Unreachable when the fast path and this walk agree; kept as a safety net.
    raise MeshFileError(
        f"{name}: malformed ASCII STL between lines {_line_of(lower, start)} and {end_line}"
    )
