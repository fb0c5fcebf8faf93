"""Check issue 18's claim that masks from the runs rasteriser equal main's masks pixel for pixel: run
``gpuslice raster MESH --fit 60 -t T --resolution R --pixel P --gamma G -o DIR/`` (a PNG stack) for revision A
(default 8c0d960, whose default rasteriser is the OpenCL bitmap kernel) and B (default: the working tree, whose
default is the run-length runs) on every mesh of ``<meshes>/catalog.csv``, and compare every layer's decoded
pixels.

    python scripts/compare_masks.py --log /tmp/compare_masks.log             # everything
    python scripts/compare_masks.py --only cow --display 3840x2400 --gamma 0  # one case
    python scripts/compare_masks.py --t12k 0.2 --keep-diffs                   # 12K at 0.2 mm layers
    python scripts/compare_masks.py --a . --a-args=--raster-backend=opencl-bitmap --only cow  # vs bitmap

Reuses ``scripts/compare_outputs.py``'s ``Side`` (a ``git worktree add --detach`` in a temp folder, removed at the
end, ``PYTHONPATH=<tree>``, a ``gpuslice/kernels`` symlink so each side uses its own kernels) and catalog loader.
Per layer: PNG bytes equal, or inflated IDAT streams equal, mean equal pixels; otherwise both PNGs are decoded with
PIL and compared as numpy arrays. A mesh both sides refuse (same exit code, same first stderr line) counts as
"refused by both". For a case with differing pixels, ``--keep-diffs`` keeps both stacks and the log lists the first
differing pixels (layer, row, column, A grey, B grey). Exit status 1 when any pixel differs.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_outputs import ROOT, Side, load_catalog, png_chunks  # noqa: E402

try:  # ISA-L inflates these mostly-blank layers ~3.5x faster than zlib
    from isal.isal_zlib import decompress as inflate
except ImportError:
    from zlib import decompress as inflate

DISPLAYS = {"3840x2400": "0.05", "11520x5120": "0.019"}


def png_pixels(data: bytes) -> tuple[bytes, bytes]:
    """(every chunk but IDAT, the inflated IDAT stream): equal pairs mean equal pixels, whatever the deflater chose
    (both revisions write filter type 0 rows, so equal pixels give equal streams)."""
    head, idat = png_chunks(data)
    return head, inflate(idat)


def decode(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im)


def compare_stacks(a: Path, b: Path, show: int) -> tuple[int, int, int, int, list[str], str | None]:
    """(layers, layers differing, pixels differing, max grey difference, details, structural problem)."""
    fa, fb = (sorted(p.name for p in d.iterdir() if p.suffix == ".png") for d in (a, b))
    if fa != fb:
        return len(fa), 0, 0, 0, [], f"layer files differ: A {len(fa)}, B {len(fb)} " \
                                     f"(only A {sorted(set(fa) - set(fb))[:2]}, only B {sorted(set(fb) - set(fa))[:2]})"
    nl = npx = gmax = 0
    details: list[str] = []
    for name in fa:
        x, y = (a / name).read_bytes(), (b / name).read_bytes()
        if x == y:
            continue
        px, py = png_pixels(x), png_pixels(y)
        same = px == py
        del px, py
        if same:
            continue
        ia, ib = decode(a / name), decode(b / name)
        if ia.shape != ib.shape or ia.dtype != ib.dtype:
            return len(fa), nl, npx, gmax, details, f"{name}: {ia.dtype}{ia.shape} vs {ib.dtype}{ib.shape}"
        d = ia != ib
        n = int(np.count_nonzero(d))
        if not n:
            continue
        nl, npx = nl + 1, npx + n
        diff = np.abs(ia.astype(np.int16) - ib.astype(np.int16))
        gmax = max(gmax, int(diff.max()))
        rows, cols = np.nonzero(d)
        if len(details) < show:
            pts = ", ".join(f"({r},{c}) {ia[r, c]}/{ib[r, c]}" for r, c in zip(rows[:6], cols[:6], strict=True))
            details.append(f"{name}: {n} px, max {int(diff.max())}: {pts}")
    return len(fa), nl, npx, gmax, details, None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", default="8c0d960", help="revision A (default: 8c0d960; '.': the working tree)")
    ap.add_argument("--b", default=None, help="revision B (default: the working tree)")
    ap.add_argument("--meshes", type=Path, default=ROOT.parent / "shared" / "meshes", help="folder with catalog.csv")
    ap.add_argument("--only", action="append", default=[], help="mesh name (repeatable)")
    ap.add_argument("--display", action="append", default=[], choices=list(DISPLAYS), help="display (repeatable)")
    ap.add_argument("--gamma", action="append", default=[], help="gamma (repeatable; default 1 and 0)")
    ap.add_argument("--fit", default="60", help="--fit, mm (default 60)")
    ap.add_argument("-t", dest="t", default="0.05", help="layer thickness at 3840x2400 (default 0.05)")
    ap.add_argument("--t12k", default="0.05", help="layer thickness at 11520x5120 (default 0.05)")
    ap.add_argument("--a-args", default="", help="extra arguments for side A only (e.g. '--raster-backend opencl')")
    ap.add_argument("--b-args", default="", help="extra arguments for side B only")
    ap.add_argument("--keep-diffs", action="store_true", help="keep both stacks of a case whose pixels differ")
    ap.add_argument("--show", type=int, default=5, help="differing layers detailed per case (default 5)")
    ap.add_argument("--log", type=Path, help="also write every line here")
    opt = ap.parse_args()

    meshes = load_catalog(opt.meshes.resolve())
    if opt.only:
        meshes = [(n, p) for n, p in meshes if n in opt.only]
    displays = opt.display or list(DISPLAYS)
    gammas = opt.gamma or ["1", "0"]
    base = Path(tempfile.mkdtemp(prefix="compare_masks-"))
    log = open(opt.log, "w") if opt.log else None

    def emit(text: str) -> None:
        print(text, flush=True)
        if log:
            log.write(text + "\n")
            log.flush()

    sides: list[Side] = []
    t0 = time.perf_counter()
    counts = {"same": 0, "diff": 0, "refused": 0, "error": 0}
    totals = [0, 0, 0]
    kept: list[str] = []
    try:
        for label, rev in (("A", opt.a), ("B", opt.b)):
            sides.append(Side(label, None if rev in (None, ".") else rev, base))
        for s in sides:
            emit(s.sanity(base))
        emit(f"fit {opt.fit} mm; layers {opt.t} mm at 3840x2400, {opt.t12k} mm at 11520x5120; "
             f"A args {opt.a_args!r}, B args {opt.b_args!r}")
        emit(f"{'mesh':<26} {'display':<10} {'g':>1} {'layers':>6} {'ldiff':>5} {'pxdiff':>8} {'max':>3}  "
             f"{'A s':>6} {'B s':>6}  result")
        for name, path in meshes:
            for disp in displays:
                t = opt.t12k if disp == "11520x5120" else opt.t
                for g in gammas:
                    args = ["raster", str(path), "--fit", opt.fit, "-t", t, "--resolution", disp,
                            "--pixel", DISPLAYS[disp], "--gamma", g, "-o", "stack/", "-q"]
                    case = base / "runs" / f"{name}-{disp}-g{g}"
                    res = []
                    for s, extra in ((sides[0], opt.a_args), (sides[1], opt.b_args)):
                        res.append(s.run(args + extra.split(), case / s.label))
                    (ra, ea, sa), (rb, eb, sb) = res
                    head = f"{name:<26} {disp:<10} {g:>1}"
                    tail = f"{sa:6.1f} {sb:6.1f}"
                    if ra or rb:
                        if (ra, ea) == (rb, eb):
                            counts["refused"] += 1
                            emit(f"{head} {'-':>6} {'-':>5} {'-':>8} {'-':>3}  {tail}  refused by both "
                                 f"(rc {ra}: {ea[:70]})")
                        else:
                            counts["error"] += 1
                            emit(f"{head} {'-':>6} {'-':>5} {'-':>8} {'-':>3}  {tail}  EXIT DIFFERS: "
                                 f"A rc {ra} {ea[:60]!r}, B rc {rb} {eb[:60]!r}")
                        shutil.rmtree(case, ignore_errors=True)
                        continue
                    nlay, nl, npx, gmax, details, problem = compare_stacks(case / "A" / "stack", case / "B" / "stack",
                                                                           opt.show)
                    bad = bool(problem or npx)
                    counts["diff" if bad else "same"] += 1
                    totals[0] += nlay
                    totals[1] += nl
                    totals[2] += npx
                    emit(f"{head} {nlay:>6} {nl:>5} {npx:>8} {gmax:>3}  {tail}  "
                         f"{problem or ('PIXELS DIFFER' if npx else 'identical')}")
                    for d in details:
                        emit(f"    {d}")
                    if bad and opt.keep_diffs:
                        kept.append(str(case))
                    else:
                        shutil.rmtree(case, ignore_errors=True)
        c = counts
        emit(f"elapsed {time.perf_counter() - t0:.0f} s")
        emit(f"{sum(c.values())} cases: {c['same']} identical, {c['diff']} with differing pixels, "
             f"{c['refused']} refused by both, {c['error']} with differing exit status; "
             f"{totals[0]} layers compared, {totals[1]} differ, {totals[2]} pixels differ")
        if kept:
            emit("kept: " + " ".join(kept))
        return 1 if c["diff"] or c["error"] else 0
    finally:
        for s in sides:
            if s.worktree is not None:
                os.system(f"git -C {ROOT} worktree remove --force {s.worktree}")
        if not kept:
            shutil.rmtree(base, ignore_errors=True)
        if log:
            log.close()


if __name__ == "__main__":
    sys.exit(main())
