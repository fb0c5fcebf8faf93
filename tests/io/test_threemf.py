"""gpuslice's own 3MF reader (:mod:`gpuslice.io.threemf`): the same triangles as trimesh and lib3mf (the 3MF
Consortium's reader) on files trimesh writes, hand-written XML in the forms the specification allows, the
production extension's ``p:path`` (trimesh dropped or doubled those parts), units, mirrors, and one-line refusals
naming the file and the problem."""

from __future__ import annotations

import contextlib
import io
import locale
import re
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from gpuslice.errors import MeshFileError
from gpuslice.io import threemf
from gpuslice.io.meshfile import UNITS_3MF_MM
from gpuslice.io.threemf import read_3mf

FAST_MESH = threemf._fast_mesh

CORE = "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"
PROD = "http://schemas.microsoft.com/3dmanufacturing/production/2015/06"
SHARED = Path("/work/shared/meshes")
BOX_V = [(0, 0, 0), (10, 0, 0), (10, 20, 0), (0, 20, 0), (0, 0, 30), (10, 0, 30), (10, 20, 30), (0, 20, 30)]
BOX_Q = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
BOX_T = [t for q in BOX_Q for t in ((q[0], q[1], q[2]), (q[0], q[2], q[3]))]
VERTEX = '<vertex x="{}" y="{}" z="{}"/>'
TRIANGLE = '<triangle v1="{}" v2="{}" v3="{}"/>'


def mesh(vertex: str = VERTEX, triangle: str = TRIANGLE, p: str = "", shift: int = 0, sep: str = "") -> str:
    """The 10 x 20 x 30 mm box's ``<mesh>`` (``p``: the element prefix, e.g. ``m:``)."""
    verts = sep.join(vertex.format(x + shift, y, z).replace("<", f"<{p}") for x, y, z in BOX_V)
    tris = sep.join(triangle.format(*t).replace("<", f"<{p}") for t in BOX_T)
    return f"<{p}mesh><{p}vertices>{verts}</{p}vertices><{p}triangles>{tris}</{p}triangles></{p}mesh>"


def model(resources: str, build: str = '<item objectid="1"/>', unit: str | None = "millimeter", p: str = "") -> str:
    xmlns = f'xmlns:{p[:-1]}="{CORE}"' if p else f'xmlns="{CORE}"'
    unit_attr = f' unit="{unit}"' if unit is not None else ""
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n<{p}model{unit_attr} {xmlns} xmlns:p="{PROD}" '
            'xmlns:b="http://example.com/b" xml:lang="en-US">'
            f"<{p}resources>{resources}</{p}resources><{p}build>{build}</{p}build></{p}model>")


def box_object(oid: int = 1, **kw) -> str:
    return f'<object id="{oid}" type="model">{mesh(**kw)}</object>'


def package(parts: dict[str, str | bytes], start: str | None = "/3D/3dmodel.model", linked: bool = False) -> bytes:
    """A 3MF zip of ``parts`` (name: model XML), ``_rels/.rels`` naming ``start`` (None: no ``.rels``); ``linked``:
    the root part's relationships to the other model parts (the production extension's, lib3mf wants them)."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("[Content_Types].xml", '<?xml version="1.0"?><Types xmlns="http://schemas.openxmlformats.org/'
                   'package/2006/content-types"><Default Extension="model" ContentType="application/vnd.ms-package.'
                   '3dmanufacturing-3dmodel+xml"/><Default Extension="rels" ContentType="application/'
                   'vnd.openxmlformats-package.relationships+xml"/></Types>')
        if start is not None:
            z.writestr("_rels/.rels", '<?xml version="1.0"?><Relationships xmlns="http://schemas.openxmlformats.org/'
                       f'package/2006/relationships"><Relationship Target="{start}" Id="rel0" Type="http://schemas.'
                       'microsoft.com/3dmanufacturing/2013/01/3dmodel"/></Relationships>')
        for name, text in parts.items():
            z.writestr(name, text)
        if linked:
            z.writestr("3D/_rels/3dmodel.model.rels", '<?xml version="1.0"?><Relationships xmlns="http://schemas.'
                       'openxmlformats.org/package/2006/relationships">' + "".join(
                           f'<Relationship Target="/{n}" Id="r{k}" Type="http://schemas.microsoft.com/3dmanufacturing/'
                           '2013/01/3dmodel"/>' for k, n in enumerate(parts) if n != "3D/3dmodel.model")
                       + "</Relationships>")
    return out.getvalue()


def one(resources: str, build: str = '<item objectid="1"/>', **kw) -> bytes:
    return package({"3D/3dmodel.model": model(resources, build, **kw)})


def read(data: bytes, name: str = "c.3mf") -> np.ndarray:
    """The triangle corners (F, 3, 3) gpuslice reads."""
    vertices, triangles = read_3mf(data, name, units=UNITS_3MF_MM)
    assert vertices.dtype == np.float64 and triangles.dtype == np.int64 and triangles.shape[1:] == (3,)
    return vertices[triangles]


def volume(tri: np.ndarray) -> float:
    return float(np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0)


def canonical(tri: np.ndarray) -> np.ndarray:
    """Triangles as (F, 9) rows in a fixed order, each rotated to start at its smallest corner (orientation kept)."""
    tri = np.asarray(tri, np.float64).reshape(-1, 3, 3).round(9)
    order = np.lexsort((tri[:, :, 2], tri[:, :, 1], tri[:, :, 0]), axis=1)
    rows = np.take_along_axis(tri, ((order[:, :1] + np.arange(3)) % 3)[:, :, None], axis=1).reshape(-1, 9)
    return rows[np.lexsort(rows.T[::-1])]


def trimesh_triangles(data: bytes) -> np.ndarray:
    return trimesh.load(io.BytesIO(data), file_type="3mf", force="mesh", process=False).triangles


def lib3mf_triangles(data: bytes, tmp_path: Path) -> np.ndarray:
    """The build's triangle corners in millimetres as lib3mf (the 3MF Consortium's reader) reads them: every build
    item's tree of components walked, transforms applied, mirrored instances' triangles reversed."""
    lib3mf = pytest.importorskip("lib3mf")
    path = tmp_path / "lib3mf.3mf"
    path.write_bytes(data)
    model = lib3mf.Wrapper().CreateModel()
    model.QueryReader("3mf").ReadFromFile(str(path))
    scale = {0: 0.001, 1: 1.0, 2: 10.0, 3: 25.4, 4: 304.8, 5: 1000.0}[int(model.GetUnit())]
    out = []

    def matrix(transform) -> np.ndarray:
        m = np.eye(4)
        m[:, :3] = np.array([list(row) for row in transform.Fields])
        return m

    def walk(obj, m: np.ndarray) -> None:
        if obj.IsMeshObject():
            v = np.array([p.Coordinates[:] for p in obj.GetVertices()], np.float64).reshape(-1, 3)
            t = np.array([p.Indices[:] for p in obj.GetTriangleIndices()], np.int64).reshape(-1, 3)
            out.append((v @ m[:3, :3] + m[3, :3])[t[:, ::-1] if np.linalg.det(m[:3, :3]) < 0 else t] * scale)
        else:
            for k in range(obj.GetComponentCount()):
                component = obj.GetComponent(k)
                walk(component.GetObjectResource(), matrix(component.GetTransform()) @ m)

    items = model.GetBuildItems()
    while items.MoveNext():
        item = items.GetCurrent()
        walk(item.GetObjectResource(), matrix(item.GetObjectTransform()))
    return np.concatenate(out) if out else np.zeros((0, 3, 3))


def same(a: np.ndarray, b: np.ndarray, atol: float = 0.0) -> bool:
    a, b = canonical(a), canonical(b)
    return a.shape == b.shape and np.allclose(a, b, rtol=1e-6 if atol else 0.0, atol=atol)


# ------------------------------------------------------------------------------------------------- parity


def _scene_instances() -> trimesh.Scene:
    """Three instances of one mesh: moved, turned about z and mirrored in x (build items with transforms)."""
    part = trimesh.creation.icosphere(subdivisions=2, radius=7.0)
    scene = trimesh.Scene()
    scene.add_geometry(part, transform=trimesh.transformations.translation_matrix([30, 0, 0]))
    scene.add_geometry(part, transform=trimesh.transformations.rotation_matrix(0.7, [0, 0, 1], [5, 5, 0]))
    scene.add_geometry(part, transform=np.diag([-1.0, 1.0, 1.0, 1.0]) @ trimesh.transformations.translation_matrix(
        [12, 3, 1]))
    return scene


def _scene_components() -> trimesh.Scene:
    """A parent node holding two transformed children of one geometry (an object of components)."""
    scene = trimesh.Scene()
    scene.geometry["part"] = trimesh.creation.box((10, 20, 30))
    scene.graph.update(frame_from="world", frame_to="parent", matrix=trimesh.transformations.translation_matrix(
        [100, 0, 0]))
    scene.graph.update(frame_from="parent", frame_to="a", geometry="part",
                       matrix=trimesh.transformations.rotation_matrix(0.5, [1, 0, 0]))
    scene.graph.update(frame_from="parent", frame_to="b", geometry="part", matrix=np.diag([1.0, -1.0, 1.0, 1.0]))
    return scene


@pytest.mark.parametrize("make", [
    lambda: trimesh.creation.box((10, 20, 30)),
    lambda: trimesh.creation.icosphere(subdivisions=3, radius=12.5),
    lambda: trimesh.creation.cylinder(radius=4, height=9, sections=33).apply_transform(
        trimesh.transformations.random_rotation_matrix(seed=1)),
    _scene_instances,
    _scene_components,
], ids=["box", "icosphere", "rotated-cylinder", "scene-items", "scene-components"])
def test_files_trimesh_writes_read_as_trimesh_and_lib3mf_read_them(make, tmp_path):
    data = trimesh.exchange.threemf.export_3MF(make())
    ours = read(data)
    assert len(ours) > 0
    assert same(ours, trimesh_triangles(data), atol=1e-9)  # (the same decimal text through one strtod: exact)
    assert same(ours, lib3mf_triangles(data, tmp_path), atol=1e-4)  # (lib3mf keeps float32)
    if make is _scene_components:
        assert volume(ours) == pytest.approx(2 * 6000.0)  # (the mirrored child turned back: no negative volume)


@pytest.mark.skipif(not SHARED.is_dir(), reason=f"{SHARED} (the shared test meshes) is not on this machine")
@pytest.mark.parametrize("stl", ["prusa_A.stl", "cow.stl", "prusa_extruder_idler.stl", "fandisk.stl"])
def test_shared_meshes_exported_by_trimesh_read_back_as_trimesh_reads_them(stl, tmp_path):
    if not (SHARED / stl).is_file():
        pytest.skip(f"{SHARED / stl} is not there")
    data = trimesh.exchange.threemf.export_3MF(trimesh.load(SHARED / stl, force="mesh"))
    ours = read(data)
    assert np.array_equal(canonical(ours), canonical(trimesh_triangles(data)))
    if stl == "prusa_A.stl":
        assert same(ours, lib3mf_triangles(data, tmp_path), atol=1e-4)


# ------------------------------------------------------------------------------------------- hand-written XML


@pytest.mark.parametrize("resources", [
    box_object(),
    box_object(vertex='<vertex z="{2}" x="{0}" y="{1}"/>', triangle='<triangle v3="{2}" v1="{0}" v2="{1}"/>'),
    box_object(vertex='<vertex x="{0}e0" y="{1}.0E+00" z="{2}00e-2"/>'),
    box_object(vertex='<vertex x="{0}." y="+{1}" z="{2}.000"/>'),  # ("1.": not ST_Number's, taken as trimesh did)
    box_object(vertex="<vertex x='{}' y='{}' z='{}'/>"),
    box_object(vertex='<vertex x=" {} " y="{}" z="{}"/>'),  # (whitespace around a value: XML Schema collapses it)
    box_object(vertex='<vertex x="{}" y="{}" z="&#48;{}"/>'),  # (a character reference: "0" before the number)
    box_object(vertex='<vertex\r\n  x = "{}"\r\n\ty="{}"   z="{}" />', sep="\r\n    ",
               triangle='<triangle\r\nv1="{}" v2="{}"\r\nv3="{}"/>'),
    box_object(triangle='<triangle v1="{}" v2="{}" v3="{}" pid="4" p1="0" p2="1" p3="2"/>'),
    box_object(triangle='<triangle pid="4" v1="{}" v2="{}" v3="{}"/>'),
    box_object(triangle='<triangle v1="{}" v2="{}" v3="{}" paint_color="4>2/>"/>'),  # (">" is allowed)
    box_object(vertex='<vertex x="{}" y="{}" z="{}"/><!-- <vertex x="99" y="99" z="99"/> -->'),
    "<!-- an old mesh: " + box_object(3, shift=500).replace("--", "") + " -->" + box_object(),
    box_object(triangle='<triangle v1="{}" v2="{}" v3="{}"/><?pi <triangle v1="0" v2="1" v3="9"/> ?>'),
    box_object().replace("</vertices>", "</vertices><!-- </mesh><mesh> -->"),
    box_object().replace("<vertices>", '<vertices><b:vertex xmlns:b="http://example.com/b" x="9" y="9" z="9"/>'),
    box_object().replace("<vertices>", '<vertices><b:vertex x="9" y="9" z="9"/>'),
], ids=["plain", "attribute-order", "exponents", "other-forms", "single-quotes", "padded", "char-reference",
        "crlf-in-tags", "properties", "property-first", "attribute-with-gt", "commented-vertex", "commented-mesh",
        "processing-instruction", "comment-with-mesh-tags", "foreign-vertex-first", "foreign-vertex-root-prefix"])
def test_a_box_in_every_form_the_xml_allows_reads_as_the_box(resources):
    tri = read(one(resources))
    assert tri.shape == (12, 3, 3)
    assert np.array_equal(tri.reshape(-1, 3).min(0), [0, 0, 0]) and np.array_equal(tri.reshape(-1, 3).max(0),
                                                                                     [10, 20, 30])
    assert volume(tri) == pytest.approx(6000.0)
    assert np.array_equal(canonical(tri), canonical(np.array(BOX_V, float)[BOX_T]))


def test_a_last_vertex_written_otherwise_is_kept():
    """Vertices no triangle uses are returned too (file order): a last one in single quotes is not dropped."""
    data = one(box_object().replace("</vertices>", "<vertex x='1' y='2' z='3e0'/></vertices>"))
    vertices, triangles = read_3mf(data, "c.3mf")
    assert len(vertices) == 9 and np.array_equal(vertices[8], [1, 2, 3]) and len(triangles) == 12


@pytest.mark.parametrize("prefix", ["m:", "core.v1:"])
def test_a_namespace_prefix(prefix):
    data = one(box_object().replace("<", f"<{prefix}").replace(f"<{prefix}/", f"</{prefix}"),
               f'<{prefix}item objectid="1"/>', p=prefix)
    tri = read(data)
    assert volume(tri) == pytest.approx(6000.0) and len(tri) == 12


def test_a_prefix_bound_to_another_namespace_is_not_the_core_mesh():
    """``<x:mesh>`` of an unknown namespace is ignored (the specification: consumers ignore what they do not know);
    the object then has neither a mesh nor components."""
    other = '<x:mesh xmlns:x="http://example.com/x">' + mesh()[len("<mesh>") : -len("</mesh>")].replace(
        "<", "<x:").replace("<x:/", "</x:") + "</x:mesh>"
    with pytest.raises(MeshFileError, match=r"object '1' in 3D/3dmodel\.model is neither a mesh nor components"):
        read(one(f'<object id="1">{other}</object>'))


def _lib3mf_written(tmp_path: Path) -> bytes:
    """The box as lib3mf writes it (tabs, ``<vertex x="10.000000" … />``), in inches: a mirrored build item and an
    object of one component, placed again."""
    lib3mf = pytest.importorskip("lib3mf")
    model = lib3mf.Wrapper().CreateModel()
    box = model.AddMeshObject()
    positions, triangles = [lib3mf.Position() for _ in BOX_V], [lib3mf.Triangle() for _ in BOX_T]
    for p, v in zip(positions, BOX_V, strict=True):
        p.Coordinates[:] = v
    for t, f in zip(triangles, BOX_T, strict=True):
        t.Indices[:] = f
    box.SetGeometry(positions, triangles)
    mirror = lib3mf.Transform()
    for r, row in enumerate([[-1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 6, 7]]):
        mirror.Fields[r][:] = row
    model.AddBuildItem(box, mirror)
    model.AddBuildItem(model.AddComponentsObject(), mirror)
    model.GetComponentsObjectByID(2).AddComponent(box, lib3mf.Wrapper().GetIdentityTransform())
    model.SetUnit(lib3mf.ModelUnit.Inch)
    with _locale_kept():  # (lib3mf's writer sets the C locale and leaves it: later text files were ASCII)
        model.QueryWriter("3mf").WriteToFile(str(tmp_path / "written.3mf"))
    return (tmp_path / "written.3mf").read_bytes()


@contextlib.contextmanager
def _locale_kept():
    """The process's locale as it was, whatever the code inside sets."""
    saved = locale.setlocale(locale.LC_ALL)
    try:
        yield
    finally:
        locale.setlocale(locale.LC_ALL, saved)


def _painted(style: str) -> bytes:
    """The box as PrusaSlicer (indented lines, painted triangles marked ``slic3rpe:mmu_segmentation``) or Bambu
    Studio (``paint_color``; the mesh in ``/3D/Objects/object_1.model``, placed by a p:path component) write it:
    only some triangles carry the paint attribute."""
    paint = "slic3rpe:mmu_segmentation" if style == "prusa" else "paint_color"
    tris = "".join(f'\n     <triangle v1="{a}" v2="{b}" v3="{c}"' + (f' {paint}="4C"' if k % 3 == 0 else "") + "/>"
                   for k, (a, b, c) in enumerate(BOX_T))
    verts = "".join(f'\n     <vertex x="{x}" y="{y}" z="{z}"/>' for x, y, z in BOX_V)
    obj = (f'\n  <object id="1" type="model">\n   <mesh>\n    <vertices>{verts}\n    </vertices>\n    <triangles>'
           f"{tris}\n    </triangles>\n   </mesh>\n  </object>")
    if style == "prusa":
        return package({"3D/3dmodel.model": model(obj).replace("<model ", '<model xmlns:slic3rpe="http://schemas.'
                                                                         'slic3r.org/3mf/2017/06" ')})
    root = model('<object id="2" type="model"><components><component p:path="/3D/Objects/object_1.model" '
                 'objectid="1" transform="1 0 0 0 1 0 0 0 1 0 0 0"/></components></object>', '<item objectid="2"/>')
    return package({"3D/3dmodel.model": root, "3D/Objects/object_1.model": model(obj, build="")}, linked=True)


@pytest.mark.parametrize("writer", ["trimesh", "lib3mf", "prusa", "bambu"])
def test_the_usual_writers_files_are_read_in_bulk(writer, monkeypatch, tmp_path):
    """Every mesh of the files these write goes the fast way (no element tree of its vertices), and reads as
    lib3mf reads it."""
    data = {"trimesh": lambda: trimesh.exchange.threemf.export_3MF(trimesh.creation.box((10, 20, 30))),
            "lib3mf": lambda: _lib3mf_written(tmp_path), "prusa": lambda: _painted("prusa"),
            "bambu": lambda: _painted("bambu")}[writer]()
    bulk = []
    monkeypatch.setattr(threemf, "_fast_mesh", lambda *a: bulk.append(FAST_MESH(*a)) or bulk[-1])
    tri = read(data)
    assert bulk and all(b is not None for b in bulk)
    assert volume(tri) == pytest.approx(6000.0 * (2 * 25.4**3 if writer == "lib3mf" else 1))
    assert same(tri, lib3mf_triangles(data, tmp_path), atol=1e-3)


def test_fast_and_element_by_element_readings_agree_on_a_large_mesh(monkeypatch):
    """A mesh of 3000 random vertices read in bulk, and again written with its attributes in another order (read
    from the element tree): the same numbers to the last bit, the same triangles."""
    rng = np.random.default_rng(7)
    v = rng.normal(scale=50.0, size=(3000, 3))
    t = rng.integers(0, len(v), size=(5000, 3))
    tris = "".join(TRIANGLE.format(*f) for f in t.tolist())
    bulk = []
    monkeypatch.setattr(threemf, "_fast_mesh", lambda *a: bulk.append(fast(*a)) or bulk[-1])
    fast = FAST_MESH
    for vertex in ('<vertex x="{!r}" y="{!r}" z="{!r}"/>', '<vertex y="{1!r}" x="{0!r}" z="{2!r}"/>'):
        verts = "".join(vertex.format(*p) for p in v.tolist())
        vertices, triangles = read_3mf(one(f'<object id="1"><mesh><vertices>{verts}</vertices><triangles>{tris}'
                                           "</triangles></mesh></object>"), "r.3mf")
        assert np.array_equal(vertices, v) and np.array_equal(triangles, t)
    assert [b is not None for b in bulk] == [True, False]


def test_components_nested_two_deep_with_transforms(tmp_path):
    """Object 3 holds object 2 turned 90 degrees about z; object 2 holds the box moved 100 mm along x; the item
    lifts object 3 by 5 mm: a point p lands at turn(p + (100, 0, 0)) + (0, 0, 5)."""
    resources = (box_object(1) + '<object id="2"><components><component objectid="1" transform="1 0 0 0 1 0 0 0 1 '
                 '100 0 0"/></components></object><object id="3"><components><component objectid="2" transform="0 1 '
                 '0 -1 0 0 0 0 1 0 0 0"/></components></object>')
    data = one(resources, '<item objectid="3" transform="1 0 0 0 1 0 0 0 1 0 0 5"/>')
    tri = read(data)
    box = np.array(BOX_V, float)[BOX_T] + [100, 0, 0]
    expected = np.stack([-box[..., 1], box[..., 0], box[..., 2] + 5], axis=-1)  # (x, y) -> (-y, x)
    assert np.allclose(canonical(tri), canonical(expected), atol=1e-12)
    assert same(tri, trimesh_triangles(data), atol=1e-9) and same(tri, lib3mf_triangles(data, tmp_path), atol=1e-4)


@pytest.mark.parametrize("item, component, flipped", [
    ("-1 0 0 0 1 0 0 0 1 0 0 0", None, True),
    ("1 0 0 0 1 0 0 0 -2 0 0 60", None, True),
    ("-1 0 0 0 1 0 0 0 1 0 0 0", "1 0 0 0 -1 0 0 0 1 0 0 0", False),  # (two mirrors: a half turn)
    ("1 0 0 0 1 0 0 0 1 0 0 0", "1 0 0 0 1 0 0 0 -1 0 0 0", True),
])
def test_a_mirrored_instance_keeps_its_triangles_facing_outwards(item, component, flipped, tmp_path):
    if component is None:
        data = one(box_object(), f'<item objectid="1" transform="{item}"/>')
    else:
        data = one(box_object() + f'<object id="2"><components><component objectid="1" transform="{component}"/>'
                   "</components></object>", f'<item objectid="2" transform="{item}"/>')
    vertices, triangles = read_3mf(data, "m.3mf")
    tri = vertices[triangles]
    assert volume(tri) > 0  # (each mirror reversed the triangles; two mirrors left them)
    assert tuple(triangles[0]) == (BOX_T[0][::-1] if flipped else BOX_T[0])
    assert same(tri, lib3mf_triangles(data, tmp_path), atol=1e-4)


def _production(sub_unit: str = "millimeter", item_path: str = "/3D/Objects/object_1.model") -> dict[str, str]:
    """Bambu Studio's layout: the root part's object 1 places objects 1 and 2 of ``/3D/Objects/object_1.model``
    (ids that the root part uses too); a build item names object 2 of that part directly."""
    sub = model(box_object(1) + box_object(2, shift=50), build="", unit=sub_unit)
    root = model('<object id="1" type="model"><components><component p:path="/3D/Objects/object_1.model" '
                 'objectid="1"/><component p:path="/3D/Objects/object_1.model" objectid="2" transform="1 0 0 0 1 0 '
                 '0 0 1 0 0 40"/></components></object><object id="2">' + mesh(shift=-300) + "</object>",
                 f'<item objectid="1"/><item objectid="2" p:path="{item_path}" transform="1 0 0 0 1 0 0 0 1 0 100 '
                 '0"/>')
    return {"3D/3dmodel.model": root, "3D/Objects/object_1.model": sub}


def test_p_path_components_and_items_read_the_other_model_part(tmp_path):
    """trimesh put every mesh of the part under each component naming it (the part twice here) and looked an
    item's p:path object up in the root part; lib3mf reads what the production extension says."""
    data = package(_production(sub_unit="inch"), linked=True)  # (a non-root part's unit is not used: lib3mf's reading)
    tri = read(data)
    box = np.array(BOX_V, float)[BOX_T]
    expected = np.concatenate([box, box + [50, 0, 40], box + [50, 100, 0]])
    assert np.array_equal(canonical(tri), canonical(expected))
    assert same(tri, lib3mf_triangles(data, tmp_path), atol=1e-4)
    assert not same(tri, trimesh_triangles(data), atol=1e-6)  # (if trimesh reads it right one day: drop this line)
    other_case = package(_production(item_path="3d/objects/OBJECT_1.model"), linked=True)  # (lib3mf: not found)
    assert np.array_equal(read(other_case), tri)


@pytest.mark.parametrize("unit, mm", [(None, 1.0), *UNITS_3MF_MM.items()])
def test_each_unit_reads_in_millimetres(unit, mm, tmp_path):
    data = one(box_object(), '<item objectid="1" transform="1 0 0 0 1 0 0 0 1 1 0 0"/>', unit=unit)
    tri = read(data)
    assert np.allclose(tri.reshape(-1, 3).max(0), np.array([11, 20, 30]) * mm)
    assert np.allclose(tri.reshape(-1, 3).min(0), np.array([1, 0, 0]) * mm)
    assert same(tri, lib3mf_triangles(data, tmp_path), atol=1e-4 * mm)


def test_a_one_inch_cube_is_25_4_mm():
    cube = trimesh.creation.box((1, 1, 1))
    text = "".join(VERTEX.format(*v) for v in cube.vertices.tolist())
    tris = "".join(TRIANGLE.format(*f) for f in cube.faces.tolist())
    tri = read(one(f'<object id="1"><mesh><vertices>{text}</vertices><triangles>{tris}</triangles></mesh>'
                   "</object>", unit="inch"))
    assert np.allclose(np.ptp(tri.reshape(-1, 3), axis=0), 25.4)
    with pytest.raises(MeshFileError, match=r"^c\.3mf: unknown 3MF unit 'inch' \(the 3MF units are millimeter\)$"):
        read_3mf(one(box_object(), unit="inch"), "c.3mf")  # (no table given: millimetres only)


@pytest.mark.parametrize("kind", ["model", "solidsupport", "support", "surface", "other"])
def test_every_object_type_an_item_reaches_is_read_as_trimesh_and_lib3mf_read_it(kind, tmp_path):
    data = one(f'<object id="1" type="{kind}">{mesh()}</object>' + box_object(2, shift=200))  # (2: no item)
    tri = read(data)
    assert len(tri) == 12 and tri.max() <= 30
    assert same(tri, trimesh_triangles(data), atol=1e-9) and same(tri, lib3mf_triangles(data, tmp_path), atol=1e-4)


@pytest.mark.parametrize("parts, start", [
    ({"3D/3dmodel.model": model(box_object())}, None),  # (no .rels: the conventional name)
    ({"3D/other.model": model(box_object())}, None),  # (the first .model under 3D/)
    ({"3d/3DModel.MODEL": model(box_object())}, "/3D/3dmodel.model"),  # (OPC: case-insensitive part names)
    ({"3D/build.model": model(box_object()), "3D/3dmodel.model": model(box_object(shift=99))}, "3D/build.model"),
])
def test_the_root_model_part(parts, start):
    tri = read(package(parts, start))
    assert len(tri) == 12 and tri.reshape(-1, 3).max(0)[0] == 10


def test_no_build_item_is_an_empty_mesh():
    vertices, triangles = read_3mf(one(box_object(), build=""), "e.3mf")
    assert vertices.shape == (0, 3) and triangles.shape == (0, 3)


# ------------------------------------------------------------------------------------------------- refusals


def _deep(n: int) -> str:
    return box_object(1) + "".join(f'<object id="{k}"><components><component objectid="{k - 1}"/></components>'
                                   "</object>" for k in range(2, n + 2))


def _bad_index(value: str) -> str:
    return box_object(triangle='<triangle v1="{}" v2="{}" v3="{}"/>').replace('v3="1"/>', f'v3="{value}"/>', 1)


def _bad_vertex(value: str) -> str:
    return box_object().replace('x="10" y="0" z="0"', f'x="{value}" y="0" z="0"', 1)


BAD = [
    (b"PK\x03\x04junk", r"cannot read 3MF file: BadZipFile: "),
    (package({"3D/readme.txt": "x"}, None), r"not a 3MF file: the zip holds no 3D model part"),
    (package({"3D/3dmodel.model": model(box_object())}, "/3D/gone.model"),
     r"cannot read 3MF file: its start part /3D/gone\.model \(named in _rels/\.rels\) is not in the zip"),
    (package({"3D/3dmodel.model": model(box_object()).replace("<build>", "<build")}),
     r"3D/3dmodel\.model is not well-formed XML \(not well-formed \(invalid token\): line 2, column \d+\)"),
    (package({"3D/3dmodel.model": model(box_object()).replace("</object>", "</objects>")}),
     r"cannot read 3MF file: 3D/3dmodel\.model is not well-formed XML \(mismatched tag: line 2, column \d+\)"),
    (package({"3D/3dmodel.model": model(box_object()).replace("<vertex ", "<vertex <", 1)}),
     r"3D/3dmodel\.model is not well-formed XML"),
    (package({"3D/3dmodel.model": '<?xml version="1.0"?><!DOCTYPE model [<!ENTITY a "1">]>'
              + model(box_object()).split("?>", 1)[1]}), r"3D/3dmodel\.model holds a DTD \(<!DOCTYPE>\), which 3MF"),
    (package({"3D/3dmodel.model": model(box_object()).replace(CORE, "http://example.com/not-3mf")}),
     r"3D/3dmodel\.model is not a 3MF model \(its root element is '\{http://example\.com/not-3mf\}model'\)"),
    (one(box_object(), '<item objectid="2"/>'), r"build item 1 names object '2', which 3D/3dmodel\.model does not "
                                                r"define"),
    (one(box_object() + '<object id="2"><components><component objectid="7"/></components></object>',
         '<item objectid="1"/><item objectid="2"/>'), r"a component of object '2' in 3D/3dmodel\.model names object "
                                                      r"'7', which 3D/3dmodel\.model does not define"),
    (one(box_object(), "<item/>"), r"build item 1 names no object \(no objectid\)"),
    (one(box_object(), '<item objectid="1" p:path="/3D/nowhere.model"/>'),
     r"build item 1 names the model part /3D/nowhere\.model, which is not in the zip"),
    (package({**_production(), "3D/Objects/object_1.model": model(
        box_object(1) + '<object id="2"><components><component objectid="1" p:path="/3D/Objects/object_1.model"/>'
        "</components></object>", build="")}),
     r"a component of object '2' in 3D/Objects/object_1\.model names a model part \(p:path /3D/Objects/object_1\."
     r"model\), which only the root part may"),
    (one(_bad_index("8")), r"a 3MF face names vertex 8, but the file has 8 vertices in the mesh of object '1' in "
                           r"3D/3dmodel\.model \(counted from 0; out of range\)"),
    (one(_bad_index("-1")), r"a 3MF face names vertex -1, but the file has 8 vertices"),
    (one(_bad_index("99999999999999999999999")), r"a 3MF face names vertex 99999999999999999999999, but the file "),
    (one(_bad_index("1.5")), r"triangle 1 of object '1' in 3D/3dmodel\.model: its v3 vertex index \('1\.5'\) is not "
                             r"a number"),
    (one(_bad_index("")), r"triangle 1 of object '1' .*: its v3 vertex index \(''\) is not a number"),
    (one(box_object(triangle='<triangle v1="{}" v2="{}" v4="{}"/>')), r"triangle 0 of object '1' .*: its v3 vertex "
                                                                      r"index \(missing\) is not a number"),
    (one(_bad_vertex("abc")), r"vertex 1 of object '1' in 3D/3dmodel\.model: its x coordinate \('abc'\) is not a "
                              r"number"),
    (one(_bad_vertex("1_000")), r"vertex 1 of object '1' .*: its x coordinate \('1_000'\) is not a number"),
    (one(_bad_vertex("inf")), r"vertex 1 of object '1' .*: its x coordinate \('inf'\) is not a number"),
    (one(_bad_vertex("nan")), r"its x coordinate \('nan'\) is not a number"),
    (one(_bad_vertex("0x10")), r"its x coordinate \('0x10'\) is not a number"),
    (one(_bad_vertex("1e")), r"its x coordinate \('1e'\) is not a number"),
    (one(_bad_vertex("1-2")), r"its x coordinate \('1-2'\) is not a number"),
    (one(_bad_vertex("")), r"its x coordinate \(''\) is not a number"),
    (one(box_object(vertex='<vertex x="{}" y="{}" w="{}"/>')), r"vertex 0 of object '1' .*: its z coordinate "
                                                               r"\(missing\) is not a number"),
    (one(box_object(), unit="parsec"), r"unknown 3MF unit 'parsec' \(the 3MF units are micron, millimeter, "
                                       r"centimeter, inch, foot, meter\)$"),
    (one(box_object() + '<object id="2"><components><component objectid="3"/></components></object><object id="3">'
         '<components><component objectid="1"/><component objectid="2"/></components></object>',
         '<item objectid="2"/>'), r"object '2' in 3D/3dmodel\.model contains itself \(components 2 -> 3 -> 2\)"),
    (one(_deep(threemf.MAX_COMPONENT_DEPTH + 1), f'<item objectid="{threemf.MAX_COMPONENT_DEPTH + 2}"/>'),
     rf"components nested more than {threemf.MAX_COMPONENT_DEPTH} deep under a component of object '\d+' in "),
    (one(box_object() + box_object(1, shift=5)), r"two objects have the id '1' in 3D/3dmodel\.model"),
    (one('<object type="model">' + mesh() + "</object>"), r"an object in 3D/3dmodel\.model has no id"),
    (one('<object id="1"><bo:booleanshape xmlns:bo="http://example.com/bo" objectid="2"/></object>'),
     r"object '1' in 3D/3dmodel\.model is neither a mesh nor components \(an extension gpuslice does not read\)"),
    (one(box_object(), '<item objectid="1" transform="1 0 0 0 1 0 0 0 1 0 0"/>'),
     r"build item 1: its transform '1 0 0 0 1 0 0 0 1 0 0' is not 12 numbers"),
    (one(box_object(), '<item objectid="1" transform="1 0 0 0 1 0 0 0 1 0 0 x"/>'), r"is not 12 numbers"),
    (package({"3D/3dmodel.model": '<?xml version="1.0" encoding="utf--18"?>' + model(box_object()).split("?>", 1)[1]}),
     r"3D/3dmodel\.model declares an unknown encoding"),  # (a fuzzer: Python's LookupError escaped)
]


@pytest.mark.parametrize("data, message", BAD, ids=[
    "not-a-zip", "no-model-part", "start-part-missing", "broken-build-tag", "mismatched-tag", "broken-vertex-list",
    "dtd", "foreign-root", "item-undefined", "component-undefined", "no-objectid", "path-missing",
    "path-in-non-root", "index-past-end", "index-negative", "index-huge", "index-fraction", "index-empty",
    "index-missing", "coordinate-word", "coordinate-underscore", "coordinate-inf", "coordinate-nan",
    "coordinate-hex", "coordinate-e", "coordinate-minus", "coordinate-empty", "coordinate-missing", "unit", "cycle",
    "too-deep", "duplicate-id", "no-id", "no-mesh", "transform-short", "transform-word", "unknown-encoding"])
def test_a_broken_3mf_is_one_line_naming_the_file_and_the_problem(data, message):
    with pytest.raises(MeshFileError) as info:
        read_3mf(data, "dir/b.3mf", units=UNITS_3MF_MM)
    text = str(info.value)
    assert "\n" not in text and text.startswith("dir/b.3mf: "), text
    assert re.search(message, text), text


def test_more_triangles_than_the_limit_are_refused(monkeypatch):
    """Instancing multiplies a small file: 5 items of the 12-triangle box against a limit of 50."""
    monkeypatch.setattr(threemf, "MAX_TRIANGLES", 50)
    data = one(box_object(), '<item objectid="1"/>' * 4)
    assert len(read(data)) == 48
    with pytest.raises(MeshFileError, match=r"^c\.3mf: cannot read 3MF file: the build places more than 50 "):
        read(one(box_object(), '<item objectid="1"/>' * 5))
    monkeypatch.setattr(threemf, "MAX_MESHES", 4)  # (empty meshes, placed without end, cost time all the same)
    with pytest.raises(MeshFileError, match=r"the build places more than 50 triangles \(or 150 vertices, or 4 "):
        read(one('<object id="1"><mesh><vertices/><triangles/></mesh></object>', '<item objectid="1"/>' * 5))


def test_objects_placing_each_other_exponentially_often_are_refused_at_once():
    """25 objects, each placing the one below twice: 2**25 boxes, counted (once per object), not built."""
    resources = box_object(1) + "".join(f'<object id="{k}"><components><component objectid="{k - 1}"/><component '
                                        f'objectid="{k - 1}"/></components></object>' for k in range(2, 27))
    with pytest.raises(MeshFileError, match=r"the build places more than \d+ triangles"):
        read(one(resources, '<item objectid="26"/>'))


def test_the_marker_text_in_a_file_is_not_taken_for_a_mesh_read_in_bulk():
    """The skeleton marks each mesh read in bulk with a text; a file holding that text itself is read as written
    (here: an object whose mesh element holds only that text, i.e. an empty mesh, placed nowhere)."""
    fake = '<object id="9"><mesh>gpuslice-mesh:0</mesh></object>'
    tri = read(one(fake + box_object(shift=-5), '<item objectid="1"/><item objectid="9"/>'))
    assert len(tri) == 12 and tri.reshape(-1, 3).min(0)[0] == -5


def test_a_compressed_zip_is_read_and_a_stored_one_too():
    data = one(box_object())
    stored = io.BytesIO()
    with zipfile.ZipFile(io.BytesIO(data)) as src, zipfile.ZipFile(stored, "w", zipfile.ZIP_STORED) as dst:
        for info in src.infolist():
            dst.writestr(info.filename, src.read(info))
    assert np.array_equal(read(data), read(stored.getvalue()))


def test_a_zip_with_two_members_of_one_name_is_refused(capsys):
    """zipfile read the last copy and warned on stderr (a fuzzing helper): OPC part names are unique."""
    import warnings

    from gpuslice import load_mesh

    data = package({"3D/3dmodel.model": model(box_object())})
    out = io.BytesIO()
    with warnings.catch_warnings(), zipfile.ZipFile(out, "w") as z:
        warnings.simplefilter("ignore")
        with zipfile.ZipFile(io.BytesIO(data)) as src:
            for n in src.namelist():
                z.writestr(n, src.read(n))
        z.writestr("/3D/3DModel.model", model(box_object()))  # (the same part, its case and leading "/" aside)
    with pytest.raises(MeshFileError, match=r"^d\.3mf: not a valid 3MF file: it holds two members named "
                                            r"'/3D/3DModel\.model'$"):
        load_mesh(out.getvalue(), name="d.3mf")
    assert capsys.readouterr().err == ""


def test_empty_components_and_deep_chains_are_refused_at_once():
    """Objects of no component placed by 1,000 components each, three deep, walked 10^9 placements of nothing for
    minutes; 3,000 levels of components ended in a RecursionError (a review)."""
    empty = '<object id="1" type="model"><components></components></object>' + "".join(
        f'<object id="{k}" type="model"><components>' + f'<component objectid="{k - 1}"/>' * 1000
        + "</components></object>" for k in (2, 3, 4))
    with pytest.raises(MeshFileError, match=r"object '1' in 3D/3dmodel\.model has no component$"):
        read_3mf(one(empty, '<item objectid="4"/>'), "e.3mf", units=UNITS_3MF_MM)
    deep = box_object() + "".join(f'<object id="{k}" type="model"><components><component objectid="{k - 1}"/>'
                                  "</components></object>" for k in range(2, 3002))
    with pytest.raises(MeshFileError, match=r"components nested more than 32 deep"):
        read_3mf(one(deep, '<item objectid="3001"/>'), "d.3mf", units=UNITS_3MF_MM)
