"""Issue 5, part 5: property-based fuzzing of the reader and the whole pipeline (hypothesis, a modest number of
examples in CI; the long run is ``scripts/fuzz_stl.py``).

Mutations of real STL files (the same mutators as the long run: bit flips, truncation, header edits, ASCII token
edits, special coordinates, facet edits, random bytes) and free-form byte strings must either load and slice to a
well-formed result or raise a :class:`gpuslice.errors.GpusliceError` subclass with a one-line message naming the
file; an ``.npz`` written from the result must be complete, and nothing else may be left in the folder.
"""

from __future__ import annotations

import random
import sys
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import gpuslice  # noqa: E402
from gpuslice.errors import GpusliceError  # noqa: E402
from gpuslice.io.meshfile import read_stl_bytes  # noqa: E402
from gpuslice.slicing.result import SliceResult  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))
import fuzz_stl  # noqa: E402

SEEDS = [(p.name, p.read_bytes()) for p in fuzz_stl.seed_files() if p.stat().st_size <= 60_000] \
    if fuzz_stl.MESHES.is_dir() else []
needs_seeds = pytest.mark.skipif(not SEEDS, reason="../shared/meshes not found: no real STL files to mutate")
FUZZ = settings(max_examples=150, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def _slice_or_error(path: Path, out: Path) -> str:
    """Load, slice (numpy backend) and save; returns 'ok' or the error class name. Any other exception fails."""
    try:
        mesh = gpuslice.load_mesh(path, fit=40.0)
        res = gpuslice.slice_mesh(mesh, thickness=0.2, backend="numpy")
    except GpusliceError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg and msg.startswith(f"{path}: "), msg
        assert not out.exists()
        return type(exc).__name__
    assert np.all(np.isfinite(res.points)) and np.all(np.isfinite(res.area))
    assert res.layer_offsets[-1] == res.n_loops and res.loop_offsets[-1] == res.points.shape[0]
    res.save(out)
    back = SliceResult.load(out)
    np.testing.assert_array_equal(back.points, res.points)
    return "ok"


@needs_seeds
@FUZZ
@given(seed=st.sampled_from(range(len(SEEDS)) if SEEDS else [0]), rnd=st.randoms(use_true_random=False))
def test_mutated_real_files_raise_only_project_errors(tmp_path_factory, seed, rnd):
    folder = tmp_path_factory.mktemp("fuzz")
    seed_name, seed_bytes = SEEDS[seed]
    _, _, data, _ = fuzz_stl.make_case(random.Random(rnd.getrandbits(64)), [(Path(seed_name), seed_bytes)])
    path = folder / "case.stl"
    path.write_bytes(data)
    _slice_or_error(path, folder / "out.npz")
    assert sorted(p.name for p in folder.iterdir()) in (["case.stl"], ["case.stl", "out.npz"])


@FUZZ
@given(data=st.binary(max_size=2_000))
def test_arbitrary_bytes_raise_only_mesh_errors(data):
    try:
        read_stl_bytes(data, "x.stl")
    except GpusliceError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("x.stl: ")


_NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32).map(lambda v: repr(float(v)).encode()),
    st.sampled_from([b"1e39", b"-3.4e38", b"weird", b"", b"1.5.5", b"0x1p3", b"--1", b"1e18", b"3.4028235e38"]),
)


@FUZZ
@given(facets=st.lists(st.lists(st.tuples(_NUMBER, _NUMBER, _NUMBER), min_size=0, max_size=4), max_size=6),
       keyword_junk=st.sampled_from([b"", b"vertex", b"endloop", b"facet normal", b"solid", b"\x00"]),
       where=st.integers(min_value=0, max_value=400))
def test_ascii_token_soup_raises_only_mesh_errors(tmp_path_factory, facets, keyword_junk, where):
    """ASCII STL built from random numbers (NaN, inf, ±3.4e38, junk) and 0-4 vertices per facet, plus a keyword
    dropped in anywhere."""
    body = b"".join(
        b"facet normal 0 0 1\n outer loop\n" + b"".join(b"  vertex %s %s %s\n" % v for v in f) + b" endloop\nendfacet\n"
        for f in facets
    )
    text = b"solid fuzz\n" + body + b"endsolid fuzz\n"
    text = text[:where] + keyword_junk + text[where:]
    folder = tmp_path_factory.mktemp("ascii")
    path = folder / "case.stl"
    path.write_bytes(text)
    _slice_or_error(path, folder / "out.npz")
