"""STL in memory: binary or ASCII, into a raw triangle array, with strict validation.

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

import numpy as np

from ..errors import EmptyMeshError, MeshFileError
from .rawmesh import (
    _BINARY_BYTES,
    _HEADER_BYTES,
    _MAGIC,
    _MAX_TRAILING_BYTES,
    _RECORD_BYTES,
    _TRAILING_PADDING,
    BINARY_STL_RECORD,
    RawMesh,
    check_coordinates,
)
from .stl_ascii import parse_ascii

__all__ = ["read_stl_bytes"]


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
            return parse_ascii(text, name)
    is_text = _is_text(data)

    # Neither a binary STL of matching size nor ASCII: say as precisely as possible what it is.
    if size == 0:
        raise MeshFileError(f"{name}: not an STL file: the file is empty (0 bytes)")
    kind = _sniff(data)
    if kind is not None and kind.startswith("ZIP") and str(name).lower().endswith(".npz"):
        raise MeshFileError(f"{name}: a saved slice result (.npz), not a mesh: this command reads the model (STL, OBJ, "
                            "PLY, OFF, 3MF); gpuslice view shows a saved result")
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
    check_coordinates(triangles, name)
    return RawMesh(triangles=triangles, normals=normals, source_format="binary STL", solids=1,
                   header=data[:80], path=name)


# --------------------------------------------------------------------------------------------------------
# ASCII STL


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
