"""Read 3MF files (3MF core specification 1.3, production extension 1.1) into one triangle mesh, strictly.

The root model part is the ``_rels/.rels`` target of type ``…/3dmodel``; without a readable one, ``3D/3dmodel.model``,
else the first ``3D/*.model`` (trimesh never read the ``.rels``). Part names match ASCII case-insensitively, as OPC
compares them (lib3mf missed ``3d/3DModel.model``), the leading ``/`` optional. Every ``<build><item>`` is read
down its ``<components>``; ``p:path`` (production extension: Bambu Studio, PrusaSlicer) on an item or a root-part
component names the part holding the object (ids are per part; a non-root part's unit and build are not used, as in
lib3mf; trimesh put all of a part's meshes under each component naming it, and ignored an item's path). A
``transform="m00 m01 m02 m10 m11 m12 m20 m21 m22 m30 m31 m32"`` maps the row vector ``(x y z 1)`` times that 4x3
matrix, a component's before its parent's; where the product mirrors (negative determinant) the instance's triangles
are reversed to keep facing outwards (a transform keeps a volume's sign, says the specification). Instances are
merged in build order, in millimetres from the root model's ``unit``. A mesh of any object type an item reaches
(``model``, ``solidsupport``, ``support``, ``surface``, even ``other``, which items must not reach) is read, as
trimesh and lib3mf read them; objects no item reaches are not (a consumer must not output them).

Speed: no element tree of the meshes. ``<vertex x="…" y="…" z="…"/>`` and ``<triangle v1= v2= v3= …/>`` lists
written the usual way (the same text between the values everywhere; properties after ``v3`` dropped) are checked
and converted by numpy passes and one ``np.fromstring``; the rest, each block replaced by a marker, is parsed by
:mod:`xml.etree.ElementTree`. Any other form (attribute order, quotes, entities, comments) is left to the element
tree, converted the same way, with a pass naming the first wrong value where that fails.

Numbers are the schema's ``ST_Number`` (``1.`` taken; ``1_000``, ``inf``, ``0x10`` refused: lib3mf read ``1_0`` as
1). Refused in one line naming the file and the problem: a zip or part that cannot be read, no model part, a DTD
(forbidden), XML that does not parse, a value not a number, an index out of range, an item or component naming an
object not defined (trimesh logged "id 2 included but not defined!" and dropped it) or a part not in the zip, two
objects of one id (trimesh merged them), an object neither mesh nor components, a component cycle (trimesh read
nothing) or nesting past :data:`MAX_COMPONENT_DEPTH`, past :data:`MAX_TRIANGLES` or :data:`MAX_MESHES`, a unit not
in the table given."""

from __future__ import annotations

import io
import posixpath
import re
import xml.etree.ElementTree as ET
import zipfile
from collections.abc import Mapping
from functools import lru_cache
from typing import NamedTuple
from urllib.parse import unquote

import numpy as np
from numpy.lib.stride_tricks import as_strided

from ..errors import MeshFileError, flatten
from .rawmesh import ZIP_ERRORS

__all__ = ["read_3mf", "MAX_COMPONENT_DEPTH", "MAX_TRIANGLES", "MAX_MESHES", "CORE_NS", "PRODUCTION_NS"]

CORE_NS = "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"
PRODUCTION_NS = "http://schemas.microsoft.com/3dmanufacturing/production/2015/06"
#: components nested deeper than this under a build item are refused (real files nest one or two deep)
MAX_COMPONENT_DEPTH = 32
#: the most triangles (and 3 times the most vertices) the build may place: instancing multiplies a small file (a
#: fuzzing helper's 10 KB file placed 2^26 and ran out of memory; 2^24 corners take 1.2 GB, and the largest meshes
#: gpuslice is measured on have 6.4M triangles)
MAX_TRIANGLES = 1 << 24
#: the most meshes the build may place (instances, each placed by Python code)
MAX_MESHES = 1 << 16
_P_PATH = f"{{{PRODUCTION_NS}}}path"
_MARK = b"gpuslice-mesh:"  # a <mesh> block read in bulk, in the skeleton the element tree parses
_WS = rb"[ \t\r\n]"
_MESH_OPEN = re.compile(rb"<((?:[A-Za-z_][A-Za-z0-9_.-]*:)?)mesh" + _WS + rb"*>")
_TAG_END = re.compile(_WS + b"*>")
_NOT_PLAIN = re.compile(rb"xmlns|<[!?]|-->|]]>|\?>")
_TRIANGLE_TAIL = re.compile(rb'(' + _WS + rb'v3' + _WS + rb'*=' + _WS + rb'*"[^"<>]*")[^<>]*?(/>)')
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INDEX = re.compile(r"[+-]?[0-9]+")
_IDENTITY = np.eye(4)
_CHARS = {np.float64: b'0123456789+-.eE"', np.int64: b'0123456789"'}

Instance = tuple[np.ndarray, np.ndarray, np.ndarray]  # vertices, triangles, 4x4 row-vector matrix


def read_3mf(data: bytes, name: str, *, units: Mapping[str, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` float64 in millimetres (the model's unit applied) and triangles ``(F, 3)`` int64 (indices
    into them, each facing as written, mirrored instances turned back) of every build item's meshes, their
    transforms applied, merged in build order.

    ``data``: the 3MF's zip bytes (gpuslice's :func:`~gpuslice.io.meshfile.inflate_3mf` first inflates them under
    its limits; a compressed zip is read too, without those limits). ``name``: the file, as messages name it.
    ``units``: millimetres per 3MF unit name (pass :data:`gpuslice.io.meshfile.UNITS_3MF_MM`); None knows only the
    default ``millimeter``. No build item: empty arrays. Raises :class:`MeshFileError` (one line naming ``name``).
    """
    units = {"millimeter": 1.0} if units is None else units
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            package = _Package(zf, name)
            unit = (package.part(package.root).unit or "millimeter").strip()
            if unit not in units:
                raise MeshFileError(f"{name}: unknown 3MF unit {flatten(unit, 40)!r} (the 3MF units are "
                                    f"{', '.join(units)})")
            instances = package.instances()
    except ZIP_ERRORS as exc:
        raise MeshFileError(f"{name}: cannot read 3MF file: {type(exc).__name__}: "
                            f"{flatten(str(exc), 200) or type(exc).__name__}") from None
    return _merge(instances, float(units[unit]))


class _Model(NamedTuple):
    """One model part: ``objects`` ``{id: ("mesh", vertices, triangles) | ("components", [(part, id, matrix, what)])
    | ("none",)}`` and build ``items`` ``[(part, id, matrix, what)]``."""

    unit: str | None
    objects: dict[str, tuple]
    items: list[tuple]


class _Package:
    """The zip's model parts (``root``: the root part's member name), each parsed when first referenced."""

    def __init__(self, zf: zipfile.ZipFile, name: str) -> None:
        self.zf, self.name = zf, name
        self.members = {n.lstrip("/").lower(): n for n in zf.namelist() if not n.endswith("/")}
        self.models: dict[str, _Model] = {}
        self.root = self.root_part()

    def fail(self, reason: str) -> MeshFileError:
        return MeshFileError(f"{self.name}: cannot read 3MF file: {flatten(reason, 300)}")

    def member(self, path: str) -> str | None:
        """The zip member of the part ``path`` (case-insensitive, leading ``/`` optional, %-escapes taken)."""
        key = path.strip().lstrip("/").lower()
        return self.members.get(key) or self.members.get(unquote(key))

    def root_part(self) -> str:
        """The root model part's member name: the ``.rels`` start part, else the conventional names."""
        rels = self.member("_rels/.rels")
        try:
            tree = ET.fromstring(self.zf.read(rels)) if rels is not None else None
        except (ET.ParseError, LookupError):  # (the model part is what matters; LookupError: an unknown encoding)
            tree = None
        for rel in tree.iterfind(".//{*}Relationship") if tree is not None else ():
            if rel.get("Type", "").strip().endswith("/3dmodel"):
                target = posixpath.normpath("/" + rel.get("Target", "").strip().lstrip("/"))
                if (found := self.member(target)) is None:
                    raise self.fail(f"its start part {flatten(target, 80)} (named in _rels/.rels) is not in the zip")
                return found
        models = [m for k, m in self.members.items() if k.startswith("3d/") and k.endswith(".model")]
        if (found := self.member("3D/3dmodel.model") or (models[0] if models else None)) is None:
            raise MeshFileError(f"{self.name}: not a 3MF file: the zip holds no 3D model part (3D/3dmodel.model)")
        return found

    def part(self, member: str) -> _Model:
        return self.models[member] if member in self.models else self.models.setdefault(member, self.parse(member))

    def parse(self, member: str) -> _Model:
        """One model part: its meshes in bulk where their text allows, the rest by the element tree."""
        text = self.zf.read(member)
        fast: list[tuple[np.ndarray, np.ndarray]] = []
        pieces, pos, start = [], 0, 0
        while (found := _MESH_OPEN.search(text, start)) is not None:
            prefix = found.group(1)
            if (close := _patterns(prefix, b"", ())[-1].search(text, found.end())) is None:
                break
            start = close.end()
            if (mesh := _fast_mesh(text, found.end(), close.start(), prefix)) is not None:
                pieces += [text[pos : found.start()], b"<%smesh>%s%d</%smesh>" % (prefix, _MARK, len(fast), prefix)]
                pos = close.end()
                fast.append(mesh)
        skeleton = b"".join(pieces) + text[pos:] if pieces else text
        if b"<!DOCTYPE" in skeleton:  # (in the prolog, never inside a list read in bulk)
            raise self.fail(f"{member} holds a DTD (<!DOCTYPE>), which 3MF forbids")
        if skeleton.count(_MARK) != len(fast):  # (the file's own text holds the marker)
            skeleton, fast = text, []
        try:
            root = ET.fromstring(skeleton)
        except (ET.ParseError, LookupError):
            fast = []  # (the part as written: the error's line and column are the file's)
            try:
                root = ET.fromstring(text)
            except ET.ParseError as exc:
                raise self.fail(f"{member} is not well-formed XML ({flatten(str(exc), 120)})") from None
            except LookupError as exc:  # (its XML declaration names an encoding Python does not know)
                raise self.fail(f"{member} declares an unknown encoding ({flatten(str(exc), 120)})") from None
        ns = root.tag[1 : root.tag.index("}")] if root.tag.startswith("{") else ""
        if root.tag.rsplit("}", 1)[-1] != "model" or ns not in (CORE_NS, ""):  # (no namespace: as trimesh, lib3mf)
            raise self.fail(f"{member} is not a 3MF model (its root element is {flatten(root.tag, 80)!r})")
        q = f"{{{ns}}}" if ns else ""
        objects: dict[str, tuple] = {}
        for obj in root.iterfind(f"{q}resources/{q}object"):
            oid = (obj.get("id") or "").strip()
            where = f"object {flatten(oid, 20)!r} in {member}"
            if not oid or oid in objects:
                raise self.fail(f"two objects have the id {oid!r} in {member}" if oid else f"an object in {member} "
                                "has no id")
            mesh, components = obj.find(f"{q}mesh"), obj.find(f"{q}components")
            if fast and mesh is not None and len(mesh) == 0 and (mesh.text or "").startswith(_MARK.decode()):
                objects[oid] = ("mesh", *fast[int(mesh.text[len(_MARK) :])])
            elif mesh is not None:
                objects[oid] = ("mesh", *self.slow_mesh(mesh, q, where))
            elif components is not None:
                objects[oid] = ("components", [self.reference(c, member, f"a component of {where}")
                                               for c in components.iterfind(f"{q}component")])
            else:
                objects[oid] = ("none",)
        items = [self.reference(item, member, f"build item {k + 1}")
                 for k, item in enumerate(root.iterfind(f"{q}build/{q}item"))]
        return _Model(root.get("unit"), objects, items)

    def reference(self, el: ET.Element, member: str, what: str) -> tuple[str, str, np.ndarray, str]:
        """``(part, object id, 4x4 row-vector matrix, what)`` of an item or component element."""
        if (oid := el.get("objectid")) is None:
            raise self.fail(f"{what} names no object (no objectid)")
        matrix = _IDENTITY
        if (text := el.get("transform")) is not None:
            values = text.split()
            if len(values) != 12 or not all(_NUMBER.fullmatch(v) for v in values):
                raise self.fail(f"{what}: its transform {flatten(text, 60)!r} is not 12 numbers")
            matrix = np.eye(4)
            matrix[:, :3] = np.array([float(v) for v in values]).reshape(4, 3)
        if (path := el.get(_P_PATH)) is None:
            return member, oid.strip(), matrix, what
        if member != self.root:  # (the production extension: a consumer must refuse it)
            raise self.fail(f"{what} names a model part (p:path {flatten(path, 80)}), which only the root part may")
        if (found := self.member(path)) is None:
            raise self.fail(f"{what} names the model part {flatten(path, 80)}, which is not in the zip")
        return found, oid.strip(), matrix, what

    def slow_mesh(self, mesh: ET.Element, q: str, where: str) -> tuple[np.ndarray, np.ndarray]:
        """A mesh element's vertices and triangles read from its element tree (converted in bulk; a pass naming the
        first value that is wrong where that fails)."""
        lists, texts = [], []
        for path, tag, names, pattern, dtype in (("vertices", "vertex", "xyz", _NUMBER, np.float64),
                                                 ("triangles", "triangle", ("v1", "v2", "v3"), _INDEX, np.int64)):
            texts = [el.get(a) for el in mesh.iterfind(f"{q}{path}/{q}{tag}") for a in names]
            values = _numbers(('"'.join(texts) + '"').encode(), dtype) if None not in texts else None
            if values is None or values.size != len(texts):
                for k, value in enumerate(texts):
                    if value is None or not pattern.fullmatch(value.strip()):
                        shown = "missing" if value is None else repr(flatten(value, 40))
                        kind = "coordinate" if tag == "vertex" else "vertex index"
                        raise self.fail(f"{tag} {k // 3} of {where}: its {names[k % 3]} {kind} ({shown}) is not a "
                                        "number")
                values = np.array([float(v) if tag == "vertex" else min(max(int(v), -1), 1 << 62) for v in texts],
                                  dtype)  # (padded with whitespace, signed, past int64: named below)
            lists.append(values.reshape(-1, 3))
        vertices, triangles = lists
        if len(bad := np.flatnonzero((triangles < 0) | (triangles >= len(vertices)))):
            raise MeshFileError(f"{self.name}: a 3MF face names vertex {flatten(texts[bad[0]], 40)}, but the file has "
                                f"{len(vertices)} vertices in the mesh of {where} (counted from 0; out of range)")
        return vertices, triangles

    def instances(self) -> list[Instance]:
        """``(vertices, triangles, matrix)`` of every mesh every build item places, depth first in file order; the
        sizes counted first, once per object (a few objects can place each other's meshes exponentially often)."""
        sizes: dict[tuple[str, str], tuple[int, int, int, int]] = {}  # triangles, vertices, meshes, nesting depth

        def size(part: str, oid: str, what: str, chain: tuple[tuple[str, str], ...]) -> tuple[int, int, int, int]:
            if len(chain) > MAX_COMPONENT_DEPTH:  # (before going deeper: 3,000 levels ended in a RecursionError)
                raise self.fail(f"components nested more than {MAX_COMPONENT_DEPTH} deep under {what}")
            if (found := sizes.get((part, oid))) is None:
                if (obj := self.part(part).objects.get(oid)) is None:  # (trimesh: "id 2 included but not defined!")
                    raise self.fail(f"{what} names object {flatten(oid, 20)!r}, which {part} does not define")
                if (part, oid) in chain:
                    cycle = " -> ".join(i for _, i in (*chain[chain.index((part, oid)) :], (part, oid)))
                    raise self.fail(f"object {flatten(oid, 20)!r} in {part} contains itself (components {cycle})")
                if obj[0] == "none":
                    raise self.fail(f"object {flatten(oid, 20)!r} in {part} is neither a mesh nor components (an "
                                    "extension gpuslice does not read)")
                if obj[0] == "components":
                    if not obj[1]:  # (the schema asks for one; empty ones placed 10^9 times took minutes: a review)
                        raise self.fail(f"object {flatten(oid, 20)!r} in {part} has no component")
                    parts = [size(p, i, w, (*chain, (part, oid))) for p, i, _, w in obj[1]]
                    found = (*(sum(s[k] for s in parts) for k in range(3)), 1 + max(s[3] for s in parts))
                else:
                    found = (len(obj[2]), len(obj[1]), 1, 0)
                sizes[part, oid] = found
            if len(chain) + found[3] > MAX_COMPONENT_DEPTH:
                raise self.fail(f"components nested more than {MAX_COMPONENT_DEPTH} deep under {what}")
            return found

        def expand(part: str, oid: str, matrix: np.ndarray) -> None:
            if (obj := self.models[part].objects[oid])[0] == "components":
                for cpart, cid, cmatrix, _ in obj[1]:
                    expand(cpart, cid, cmatrix @ matrix)
            else:
                out.append((obj[1], obj[2], matrix))

        items, out = self.part(self.root).items, []
        totals = [size(part, oid, what, ()) for part, oid, _, what in items]
        if any(sum(t[k] for t in totals) > limit for k, limit in enumerate((MAX_TRIANGLES, 3 * MAX_TRIANGLES,
                                                                               MAX_MESHES))):
            raise self.fail(f"the build places more than {MAX_TRIANGLES} triangles (or {3 * MAX_TRIANGLES} vertices, "
                            f"or {MAX_MESHES} meshes)")
        for part, oid, matrix, _ in items:
            expand(part, oid, matrix)
        return out


def _merge(instances: list[Instance], scale: float) -> tuple[np.ndarray, np.ndarray]:
    """One vertex and one triangle array of the placed instances, scaled by ``scale``; a mirroring instance's
    triangles reversed."""
    vertices = np.empty((sum(len(v) for v, _, _ in instances), 3), np.float64)
    triangles = np.empty((sum(len(t) for _, t, _ in instances), 3), np.int64)
    at_v = at_t = 0
    for v, t, matrix in instances:
        out = vertices[at_v : at_v + len(v)]
        if matrix is _IDENTITY:
            out[:] = v
        else:
            np.matmul(v, matrix[:3, :3], out=out)
            out += matrix[3, :3]
        triangles[at_t : at_t + len(t)] = (t[:, ::-1] if np.linalg.det(matrix[:3, :3]) < 0 else t) + at_v
        at_v, at_t = at_v + len(v), at_t + len(t)
    if scale != 1.0:
        vertices *= scale
    return vertices, triangles


@lru_cache(maxsize=16)
def _patterns(prefix: bytes, tag: bytes, names: tuple[bytes, ...]) -> tuple[re.Pattern[bytes], ...]:
    """Patterns of the text of ``<tag n0="…" n1="…" n2="…"/>`` lists (before the first value, the second, the
    third, between elements, after the last; none when ``names`` is empty), and of a closing ``</mesh>``."""
    eq, end = _WS + b"*=" + _WS + b"*", re.compile(b"</" + re.escape(prefix) + b"mesh" + _WS + b"*>")
    if not names:  # (then only the closing tag)
        return (end,)
    element = b"<" + re.escape(prefix) + tag + _WS + b"+" + names[0] + eq
    return (re.compile(_WS + b"*" + element), re.compile(_WS + b"+" + names[1] + eq),
            re.compile(_WS + b"+" + names[2] + eq), re.compile(_WS + b"*/>" + _WS + b"*" + element),
            re.compile(_WS + b"*/>" + _WS + b"*"), end)


def _numbers(text: bytes, dtype: type) -> np.ndarray | None:
    """The numbers of ``text``, each value followed by a ``"``, or None where a value is not made of digits and
    ``+-.eE`` (float64) or of digits (int64) or is not a number."""
    if text.translate(None, _CHARS[dtype]):  # (an empty value: one number short, found by the caller's count)
        return None
    try:
        return np.fromstring(text.replace(b'"', b" "), dtype, sep=" ")  # (text mode: not deprecated; "1-2" raises)
    except ValueError:
        return None


def _bulk(arr: np.ndarray, prefix: bytes, tag: bytes, names: tuple[bytes, ...], dtype: type) -> np.ndarray | None:
    """``(n, 3)`` values of a list of ``<tag n0="…" n1="…" n2="…"/>`` elements that makes up all of the text
    ``arr`` (uint8) with the same text between the values everywhere, or None where it is written otherwise."""
    q = np.flatnonzero(arr == 34)  # the quotes around the values
    if len(q) == 0 or len(q) % 6:
        return np.zeros((0, 3), dtype) if not arr.tobytes().strip(b" \t\r\n") else None
    starts, ends = q[0::2] + 1, q[1::2]
    first, second, third, between, last, _ = _patterns(prefix, tag, names)
    if not first.fullmatch(arr[: q[0]].tobytes()) or not last.fullmatch(arr[q[-1] + 1 :].tobytes()):
        return None
    gaps, sizes = ends[:-1] + 1, starts[1:] - ends[:-1] - 2  # the text between values k and k + 1
    for k, pattern in enumerate((second, third, between)):
        if len(at := gaps[k::3]) == 0:
            continue
        if (size := int(sizes[k])) <= 0 or (sizes[k::3] != size).any():
            return None
        rows = as_strided(arr, (len(arr) - size + 1, size), (1, 1))[at]
        if not (rows == rows[0]).all() or not pattern.fullmatch(rows[0].tobytes()):
            return None
    inside = np.zeros(len(arr) + 1, np.int8)  # each value and its closing quote
    inside[starts], inside[ends + 1] = 1, -1
    values = _numbers(arr[np.cumsum(inside[:-1], dtype=np.int8).view(bool)].tobytes(), dtype)
    return values.reshape(-1, 3) if values is not None and values.size == len(starts) else None


def _inner(text: bytes, start: int, end: int, prefix: bytes, tag: bytes) -> tuple[int, int, int, int] | None:
    """Where the first ``<prefix:tag>`` element of ``text[start:end]`` opens, its inside starts and ends, and it
    closes (all ``end`` where there is none), or None where it is not written plainly."""
    opening, closing = b"<" + prefix + tag, b"</" + prefix + tag
    if (at := text.find(opening, start, end)) < 0:
        return end, end, end, end
    inner = _TAG_END.match(text, at + len(opening), end)
    stop = text.find(closing, inner.end(), end) if inner is not None else -1
    if stop < 0 or (after := _TAG_END.match(text, stop + len(closing), end)) is None:
        return None
    return at, inner.end(), stop, after.end()


def _fast_mesh(text: bytes, start: int, end: int, prefix: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices and triangles of the ``<mesh>`` block ``text[start:end]`` (inside its tags) read in bulk, or None
    where they are not written the usual way (then the element tree reads them)."""
    at_v = _inner(text, start, end, prefix, b"vertices")
    at_t = _inner(text, at_v[3], end, prefix, b"triangles") if at_v is not None and at_v[1] < at_v[2] else None
    if at_t is None:
        return None
    rest = b"".join((text[start : at_v[0]], text[at_v[3] : at_t[0]], text[at_t[3] : end]))
    if _NOT_PLAIN.search(rest) or b"<" + prefix + b"vertices" in rest or b"<" + prefix + b"triangles" in rest:
        return None  # (the prefix bound anew; a comment, CDATA or PI that the block's ends might lie in; a second list)
    arr = np.frombuffer(text, np.uint8)
    vertices = _bulk(arr[at_v[1] : at_v[2]], prefix, b"vertex", (b"x", b"y", b"z"), np.float64)
    names = (b"v1", b"v2", b"v3")
    triangles = _bulk(arr[at_t[1] : at_t[2]], prefix, b"triangle", names, np.int64) if vertices is not None else None
    if vertices is not None and triangles is None:  # (properties after v3: p1 p2 p3 pid, a slicer's paint)
        tails = _TRIANGLE_TAIL.sub(rb"\1\2", text[at_t[1] : at_t[2]])
        triangles = _bulk(np.frombuffer(tails, np.uint8), prefix, b"triangle", names, np.int64)
    if triangles is None or (len(triangles) and triangles.max() >= len(vertices)):
        return None  # (the element tree names what is wrong)
    return vertices, triangles
