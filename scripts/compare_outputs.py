"""Prove that a refactor changed no output: run the gpuslice CLI of two git revisions on every test mesh and
compare what they write, byte for byte.

    python scripts/compare_outputs.py                    # A = 8c0d960, B = this working tree, all meshes
    python scripts/compare_outputs.py --a 8c0d960 --b 8c0d960 --jobs 2 --log /tmp/self.log   # self-check
    python scripts/compare_outputs.py --quick --only cow --only benchy --keep

Revision A (and B when ``--b REV`` is given) is checked out with ``git worktree add --detach`` in a temp folder,
removed at the end. Each side runs ``python -c "...; from gpuslice.cli import main; ..." ARGS`` with
``PYTHONPATH=<tree>``. The package is installed in editable mode, and its editable finder maps
``gpuslice.kernels`` to ``<main checkout>/kernels``: a worktree gets a symlink ``gpuslice/kernels -> ../kernels``
so that its own kernels are used (the sanity check prints where each side imports from).

Per mesh of ``<meshes>/catalog.csv`` (``--meshes``, default ``<repo>/../shared/meshes``), with
``SOURCE_DATE_EPOCH=1700000000``: ``slice`` to .npz (+ JSON report), .svg and .cli; ``raster`` to .sl1 and a PNG
stack; ``view``; for the first few meshes also ``raster --gamma 0`` and ``view --raster``. Plus one ``batch`` of
three meshes to npz and to sl1 (``--only batch`` selects it when ``--only`` is used). A mesh both sides refuse
(same exit code, same first stderr line) counts as "refused by both". Exit status 1 when anything differs.
PNGs are compared byte for byte; a DIFF says when the pixels are identical anyway (the isal deflater does not always
pick the same LZ77 matches twice), and ``--png-pixels`` lets such PNGs pass (counted in a note); ``--no-isal`` hides
ISA-L on both sides, so both deflate with zlib and PNG bytes can be compared strictly.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import zipfile
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
EPOCH = "1700000000"
STAMP = dt.datetime.fromtimestamp(int(EPOCH), dt.timezone.utc).strftime("%Y-%m-%d at %H:%M:%S UTC")
ENTRY = "import sys; sys.argv[0] = 'gpuslice'; from gpuslice.cli import main; sys.exit(main())"
SANITY = ("import gpuslice, gpuslice.cli; from importlib import resources; "
          "print(gpuslice.__file__); print(gpuslice.cli.__file__); print(resources.files('gpuslice.kernels'))")
EXTRA = 4  # meshes (the first ones) that also get raster --gamma 0 and view --raster
QUICK = 6  # --quick: only the first meshes
BATCH_MESHES = ("xyz_cube_20mm", "cow", "prusa_bridge")
SLICE, RASTER = ["--fit", "60", "-t", "0.1"], ["--fit", "40", "-t", "0.1"]


def git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], check=True, capture_output=True, text=True).stdout.strip()


class Side:
    """One revision's source tree (a temp worktree, or the working tree itself for rev None)."""

    def __init__(self, label: str, rev: str | None, base: Path) -> None:
        self.label, self.rev, self.worktree = label, rev, None
        if rev is None:
            self.tree = ROOT
        else:
            sha = git("rev-parse", "--verify", f"{rev}^{{commit}}")
            self.tree = self.worktree = base / f"tree-{label}"
            git("worktree", "add", "--detach", str(self.tree), sha)
            self.rev = f"{rev} ({sha[:10]})"
            kernels, link = self.tree / "kernels", self.tree / "gpuslice" / "kernels"
            if kernels.is_dir() and not link.exists():  # else the editable finder serves the main checkout's
                link.symlink_to("../kernels")
        self.env = {**os.environ, "PYTHONPATH": str(self.tree), "SOURCE_DATE_EPOCH": EPOCH}

    def sanity(self, cwd: Path) -> str:
        out = subprocess.run([sys.executable, "-c", SANITY], cwd=cwd, env=self.env, capture_output=True, text=True)
        paths = out.stdout.split()
        if out.returncode or len(paths) != 3:
            raise SystemExit(f"{self.label}: cannot import gpuslice from {self.tree}:\n{out.stderr}")
        for p in paths:
            if not Path(os.path.realpath(p)).is_relative_to(self.tree.resolve()):
                raise SystemExit(f"{self.label}: {p} is not under {self.tree} (editable install shadowing it?)")
        return f"{self.label} = {self.rev or 'working tree'}: gpuslice {paths[0]}, cli {paths[1]}, kernels {paths[2]}"

    def run(self, args: list[str], cwd: Path) -> tuple[int, str, float]:
        """Exit code, first non-empty stderr line (temp paths masked), seconds."""
        cwd.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        try:
            p = subprocess.run([sys.executable, "-c", ENTRY, *args], cwd=cwd, env=self.env, capture_output=True,
                               text=True, timeout=3600)
            rc, err = p.returncode, p.stderr
        except subprocess.TimeoutExpired:
            rc, err = -9, "timed out after 3600 s"
        first = next((ln for ln in err.splitlines() if ln.strip()), "")
        for path in (str(cwd), str(self.tree)):
            first = first.replace(path, "<dir>")
        return rc, first, time.perf_counter() - t0


# ---- comparisons: each returns None when equal, else a short detail; ``notes`` collects what was let pass ------
PIXELS_ONLY = [False]  # --png-pixels: a PNG whose bytes differ but whose pixels do not counts as the same


def first_diff(a: bytes, b: bytes) -> str:
    i = next((k for k, (x, y) in enumerate(zip(a, b, strict=False)) if x != y), min(len(a), len(b)))
    line = f" (line {a[:i].count(10) + 1})" if 0 not in a[:i] else ""
    return f"{len(a)} vs {len(b)} bytes, first difference at byte {i}{line}"


def png_chunks(data: bytes) -> tuple[bytes, bytes]:
    """(the signature and every chunk but IDAT, the IDAT stream still deflated) of a PNG file."""
    i, head, idat = 8, [data[:8]], []
    while i + 8 <= len(data):
        n, kind = int.from_bytes(data[i : i + 4], "big"), data[i + 4 : i + 8]
        if kind == b"IDAT":
            idat.append(data[i + 8 : i + 8 + n])
        else:
            head.append(kind + data[i + 8 : i + 8 + n])
        i += 12 + n
    return b"".join(head), b"".join(idat)


def png_pixels(data: bytes) -> bytes:
    """Every chunk but IDAT, then the inflated IDAT stream: what a PNG shows, whatever the deflater chose (raw
    bytes when it cannot be inflated)."""
    head, idat = png_chunks(data)
    try:
        return head + zlib.decompress(idat)
    except zlib.error:
        return data


def first_of(diffs: list[str], what: str) -> str | None:
    return f"{diffs[0]} (+{len(diffs) - 1} more {what})" if len(diffs) > 1 else (diffs[0] if diffs else None)


def cmp_blob(name: str, x: bytes, y: bytes, notes: list[str]) -> str | None:
    if x == y:
        return None
    if name.endswith(".png") and png_pixels(x) == png_pixels(y):
        if PIXELS_ONLY[0]:
            notes.append("PNG bytes differ, pixels identical")
            return None
        return f"{len(x)} vs {len(y)} bytes, pixels identical (deflate chose other LZ77 matches)"
    return first_diff(x, y)


def json_path_diff(a, b, path: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                return f"{path}/{k} only in {'B' if k not in a else 'A'}"
            if (d := json_path_diff(a[k], b[k], f"{path}/{k}")) is not None:
                return d
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path}: {len(a)} vs {len(b)} items"
        pairs = enumerate(zip(a, b, strict=True))
        return next((d for i, (x, y) in pairs if (d := json_path_diff(x, y, f"{path}[{i}]"))), None)
    same = json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)  # NaN == NaN here
    return None if same else f"{path or '/'}: {str(a)[:40]!r} vs {str(b)[:40]!r}"


def scrub(x):
    """The report less what legitimately differs between runs:
    - ``timings_s`` (and any ``timings*`` key, at any depth): wall-clock seconds of each stage, never equal twice;
    - ``device`` when a string: the OpenCL device's name (an environment fact, not an output; ``params.device``
      is the ``--device`` option echoed, None here, and is kept).
    Kept: ``file`` (the mesh path, the same absolute path on both sides) and every count, area, z and parameter."""
    if isinstance(x, dict):
        return {k: scrub(v) for k, v in x.items()
                if not k.startswith("timings") and not (k == "device" and isinstance(v, str))}
    return [scrub(v) for v in x] if isinstance(x, list) else x


def cmp_json(a: Path, b: Path, notes: list[str]) -> str | None:
    return json_path_diff(scrub(json.loads(a.read_text())), scrub(json.loads(b.read_text())))


def cmp_npz(a: Path, b: Path, notes: list[str]) -> str | None:
    if a.read_bytes() == b.read_bytes():
        return None
    with np.load(a, allow_pickle=False) as za, np.load(b, allow_pickle=False) as zb:
        if za.files != zb.files:
            return f"arrays differ: A {za.files} vs B {zb.files}"
        for k in za.files:
            x, y = za[k], zb[k]
            if k == "meta_json":
                d = json_path_diff(json.loads(bytes(x)), json.loads(bytes(y)))
                if d:
                    return f"meta: {d}"
            elif x.dtype != y.dtype or x.shape != y.shape:
                return f"array {k}: {x.dtype}{x.shape} vs {y.dtype}{y.shape}"
            elif x.tobytes() != y.tobytes():
                n = int(np.count_nonzero(x.reshape(-1).view(np.uint8) != y.reshape(-1).view(np.uint8)))
                return f"array {k} ({x.dtype}{x.shape}): {n} bytes differ"
    return "arrays and meta equal, zip container bytes differ"


def cmp_bytes(a: Path, b: Path, notes: list[str]) -> str | None:
    return cmp_blob(a.name, a.read_bytes(), b.read_bytes(), notes)


def cmp_dir(a: Path, b: Path, notes: list[str]) -> str | None:
    fa, fb = (sorted(str(p.relative_to(d)) for p in d.rglob("*") if p.is_file()) for d in (a, b))
    if fa != fb:
        return f"file lists differ: only A {sorted(set(fa) - set(fb))[:3]}, only B {sorted(set(fb) - set(fa))[:3]}"
    return first_of([f"{n}: {d}" for n in fa if (d := compare_file(a / n, b / n, notes))], "files")


def cmp_sl1(a: Path, b: Path, notes: list[str]) -> str | None:
    """Members byte for byte, in order; config.ini's creation date and the zip member dates are let pass (noted:
    ``gpuslice raster`` may date the archive now whatever SOURCE_DATE_EPOCH says)."""
    with zipfile.ZipFile(a) as za, zipfile.ZipFile(b) as zb:
        now = [s for s, z in (("A", za), ("B", zb)) if f"= {STAMP}" not in z.read("config.ini").decode()]
        if now:
            notes.append(f"{' and '.join(now)} wrote the current time")
        if za.namelist() != zb.namelist():
            return f"members differ: {len(za.namelist())} vs {len(zb.namelist())}"
        diffs = []
        for ia, ib in zip(za.infolist(), zb.infolist(), strict=True):
            x, y = za.read(ia), zb.read(ib)
            if ia.filename == "config.ini":
                x, y = (re.sub(rb"(?m)^fileCreationTimestamp = .*$", b"", v) for v in (x, y))
            if d := cmp_blob(ia.filename, x, y, notes):
                diffs.append(f"member {ia.filename}: {d}")
            elif ia.compress_type != ib.compress_type or ia.external_attr != ib.external_attr:
                diffs.append(f"member {ia.filename}: zip attributes differ")
            if ia.date_time != ib.date_time and "zip member dates differ" not in notes:
                notes.append("zip member dates differ")
    return first_of(diffs, "members")


def compare_file(a: Path, b: Path, notes: list[str]) -> str | None:
    if a.is_dir() or b.is_dir():
        return cmp_dir(a, b, notes) if a.is_dir() and b.is_dir() else "a folder on one side only"
    return {".json": cmp_json, ".npz": cmp_npz, ".sl1": cmp_sl1}.get(a.suffix, cmp_bytes)(a, b, notes)


# ---- the runs ------------------------------------------------------------------------------------------------
def mesh_runs(mesh: Path, extra: bool) -> list[tuple[list[str], list[str]]]:
    """(CLI arguments, outputs to compare) of every run for one mesh; outputs are relative to the run folder."""
    m = str(mesh)
    runs = [(["slice", m, *SLICE, "-o", "out.npz", "--report", "rep.json", "-q"], ["out.npz", "rep.json"]),
            (["slice", m, *SLICE, "-o", "out.svg", "-q"], ["out.svg"]),
            (["slice", m, *SLICE, "-o", "out.cli", "-q"], ["out.cli"])]
    for g in ("1", "0") if extra else ("1",):
        runs += [(["raster", m, *RASTER, "-o", f"g{g}.sl1", "-q", "--gamma", g], [f"g{g}.sl1"]),
                 (["raster", m, *RASTER, "-o", f"stack-g{g}/", "-q", "--gamma", g], [f"stack-g{g}"])]
    runs.append((["view", m, "--fit", "60", "-t", "0.2", "-o", "page.html", "-q"], ["page.html"]))
    if extra:
        runs.append((["view", m, "--fit", "60", "-t", "0.2", "-o", "page-raster.html", "-q", "--raster"],
                     ["page-raster.html"]))
    return runs


class Compare:
    def __init__(self, a: Side, b: Side, work: Path, keep: bool, log) -> None:
        self.a, self.b, self.work, self.keep, self.log = a, b, work, keep, log
        self.lock = threading.Lock()
        self.counts = {"same": 0, "diff": 0, "refused": 0}
        self.notes: dict[str, list[str]] = {}  # note -> the outputs it was let pass in

    def emit(self, text: str, to_stdout: bool = True) -> None:
        with self.lock:
            if to_stdout:
                print(text, flush=True)
            if self.log:
                self.log.write(text + "\n")
                self.log.flush()

    def case(self, name: str, runs: list[tuple[list[str], list[str]]]) -> None:
        t0, lines = time.perf_counter(), []
        for args, outputs in runs:
            ra, rb = (s.run(args, self.work / name / s.label) for s in (self.a, self.b))
            self.emit(f"  {name} {args[0]} {' '.join(args[2:])}: A rc={ra[0]} {ra[2]:.1f} s, B rc={rb[0]} "
                      f"{rb[2]:.1f} s {ra[1]!r}", to_stdout=False)
            for out in outputs:
                label = f"{args[0]}:{out.rstrip('/')}"
                if ra[0] or rb[0]:
                    same = ra[:2] == rb[:2]
                    kind, text = ("refused", f"both refuse (rc {ra[0]}: {ra[1]})") if same else \
                        ("diff", f"DIFF: A rc {ra[0]} {ra[1]!r}, B rc {rb[0]} {rb[1]!r}")
                else:
                    pa, pb = (self.work / name / s.label / out for s in (self.a, self.b))
                    missing, notes = [s for s, p in (("A", pa), ("B", pb)) if not p.exists()], []
                    try:
                        d = f"missing in {' and '.join(missing)}" if missing else compare_file(pa, pb, notes)
                    except Exception as exc:  # an unreadable output is a difference, not the end of the run
                        d = f"cannot compare: {type(exc).__name__}: {exc}"
                    note = "; ".join(n + (f" ({notes.count(n)}x)" if notes.count(n) > 1 else "")
                                     for n in dict.fromkeys(notes))
                    for n in dict.fromkeys(notes) if d is None else ():
                        with self.lock:
                            self.notes.setdefault(n, []).append(f"{name} {label}")
                    kind, text = ("diff", f"DIFF: {d}") if d else ("same", f"same ({note})" if notes else "same")
                with self.lock:
                    self.counts[kind] += 1
                lines.append(f"{name:<26} {label:<26} {text}")
        self.emit("\n".join(lines) + f"\n{'':<26} ({time.perf_counter() - t0:.1f} s)")
        if not self.keep:
            shutil.rmtree(self.work / name, ignore_errors=True)


def load_catalog(folder: Path) -> list[tuple[str, Path]]:
    meshes = []
    with open(folder / "catalog.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            path = folder / row["file"]
            if not path.is_file():
                print(f"warning: {path} listed in catalog.csv is missing", file=sys.stderr)
                continue
            if row.get("sha256") and hashlib.sha256(path.read_bytes()).hexdigest() != row["sha256"]:
                print(f"warning: {path} does not match its catalog sha256", file=sys.stderr)
            meshes.append((row["name"], path))
    return meshes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", default="8c0d960", help="revision A (default: 8c0d960)")
    ap.add_argument("--b", default=None, help="revision B (default: the working tree)")
    ap.add_argument("--meshes", type=Path, default=ROOT.parent / "shared" / "meshes", help="folder with catalog.csv")
    ap.add_argument("--only", action="append", default=[], help="mesh name (repeatable); 'batch' for the batch")
    ap.add_argument("--quick", action="store_true", help=f"only the first {QUICK} meshes")
    ap.add_argument("--jobs", type=int, default=1, help="meshes run in parallel")
    ap.add_argument("--keep", action="store_true", help="keep the run folders")
    ap.add_argument("--png-pixels", action="store_true", help="PNGs whose pixels match count as same")
    ap.add_argument("--no-isal", action="store_true",
                    help="hide ISA-L on both sides (PNGs deflated by zlib, whose bytes are deterministic)")
    ap.add_argument("--log", type=Path, help="also write every line and each command's exit code and time here")
    opt = ap.parse_args()

    PIXELS_ONLY[0] = opt.png_pixels
    meshes = catalog = load_catalog(opt.meshes.resolve())
    if opt.only:
        unknown = set(opt.only) - {n for n, _ in meshes} - {"batch"}
        if unknown:
            ap.error(f"unknown mesh names: {', '.join(sorted(unknown))}")
        meshes = [(n, p) for n, p in meshes if n in opt.only]
    if opt.quick:
        meshes = meshes[:QUICK]
    base = Path(tempfile.mkdtemp(prefix="compare_outputs-"))
    log = open(opt.log, "w") if opt.log else None
    sides: list[Side] = []
    t0 = time.perf_counter()
    try:
        for label, rev in (("A", opt.a), ("B", opt.b)):
            sides.append(Side(label, rev, base))
        if opt.no_isal:  # a package named isal that fails to import, ahead of the real one on both sides
            (base / "no-isal" / "isal").mkdir(parents=True)
            (base / "no-isal" / "isal" / "__init__.py").write_text("raise ImportError('hidden by --no-isal')\n")
            for s in sides:
                s.env["PYTHONPATH"] = f"{base / 'no-isal'}{os.pathsep}{s.env['PYTHONPATH']}"
        cmp = Compare(*sides, base / "runs", opt.keep, log)
        for s in sides:
            cmp.emit(s.sanity(base))
        cases = [(n, mesh_runs(p, i < EXTRA)) for i, (n, p) in enumerate(meshes)]
        if not opt.only or "batch" in opt.only:
            src = base / "batch-in"
            src.mkdir()
            by_name = dict(catalog)
            for n in [n for n in BATCH_MESHES if n in by_name] or list(by_name)[:3]:
                shutil.copy(by_name[n], src / by_name[n].name)
            common = ["-t", "0.2", "--fit", "60", "-q"]  # -q: batch's progress bar and table are not compared
            cases.append(("batch", [(["batch", str(src), "-o", "npz", *common, "--format", "npz"], ["npz"]),
                                    (["batch", str(src), "-o", "sl1", *common, "--raster", "sl1"], ["sl1"])]))
        with ThreadPoolExecutor(max(1, opt.jobs)) as pool:
            for f in [pool.submit(cmp.case, n, r) for n, r in cases]:
                f.result()
        for note, where in cmp.notes.items():
            more = " ..." if len(where) > 3 else ""
            cmp.emit(f"note: {note}, let pass in {len(where)} outputs: {', '.join(where[:3])}{more}")
        c = cmp.counts
        cmp.emit(f"elapsed {time.perf_counter() - t0:.0f} s; run folders: {base / 'runs' if opt.keep else 'removed'}")
        cmp.emit(f"{sum(c.values())} compared, {c['same']} identical, {c['diff']} differ, "
                 f"{c['refused']} refused by both")
        return 1 if c["diff"] else 0
    finally:
        for s in sides:
            if s.worktree is not None:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(s.worktree)])
        if not opt.keep:
            shutil.rmtree(base, ignore_errors=True)
        if log:
            log.close()


if __name__ == "__main__":
    sys.exit(main())
