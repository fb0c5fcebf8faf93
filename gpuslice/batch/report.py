"""The batch summary table printed by ``gpuslice batch``."""

from __future__ import annotations

from typing import Any

from ..errors import flatten

__all__ = ["checks_summary", "format_summary"]


def checks_summary(done: list[dict[str, Any]]) -> dict[str, int]:
    """How many of the checked models have islands, resin traps, suction cups (``--check``)."""
    checks = [r["checks"] for r in done if "checks" in r]
    return {"models": len(checks), "with_islands": sum(c["islands"] > 0 for c in checks),
            "with_traps": sum(c["traps"] > 0 for c in checks),
            "with_suction_cups": sum(c["suction_cups"] > 0 for c in checks)}


def _checks_cell(r: dict[str, Any]) -> str:
    """A model's pre-print checks in one cell: islands, traps, suction cups (``-``: not checked)."""
    c = r.get("checks")
    if c is None:
        return "-"
    found = [f"{c[k]} {label}" for k, label in (("islands", "isl"), ("traps", "trap"), ("suction_cups", "cup"))
             if c.get(k)]
    return ", ".join(found) or "ok"


def _note(r: dict[str, Any]) -> str:
    """The last cell: the error of a failed model, else a warning (open chains: the mesh is not closed there, so a
    resin archive leaves what they outline unfilled), else nothing."""
    if r.get("error"):
        return flatten(r["error"])
    n = r.get("open_chains") or 0
    return f"warning: {n} open chains (the mesh is not closed there; a resin layer leaves them unfilled)" if n else ""


def format_summary(report: dict[str, Any], max_rows: int = 40) -> str:
    """A plain-text summary table of a batch report: one row per model (failed ones first; at most
    ``max_rows``), then the totals; with ``--check``, a ``checks`` column (islands, resin traps, suction cups); the
    last column holds a failed model's error, or a warning (:func:`_note`)."""
    rows = sorted(report["models"], key=lambda r: (r["status"] != "failed", r["model"]))
    width = min(60, max([len(flatten(r["model"])) for r in rows] + [5]))
    checked = "checks" in report["summary"]
    cw = max([len(_checks_cell(r)) for r in rows[:max_rows]] + [6]) if checked else 0
    head = f" {'checks':{cw}s}" if checked else ""
    lines = [f"{'model':{width}s} {'status':8s} {'facets':>9s} {'layers':>7s} {'time s':>8s}{head}  error or warning"]
    for r in rows[:max_rows]:
        t = r.get("timings_s", {}).get("total")
        shown = flatten(r["model"])  # (a file name's control characters: escaped)
        name = shown if len(shown) <= width else "…" + shown[-width + 1:]
        cell = f" {_checks_cell(r):{cw}s}" if checked else ""
        lines.append(f"{name:{width}s} {r['status']:8s} {r.get('facets', ''):>9} {r.get('layers', ''):>7} "
                     f"{'' if t is None else f'{t:.3f}':>8s}{cell}  {_note(r)}")
    if len(rows) > max_rows:
        lines.append(f"… {len(rows) - max_rows} more (every model is in the JSON report, --report FILE)")
    s = report["summary"]
    rate = s["models_per_s"]
    lines.append(
        f"{s['models']} models: {s['done']} done, {s['skipped']} skipped, {s['failed']} failed"
        + (f", {s['not_run']} not run" if s["not_run"] else "")
        + f"; {s['wall_s']:.2f} s wall, {rate:.2f} models/s ({s['mode']}, {s.get('workers', 0)} workers"
        + (f", {s['workers_lost']} lost" if s["workers_lost"] else "")
        + (f", {s['retries']} retries" if s["retries"] else "") + ")"
    )
    if checked:
        c = s["checks"]
        lines.append(f"checks: {c['models']} models checked, {c['with_islands']} with islands, {c['with_traps']} with "
                     f"resin traps, {c['with_suction_cups']} with suction cups (<output>.check.json)")
    return "\n".join(lines)
