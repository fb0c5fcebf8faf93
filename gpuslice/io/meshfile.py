"""Read mesh files into a raw triangle array, with strict validation.

The slicer works on a triangle soup: an ``(F, 3, 3)`` float32 array holding the three corners of every facet
in file order and file units (STL has no units; for 3D printing they are millimetres by convention). This
module reads that array from

* binary STL (one ``np.frombuffer`` over the 50-byte records),
* ASCII STL (a vectorised tokeniser: no Python loop per vertex on the normal path),
* OBJ, PLY, OFF and 3MF by extension, through :mod:`trimesh`, which is imported lazily.

Every problem a user can cause raises a :class:`~gpuslice.errors.MeshFileError` (or its subclasses
:class:`~gpuslice.errors.EmptyMeshError` and :class:`~gpuslice.errors.InvalidGeometryError`) whose message is
one line naming the file and the problem, e.g.
``model.stl: truncated binary STL: header declares 1200 facets (60084 bytes) but the file has 3000 bytes``.

Binary or ASCII is decided by size, not by the first bytes: a file is a binary STL when
``84 + 50 * count == file size`` (``count`` = little-endian uint32 at byte 80), even when its 80-byte header
starts with ``solid`` as many exporters write. A file that starts with ``solid`` and does not match that size
is parsed as ASCII.
"""

from __future__ import annotations

import os
import re
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import numpy as np

from ..errors import EmptyMeshError, GpusliceError, InvalidGeometryError, MeshFileError

__all__ = [
    "read_mesh_source",
    "RawMesh",
    "read_mesh_file",
    "read_stl_bytes",
    "BINARY_STL_RECORD",
    "MAX_COORDINATE",
    "TRIMESH_EXTENSIONS",
]

#: One 50-byte binary STL facet record: stored normal, three corners, the 16-bit "attribute byte count".
BINARY_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])

#: Largest accepted coordinate magnitude in file units. The slicer forms differences and products of
#: coordinates in float32 (max 3.4e38); beyond 1e18 a product of two differences can overflow.
MAX_COORDINATE = 1e18

#: Extensions (lower case) read through trimesh; every other name is parsed as an STL.
TRIMESH_EXTENSIONS = {".obj": "obj", ".ply": "ply", ".off": "off", ".3mf": "3mf"}

_HEADER_BYTES = 84
_RECORD_BYTES = 50
#: Fewer trailing bytes than one record after the declared facets are accepted as exporter padding.
_MAX_TRAILING_BYTES = _RECORD_BYTES - 1

# ASCII STL grammar of one facet as whitespace-separated tokens (21 of them):
#   facet normal nx ny nz outer loop vertex x y z vertex x y z vertex x y z endloop endfacet
_FACET_TOKENS = 21
_KEYWORD_COLUMNS = {
    0: b"facet",
    1: b"normal",
    5: b"outer",
    6: b"loop",
    7: b"vertex",
    11: b"vertex",
    15: b"vertex",
    19: b"endloop",
    20: b"endfacet",
}
_NORMAL_COLUMNS = [2, 3, 4]
_VERTEX_COLUMNS = [8, 9, 10, 12, 13, 14, 16, 17, 18]
_KEYWORDS = frozenset({b"solid", b"endsolid", b"facet", b"normal", b"outer", b"loop", b"vertex", b"endloop",
                       b"endfacet"})

#: Bytes that never occur in a text file (C0 controls except TAB, LF, VT, FF, CR; and DEL).
_BINARY_BYTES = bytes(range(0x00, 0x09)) + bytes(range(0x0E, 0x20)) + b"\x7f"
#: Trailing bytes tolerated after an ASCII STL: whitespace, NUL padding, a DOS end-of-file mark (Ctrl-Z).
_TRAILING_PADDING = b" \t\r\n\x0b\x0c\x00\x1a"
_TOKEN_RE = re.compile(rb"\S+")

_MAGIC = (
    (b"\x89PNG\r\n\x1a\n", "PNG image"),
    (b"PK\x03\x04", "ZIP archive (a 3MF is a ZIP: name it .3mf)"),
    (b"PK\x05\x06", "ZIP archive"),
    (b"\x1f\x8b", "gzip archive"),
    (b"%PDF", "PDF document"),
    (b"GIF8", "GIF image"),
    (b"\xff\xd8\xff", "JPEG image"),
    (b"7z\xbc\xaf\x27\x1c", "7-Zip archive"),
    (b"Rar!", "RAR archive"),
    (b"\x7fELF", "ELF executable"),
    (b"glTF", "binary glTF (GLB) file"),
    (b"ply\n", "PLY file (name it .ply)"),
    (b"ply\r\n", "PLY file (name it .ply)"),
    (b"OFF\n", "OFF file (name it .off)"),
    (b"OFF\r\n", "OFF file (name it .off)"),
)


@dataclass(eq=False)
class RawMesh:
    """Triangles exactly as read from a mesh file, before any repair.

    Attributes
    ----------
    triangles : numpy.ndarray
        ``(F, 3, 3)`` float32, C-contiguous: ``triangles[f, k]`` is corner ``k`` (x, y, z) of facet ``f``, in
        file order and file units (millimetres by 3D-printing convention; STL itself has no units). Every
        coordinate is finite with magnitude at most :data:`MAX_COORDINATE`; ``F >= 1``.
    normals : numpy.ndarray or None
        ``(F, 3)`` float32 facet normals as stored in the file, not validated: they may be zero, not unit
        length, infinite, or NaN where an ASCII value was unparsable (``weirdvalue``). ``None`` for formats
        read through trimesh, which store no per-facet normal.
    source_format : str
        ``"binary STL"``, ``"ASCII STL"``, or the trimesh file type: ``"obj"``, ``"ply"``, ``"off"``,
        ``"3mf"``.
    solids : int
        Number of ``solid ... endsolid`` blocks of an ASCII STL (empty blocks included), 1 for a binary STL
        and for trimesh formats (trimesh merges a file's objects into one mesh, so the count is unknown).
    header : bytes
        The 80-byte header of a binary STL, the first ``solid`` line of an ASCII STL (surrounding whitespace
        and line end stripped), ``b""`` otherwise.
    path : str
        The path or name the mesh was read from, as given.
    """

    triangles: np.ndarray
    normals: np.ndarray | None
    source_format: str
    solids: int
    header: bytes
    path: str

    def __repr__(self) -> str:
        return (
            f"RawMesh(path={self.path!r}, source_format={self.source_format!r}, "
            f"facets={len(self.triangles)}, solids={self.solids}, header={self.header[:40]!r})"
        )


# --------------------------------------------------------------------------------------------------------
# public entry points


def read_mesh_file(path: str | os.PathLike[str]) -> RawMesh:
    """Read a mesh file into a :class:`RawMesh`.

    Files named ``.obj``, ``.ply``, ``.off`` or ``.3mf`` (any case) are read with
    ``trimesh.load(path, force="mesh", process=False)`` (all objects of the file merged, vertices not merged,
    nothing repaired); every other name, ``.stl`` or not, goes through :func:`read_stl_bytes`, which tells
    binary from ASCII STL and recognises common non-STL files.

    Parameters
    ----------
    path : str or os.PathLike
        The file to read. Messages name it exactly as given.

    Returns
    -------
    RawMesh
        At least one facet, all coordinates finite and within :data:`MAX_COORDINATE`.

    Raises
    ------
    MeshFileError
        The path is missing, a directory or unreadable; the file is not a mesh of its type, is truncated or
        malformed (see :func:`read_stl_bytes`); trimesh failed to read it.
    EmptyMeshError
        The file is well formed but holds no facets.
    InvalidGeometryError
        A vertex coordinate is NaN, infinite, or larger in magnitude than :data:`MAX_COORDINATE`.
    """
    name = os.fspath(path)
    if isinstance(name, bytes):  # os.PathLike[bytes]
        name = os.fsdecode(name)
    try:
        if stat.S_ISDIR(os.stat(name).st_mode):
            raise IsADirectoryError
        ext = os.path.splitext(name)[1].lower()
        if ext in TRIMESH_EXTENSIONS:  # trimesh opens the file itself
            return _read_with_trimesh(name, TRIMESH_EXTENSIONS[ext])
        with open(name, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise _file_error(name, exc) from None
    return read_stl_bytes(data, name)


def read_mesh_source(path: str | os.PathLike[str], data: bytes | None = None, label: str | None = None) -> RawMesh:
    """Read a mesh from ``path``, or from ``data`` (the file's bytes, e.g. sent to a batch worker) with ``path``'s
    suffix telling the format; messages name the file ``label`` (default: ``path``)."""
    where = os.fspath(path)
    label = label or where
    if data is None:
        try:
            return read_mesh_file(where)
        except GpusliceError as exc:  # name the file as the user gave it
            if label == where:
                raise
            raise type(exc)(str(exc).replace(where, label)) from None
    suffix = Path(where).suffix.lower()
    if suffix in TRIMESH_EXTENSIONS:  # trimesh reads files: through a private temporary folder
        with tempfile.TemporaryDirectory(prefix="gpuslice-") as tmp:
            p = Path(tmp) / ("model" + suffix)
            p.write_bytes(data)
            try:
                return read_mesh_file(p)
            except GpusliceError as exc:
                raise type(exc)(str(exc).replace(str(p), label)) from None
    return read_stl_bytes(data, label)


def _file_error(name: str, exc: OSError) -> MeshFileError:
    """The one-line error for an OS error met while opening or reading ``name``."""
    if isinstance(exc, IsADirectoryError):
        return MeshFileError(f"{name}: is a directory")
    if isinstance(exc, FileNotFoundError):
        return MeshFileError(f"{name}: no such file")
    if isinstance(exc, NotADirectoryError):
        return MeshFileError(f"{name}: no such file (a parent is not a directory)")
    return MeshFileError(f"{name}: cannot read: {_os_reason(exc)}")


def read_stl_bytes(data: bytes, name: str = "<bytes>") -> RawMesh:
    """Parse a binary or ASCII STL held in memory.

    Binary or ASCII is decided by size: with ``count`` the little-endian uint32 at byte 80, the data is a
    binary STL when ``len(data) == 84 + 50 * count``, whatever its header says (many binary headers start with
    ``solid``). Otherwise data starting with ``solid`` (any case, after optional whitespace or a UTF-8 BOM)
    and holding only text is parsed as ASCII STL.

    Binary STL rules: the records are read with one ``np.frombuffer`` of :data:`BINARY_STL_RECORD`, and the
    claimed ``count`` is checked against the data size before anything is allocated from it. Fewer than 50
    bytes after the declared facets (less than one record: padding some exporters add) are ignored; 50 or more
    are an error, as is a file too short for the facets its header declares.

    ASCII STL rules: LF, CRLF or CR-only line ends; keywords in any case; any layout of the tokens on lines;
    several ``solid ... endsolid`` blocks (each ``solid``/``endsolid`` keyword must start its line, the rest
    of that line is the solid's name); text after ``endloop``/``endfacet``/``endsolid`` on the same line is
    ignored; stored normals may be junk (``+inf``, ``weirdvalue``: kept as inf / NaN). Each facet must be
    ``facet normal a b c``, ``outer loop``, exactly three ``vertex x y z``, ``endloop``, ``endfacet``; each
    ``solid`` needs its ``endsolid``; only whitespace may stand between blocks and after the last one (plus
    trailing NUL bytes or a Ctrl-Z end-of-file mark).

    Parameters
    ----------
    data : bytes
        The whole file (any bytes-like object).
    name : str, optional
        The file name used in messages and stored as :attr:`RawMesh.path`.

    Returns
    -------
    RawMesh
        ``source_format`` is ``"binary STL"`` or ``"ASCII STL"``.

    Raises
    ------
    MeshFileError
        Not an STL file (empty, a PNG, a ZIP, other text or binary junk), too short to be a binary STL,
        truncated, followed by 50 or more unexpected bytes, or a malformed ASCII facet (the message names the
        facet number and line).
    EmptyMeshError
        A well-formed STL with zero facets.
    InvalidGeometryError
        A vertex coordinate is NaN, infinite, or larger in magnitude than :data:`MAX_COORDINATE`.
    """
    if not isinstance(data, bytes):
        data = bytes(data)
    size = len(data)
    count = int.from_bytes(data[80:84], "little") if size >= _HEADER_BYTES else -1
    expected = _HEADER_BYTES + _RECORD_BYTES * count
    if size >= _HEADER_BYTES and expected == size:
        return _parse_binary(data, count, name)

    starts_with_solid = _starts_with_solid(data)
    if starts_with_solid:
        text = data.rstrip(_TRAILING_PADDING)
        if _is_text(text):
            return _parse_ascii(text, name)
    is_text = _is_text(data)

    # Neither a binary STL of matching size nor ASCII: say as precisely as possible what it is.
    if size == 0:
        raise MeshFileError(f"{name}: not an STL file: the file is empty (0 bytes)")
    kind = _sniff(data)
    if kind is not None:
        raise MeshFileError(f"{name}: not an STL file (looks like a {kind})")
    if size < _HEADER_BYTES:
        if starts_with_solid:
            raise MeshFileError(
                f"{name}: not an STL file: starts with 'solid' but holds binary data, and is too short to be "
                f"a binary STL ({size} bytes)"
            )
        raise MeshFileError(
            f"{name}: not an STL file: too short to be a binary STL ({size} bytes) and does not start with "
            "'solid'"
        )
    if is_text:
        raise MeshFileError(f"{name}: not an STL file: text that does not start with 'solid' ({size} bytes)")
    solid_note = " (header starts with 'solid' but the file holds binary data)" if starts_with_solid else ""
    if starts_with_solid and b"\0" not in data[80:84]:
        # Text where a binary facet count would be: an ASCII-looking file with binary junk in it.
        raise MeshFileError(
            f"{name}: not an STL file: starts with 'solid' but holds binary data and is not a binary STL "
            f"either (as one it would declare {count} facets, {expected} bytes; the file has {size} bytes)"
        )
    if expected > size:
        raise MeshFileError(
            f"{name}: truncated binary STL: header declares {count} facets ({expected} bytes) but the file "
            f"has {size} bytes{solid_note}"
        )
    extra = size - expected
    if extra <= _MAX_TRAILING_BYTES:
        return _parse_binary(data, count, name)
    raise MeshFileError(
        f"{name}: binary STL has {extra} unexpected bytes after the {count} facets its header declares "
        f"({expected} of {size} bytes; at most {_MAX_TRAILING_BYTES} trailing bytes are accepted){solid_note}"
    )


# --------------------------------------------------------------------------------------------------------
# binary STL


def _parse_binary(data: bytes, count: int, name: str) -> RawMesh:
    """Parse a binary STL whose ``count`` records were checked to fit in ``data``."""
    if count == 0:
        raise EmptyMeshError(f"{name}: no facets (binary STL whose header declares 0 facets)")
    records = np.frombuffer(data, dtype=BINARY_STL_RECORD, count=count, offset=_HEADER_BYTES)
    triangles = np.ascontiguousarray(records["v"])  # copies: frombuffer views are read-only
    normals = np.ascontiguousarray(records["normal"])
    _check_coordinates(triangles, name)
    return RawMesh(triangles=triangles, normals=normals, source_format="binary STL", solids=1,
                   header=data[:80], path=name)


# --------------------------------------------------------------------------------------------------------
# ASCII STL


def _parse_ascii(data: bytes, name: str) -> RawMesh:
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
    _check_coordinates(coords, name)
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


# --------------------------------------------------------------------------------------------------------
# shared checks


def _check_coordinates(coords: np.ndarray, name: str) -> None:
    """Reject NaN / infinite coordinates and magnitudes above :data:`MAX_COORDINATE`.

    ``coords`` has one row (or one ``(3, 3)`` block) per facet. Two reductions on the happy path; the counting
    work only runs when something is wrong.
    """
    if coords.size == 0:
        return
    lo = coords.min()
    hi = coords.max()
    if lo >= -MAX_COORDINATE and hi <= MAX_COORDINATE:  # False for NaN
        return
    per_facet = coords.reshape(len(coords), -1)
    finite = np.isfinite(per_facet)
    bad = ~finite.all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0]) + 1
        n_bad = int(bad.sum())
        noun = "facet has" if n_bad == 1 else "facets have"
        raise InvalidGeometryError(
            f"{name}: {n_bad} {noun} NaN or infinite vertex coordinates "
            f"(first: facet {first} of {len(coords)})"
        )
    magnitude = np.abs(per_facet)
    biggest = float(magnitude.max())
    n_big = int((magnitude > MAX_COORDINATE).any(axis=1).sum())
    noun = "facet" if n_big == 1 else "facets"
    raise InvalidGeometryError(
        f"{name}: coordinates up to {biggest:.2g} overflow float32 arithmetic (limit {MAX_COORDINATE:.0e}; "
        f"{n_big} {noun} affected)"
    )


def _starts_with_solid(data: bytes) -> bool:
    head = data[:512]
    if head.startswith(b"\xef\xbb\xbf"):
        head = head[3:]
    head = head.lstrip()
    return head[:5].lower() == b"solid" and (len(head) == 5 or head[5:6].isspace())


def _is_text(data: bytes) -> bool:
    """True when ``data`` holds no byte that a text file never contains (NUL and other C0 controls)."""
    return len(data.translate(None, _BINARY_BYTES)) == len(data)


def _sniff(data: bytes) -> str | None:
    """Name the kind of a well-known non-STL file from its first bytes, ``None`` if unknown."""
    for magic, kind in _MAGIC:
        if data.startswith(magic):
            return kind
    return None


def _os_reason(exc: OSError) -> str:
    if exc.strerror:
        return exc.strerror[:1].lower() + exc.strerror[1:]
    return " ".join(str(exc).split()) or type(exc).__name__


# --------------------------------------------------------------------------------------------------------
# other formats via trimesh


def _read_with_trimesh(name: str, file_type: str) -> RawMesh:
    """Read OBJ / PLY / OFF / 3MF with trimesh (imported here: it is slow to import)."""
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - trimesh is a dependency
        raise MeshFileError(f"{name}: reading {file_type.upper()} files needs trimesh ({exc})") from None
    try:
        mesh = trimesh.load(name, force="mesh", process=False)
        triangles = np.asarray(mesh.triangles, dtype=np.float64)
    except Exception as exc:  # any trimesh failure means a file it cannot read: one line for the user
        reason = " ".join(str(exc).split()) or type(exc).__name__
        if len(reason) > 200:
            reason = reason[:197] + "..."
        raise MeshFileError(
            f"{name}: cannot read {file_type.upper()} file: {type(exc).__name__}: {reason}"
        ) from None
    triangles = triangles.reshape(-1, 3, 3)
    if len(triangles) == 0:
        raise EmptyMeshError(f"{name}: no facets ({file_type.upper()} file read by trimesh)")
    _check_coordinates(triangles, name)
    return RawMesh(triangles=np.ascontiguousarray(triangles, dtype=np.float32), normals=None,
                   source_format=file_type, solids=1, header=b"", path=name)
