"""The raw triangle soup every reader returns (:class:`RawMesh`), the file-format constants the readers share and the
coordinate check (one-line errors naming the file)."""

from __future__ import annotations

import re
import zipfile
import zlib
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidGeometryError

__all__ = ["RawMesh", "BINARY_STL_RECORD", "MAX_COORDINATE", "NON_STL_EXTENSIONS", "check_coordinates", "plain_text",
           "ZIP_ERRORS"]

#: One 50-byte binary STL facet record: stored normal, three corners, the 16-bit "attribute byte count".
BINARY_STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])

#: Largest accepted coordinate magnitude in file units. The slicer forms differences and products of
#: coordinates in float32 (max 3.4e38); beyond 1e18 a product of two differences can overflow.
MAX_COORDINATE = 1e18

#: What reading a broken zip (a 3MF) raises: a bad archive or deflate stream, a member cut short, a compression
#: method zipfile does not implement (NotImplementedError), an encrypted member (RuntimeError), a bad header field
ZIP_ERRORS = (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError, ValueError)

#: Extensions (lower case) of the other mesh formats (OBJ, PLY, OFF, 3MF: gpuslice's readers in this package);
#: every other name is parsed as an STL.
NON_STL_EXTENSIONS = {".obj": "obj", ".ply": "ply", ".off": "off", ".3mf": "3mf"}

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
        ``(F, 3, 3)`` C-contiguous, float32 for STL (as stored) and float64 for the other formats (OBJ, PLY,
        OFF, 3MF: placed before they are rounded, :func:`gpuslice.mesh.mesh.mesh_from_triangles`):
        ``triangles[f, k]`` is corner ``k`` (x, y, z) of facet ``f``, in
        file order and file units (millimetres by 3D-printing convention; STL itself has no units). Every
        coordinate is finite with magnitude at most :data:`MAX_COORDINATE`; ``F >= 1``.
    normals : numpy.ndarray or None
        ``(F, 3)`` float32 facet normals as stored in the file, not validated: they may be zero, not unit
        length, infinite, or NaN where an ASCII value was unparsable (``weirdvalue``). ``None`` for the other
        formats, which store no per-facet normal.
    source_format : str
        ``"binary STL"``, ``"ASCII STL"``, or the other format's name: ``"obj"``, ``"ply"``, ``"off"``,
        ``"3mf"``.
    solids : int
        Number of ``solid ... endsolid`` blocks of an ASCII STL (empty blocks included), 1 for a binary STL
        and for the other formats (a file's objects are merged into one mesh, so the count is not kept).
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


def check_coordinates(coords: np.ndarray, name: str) -> None:
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
        f"{name}: coordinates up to {biggest:.2g} overflow float32 arithmetic (limit {MAX_COORDINATE:.0e} as "
        f"given, before any scaling; {n_big} {noun} affected)"
    )


def plain_text(data: bytes) -> bytes:
    """A text mesh file's bytes with a UTF-8 byte-order mark dropped, CR and CRLF line ends made LF, and ``#``
    comments (to the end of their line) removed: what the OBJ and OFF readers split into lines."""
    if data.startswith(b"\xef\xbb\xbf"):
        data = data[3:]
    if b"\r" in data:
        data = data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    if b"#" in data:
        data = re.sub(rb"#[^\n]*", b"", data)
    return data
