"""The issue's acceptance tests on the real meshes of ``../shared/meshes`` (see its ``catalog.csv``).

1. Every watertight mesh of the catalog, scaled to an 80 mm longest side and sliced at 0.1 mm on OpenCL, gives only
   closed loops, and Σ area·thickness is within 0.5 % of the catalog volume × scale³. Where the catalog volume is
   not what a correct slicer can give at 0.1 mm (a thin part's midpoint-rule error, the signed volume of a
   mis-wound mesh) or gpuslice is known to be wrong (crossing loops), the case is a strict xfail with the measured
   numbers, and a companion test checks the right reference.
2. Per-layer areas against Slic3r 1.3 on the same float32 STL, layers matched by their cutting plane.
3. The OpenCL kernels against their numpy twins on real meshes, stage by stage and for the whole result.

Skips: the shared data folder, slic3r and an OpenCL device are each optional; tests that need one skip with a
reason naming it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import read_catalog

import gpuslice
from gpuslice.errors import MeshFileError

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import peers  # noqa: E402

MESHES = Path(__file__).resolve().parents[3] / "shared" / "meshes"
NO_MESHES = "../shared/meshes not found: real-mesh tests need the shared data folder"
NO_SLIC3R = "slic3r not installed: run ../shared/peers/setup-peers.sh"

pytestmark = pytest.mark.skipif(not (MESHES / "catalog.csv").is_file(), reason=NO_MESHES)

FIT = 80.0  # mm, the longest bounding-box side after scaling
H = 0.1  # mm, layer thickness of the volume test
VOLUME_RTOL = 5e-3


CATALOG = read_catalog()


def _opencl_skip_reason() -> str | None:
    try:
        from gpuslice.device import list_devices

        devices = list_devices()
    except Exception as exc:  # pyopencl missing, no platform, broken ICD
        return f"no OpenCL device ({type(exc).__name__}: {exc})"
    return None if devices else "no OpenCL device (gpuslice.device.list_devices() is empty)"


NO_OPENCL = _opencl_skip_reason()
needs_opencl = pytest.mark.skipif(NO_OPENCL is not None, reason=NO_OPENCL or "")

# ---- known deviations from the catalog volume at h = 0.1 mm (measured on PoCL; fit = 80 mm) --------------------------
# Thin parts: the midpoint rule Σ area(z_i)·h misses steps in the section area that fall between planes by up to h/2
# times the step. Per-layer areas agree with manifold3d's exact sections and the volume converges as h shrinks.
THIN_PARTS = {
    "prusa_two_hollow_squares": (
        "midpoint-rule error of a 3.26 mm tall part in 33 layers, not a slicing error: Σ area·h = 332.47 vs catalog "
        "328.98 mm^3 (+1.06 %); per-layer areas match manifold3d's sections to 2.7e-4 mm^2; -0.06 % at h = 0.02 mm"
    ),
    "thingi_88566": (
        "midpoint-rule error of a 7.06 mm tall part in 71 layers, not a slicing error: Σ area·h = 5111.33 vs "
        "catalog 5080.12 mm^3 (+0.61 %); per-layer areas match manifold3d's sections to 7.3e-5 mm^2; +0.017 % at "
        "h = 0.02 mm"
    ),
}
# Mis-wound meshes: the catalog volume is the signed volume of the file as wound; gpuslice slices the solid the
# facets bound (loops are oriented by the fill rule), i.e. the volume after repairing the winding.
MISWOUND = {
    "p_ascii_multibody": (
        "catalog volume is the signed volume of an inconsistently wound mesh: gpuslice 2947.76 vs catalog "
        "1468.26 mm^3 (+100.8 %); trimesh fix_winding/fix_inversion gives 2947.53 mm^3"
    ),
    "p_block_flipped_facet": (
        "catalog volume counts the flipped (top) facet negatively: gpuslice 512000 = the 80 mm cube vs catalog "
        "426666 mm^3 (+20.0 %)"
    ),
    "p_hourglass_inverted": (
        "catalog volume is the signed volume of a mostly inside-out mesh: gpuslice 51195.5 vs catalog 11729.5 "
        "mm^3 (+336 %); trimesh fix_winding/fix_inversion gives 51195.5 mm^3"
    ),
    "p_triamid": (
        "catalog volume is the signed volume of an inconsistently wound mesh: gpuslice 85333.3 vs catalog "
        "42666.6 mm^3 (+100 %); trimesh fix_winding/fix_inversion gives 85333.3 mm^3"
    ),
}
# A self-intersecting surface: its signed volume (the catalog's) counts the part where the surface overlaps itself
# twice; gpuslice fills it once under the nonzero rule, as manifold3d's union does (checked per layer below).
CROSSING_LOOPS = {
    "p_self_intersect_a": (
        "catalog volume counts the self-overlap twice: gpuslice Σ area·h = 9258.8 vs catalog 9602.2 mm^3 "
        "(-3.58 %), equal to manifold3d's union sections Σ·h 9258.85 mm^3"
    ),
}
VOLUME_XFAIL = {**THIN_PARTS, **MISWOUND, **CROSSING_LOOPS}


WATERTIGHT = [n for n, row in CATALOG.items() if row["watertight"] == "True"] or ["no-catalog"]


def _watertight_params() -> list:
    out = []
    for name in WATERTIGHT:
        marks = [pytest.mark.xfail(strict=True, reason=VOLUME_XFAIL[name])] if name in VOLUME_XFAIL else []
        out.append(pytest.param(name, id=name, marks=marks))
    return out


# ---- loading ----------------------------------------------------------------------------------------------------


def _load(path: Path, fit: float | None = None) -> gpuslice.Mesh:
    """``load_mesh``, or a plain binary-STL read while ``gpuslice.io.meshfile`` does not exist yet."""
    try:
        return gpuslice.load_mesh(path, fit=fit)
    except ImportError:
        data = path.read_bytes()
        n = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
        dt = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
        rec = np.frombuffer(data, dtype=dt, count=n, offset=84)
        return gpuslice.mesh_from_triangles(rec["v"], fit=fit, name=str(path))


@pytest.fixture(scope="module")
def catalog_slices():
    """name -> (mesh, result at H, OpenCL), each mesh loaded and sliced once per module."""
    cache: dict = {}

    def get(name: str):
        if name not in cache:
            row = CATALOG[name]
            try:
                mesh = _load(MESHES / row["file"], fit=FIT)
            except MeshFileError as exc:
                if not name.startswith("p_"):
                    raise
                cache[name] = exc
            else:
                cache[name] = (mesh, gpuslice.slice_mesh(mesh, thickness=H, backend="opencl"))
        got = cache[name]
        if isinstance(got, Exception):
            pytest.skip(f"{name}: load_mesh rejects the file, a file problem, not slicing: {got}")
        return got

    return get


# The peer comparisons and the kernel checks use scaled copies written by scripts/peers.py, loaded unscaled, so
# Slic3r and gpuslice slice the same float32 triangles.
SCALED = {"cow": 80.0, "nefertiti": 80.0, "benchy": 60.0}


@pytest.fixture(scope="module")
def scaled_meshes(tmp_path_factory):
    cache: dict = {}
    folder = tmp_path_factory.mktemp("scaled")

    def get(name: str) -> tuple[Path, gpuslice.Mesh]:
        if name not in cache:
            stl = folder / f"{name}_{SCALED[name]:g}mm.stl"
            peers.write_scaled_stl(MESHES / CATALOG[name]["file"], stl, fit=SCALED[name])
            mesh = _load(stl)
            assert np.isclose(mesh.bounds[1] - mesh.bounds[0], SCALED[name], rtol=1e-6).any()
            cache[name] = (stl, mesh)
        return cache[name]

    return get


@pytest.fixture(scope="module")
def opencl_device():
    if NO_OPENCL:
        pytest.skip(NO_OPENCL)
    from gpuslice.device import get_device

    return get_device()


# ---- 1. closed loops and volume on every watertight mesh ------------------------------------------------------


@needs_opencl
@pytest.mark.parametrize("name", WATERTIGHT)
def test_watertight_mesh_gives_only_closed_loops(catalog_slices, name):
    mesh, res = catalog_slices(name)
    per_layer = res.open_chains_per_layer
    assert res.meta["open_chains"] == 0 and bool(res.loop_closed.all()), (
        f"{name}: {res.meta['open_chains']} open chains in layers {np.flatnonzero(per_layer)[:10].tolist()} "
        f"(repairs {res.meta['repairs']})"
    )


@needs_opencl
@pytest.mark.parametrize("name", _watertight_params())
def test_watertight_mesh_volume_matches_catalog(catalog_slices, name):
    mesh, res = catalog_slices(name)
    expected = float(CATALOG[name]["volume"]) * mesh.scale**3
    rel = (res.volume - expected) / expected
    assert abs(rel) <= VOLUME_RTOL, (
        f"{name}: Σ area·thickness = {res.volume:.6g} mm^3 vs catalog {expected:.6g} mm^3 ({100 * rel:+.3f} %, "
        f"{res.n_layers} layers of {H} mm, scale {mesh.scale:.6g}, repairs {res.meta['repairs']})"
    )


@needs_opencl
@pytest.mark.parametrize("name", sorted(THIN_PARTS))
def test_thin_part_volume_converges(catalog_slices, name):
    """The thin parts' 0.1 mm deviation is the midpoint rule's: at 0.02 mm they are within 0.5 % too."""
    mesh, _ = catalog_slices(name)
    res = gpuslice.slice_mesh(mesh, thickness=0.02)
    expected = float(CATALOG[name]["volume"]) * mesh.scale**3
    rel = (res.volume - expected) / expected
    assert abs(rel) <= VOLUME_RTOL, f"{name}: {res.volume:.6g} vs {expected:.6g} mm^3 at h = 0.02 ({rel:+.3e})"


@needs_opencl
@pytest.mark.parametrize("name", sorted(MISWOUND))
def test_miswound_mesh_volume_matches_repaired_winding(catalog_slices, name):
    """For mis-wound meshes the right reference is the volume once the winding is repaired (trimesh)."""
    import trimesh

    mesh, res = catalog_slices(name)
    tm = trimesh.Trimesh(mesh.vertices.astype(np.float64), mesh.faces, process=True)
    trimesh.repair.fix_winding(tm)
    trimesh.repair.fix_inversion(tm)
    expected = float(tm.volume)
    rel = (res.volume - expected) / expected
    assert abs(rel) <= VOLUME_RTOL, (
        f"{name}: Σ area·thickness = {res.volume:.6g} vs repaired-winding volume {expected:.6g} mm^3 ({rel:+.3e})"
    )


# ---- 2. per-layer areas against Slic3r --------------------------------------------------------------------------

SLIC3R_CASES = [("cow", 0.2), ("cow", 0.1), ("nefertiti", 0.2), ("benchy", 0.2)]


@pytest.mark.skipif(peers.find_peer("slic3r") is None, reason=NO_SLIC3R)
@pytest.mark.parametrize(("name", "h"), SLIC3R_CASES, ids=[f"{n}-{SCALED[n]:g}mm-h{h:g}" for n, h in SLIC3R_CASES])
def test_layer_areas_match_slic3r(scaled_meshes, name, h):
    stl, mesh = scaled_meshes(name)
    sl = peers.slic3r_layers(stl, h)
    res = gpuslice.slice_mesh(mesh, thickness=h, backend="numpy" if NO_OPENCL else "opencl")
    z_s = np.array([layer.z for layer in sl])
    a_s = np.array([layer.area for layer in sl])
    # the gpuslice plane nearest to every Slic3r plane
    j = np.searchsorted(res.z, z_s)
    lo, hi = np.clip(j - 1, 0, res.n_layers - 1), np.clip(j, 0, res.n_layers - 1)
    i = np.where(np.abs(res.z[lo] - z_s) <= np.abs(res.z[hi] - z_s), lo, hi)
    matched = np.abs(res.z[i] - z_s) <= 1e-6
    n_matched = int(matched.sum())
    assert n_matched >= min(res.n_layers, len(sl)) - 1, (
        f"{name} h={h}: only {n_matched} layers matched by z (gpuslice {res.n_layers}: {res.z[:3]}..., "
        f"slic3r {len(sl)}: {z_s[:3]}...)"
    )
    a_g = res.area[i[matched]]
    a_ref = a_s[matched]
    z_m = z_s[matched]
    nonzero = a_ref > 0
    assert np.all(a_g[~nonzero] == 0), f"{name} h={h}: gpuslice area where slic3r has none at z={z_m[~nonzero]}"
    rel = np.abs(a_g[nonzero] - a_ref[nonzero]) / a_ref[nonzero]
    k = int(np.argmax(rel))
    summary = (
        f"{name} ({SCALED[name]:g} mm) h={h}: {n_matched} matched layers (gpuslice {res.n_layers}, slic3r "
        f"{len(sl)}); |a_gpuslice - a_slic3r| / a_slic3r median {np.median(rel):.3e}, max {rel[k]:.3e} at "
        f"z = {z_m[nonzero][k]:.4f} mm (gpuslice {a_g[nonzero][k]:.6f}, slic3r {a_ref[nonzero][k]:.6f} mm^2)"
    )
    print(summary)
    assert np.median(rel) <= 1e-5, summary


# ---- 3. OpenCL kernels against the numpy reference --------------------------------------------------------------

KERNEL_MESHES = ["cow", "benchy", "nefertiti"]
H_KERNEL = 0.05


@pytest.fixture(scope="module")
def kernel_cases(scaled_meshes, opencl_device):
    """name -> (mesh, float32 planes, numpy segments, OpenCL segments), computed once."""
    from gpuslice.slicing.crossings import compute_crossings, crossings_numpy

    cache: dict = {}

    def get(name: str):
        if name not in cache:
            _, mesh = scaled_meshes(name)
            zs = gpuslice.uniform(mesh.height, H_KERNEL).z.astype(np.float32)
            cache[name] = (mesh, zs, crossings_numpy(mesh, zs), compute_crossings(mesh, zs, opencl_device))
        return cache[name]

    return get


@needs_opencl
@pytest.mark.parametrize("name", KERNEL_MESHES)
def test_crossings_kernel_matches_numpy(kernel_cases, name):
    mesh, zs, ref, got = kernel_cases(name)
    assert len(got) == len(ref), f"{name}: {len(got)} segments on OpenCL, {len(ref)} in numpy"
    np.testing.assert_array_equal(got.layer, ref.layer, err_msg=f"{name}: segment layers")
    np.testing.assert_array_equal(got.edges, ref.edges, err_msg=f"{name}: segment edges")
    diff = float(np.abs(got.points.astype(np.float64) - ref.points).max()) if len(ref) else 0.0
    assert diff <= 1e-5, f"{name}: segment end points differ by up to {diff:.3g} mm"


@needs_opencl
@pytest.mark.parametrize("name", KERNEL_MESHES)
def test_walk_kernel_matches_order_chains(kernel_cases, opencl_device, name):
    from gpuslice.slicing.chain import link_segments, order_chains
    from gpuslice.slicing.walk import walk_chains

    mesh, zs, seg, _ = kernel_cases(name)
    nxt, _, _ = link_segments(seg, mesh, zs)
    ref = order_chains(nxt, seg.layer)
    got = walk_chains(nxt, seg.layer, int(zs.size), opencl_device)
    for what, a, b in zip(("order", "chain offsets", "chain closed"), got, ref, strict=True):
        np.testing.assert_array_equal(a, b, err_msg=f"{name}: {what}")


@needs_opencl
@pytest.mark.parametrize("name", KERNEL_MESHES)
def test_numpy_and_opencl_results_agree(scaled_meshes, name):
    _, mesh = scaled_meshes(name)
    ref = gpuslice.slice_mesh(mesh, thickness=H_KERNEL, backend="numpy")
    got = gpuslice.slice_mesh(mesh, thickness=H_KERNEL, backend="opencl")
    for field in ("z", "thickness", "layer_offsets", "loop_offsets", "loop_layer", "loop_is_hole", "loop_parent",
                  "loop_closed"):
        np.testing.assert_array_equal(getattr(got, field), getattr(ref, field), err_msg=f"{name}: {field}")
    assert got.meta["repairs"] == ref.meta["repairs"]
    dp = float(np.abs(got.points.astype(np.float64) - ref.points).max()) if ref.points.size else 0.0
    assert dp <= 1e-5, f"{name}: points differ by up to {dp:.3g} mm"
    rel = np.abs(got.area - ref.area) / np.maximum(np.abs(ref.area), 1e-300)
    k = int(np.argmax(rel)) if rel.size else 0
    assert rel.size == 0 or rel[k] <= 1e-9, (
        f"{name}: layer {k} (z = {ref.z[k]:.4f} mm) area {got.area[k]!r} on OpenCL vs {ref.area[k]!r} mm^2 in numpy "
        f"({rel[k]:.3g} relative; points differ by up to {dp:.3g} mm)"
    )


@needs_opencl
@pytest.mark.parametrize("name", ["p_self_intersect_a", "prusa_mk4_gantry"])
def test_crossing_loops_area_equals_manifold_union(catalog_slices, name):
    """Crossing loops (a self-intersecting surface, overlapping bodies) are filled once, as manifold3d's union."""
    pytest.importorskip("manifold3d")
    from peers import manifold_slices

    mesh, res = catalog_slices(name)
    ref = np.array([a for a, _ in manifold_slices(mesh.vertices.astype(np.float64), mesh.faces, res.z)])
    assert res.repairs["overlaps_resolved"].sum() > 0
    rel = np.abs(res.area - ref) / np.maximum(ref, 1e-9)
    big = ref > 1e-3 * ref.max()
    assert np.median(rel[big]) <= 1e-5, f"{name}: median {np.median(rel[big]):.2e}, max {rel[big].max():.2e}"
