"""Read PLY files (Stanford's Polygon File Format; ASCII, binary little- or big-endian) into vertices and polygons.

The layout (Paul Bourke's PLY page): header lines ``ply``, ``format ascii|binary_little_endian|binary_big_endian
1.0``, ``comment``/``obj_info`` (ignored), ``element NAME COUNT`` each followed by its ``property TYPE NAME`` and
``property list COUNT_TYPE ITEM_TYPE NAME`` lines (types char/int8 ... double/float64), ``end_header``; then each
element's records in header order (ASCII: a line each, a list as its count then its items; binary: packed). Read:
``vertex`` ``x y z`` (among any properties, any type) and the ``face`` list ``vertex_indices`` (else
``vertex_index``); other properties and elements, lists included, are skipped.

Decided where the format leaves room: a UTF-8 byte-order mark dropped; LF, CRLF or CR line ends; refused: an unknown
header keyword, a second ``format`` line or ``vertex``/``face`` element, a property named twice, a float or negative
list count, a face of fewer than 3 vertices, no ``face`` element (a point cloud; 0 face records: no faces). ASCII:
blank lines skipped, other lines exactly the records declared ("cut short?" / "a wrong count?"; other elements' lines
counted, not parsed), numbers rounded to their declared type (a ``float`` x to float32, as in a binary file).
Binary: bytes after the last record refused.

Columnar: binary, an element whose lists keep the first record's lengths is one ``np.frombuffer`` (structured);
mixed lengths are read a run of equal lengths at a time, and where runs are short (triangles and quads alternating)
walked 512 records at a time in Python (``struct``): the only loop per record. ASCII: one ``np.fromstring`` per
element (token counts per line found on the bytes: lists of any lengths); a loop per line only to name a bad line
or to read an element with several lists, or with a float property beside its list.
"""

from __future__ import annotations

import re
import struct
import warnings
from typing import NamedTuple

import numpy as np

from ..errors import MeshFileError, flatten

__all__ = ["read_ply"]

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
          "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
          "double": "f8", "float64": "f8"}
_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
_FIRST = re.compile(rb"ply[ \t]*(?:\r\n|\n|\r)")
_END = re.compile(rb"(?:\r\n|\n|\r)end_header[ \t]*(?:\r\n|\n|\r|\Z)")  # (a CR before binary data's first LF: lost)
_INTEGER = re.compile(rb"[+-]?[0-9]+")


class _Prop(NamedTuple):
    name: str
    type: str  # numpy's code (a list's item type): "u1", "f4", ...
    count: str | None  # a list's count type; None for a single number


def read_ply(data: bytes, name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` float64 (file units), ``counts`` ``(F,)`` int64 (vertices per face, each at least 3) and
    ``indices`` ``(counts.sum(),)`` int64 (vertex indices counted from 0, face by face in file order, not checked
    against V) of the PLY file ``data``; a one-line :class:`MeshFileError` naming ``name`` for a file that is not
    PLY, a broken header, no ``x y z`` or ``vertex_indices``, a record short of numbers or not numbers, a file cut
    short or longer than its header declares, a face of fewer than 3 vertices."""

    def fail(reason: str) -> MeshFileError:
        return MeshFileError(f"{name}: cannot read PLY file: {flatten(reason, 300)}")  # (its names: escaped)

    data = bytes(data)
    order, elements, body = _header(data, 3 if data.startswith(b"\xef\xbb\xbf") else 0, fail)
    found = {el: props for el, _, props in elements}
    if "vertex" not in found:
        raise fail("no vertex element in the header")
    if "face" not in found:
        others = [el for el in found if el != "vertex"]
        raise fail(f"no face element (its elements: {', '.join(['vertex', *others])}; gpuslice reads faces, not "
                   f"{others[0]})" if others else "no faces (a point cloud?): the header declares no face element")
    vnames, fnames = [p.name for p in found["vertex"]], [p.name for p in found["face"]]
    for axis in "xyz":
        if axis not in vnames:
            raise fail(f"the vertex element has no {axis} property")
        if found["vertex"][vnames.index(axis)].count:
            raise fail(f"the vertex property {axis} is a list, not a coordinate")
    lname = "vertex_indices" if "vertex_indices" in fnames else "vertex_index"
    if lname not in fnames:
        raise fail("the face element has no vertex_indices list")
    if not (listed := found["face"][fnames.index(lname)]).count:
        raise fail(f"the face property {lname} is not a list (property list COUNT_TYPE ITEM_TYPE {lname})")
    if listed.type[0] == "f":
        raise fail(f"the face list {lname} holds floating-point numbers, not vertex indices")
    want = {"vertex": [vnames.index(a) for a in "xyz"], "face": [fnames.index(lname)]}
    got = (_binary if order else _ascii)(data, body, elements, order, want, fail)
    vertices = np.empty((len(got["vertex"][0]), 3))
    with np.errstate(over="ignore"):  # (a float x past float32: infinite, refused with the coordinates' checks)
        for k, (column, i) in enumerate(zip(got["vertex"], want["vertex"], strict=True)):
            vertices[:, k] = np.asarray(column, np.float32 if found["vertex"][i].type == "f4" else np.float64)
    counts, indices = (np.asarray(a, np.int64) for a in got["face"][0])
    if (bad := np.flatnonzero(counts < 3)).size:
        raise fail(f"face {bad[0] + 1} (of {len(counts)}) has {counts[bad[0]]} vertices (a face needs 3)")
    return vertices, counts, indices


def _header(data: bytes, start: int, fail) -> tuple[str, list[tuple[str, int, list[_Prop]]], int]:
    """The byte order (``""`` for ASCII, ``"<"``, ``">"``), the elements (name, record count, properties) and the
    offset of the first record, from the header at ``data[start:]``."""
    if not _FIRST.match(data, start):
        raise fail("not a PLY file (no 'ply' line at its start)")
    if (end := _END.search(data, start)) is None:
        raise fail("no end_header line (not a PLY file, or its header is cut short)")
    order, elements = None, []
    for k, line in enumerate(data[start : end.start()].decode("ascii", "replace").splitlines()[1:], 2):
        t, where = line.split(), f"header line {k} ({line.strip()[:50]!r})"
        if not t or t[0] in ("comment", "obj_info"):
            continue
        if t[0] == "format":
            if order is not None:
                raise fail(f"{where}: a second format line")
            if len(t) != 3 or t[1] not in _FORMATS or t[2] != "1.0":
                raise fail(f"{where} is not 'format ascii|binary_little_endian|binary_big_endian 1.0'")
            order = _FORMATS[t[1]]
        elif t[0] == "element":
            if len(t) != 3 or not t[2].isdigit():
                raise fail(f"{where} is not 'element NAME COUNT'")
            if t[1] in ("vertex", "face") and any(e[0] == t[1] for e in elements):
                raise fail(f"{where}: a second {t[1]} element")
            elements.append((t[1], int(t[2]), []))
        elif t[0] == "property":
            if len(t) == 3 and t[1] in _TYPES:
                prop = _Prop(t[2], _TYPES[t[1]], None)
            elif len(t) == 5 and t[1] == "list" and _TYPES.get(t[2], "f")[0] != "f" and t[3] in _TYPES:
                prop = _Prop(t[4], _TYPES[t[3]], _TYPES[t[2]])
            else:
                raise fail(f"{where} is not 'property TYPE NAME' or 'property list COUNT_TYPE ITEM_TYPE NAME' "
                           "(an integer COUNT_TYPE) with PLY's types")
            if not elements:
                raise fail(f"{where}: a property before any element")
            if any(p.name == prop.name for p in elements[-1][2]):
                raise fail(f"{where}: a second property {prop.name} in element {elements[-1][0]}")
            elements[-1][2].append(prop)
        else:
            raise fail(f"{where}: unknown keyword {t[0][:20]!r}")
    if order is None:
        raise fail("no format line in the header")
    return order, elements, end.end()


def _ascii(data: bytes, body: int, elements, order: str, want: dict[str, list[int]], fail) -> dict[str, list]:
    """The ``want`` properties (by index: a column, or ``(counts, items)`` for a list) of the ASCII records after
    the header. The lines' tokens are found on the bytes (numpy), no line split in Python."""
    text = data[body:]
    if b"\r" in text:
        text = text.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    byte = np.frombuffer(text, np.uint8)
    blank = np.r_[True, byte <= 32, True]
    start = np.flatnonzero(~blank[1:-1] & blank[:-2])  # (every token's first byte)
    line = np.searchsorted(np.flatnonzero(byte == 10), start)  # (its line)
    first = np.flatnonzero(np.r_[True, line[1:] != line[:-1]]) if start.size else start  # (the lines with tokens)
    tokens = np.diff(np.r_[first, start.size])
    total = sum(n for _, n, _ in elements)
    if len(first) != total:
        declared = ", ".join(f"{n} {el}" for el, n, _ in elements)
        raise fail(f"the header declares {total} records ({declared}), the file holds {len(first)} lines after it "
                   f"({'cut short?' if len(first) < total else 'a wrong count?'})")
    got, at, ends = {}, 0, np.r_[start[first[1:]], len(text)] if total else start
    for el, n, props in elements:
        if el in want:
            chunk = text[start[first[at]] : ends[at + n - 1]] if n else b""
            got[el] = _ascii_columns(chunk, tokens[at : at + n], props, want[el])
            if got[el] is None:
                got[el] = _ascii_lines([r for r in chunk.split(b"\n") if r.strip()], el, props, want[el], fail)
        at += n
    return got


def _ascii_columns(text: bytes, tokens: np.ndarray, props: list[_Prop], want: list[int]) -> list | None:
    """The ``want`` properties of the lines ``text`` (``tokens`` numbers on each) by one ``np.fromstring``, or None
    where a line does not fit or a float property sits beside a list (then :func:`_ascii_lines`)."""
    lists = [i for i, p in enumerate(props) if p.count]
    integer = all(p.type[0] != "f" for p in props)
    if not len(tokens) or len(lists) > 1 or (lists and not integer):
        return None
    byte = np.frombuffer(text, np.uint8)
    blank = np.r_[True, byte <= 32, True]
    sign = np.flatnonzero((byte == 43) | (byte == 45))  # (numpy's parser reads "- 2" as -2, a last "-" as 0)
    if sign.size and (blank[sign + 2].any() or not (blank[sign] | np.isin(byte[sign - 1], (69, 101))).all()):
        return None
    try:
        with warnings.catch_warnings():  # (numpy < 2.3 warns where later ones raise: a token that is no number)
            warnings.simplefilter("error", DeprecationWarning)
            nums = np.fromstring(text, np.int64 if integer else np.float64, sep=" ")
    except (ValueError, DeprecationWarning):
        return None
    if len(nums) != tokens.sum() or (integer and np.isin(nums, (-1 << 63, (1 << 63) - 1)).any()):  # (past 64 bits)
        return None
    first, j = np.cumsum(tokens) - tokens, lists[0] if lists else len(props)
    if lists and (tokens <= j).any():
        return None
    c = nums[first + j] if lists else np.zeros(len(tokens), np.int64)
    if (c < 0).any() or (tokens != len(props) + c).any():
        return None
    items = np.repeat(first + j + 1 - (np.cumsum(c) - c), c) + np.arange(c.sum())
    return [nums[first + i] if i < j else (c, nums[items]) if i == j else nums[first + c + i] for i in want]


def _ascii_lines(rows: list[bytes], el: str, props: list[_Prop], want: list[int], fail) -> list:
    """The ``want`` properties of element ``el``'s lines ``rows``, a line at a time (Python), naming a bad one."""
    out: list = [[] if props[i].count is None else ([], []) for i in want]
    slot = {i: out[s] for s, i in enumerate(want)}
    for k, row in enumerate(rows):
        tokens, t = row.split(), 0
        where = f"{el} line {k + 1} ({row.strip().decode(errors='replace')[:40]!r})"
        try:
            for i, p in enumerate(props):
                if p.count is None:
                    if i in slot:
                        slot[i].append(float(tokens[t]))
                    t += 1
                    continue
                if not _INTEGER.fullmatch(tokens[t]) or int(tokens[t]) < 0:
                    raise fail(f"{where}: {tokens[t].decode(errors='replace')[:20]!r} is not a count of {p.name}")
                n, t = int(tokens[t]), t + 1
                if len(tokens) < t + n:
                    raise IndexError
                if i in slot:
                    if not all(_INTEGER.fullmatch(v) for v in tokens[t : t + n]):
                        raise fail(f"{where}: {p.name} holds other than integers")
                    slot[i][0].append(n)
                    slot[i][1].extend(int(v) for v in tokens[t : t + n])
                t += n
        except IndexError:
            raise fail(f"{where} is short of numbers for its properties ({' '.join(p.name for p in props)})") from None
        except ValueError:
            raise fail(f"{where}: {tokens[t].decode(errors='replace')[:20]!r} is not a number") from None
        if t != len(tokens):
            raise fail(f"{where} holds more numbers than its properties ({' '.join(p.name for p in props)})")
    try:
        return [np.array(v) if isinstance(v, list) else (np.array(v[0], np.int64), np.array(v[1], np.int64))
                for v in out]
    except OverflowError:
        raise fail(f"a {el} list holds a number out of range (over 64 bits)") from None


def _binary(data: bytes, body: int, elements, order: str, want: dict[str, list[int]], fail) -> dict[str, list]:
    """The ``want`` properties (by index) of the binary records after the header, each element read in turn."""
    got, off = {}, body
    for el, n, props in elements:
        get, off = _binary_element(data, off, el, n, props, order, fail)
        if el in want:
            got[el] = [get(i) for i in want[el]]
    if off != len(data):
        raise fail(f"{len(data) - off} bytes after the last record the header declares (a wrong count?)")
    return got


def _binary_element(data: bytes, off: int, el: str, n: int, props: list[_Prop], order: str, fail):
    """A getter of element ``el``'s properties (by index: a column, or ``(counts, items)`` for a list) and the offset
    after its ``n`` records, which start at ``off``: the whole element one run of equal list lengths (the usual
    file), else runs, else records walked in Python."""
    if not n or not props:
        return (lambda i: (np.zeros(0, np.int64),) * 2 if props[i].count else np.zeros(0)), off
    lists, segs, pre = [i for i, p in enumerate(props) if p.count], [], 0
    for p in props:  # (bytes before each list's count, the count's struct, the item size; bytes after the last)
        if p.count:
            segs.append((pre, struct.Struct(order + np.dtype(p.count).char), np.dtype(p.type).itemsize))
        pre = 0 if p.count else pre + np.dtype(p.type).itemsize

    def short(have: int) -> MeshFileError:
        return fail(f"the header declares {n} {el} records, the file holds {have} (cut short?)")

    def walk(at: int, count: int, done: int) -> tuple[list[int], list[list[int]], int]:
        """Starts and list lengths of ``count`` records from byte ``at`` (record ``done`` on), and their end."""
        starts, lengths = [], []
        for j in range(count):
            starts.append(at)
            lengths.append([])
            for before, st, size in segs:
                if (at := at + before) + st.size > len(data):
                    raise short(done + j)
                if (c := st.unpack_from(data, at)[0]) < 0:
                    raise fail(f"{el} record {done + j + 1} holds a negative list count {c}")
                lengths[-1].append(c)
                at += st.size + c * size
            if (at := at + pre) > len(data):
                raise short(done + j)
        return starts, lengths, at

    def record(lengths) -> np.dtype:
        it = iter(lengths)
        return np.dtype([f for i, p in enumerate(props) for f in ([(f"c{i}", order + p.count), (
            f"p{i}", order + p.type, (next(it),))] if p.count else [(f"p{i}", order + p.type)])])

    starts, lengths, done, chunk = [], [], 0, n
    while done < n:
        c = walk(off, 1, done)[1][0]
        rec = record(c)
        m = min(n - done, (len(data) - off) // rec.itemsize, chunk)  # (at least 1: walk found the record whole)
        table = np.frombuffer(data, rec, m, off)
        same = np.logical_and.reduce([table[f"c{i}"] == ci for i, ci in zip(lists, c, strict=True)]) if lists else 1
        k = m if np.all(same) else int(np.argmin(same))
        if k == n:  # (a structured array: its fields are the columns)
            return (lambda i, t=table, c=c: t[f"p{i}"] if not props[i].count else
                    (np.full(n, c[lists.index(i)]), t[f"p{i}"].astype(np.int64).ravel())), off + n * rec.itemsize
        starts.append(off + rec.itemsize * np.arange(k))
        lengths.append(np.tile(np.array(c, np.int64), (k, 1)))
        done, off, chunk = done + k, off + k * rec.itemsize, min(chunk * 2, 1 << 20) if k == m else max(64, 2 * k)
        if k < 8 and done < n:  # (short runs: lengths alternate)
            s, cs, off = walk(off, min(n - done, 512), done)
            starts.append(np.array(s, np.int64))
            lengths.append(np.array(cs, np.int64).reshape(len(s), len(lists)))
            done += len(s)
    start, length = np.concatenate(starts), np.concatenate(lengths)

    def get(i: int):
        """Property ``i`` gathered from the records' bytes by offset."""
        at, j, item = start.copy(), 0, np.dtype(order + props[i].type)
        for p in props[:i]:
            if p.count:
                at += np.dtype(p.count).itemsize + length[:, j] * np.dtype(p.type).itemsize
                j += 1
            else:
                at += np.dtype(p.type).itemsize
        view = np.ndarray((len(data) - item.itemsize + 1,), item, data, 0, (1,))  # (a number at every byte)
        if not props[i].count:
            return view[at]
        c = length[:, j]
        at += np.dtype(props[i].count).itemsize - (np.cumsum(c) - c) * item.itemsize
        return c, view[np.repeat(at, c) + np.arange(int(c.sum())) * item.itemsize]

    return get, off
