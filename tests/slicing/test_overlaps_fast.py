"""The fast rebuild of crossing loops (``slicing/overlaps.py``, issue 14): its numpy arrangement path gives, bit for
bit, the rings that the per-layer GEOS recipe gives (node, polygonize, winding number at ``point_on_surface``,
``union_all``, normalize, orient), which is written out again here apart from the code under test; layers it does
not take on (loops touching, segments overlapping) go to GEOS with the same result; and the helpers vectorised for
it agree with their plain versions."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from test_overlap_groups import make_loops  # (tests/slicing: on sys.path under pytest's default import mode)

from gpuslice.slicing import overlaps
from gpuslice.slicing.nest import nest_loops, signed_areas
from gpuslice.slicing.rings import _affected_all, _winding_numbers

RULES = ("nonzero", "evenodd", "positive")


def square(x0, y0, s, ccw=True):
    r = np.array([[x0, y0], [x0 + s, y0], [x0 + s, y0 + s], [x0, y0 + s]], float)
    return r if ccw else r[::-1]


def bowtie(x0, y0, s):
    return np.array([[x0, y0], [x0 + s, y0 + s], [x0 + s, y0], [x0, y0 + s]], float)


def star(rng, cx, cy, r0, r1, n):
    """A random star-shaped (simple) loop around (cx, cy), either orientation, float32 points."""
    t = np.sort(rng.uniform(0, 2 * np.pi, n))
    r = rng.uniform(r0, r1, n)
    ring = np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1).astype(np.float32)
    return ring if rng.random() < 0.5 else ring[::-1]


def plain_winding(ring: np.ndarray, p: np.ndarray) -> int:
    """Winding number of ``ring`` around point ``p``, edge by edge (crossings of the rightward ray)."""
    a = ring.astype(float) - p
    b = np.roll(a, -1, axis=0)
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    up = (a[:, 1] <= 0) & (b[:, 1] > 0) & (cross > 0)
    down = (a[:, 1] > 0) & (b[:, 1] <= 0) & (cross < 0)
    return int(up.sum()) - int(down.sum())


def reference_rings(rings: list[np.ndarray], fill_rule: str) -> list[tuple[np.ndarray, bool]]:
    """The rings the original per-layer code made from ``rings`` (all of a layer's loops): (points, is_hole)."""
    rings = [np.asarray(r, np.float32).astype(float) for r in rings]
    lines = shapely.multilinestrings([shapely.linestrings(np.vstack([r, r[:1]])) for r in rings])
    faces = shapely.get_parts(shapely.polygonize(shapely.get_parts(shapely.node(lines))))
    reps = shapely.get_coordinates(shapely.point_on_surface(faces))
    w = np.array([sum(plain_winding(r, p) for r in rings) for p in reps], dtype=np.int64)
    keep = {"nonzero": w != 0, "positive": w > 0, "evenodd": w % 2 != 0}[fill_rule]
    region = shapely.union_all(faces[keep]) if keep.any() else shapely.Polygon()
    out = []
    for poly in shapely.get_parts(shapely.normalize(region)):
        if poly.is_empty or poly.area == 0:
            continue
        poly = shapely.geometry.polygon.orient(poly, 1.0)
        out.append((np.asarray(poly.exterior.coords)[:-1], False))
        out.extend((np.asarray(h.coords)[:-1], True) for h in poly.interiors)
    return out


def layer_rings(nd, k: int) -> list[tuple[np.ndarray, bool]]:
    a, b = nd.layer_offsets[k], nd.layer_offsets[k + 1]
    return [(nd.points[nd.loop_offsets[i] : nd.loop_offsets[i + 1]], bool(nd.loop_is_hole[i])) for i in range(a, b)]


@pytest.fixture
def paths(monkeypatch):
    """Counts of groups (layers) that took the arrangement path ('fast') and those left to GEOS ('geos')."""
    seen = {"fast": 0, "geos": 0}
    real = overlaps._arrangement

    def spy(*args, **kwargs):
        ok, geoms = real(*args, **kwargs)
        seen["fast"] += int(ok.sum())
        seen["geos"] += int((~ok).sum())
        return ok, geoms

    monkeypatch.setattr(overlaps, "_arrangement", spy)
    return seen


def assert_layers_match(layers: list[list[np.ndarray]], fill_rule: str) -> None:
    """Every layer is rebuilt and its rings equal the reference's exactly, in order, with the same roles."""
    nd = nest_loops(make_loops(layers), len(layers), fill_rule)
    for k, rings in enumerate(layers):
        assert nd.overlaps_resolved[k] == 1, k
        got, want = layer_rings(nd, k), reference_rings(rings, fill_rule)
        assert len(got) == len(want), (k, len(got), len(want))
        for (g, gh), (w, wh) in zip(got, want, strict=True):
            assert gh == wh
            np.testing.assert_array_equal(g, w.astype(np.float32))
        assert nd.area[k] == pytest.approx(sum((-1 if h else 1) * abs(signed_areas(r, np.array([0, len(r)]))[0])
                                               for r, h in want), abs=1e-9)


def nested_islands():
    """Shell, hole, island, hole, and a bow-tie inside the inner hole: the bow-tie's lobes and the holes each have
    two shells whose boxes hold theirs (the smallest containing one is the parent)."""
    return [square(0, 0, 100), square(10, 10, 80, ccw=False), square(20, 20, 60), square(30, 30, 40, ccw=False),
            bowtie(45, 45, 10)]


GENERIC = {
    "bowtie": [bowtie(0, 0, 10)],
    "squares_same_way": [square(0, 0, 10), square(5, 5, 10)],
    "squares_opposite": [square(0, 0, 10), square(5, 5, 10, ccw=False)],
    "bar_through_a_hole": [square(0, 0, 30), square(10, 10, 10, ccw=False),
                           np.array([[-5, 13], [35, 12], [35, 17], [-5, 18]], float)],
    "three_triangles": [np.array([[0, 0], [10, 1], [4, 9]], float), np.array([[3, -2], [9, 7], [-1, 6]], float),
                        np.array([[-2, 3], [11, 4], [5, 11]], float)],
    "nested_islands": nested_islands(),
}


@pytest.mark.parametrize("fill_rule", RULES)
@pytest.mark.parametrize("name", sorted(GENERIC))
def test_generic_layers_take_the_arrangement_path_and_match_geos(paths, name, fill_rule):
    assert_layers_match([GENERIC[name]], fill_rule)
    assert paths == {"fast": 1, "geos": 0}


@pytest.mark.parametrize("fill_rule", RULES)
def test_random_overlapping_stars_match_geos(paths, fill_rule):
    """Forty layers of three to five random stars around nearby centres: many crossings, faces winding 0 to 5."""
    rng = np.random.default_rng(14)
    layers = [[star(rng, *rng.uniform(0, 4, 2), 3, 12, int(rng.integers(5, 40))) for _ in range(rng.integers(3, 6))]
              for _ in range(40)]
    assert_layers_match(layers, fill_rule)
    assert paths["fast"] == 40


TOUCHING = {
    "loop_through_its_own_point": [np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 0], [2, 2], [6, 2], [6, 6],
                                             [2, 6]], float)],
    "shared_edge": [square(0, 0, 10), square(10, 0, 10), np.array([[5, 5], [15, 6], [15, 8]], float)],
    "corner_on_an_edge": [bowtie(0, 0, 10), np.array([[10, 5], [20, 0], [20, 10]], float)],
    "same_loop_twice": [bowtie(0, 0, 10), bowtie(0, 0, 10)],
}


@pytest.mark.parametrize("fill_rule", RULES)
@pytest.mark.parametrize("name", sorted(TOUCHING))
def test_touching_loops_go_to_geos_and_match(paths, name, fill_rule):
    assert_layers_match([TOUCHING[name]], fill_rule)
    assert paths == {"fast": 0, "geos": 1}


def test_holes_pinched_at_a_crossing_go_to_geos(paths):
    """A bow-tie in a square under even-odd: both lobes are holes, touching at the crossing. Linking the boundary
    around the filled corners there would make one hole through that point twice; GEOS makes two holes."""
    assert_layers_match([[square(0, 0, 30), bowtie(10, 10, 10)]], "evenodd")
    assert paths == {"fast": 0, "geos": 1}
    assert len(reference_rings([square(0, 0, 30), bowtie(10, 10, 10)], "evenodd")) == 3


def test_real_mesh_arrangement_equals_geos(shared_meshes, monkeypatch):
    """Benchy and a self-intersecting part: the slices are the same bytes whether the crossing layers go through
    the arrangement path or all through GEOS, and the arrangement path takes most of them."""
    from gpuslice import load_mesh, slice_mesh

    for name in ("benchy", "p_self_intersect_a"):
        path = shared_meshes / f"{name}.stl"
        if not path.is_file():
            pytest.skip(f"{path} not found")
        mesh = load_mesh(path, fit=60)
        seen = {"fast": 0, "geos": 0}
        real = overlaps._arrangement

        def spy(*args, real=real, seen=seen, **kwargs):
            ok, geoms = real(*args, **kwargs)
            seen["fast"] += int(ok.sum())
            seen["geos"] += int((~ok).sum())
            return ok, geoms

        monkeypatch.setattr(overlaps, "_arrangement", spy)
        fast = slice_mesh(mesh, thickness=0.2)
        monkeypatch.setattr(overlaps, "_arrangement",
                            lambda ne, rz, roff, loop_g, lid, n, *a: (np.zeros(n, bool), np.zeros(0, object)))
        geos = slice_mesh(mesh, thickness=0.2)
        monkeypatch.undo()
        assert seen["fast"] >= 0.9 * (seen["fast"] + seen["geos"]) and seen["fast"] > 0, seen
        for field in ("points", "loop_offsets", "layer_offsets", "loop_is_hole", "loop_parent", "loop_closed", "area"):
            assert np.asarray(getattr(fast, field)).tobytes() == np.asarray(getattr(geos, field)).tobytes(), field


def affected_one_layer(lo: np.ndarray, hi: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The group selection of one layer as the per-layer code did it: components of overlapping boxes holding a
    seed, each grown by the loops whose box meets its hull box, until none does."""
    n = lo.shape[0]
    if n > 4000 or not seed.any():
        return np.ones(n, dtype=bool)
    meets = lambda a0, a1, b0, b1: np.all((a0 <= b1) & (b0 <= a1), axis=-1)  # noqa: E731
    ii, jj = np.nonzero(meets(lo[:, None], hi[:, None], lo[None], hi[None]))
    while True:
        label = np.arange(n)
        while True:
            new = label.copy()
            np.minimum.at(new, ii, label[jj])
            new = new[new]
            if np.array_equal(new, label):
                break
            label = new
        groups = np.unique(label[seed])
        grown = False
        for g in groups:
            member = label == g
            touch = meets(lo, hi, lo[member].min(axis=0), hi[member].max(axis=0)) & ~member
            if touch.any():
                t = np.flatnonzero(touch)
                ii, jj = np.concatenate([ii, t, np.full(t.size, g)]), np.concatenate([jj, np.full(t.size, g), t])
                grown = True
        if not grown:
            return np.isin(label, groups)


def test_affected_all_matches_layer_by_layer():
    rng = np.random.default_rng(7)
    grew = clusters = 0
    for _ in range(400):
        sizes = rng.integers(0, 9, rng.integers(1, 6))
        g = np.repeat(np.arange(sizes.size), sizes)
        lo = np.round(rng.uniform(0, 10, (g.size, 2)), 1)
        hi = lo + np.round(rng.uniform(0.1, 4, (g.size, 2)) * rng.choice([0.2, 1, 3], (g.size, 1)), 1)
        seed = rng.random(g.size) < rng.choice([0, 0.1, 0.3, 1])
        got = _affected_all(g, lo, hi, seed, sizes)
        first = np.cumsum(sizes) - sizes
        want = [affected_one_layer(lo[f : f + s], hi[f : f + s], seed[f : f + s])
                for f, s in zip(first, sizes, strict=True)]
        np.testing.assert_array_equal(got, np.concatenate(want))
        grew += int(0 < got.sum() < got.size)
        # clusters: the same loops, labelled in layer order; two loops of a layer in different clusters never have
        # meeting boxes (so each cluster is rebuilt alone)
        taken, label = _affected_all(g, lo, hi, seed, sizes, with_label=True)
        np.testing.assert_array_equal(taken, got)
        t = np.flatnonzero(taken)
        assert np.all(np.diff(g[t][np.argsort(label[t], kind="stable")]) >= 0)
        i, j = np.meshgrid(t, t, indexing="ij")
        meet = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=2) & (g[i] == g[j])
        assert not np.any(meet & (label[i] != label[j]))
        clusters += int(np.unique(label[t]).size > np.unique(g[t]).size)
    assert grew > 50  # the cases where only some loops are taken are well represented
    assert clusters > 20  # and those where a layer's taken loops form several clusters


def test_winding_numbers_match_edge_by_edge():
    rng = np.random.default_rng(3)
    rings = [star(rng, 0, 0, 1, 5, int(n)) for n in rng.integers(3, 30, 20)]
    rings.append(bowtie(-3, -3, 6).astype(np.float32))
    offsets = np.concatenate([[0], np.cumsum([len(r) for r in rings])])
    pc = np.concatenate(rings).astype(np.float64).view(np.complex128).reshape(-1)
    q = rng.uniform(-6, 6, 300) + 1j * rng.uniform(-6, 6, 300)
    q[:20] = pc[rng.integers(0, pc.size, 20)]  # on vertices: at the y of the ray's half-open rule
    pi, pj = np.repeat(np.arange(q.size), len(rings)), np.tile(np.arange(len(rings)), q.size)
    got = _winding_numbers(pc, offsets, pi, pj, q)
    want = [plain_winding(rings[j], np.array([q[i].real, q[i].imag])) for i, j in zip(pi, pj, strict=True)]
    np.testing.assert_array_equal(got, want)


def test_signed_areas_bit_for_bit_as_complex_products():
    """The real-arithmetic shoelace gives the very bits of the complex form (products of float32 values are
    exact in float64, so both round once per edge)."""
    rng = np.random.default_rng(5)
    pts = rng.uniform(-300, 300, (5000, 2)).astype(np.float32)
    offsets = np.concatenate([[0], np.sort(rng.choice(np.arange(3, 4997), 300, replace=False)), [5000]])
    pc = pts.astype(np.float64).view(np.complex128).reshape(-1)
    nxt = np.empty_like(pc)
    nxt[:-1] = pc[1:]
    nxt[offsets[1:] - 1] = pc[offsets[:-1]]
    want = np.add.reduceat((pc.conj() * nxt).imag, offsets[:-1]) / 2.0
    assert signed_areas(pts, offsets).tobytes() == want.tobytes()


def test_rebuilt_layers_hold_no_sliver_narrower_than_a_float32_step(shared_meshes, tmp_path):
    """Benchy at 30 mm, 1 mm layers: the arrangement of layers 4 and 5 left 3-point rings of 8e-12 and 1.6e-12 mm²
    that every export rounded into self-touching polygons (invalid GeoJSON, a CLI outer of four equal points; an
    audit). No loop of a rebuilt layer is narrower on average than one float32 step of its coordinates, and the
    GeoJSON's polygons are valid."""
    import json

    from gpuslice import load_mesh, slice_mesh
    from gpuslice.formats import export

    path = shared_meshes / "benchy.stl"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    res = slice_mesh(load_mesh(path, fit=30), thickness=1.0)
    rebuilt = np.flatnonzero(res.repairs["overlaps_resolved"])
    assert rebuilt.size
    pts, off = res.points.astype(np.float64), res.loop_offsets
    area = np.abs(signed_areas(pts, off))
    nxt = np.concatenate([pts[1:], pts[:1]])
    seg = np.hypot(*(nxt - pts).T)
    seg[off[1:] - 1] = np.hypot(*(pts[off[:-1]] - pts[off[1:] - 1]).T)
    perimeter = np.add.reduceat(seg, off[:-1])
    step = np.spacing(np.abs(pts).max().astype(np.float32))
    in_rebuilt = np.isin(res.loop_layer, rebuilt) & res.loop_closed
    assert np.all(2 * area[in_rebuilt] > step * perimeter[in_rebuilt])
    export(res, tmp_path / "b.geojson")
    feats = json.loads((tmp_path / "b.geojson").read_text())["features"]
    for k in rebuilt:
        geom = shapely.geometry.shape(feats[k]["geometry"])
        assert geom.is_valid, (k, shapely.is_valid_reason(geom))
