"""Where a whole `gpuslice` command's time goes, function by function, in every thread: a wall-clock profile.

    python scripts/profile_stages.py [--modules gpuslice.raster,gpuslice.slicing] [--top 40] [--cold] -- raster x.stl

Runs the CLI command (after ``--``) in this process twice, the first as a warm-up (kernel builds), and times the
second (``--cold``: runs it once and times that, kernel loads, first imports and first page faults included): every
function and method defined in the named packages' modules is wrapped by a timer, also where other modules imported
it by name, so calls on the writers' encoder threads and the prefetch threads count too (cProfile
sees one thread). Prints, per function: calls, total wall seconds (inclusive: nested and concurrent calls each
count theirs, so the column adds up to more than the run) and the thread count. A tool for finding the next step
(used on a lent GPU: docs/GPU.md), not a benchmark: the timers' own cost is ~1 µs a call.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import os
import pkgutil
import sys
import threading
import time
from collections import defaultdict

STATS: dict[str, list] = defaultdict(lambda: [0, 0.0, set()])


def _timed(name: str, fn):
    def wrapper(*args, **kwargs):
        t = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            s = STATS[name]
            s[0] += 1
            s[1] += time.perf_counter() - t
            s[2].add(threading.get_ident())

    wrapper.__wrapped__ = fn
    wrapper.__name__ = getattr(fn, "__name__", name)
    wrapper.__doc__ = getattr(fn, "__doc__", None)
    return wrapper


def instrument(packages: list[str]) -> int:
    """Wrap the functions and methods defined in every module of ``packages``; returns how many."""
    mods = []
    for pkg in packages:
        p = importlib.import_module(pkg)
        mods.append(p)
        for info in pkgutil.iter_modules(p.__path__, pkg + "."):
            try:
                mods.append(importlib.import_module(info.name))
            except Exception:  # an optional module whose dependency is missing
                continue
    replaced: dict[int, object] = {}
    for mod in mods:
        for attr, obj in list(vars(mod).items()):
            if inspect.isfunction(obj) and obj.__module__ == mod.__name__ and not attr.startswith("__"):
                replaced[id(obj)] = _timed(f"{mod.__name__}.{attr}", obj)
            elif inspect.isclass(obj) and obj.__module__ == mod.__name__:
                for name, member in list(vars(obj).items()):
                    if inspect.isfunction(member) and not (name.startswith("__") and name != "__call__"):
                        setattr(obj, name, _timed(f"{mod.__name__}.{obj.__name__}.{name}", member))
    # every module that holds one of these functions by name gets the wrapper (from-imports included)
    for mod in list(sys.modules.values()):
        if mod is None or not getattr(mod, "__name__", "").startswith("gpuslice"):
            continue
        for attr, obj in list(vars(mod).items()):
            if id(obj) in replaced and inspect.isfunction(obj):
                setattr(mod, attr, replaced[id(obj)])
    return len(replaced)


def main() -> int:
    argv = sys.argv[1:]
    if "--" not in argv:
        print(__doc__)
        return 2
    cut = argv.index("--")
    ap = argparse.ArgumentParser()
    ap.add_argument("--modules", default="gpuslice.raster,gpuslice.slicing,gpuslice.mesh,gpuslice.io")
    ap.add_argument("--top", type=int, default=40)
    ap.add_argument("--cold", action="store_true", help="time the first run (no warm-up): imports, builds, first touch")
    args = ap.parse_args(argv[:cut])
    command = argv[cut + 1 :]
    os.environ["GPUSLICE_SLOW_EXIT"] = "1"  # (the CLI's fast exit would end this process)
    from gpuslice.cli import main as cli

    n = instrument(args.modules.split(","))
    for run in ("timed",) if args.cold else ("warm-up", "timed"):
        STATS.clear()
        t = time.perf_counter()
        try:
            code = cli(command)
        except SystemExit as exc:
            code = exc.code
        wall = time.perf_counter() - t
        print(f"{run}: exit {code}, {wall:.3f} s", flush=True)
    print(f"{n} functions wrapped; the timed run, by total wall time (inclusive):")
    print(f"{'calls':>8} {'total s':>9} {'threads':>7}  function")
    for name, (calls, total, threads) in sorted(STATS.items(), key=lambda kv: -kv[1][1])[: args.top]:
        print(f"{calls:8d} {total:9.3f} {len(threads):7d}  {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
