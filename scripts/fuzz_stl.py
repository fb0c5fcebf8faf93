"""Fuzz the STL reader and the whole slicing pipeline with mutated real STL files (issue 5, part 5).

Every case is one mutation of a real STL file of ``../shared/meshes`` (binary copies and the ASCII originals under
``raw/``): bit flips, truncation, header edits (text, facet count), ASCII token edits (a number, a keyword or a
line replaced, deleted or duplicated), special coordinates written into binary records (NaN, ±inf, ±3.4e38, 1e30,
denormals), facet edits that keep a valid file but break the mesh (facets deleted, duplicated, reversed, collapsed,
moved; all coordinates scaled by 1e-30..1e30), random bytes spliced in, and files of random bytes. Each case is

1. run through the library API in this process: ``gpuslice.load_mesh(path, fit=40)`` and ``slice_mesh(mesh,
   thickness=0.2)`` (alternately on the numpy and the OpenCL backend), ``defects.mesh_repairs(mesh)``, then
   ``export`` to ``.npz`` and read back.
   Passing: it completes, or raises a :class:`gpuslice.errors.GpusliceError` subclass with a one-line message;
   any other exception, or a case running past ``--timeout`` seconds (SIGALRM), is a failure;
2. for a sample (``--cli-cases``), also run as ``gpuslice slice FILE --fit 40 -t 0.2 -o out.npz`` in a subprocess
   with a ``--timeout`` (60 s) cap. Passing: exit 0 with a complete ``out.npz`` (``SliceResult.load`` reads it and
   its offsets are consistent), or exit 2 with exactly one stderr line ``gpuslice: error: ...`` and neither
   ``out.npz`` nor a temporary file left in the folder; never a traceback, another exit code, or a timeout.

Cases are generated from ``--seed`` (reproducible); failing inputs are kept under ``--keep`` with a JSON line each.
The summary (cases, outcomes by error class, timings, failures) is printed and written as JSON (``--json``).

    python scripts/fuzz_stl.py --cases 10000 --cli-cases 1000 --json fuzz.json      # the long run (~30 min, 2 cores)
    python scripts/fuzz_stl.py --cases 200 --cli-cases 20                           # a quick look
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"
#: seeds: binary copies up to this size, ASCII originals (raw/) up to RAW_MAX_BYTES
SEED_MAX_BYTES = 200_000
RAW_MAX_BYTES = 700_000
SPECIAL_FLOATS = [float("nan"), float("inf"), -float("inf"), 3.4028235e38, -3.4028235e38, 1e30, -1e19, 1e-45, 0.0,
                  -0.0, 1e18, 2.5e17]
ASCII_TOKENS = [b"nan", b"inf", b"-inf", b"3.4e38", b"-3.4028235e38", b"1e39", b"1e-39", b"weirdvalue", b"", b"0x10",
                b"1,5", b"vertex", b"facet", b"endloop", b"endfacet", b"endsolid", b"solid", b"outer", b"\x00", b"\xff",
                b"1e18", b"-0", b"+.5", b"1.5.5", b"9" * 400]


#: the installed command (beside this Python, else on PATH)
GPUSLICE = str(Path(sys.executable).with_name("gpuslice")) if Path(sys.executable).with_name("gpuslice").is_file() \
    else (shutil.which("gpuslice") or "gpuslice")


class CaseTimeout(Exception):
    """A library case ran past its time cap."""


def seed_files() -> list[Path]:
    """The real STL files mutated: small binary copies and the ASCII originals."""
    out = [p for p in sorted(MESHES.glob("*.stl")) if p.stat().st_size <= SEED_MAX_BYTES]
    out += [p for p in sorted((MESHES / "raw").glob("*.stl")) if p.stat().st_size <= RAW_MAX_BYTES]
    return out


# ---- mutations ------------------------------------------------------------------------------------------------


def _bitflip(rng: random.Random, data: bytearray) -> str:
    n = rng.choice([1, 1, 2, 4, 16, 64])
    for _ in range(n):
        if data:
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
    return f"bitflip x{n}"


def _truncate(rng: random.Random, data: bytearray) -> str:
    cut = rng.choice([rng.randrange(len(data) + 1), rng.randrange(min(len(data), 100) + 1), len(data) - 1,
                      len(data) - rng.randrange(1, 60)])
    cut = max(0, min(len(data), cut))
    del data[cut:]
    return f"truncate to {cut}"


def _header(rng: random.Random, data: bytearray) -> str:
    if len(data) < 84:
        data.extend(b"\0" * (84 - len(data)))
    kind = rng.randrange(6)
    count = struct.unpack_from("<I", data, 80)[0]
    if kind == 0:
        data[0:80] = bytes(rng.randrange(256) for _ in range(80))
        return "random header text"
    if kind == 1:
        data[0:80] = b"solid " + bytes(rng.randrange(32, 127) for _ in range(74))
        return "header 'solid ...'"
    new = [0, 1, count + 1, max(count - 1, 0), 0xFFFFFFFF, 0x7FFFFFFF, rng.randrange(1 << 32), count * 2][
        rng.randrange(8)
    ]
    new &= 0xFFFFFFFF
    struct.pack_into("<I", data, 80, new)
    return f"facet count {count} -> {new}"


def _coordinate(rng: random.Random, data: bytearray) -> str:
    n = (len(data) - 84) // 50
    if n <= 0:
        return _bitflip(rng, data)
    value = rng.choice(SPECIAL_FLOATS)
    k = rng.randrange(1, 4)
    for _ in range(k):
        rec = rng.randrange(n)
        struct.pack_into("<f", data, 84 + 50 * rec + 12 + 4 * rng.randrange(9), value)
    return f"{k} coordinate(s) = {value!r}"


def _facets(rng: random.Random, data: bytearray) -> str:
    """Valid binary STL, broken mesh: facets deleted, duplicated, reversed, collapsed or moved (count kept right)."""
    n = (len(data) - 84) // 50
    if n <= 0 or len(data) != 84 + 50 * n:
        return _bitflip(rng, data)
    rec = np.frombuffer(bytes(data[84:]), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]).copy()
    kind = rng.randrange(6)
    pick = np.array(sorted(rng.sample(range(n), min(n, rng.choice([1, 2, 5, 20])))))
    if kind == 0:
        rec = np.delete(rec, pick)
        what = f"{pick.size} facets deleted"
    elif kind == 1:
        rec = np.concatenate([rec, rec[pick]])
        what = f"{pick.size} facets duplicated"
    elif kind == 2:
        rec["v"][pick] = rec["v"][pick][:, ::-1]
        what = f"{pick.size} facets reversed"
    elif kind == 3:
        rec["v"][pick, 1] = rec["v"][pick, 0]
        what = f"{pick.size} facets collapsed"
    elif kind == 4:
        with np.errstate(over="ignore"):
            rec["v"][pick] += np.float32(rng.uniform(-1, 1)) * np.abs(rec["v"]).max()
        what = f"{pick.size} facets moved"
    else:
        with np.errstate(over="ignore", under="ignore"):
            rec["v"] *= np.float32(10.0 ** rng.uniform(-30, 30))
        what = "all coordinates scaled"
    data[84:] = rec.tobytes()
    struct.pack_into("<I", data, 80, len(rec))
    return what


def _ascii_token(rng: random.Random, data: bytearray) -> str:
    text = bytes(data)
    lines = text.splitlines(keepends=True)
    if not lines:
        return _bitflip(rng, data)
    kind = rng.randrange(5)
    i = rng.randrange(len(lines))
    if kind == 0:  # replace one token of a line
        toks = lines[i].split()
        if toks:
            j = rng.randrange(len(toks))
            toks[j] = rng.choice(ASCII_TOKENS)
            lines[i] = b" ".join(toks) + b"\n"
        what = "token replaced"
    elif kind == 1:
        del lines[i]
        what = "line deleted"
    elif kind == 2:
        lines.insert(i, lines[rng.randrange(len(lines))])
        what = "line duplicated"
    elif kind == 3:  # a number replaced everywhere on a line
        lines[i] = b" ".join(rng.choice(ASCII_TOKENS[:8]) if t[:1].isdigit() or t[:1] in b"-+." else t
                             for t in lines[i].split()) + b"\n"
        what = "numbers of a line replaced"
    else:
        lines.insert(i, bytes(rng.randrange(32, 127) for _ in range(rng.randrange(1, 40))) + b"\n")
        what = "garbage line inserted"
    data[:] = b"".join(lines)
    return f"ASCII {what} at line {i + 1}"


def _splice(rng: random.Random, data: bytearray) -> str:
    i = rng.randrange(len(data) + 1)
    n = rng.randrange(1, 200)
    data[i:i] = bytes(rng.randrange(256) for _ in range(n))
    return f"{n} random bytes inserted at {i}"


def _random_file(rng: random.Random, data: bytearray) -> str:
    n = rng.choice([0, 1, 10, 83, 84, 85, 134, 500, 5000])
    head = rng.choice([b"", b"solid", b"solid x\n", b"\0" * 80])
    data[:] = head + bytes(rng.randrange(256) for _ in range(n))
    return f"random file of {len(data)} bytes"


MUTATIONS = {
    "bitflip": _bitflip,
    "truncate": _truncate,
    "header": _header,
    "coordinate": _coordinate,
    "ascii_token": _ascii_token,
    "splice": _splice,
    "facets": _facets,
    "random": _random_file,
}


def make_case(rng: random.Random, seeds: list[tuple[Path, bytes]]) -> tuple[str, str, bytes, list[str]]:
    """(seed name, mutation description, mutated bytes, mutation kinds)."""
    path, original = rng.choice(seeds)
    data = bytearray(original)
    is_ascii = original.lstrip()[:5].lower() == b"solid" and b"\0" not in original[:200]
    kinds = ["bitflip", "truncate", "header", "splice", "random"]
    kinds += ["ascii_token"] * 3 if is_ascii else ["coordinate", "facets", "facets", "header"]
    chosen = [rng.choice(kinds) for _ in range(rng.choice([1, 1, 1, 2, 3]))]
    steps = [MUTATIONS[k](rng, data) for k in chosen]
    return path.name, "; ".join(steps), bytes(data), chosen


# ---- running a case -------------------------------------------------------------------------------------------


def _check_result(res) -> None:
    """Structural checks of a SliceResult (raises AssertionError)."""
    assert res.layer_offsets[-1] == res.loop_offsets.size - 1
    assert res.loop_offsets[-1] == res.points.shape[0]
    assert np.all(np.diff(res.loop_offsets) >= 0) and np.all(np.diff(res.layer_offsets) >= 0)
    assert np.all(np.isfinite(res.points)), "non-finite points"
    assert np.all(np.isfinite(res.area)), "non-finite area"


def run_library(path: Path, backend: str, timeout: float, out_dir: Path) -> tuple[str, str]:
    """(outcome, detail): outcome 'ok', an error class name, or 'FAIL:...'."""
    import gpuslice
    from gpuslice.errors import GpusliceError
    from gpuslice.formats import export
    from gpuslice.mesh.defects import mesh_repairs
    from gpuslice.slicing.result import SliceResult

    def alarm(signum, frame):
        raise CaseTimeout

    old = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, timeout)
    out = out_dir / "lib.npz"
    try:
        mesh = gpuslice.load_mesh(path, fit=40.0)
        res = gpuslice.slice_mesh(mesh, thickness=0.2, backend=backend)
        _check_result(res)
        mesh_repairs(mesh)  # what `gpuslice slice` reports: must not fail either
        export(res, out)
        _check_result(SliceResult.load(out))
        return "ok", f"{res.n_layers} layers, {res.n_loops} loops"
    except GpusliceError as exc:
        msg = str(exc)
        if "\n" in msg or not msg:
            return "FAIL:multi-line message", msg
        return type(exc).__name__, msg
    except CaseTimeout:
        return "FAIL:timeout", f"> {timeout} s"
    except Exception as exc:  # noqa: BLE001 - the point of the fuzzer
        return f"FAIL:{type(exc).__name__}", " ".join(str(exc).split())[:300]
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
        out.unlink(missing_ok=True)


def run_cli(data: bytes, timeout: float) -> tuple[str, str, float]:
    """Run ``gpuslice slice`` on ``data`` in a fresh folder: (outcome, detail, seconds)."""
    from gpuslice.slicing.result import SliceResult

    with tempfile.TemporaryDirectory(prefix="fuzz-cli-") as tmp:
        folder = Path(tmp)
        model = folder / "case.stl"
        model.write_bytes(data)
        out = folder / "out.npz"
        cmd = [GPUSLICE, "slice", str(model), "--fit", "40", "-t", "0.2", "-o", str(out)]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, errors="replace")
        except subprocess.TimeoutExpired:
            return "FAIL:timeout", f"> {timeout} s", time.perf_counter() - t0
        wall = time.perf_counter() - t0
        leftovers = sorted(p.name for p in folder.iterdir() if p.name not in ("case.stl", "out.npz"))
        err = proc.stderr.strip()
        if "Traceback" in proc.stderr:
            return "FAIL:traceback", err[-300:], wall
        if leftovers:
            return "FAIL:temporary file left", ", ".join(leftovers), wall
        if proc.returncode == 0:
            if not out.is_file():
                return "FAIL:exit 0 without output", err, wall
            try:
                _check_result(SliceResult.load(out))
            except Exception as exc:  # noqa: BLE001
                return "FAIL:incomplete output", f"{type(exc).__name__}: {exc}", wall
            return "ok", "", wall
        if proc.returncode == 2:
            if out.exists():
                return "FAIL:output left after an error", err, wall
            if len(err.splitlines()) != 1 or not err.startswith("gpuslice: error: "):
                return "FAIL:not one error line", err[:300], wall
            return "exit 2", err, wall
        return f"FAIL:exit {proc.returncode}", err[:300], wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=10_000, help="library cases (default 10000)")
    ap.add_argument("--cli-cases", type=int, default=1_000, help="of those, run through the CLI too (default 1000)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--timeout", type=float, default=60.0, help="cap per case, s (default 60)")
    ap.add_argument("--jobs", type=int, default=2, help="CLI subprocesses at once (default 2)")
    ap.add_argument("--keep", type=Path, default=Path("fuzz-failures"), help="folder for failing inputs")
    ap.add_argument("--json", type=Path, default=None, help="write the summary here")
    args = ap.parse_args(argv)

    seeds = [(p, p.read_bytes()) for p in seed_files()]
    if not seeds:
        print(f"no seed files under {MESHES}", file=sys.stderr)
        return 2
    rng = random.Random(args.seed)
    cli_every = max(1, args.cases // max(1, args.cli_cases)) if args.cli_cases else 0
    lib_outcomes: Counter[str] = Counter()
    cli_outcomes: Counter[str] = Counter()
    by_mutation: Counter[str] = Counter()
    failures: list[dict] = []
    lib_times: list[float] = []
    cli_times: list[float] = []
    cli_jobs = []
    args.keep.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    pool = ThreadPoolExecutor(max_workers=max(1, args.jobs))

    def record_failure(kind: str, i: int, seed: str, what: str, data: bytes, outcome: str, detail: str) -> None:
        name = args.keep / f"case{i:05d}-{kind}.stl"
        name.write_bytes(data)
        failures.append({"case": i, "where": kind, "seed": seed, "mutation": what, "outcome": outcome,
                         "detail": detail, "file": str(name)})
        print(f"  FAIL {kind} case {i} ({seed}: {what}): {outcome}: {detail[:200]}", flush=True)

    with tempfile.TemporaryDirectory(prefix="fuzz-lib-") as tmp:
        folder = Path(tmp)
        for i in range(args.cases):
            seed, what, data, kinds = make_case(rng, seeds)
            by_mutation.update(kinds)
            path = folder / "case.stl"
            path.write_bytes(data)
            backend = "opencl" if i % 2 else "numpy"
            t0 = time.perf_counter()
            outcome, detail = run_library(path, backend, args.timeout, folder)
            lib_times.append(time.perf_counter() - t0)
            lib_outcomes[outcome] += 1
            if outcome.startswith("FAIL"):
                record_failure("lib", i, seed, what, data, outcome, detail)
            if cli_every and i % cli_every == 0 and len(cli_jobs) < args.cli_cases:
                cli_jobs.append((i, seed, what, data, pool.submit(run_cli, data, args.timeout)))
            if (i + 1) % 500 == 0:
                print(f"{i + 1} library cases, {time.perf_counter() - t_start:.0f} s: {dict(lib_outcomes)}",
                      flush=True)
    for n, (i, seed, what, data, fut) in enumerate(cli_jobs):
        outcome, detail, wall = fut.result()
        if (n + 1) % 100 == 0:
            print(f"{n + 1} CLI cases, {time.perf_counter() - t_start:.0f} s: {dict(cli_outcomes)}", flush=True)
        cli_times.append(wall)
        cli_outcomes[outcome] += 1
        if outcome.startswith("FAIL"):
            record_failure("cli", i, seed, what, data, outcome, detail)
    pool.shutdown()
    summary = {
        "command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
        "seed": args.seed,
        "seeds": [p.name if p.parent == MESHES else f"raw/{p.name}" for p, _ in seeds],
        "library_cases": args.cases,
        "library_outcomes": dict(lib_outcomes.most_common()),
        "library_case_s": {"median": float(np.median(lib_times)) if lib_times else None,
                           "max": max(lib_times, default=None)},
        "cli_cases": len(cli_jobs),
        "cli_outcomes": dict(cli_outcomes.most_common()),
        "cli_case_s": {"median": float(np.median(cli_times)) if cli_times else None,
                       "max": max(cli_times, default=None)},
        "mutations": dict(by_mutation.most_common()),
        "failures": failures,
        "wall_s": time.perf_counter() - t_start,
    }
    text = json.dumps(summary, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
