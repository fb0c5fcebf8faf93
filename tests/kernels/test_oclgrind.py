"""Every kernel of ``kernels/*.cl`` once under Oclgrind, against its numpy twin (portability without a GPU).

CI has no GPU, and PoCL runs work-items in an order that hides most races. Oclgrind (Debian package ``oclgrind``,
installed by ``scripts/setup-system.sh``) is an OpenCL 1.2 simulator that interprets every instruction and reports
data races, out-of-bounds accesses, barrier divergence and uninitialised values. The kernels run in a subprocess
whose OpenCL loader sees only Oclgrind (``OCL_ICD_VENDORS`` at a temporary folder holding one ``.icd`` file), so
PoCL stays the device of the test process; the inputs are tiny (a 224-facet sphere, a box, a few layers, a 64 x 48
display) because Oclgrind is slow. The child (this file run as a script) compares every kernel's output with its
numpy twin, then prints the kernels it launched; the test fails on a mismatch, on any kernel of ``kernels/*.cl``
left unlaunched, and on any report of Oclgrind.

Two passes, because of two limits of Oclgrind 21.10 (Debian 12):

1. ``races``: ``OCLGRIND_DATA_RACES`` (plain accesses against each other and against atomics, global and local
   memory), ``OCLGRIND_UNIFORM_WRITES`` (also writes of equal values), ``OCLGRIND_CHECK_API``; bounds and barrier
   divergence are always checked. Every kernel.
2. ``uninitialized``: ``OCLGRIND_UNINITIALIZED``. (a) Oclgrind does not count ``clEnqueueFillBuffer`` as
   initialising memory, so the child fills buffers by writes (``KernelDriver._fill`` replaced: the same bytes).
   (b) Its plugin segfaults (in ``Uninitialized::instructionExecuted``) while running ``runs_prep``, so the kernels
   of ``runs.cl`` are left out of this pass only.

A canary kernel with a known race, out-of-bounds write, barrier divergence and uninitialised copy runs first: its
reports must appear, so a run where Oclgrind checks nothing cannot pass. Known noise: PyOpenCL's ``Program.build``
asks ``clGetDeviceInfo`` for a parameter Oclgrind does not know (``CL_INVALID_VALUE`` for ``param_name``); any other
API error fails. Findings (``emit_segments``'s ``(int2)`` store: a false positive, now a ``vstore2``; the weld's
plain read of a hash slot racing with atomics): docs/ROBUSTNESS.md, "Kernels under Oclgrind".
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ICD = Path("/usr/lib/oclgrind/liboclgrind-rt-icd.so")  # Debian's oclgrind package
MARK = "OCLGRIND-CHILD "
PASSES = {
    "races": {"OCLGRIND_DATA_RACES": "1", "OCLGRIND_UNIFORM_WRITES": "1", "OCLGRIND_CHECK_API": "1"},
    "uninitialized": {"OCLGRIND_UNINITIALIZED": "1", "OCLGRIND_CHECK_API": "1"},
}
# kernels the uninitialised-value pass leaves out (Oclgrind 21.10's plugin crashes on runs_prep)
UNINIT_SKIP_FILES = ("runs.cl",)
# the canary's reports that each pass must show (message heads as Oclgrind writes them)
CANARY_EXPECTED = {
    "races": ("Write-write data race", "Invalid write of size", "Work-group divergence detected (barrier)"),
    "uninitialized": ("Uninitialized value written to global memory",),
}
CANARY_SOURCE = """
__kernel void oclgrind_canary(__global int *a, const int n) {
    const int i = get_global_id(0);
    a[0] = i;                                                  // a write-write race
    if (i == 0) a[n] = 1;                                      // out of bounds: a holds n ints
    if (get_local_id(0) == 0) barrier(CLK_GLOBAL_MEM_FENCE);   // barrier divergence
}
__kernel void oclgrind_canary_uninit(__global const int *never_written, __global int *b) {
    b[get_global_id(0)] = never_written[get_global_id(0)];
}
"""
_API_NOISE = re.compile(
    r"Oclgrind - OpenCL runtime error detected\n\s*Function: clGetDeviceInfo\n\s*Error:\s*CL_INVALID_VALUE\n"
    r"\s*For argument 'param_name'\n"
)


def declared_kernels(skip_files: tuple[str, ...] = ()) -> set[str]:
    """Names of the ``__kernel`` functions of ``kernels/*.cl`` (files in ``skip_files`` left out)."""
    names: set[str] = set()
    for path in sorted((REPO / "kernels").glob("*.cl")):
        if path.name not in skip_files:
            names |= set(re.findall(r"__kernel\b[^;{]*?\bvoid\s+(\w+)\s*\(", path.read_text()))
    return names


def _reports(log: str) -> list[tuple[str, str, str]]:
    """Oclgrind's log as (message head, kernel, the whole block) per report."""
    out = []
    for block in re.split(r"\n\s*\n(?=\S)", log):
        lines = [x for x in block.splitlines() if x.strip()]
        if not lines:
            continue
        kernel = next((x.split(":", 1)[1].strip() for x in lines if x.strip().startswith("Kernel:")), "?")
        out.append((lines[0].strip(), kernel, block.strip()))
    return out


def _run_pass(name: str, icd_dir: Path, tmp: Path) -> tuple[dict, list[tuple[str, str, str]], str]:
    """Run the child under Oclgrind with the checks of pass ``name``: (its summary, Oclgrind's reports, stderr)."""
    log = tmp / f"oclgrind-{name}.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OCLGRIND_", "PYOPENCL_CTX"))}
    env.update(PASSES[name])
    env.update(
        OCL_ICD_VENDORS=str(icd_dir),
        GPUSLICE_DEVICE="oclgrind",
        PYOPENCL_NO_CACHE="1",  # build from source: Oclgrind's reports then quote the kernel's lines
        OCLGRIND_LOG=str(log),
        OCLGRIND_MAX_ERRORS="200",
    )
    proc = subprocess.run(
        [sys.executable, __file__, name], cwd=REPO, env=env, capture_output=True, text=True, timeout=110
    )
    stderr = _API_NOISE.sub("", proc.stderr)
    summary = next((json.loads(x[len(MARK):]) for x in proc.stdout.splitlines() if x.startswith(MARK)), None)
    assert proc.returncode == 0 and summary is not None, (
        f"pass {name}: the child failed (rc {proc.returncode})\n{proc.stdout[-2000:]}\n{stderr[-4000:]}"
    )
    return summary, _reports(log.read_text() if log.exists() else ""), stderr


@pytest.fixture(scope="module")
def icd_dir(tmp_path_factory) -> Path:
    if not ICD.is_file():
        msg = f"Oclgrind is not installed ({ICD} missing; scripts/setup-system.sh installs the Debian package)"
        if os.environ.get("GPUSLICE_REQUIRE_OCLGRIND"):
            pytest.fail(msg)
        pytest.skip(msg)
    folder = tmp_path_factory.mktemp("icd")
    (folder / "oclgrind.icd").write_text(f"{ICD}\n")
    return folder


@pytest.mark.parametrize("name", sorted(PASSES))
def test_kernels_clean_under_oclgrind(icd_dir, tmp_path, name):
    summary, reports, stderr = _run_pass(name, icd_dir, tmp_path)
    assert "oclgrind" in summary["device"].lower(), summary["device"]
    # the canary proves the checks are live
    canary = [head for head, kernel, _ in reports if kernel.startswith("oclgrind_canary")]
    for want in CANARY_EXPECTED[name]:
        assert any(h.startswith(want) for h in canary), f"pass {name}: Oclgrind did not report the canary's '{want}'"
    # every kernel of kernels/*.cl ran (a new kernel needs a check in _workload below)
    want = declared_kernels(UNINIT_SKIP_FILES if name == "uninitialized" else ())
    missing = want - set(summary["launched"])
    assert not missing, f"pass {name}: kernels never launched under Oclgrind: {sorted(missing)}"
    # and none of them drew a report
    found = [(head, kernel, block) for head, kernel, block in reports if not kernel.startswith("oclgrind_canary")]
    if found:
        kinds = Counter((re.sub(r" at .*", "", head), kernel) for head, kernel, _ in found)
        lines = [f"  {n} x {head} in {kernel}" for (head, kernel), n in kinds.most_common()]
        pytest.fail(f"pass {name}: Oclgrind reported (first {len(found)} reports, OCLGRIND_MAX_ERRORS caps them):\n"
                    + "\n".join(lines) + "\n\nthe first ones:\n\n" + "\n\n".join(b for _, _, b in found[:3]))
    assert "Oclgrind" not in stderr, f"pass {name}: Oclgrind API errors:\n{stderr[-3000:]}"


# ---- the child: runs on the device GPUSLICE_DEVICE names (any device: `python tests/kernels/test_oclgrind.py`) ---


def _fill_by_writes() -> None:
    """``KernelDriver._fill`` by a host write of the same bytes (Oclgrind's uninitialised-value tracking does not
    see ``clEnqueueFillBuffer``)."""
    import numpy as np

    from gpuslice.device import KernelDriver

    def fill(self, name: str, nbytes: int, value):
        import pyopencl as cl

        value = np.asarray(value)
        n = max(nbytes, 4)
        buf = self._buffer(name, n)
        host = np.full(-(-n // value.itemsize), value, dtype=value.dtype).view(np.uint8)[:n]
        cl.enqueue_copy(self.device.queue, buf, host, is_blocking=True)
        return buf

    KernelDriver._fill = fill


def _record_launches() -> set[str]:
    """The names of the kernels launched from now on (pyopencl's ``Kernel.__call__`` wrapped)."""
    import pyopencl as cl

    launched: set[str] = set()
    call = cl.Kernel.__call__

    def recording(self, *args, **kwargs):
        launched.add(self.function_name)
        return call(self, *args, **kwargs)

    cl.Kernel.__call__ = recording
    return launched


def _canary(dev) -> None:
    import numpy as np
    import pyopencl as cl

    prg = cl.Program(dev.context, CANARY_SOURCE).build()
    a = cl.Buffer(dev.context, cl.mem_flags.READ_WRITE, 4 * 4)
    cl.enqueue_copy(dev.queue, a, np.zeros(4, np.int32))
    prg.oclgrind_canary(dev.queue, (4,), (2,), a, np.int32(4))
    never = cl.Buffer(dev.context, cl.mem_flags.READ_WRITE, 4 * 4)
    prg.oclgrind_canary_uninit(dev.queue, (4,), (2,), never, a)
    dev.queue.finish()


def _same(a, b, what: str) -> None:
    import numpy as np

    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype and np.array_equal(x, y), what


def _same_result(a, b, what: str) -> None:
    import numpy as np

    for name in ("points", "loop_offsets", "layer_offsets", "loop_is_hole", "loop_parent", "loop_closed", "area"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), f"{what}: {name}"


def _workload(pass_name: str) -> dict:
    """Every kernel on tiny inputs against its numpy twin (asserts); returns the device and the kernels launched."""
    import numpy as np

    if pass_name == "uninitialized":
        _fill_by_writes()
    launched = _record_launches()
    from gpuslice import mesh_from_triangles, slice_mesh
    from gpuslice.device import get_device
    from gpuslice.mesh import shapes as S
    from gpuslice.mesh.weld import (
        ComponentsKernel,
        WeldKernel,
        edge_ids_device,
        edge_ids_numpy,
        weld_device,
        weld_numpy,
    )
    from gpuslice.raster import RasterSpec, masks
    from gpuslice.raster.runs import layer_runs, runs_to_mask
    from gpuslice.schedule.adaptive import facet_slopes, facet_slopes_numpy, slab_max_nz, slab_max_nz_numpy
    from gpuslice.slicing.chain import link_segments, order_chains
    from gpuslice.slicing.crossings import compute_crossings, crossings_numpy
    from gpuslice.slicing.walk import walk_chains

    dev = get_device()
    if "oclgrind" in dev.name.lower():  # undefined behaviour: never on a real device
        _canary(dev)
    sphere_tri = S.uv_sphere(10.0, 8, 16)  # 224 facets
    box_tri = S.box(hi=(16.0, 12.0, 10.0))
    # weld.cl: the weld and the edge ids, also with a crippled hash (long probe chains)
    corners = np.ascontiguousarray(sphere_tri.reshape(-1, 3), np.float32) + np.float32(0.0)
    _same(weld_device(corners, dev), weld_numpy(corners), "weld")
    sphere = mesh_from_triangles(sphere_tri)
    n_v = int(sphere.vertices.shape[0])
    _same(edge_ids_device(sphere.faces, n_v, dev), edge_ids_numpy(sphere.faces, n_v), "edge ids")
    crippled = WeldKernel(dev, table_factor=1.0, hash_bits=4)
    _same(crippled.weld(corners), weld_numpy(corners), "weld, colliding hash")
    _same(crippled.edge_ids(sphere.faces, n_v), edge_ids_numpy(sphere.faces, n_v), "edge ids, colliding hash")
    # weld.cl's pairing of the sides and its union-find (the mesh check's shells)
    from dataclasses import astuple

    from gpuslice.mesh.graph import connected_labels
    from gpuslice.mesh.weld import edge_table_numpy

    pairing = (WeldKernel.of(dev).edge_table(sphere.faces, n_v)[2], edge_table_numpy(sphere.faces, n_v)[2])
    _same(astuple(pairing[0]), astuple(pairing[1]), "edge pairing")
    a, b = np.random.default_rng(5).integers(0, 300, (2, 200))
    labels = ComponentsKernel.of(dev).components(300, a, b)
    _same([labels], [connected_labels(300, a, b).astype(np.int32)], "components")
    # crossings.cl, with planes through vertices (the on-plane rule); walk.cl on a host successor array
    zs = np.unique(np.concatenate([np.linspace(0.3, sphere.height - 0.3, 5), sphere.vertices[:, 2].astype(float)]))
    zs = zs[(zs > 0) & (zs <= sphere.height)]
    ref, got = crossings_numpy(sphere, zs), compute_crossings(sphere, zs, dev)
    _same((got.layer, got.edges, got.points), (ref.layer, ref.edges, ref.points), "crossings")
    nxt, _, _ = link_segments(ref, sphere, zs.astype(np.float32))
    _same(walk_chains(nxt, ref.layer, zs.size, dev), order_chains(nxt, ref.layer), "walk")
    # walk.cl's screen of simple loops, against known answers: a loop touching or crossing itself is never cleared
    # (its chain-building loop on float2 values was mis-run by Oclgrind 21.10, which then cleared all of these)
    from gpuslice.slicing.walk import chain_kernels

    touch = np.array([(0, 0), (4, 0), (4, 4), (2, 4), (2, 0.0), (0, 4)])
    loops = [touch, touch[::-1], np.roll(touch, 2, 0), touch[:, ::-1], touch * 1.5 + 10,
             np.array([(0, 0), (4, 0), (4, 4), (2, 4), (2, -0.5), (0, 4)]),  # crosses the bottom edge
             np.array([(0, 0), (4, 0), (4, 4), (2, 4), (2, 0.5), (0, 4)]),  # simple
             np.array([(0, 0), (5, 0), (5, 5), (0, 5.0)])]
    pts, offs = np.concatenate(loops).astype(np.float32), np.cumsum([0] + [len(q) for q in loops])
    got = chain_kernels(dev).simple_loops(pts, offs.astype(np.int64))
    if got is not None:  # (None: a device without doubles has no screen)
        _same((np.asarray(got, np.uint8),), (np.array([0, 0, 0, 0, 0, 0, 1, 1], np.uint8),), "simple loops")
    # walk.cl's boxes of nesting's chunks, against contain.Chunks on the host (a loop of three chunks among them)
    from gpuslice.slicing.contain import Chunks

    long_loop = np.stack([np.cos(np.arange(150) / 24.0), np.sin(np.arange(150) / 24.0)], axis=1) * 3
    pts, offs = np.concatenate([pts, long_loop.astype(np.float32)]), np.append(offs, offs[-1] + 150).astype(np.int64)
    host = Chunks(pts, offs)
    host.cut(np.arange(offs.size - 1))
    boxes = chain_kernels(dev).chunk_boxes(pts, offs).astype(np.float64)
    _same((boxes[:, :2], boxes[:, 2:]), (host.lo, host.hi), "chunk boxes")
    # walk.cl's device chaining (closed), its open-chain and conflict exits (a missing facet, a non-manifold edge)
    open_box = box_tri[1:]
    two_cubes = np.concatenate([S.box((0, 0, 0), (6, 6, 6)), S.box((6, 6, 0), (12, 12, 6))])
    # a fin on the box's edge: two segments end at one slot, which the walk finds. Not in the uninitialised-value
    # pass: there, after the box, Oclgrind 21.10 takes the crossings' segments for uninitialised (their values are
    # right: the result equals the twin's; as below, it loses track of the crossings kernels' output late in the run)
    finned = np.concatenate([box_tri, np.array([[(16, 0, 0), (16, 0, 10), (21, -5, 5)]], float)])
    fin = () if pass_name == "uninitialized" else (("box with a fin", finned),)
    results = {}
    for what, tri in (("sphere", sphere_tri), ("box", box_tri), ("open box", open_box), ("two cubes", two_cubes),
                      *fin):
        mesh = mesh_from_triangles(tri)
        a = slice_mesh(mesh, thickness=2.5, backend="numpy")
        b = slice_mesh(mesh, thickness=2.5, backend="opencl")
        _same_result(b, a, f"slice {what}")
        results[what] = a
    from gpuslice.slicing.crossings import batch_facets, batch_layers, facet_layer_ranges, vertex_layers

    vl = vertex_layers(sphere, zs)
    ranges, batches = (vl, *facet_layer_ranges(sphere, zs, vl)), [(0, zs.size // 2), (zs.size // 2, zs.size)]
    for (a, b), ids in zip(batches, batch_facets(ranges, batches), strict=True):  # a batch's facets alone
        sub, want = compute_crossings(sphere, zs[a:b], dev, layers=batch_layers(ranges, a, b, ids), facets=ids), \
            crossings_numpy(sphere, zs[a:b])
        _same((sub.layer, sub.edges, sub.points), (want.layer, want.edges, want.points), f"crossings {a}..{b}")
    # adaptive.cl
    want = facet_slopes_numpy(sphere)
    _same(facet_slopes(sphere, dev), want, "facet slopes")
    for edges in (np.linspace(0.0, sphere.height, 33), np.array([0.0, 0.7, 3.0, 3.1, 12.0, sphere.height])):
        _same((slab_max_nz(sphere, edges, dev),), (slab_max_nz_numpy(*want, edges),), "slab max |n_z|")
    # runs.cl (whole edges and cut ones: bands of 8 rows here, so the box's sides are cut) and raster.cl
    from gpuslice.raster.runs import RunsKernel

    RunsKernel.ROWS_PER_UNIT = 8
    spec = RasterSpec(resolution=(64, 48), pixel=0.5)
    for what in ("sphere", "box"):
        res = results[what]
        want_runs = layer_runs(res, spec, backend="numpy")
        bitmap = masks(res, spec, backend="opencl-bitmap", device=dev)
        twin = masks(res, spec, backend="numpy")
        assert np.abs(bitmap.astype(int) - twin).max() <= 1, f"raster {what}"  # float32 vs float64: one grey
        if pass_name == "uninitialized":
            continue
        got_runs = layer_runs(res, spec, backend="opencl", device=dev)
        fields = ("layer_offsets", "row", "x", "length", "grey")
        _same([getattr(got_runs, f) for f in fields], [getattr(want_runs, f) for f in fields], f"runs {what}")
        for k in range(res.n_layers):
            assert np.array_equal(runs_to_mask(got_runs, k), bitmap[k]), f"runs against raster, {what} layer {k}"
    # segment_edges.cl: the sphere's z sub-planes (4 a layer) from its segment buffer (made by the twin: Oclgrind
    # 21.10's uninitialised-value pass reports the crossings kernels when they run again this late in the workload)
    from gpuslice.raster.edges import z_sample_planes
    from gpuslice.raster.segment_edges import SegmentEdgesKernel, segment_edges_numpy

    zk, _ = z_sample_planes(results["sphere"], 4)
    seg = crossings_numpy(sphere, zk)  # (uploaded by the driver)
    got, got_short = SegmentEdgesKernel.of(dev)(seg, zk.size, 4, spec, (-10.0, -10.0, 10.0, 10.0))
    want, want_short = segment_edges_numpy(seg, zk.size, 4, spec, (-10.0, -10.0, 10.0, 10.0))
    _same((got.tiles, got.edge_offsets, got_short), (want.tiles, want.edge_offsets, want_short), "segment edges")
    for g in range(len(got.tiles)):
        a, b = got.edge_offsets[g], got.edge_offsets[g + 1]
        x, y = got.edges[a:b], want.edges[a:b]
        _same([x[np.lexsort(x.T)]], [y[np.lexsort(y.T)]], f"segment edges, layer {g}")  # (any order in a layer)
    # goo.cl, ctb.cl, photon.cl and png.cl: the GOO, CTB, PW0 and PNG images of the box's and the sphere's runs (as
    # the runs kernel types them), layer groups from the first entry and from one inside
    from gpuslice.raster.ctb import rle7_runs
    from gpuslice.raster.deflate_runs import encode_png_from_runs
    from gpuslice.raster.goo import encode_batch
    from gpuslice.raster.photon import encode_pw0_runs
    from gpuslice.raster.png_runs import PngRunsEncoder
    from gpuslice.raster.runs import Runs

    for what in ("sphere", "box"):
        r = layer_runs(results[what], spec, backend="numpy")
        r = Runs(r.layers, r.layer_offsets, *(np.ascontiguousarray(a, np.int32) for a in (r.row, r.x, r.length)),
                 np.ascontiguousarray(r.grey, np.uint8), r.shape)
        rows, cols = spec.shape
        for a in (0, 1):
            got = encode_batch(r, a, len(r.layers), cols, rows * cols, device=dev)
            assert got == encode_batch(r, a, len(r.layers), cols, rows * cols), f"GOO images, {what} from {a}"
            got = rle7_runs(r, a, len(r.layers), cols, rows * cols, device=dev)
            assert got == rle7_runs(r, a, len(r.layers), cols, rows * cols), f"CTB images, {what} from {a}"
            got = encode_pw0_runs(r, a, len(r.layers), cols, rows * cols, device=dev)
            want = encode_pw0_runs(r, a, len(r.layers), cols, rows * cols)
            assert got[0] == want[0], f"PW0 images, {what} from {a}"
            _same(got[1:], want[1:], f"PW0 lit, middle greys, boxes, {what} from {a}")
            got = PngRunsEncoder.of(dev).encode(r, a, len(r.layers), cols, rows)
            want = [encode_png_from_runs(r, k, cols, rows, "static") for k in range(a, len(r.layers))]
            assert got == want, f"PNG layers, {what} from {a}"
    return {"device": dev.name, "launched": sorted(launched)}


if __name__ == "__main__":
    print(MARK + json.dumps(_workload(sys.argv[1] if len(sys.argv) > 1 else "races")), flush=True)
