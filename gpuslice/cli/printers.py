"""``gpuslice printers``: the resin printer presets (:data:`gpuslice.raster.printers.PRINTERS`) as a table or JSON, or
one preset (a name, or a user's ``.toml``/``.json`` preset file) in full. Imports no OpenCL: it starts fast."""

from __future__ import annotations

import json

import click

__all__ = ["printers"]

COLUMNS = ("name", "pixels", "pixel um", "build mm", "display", "format")


#: marks a format gpuslice does not write (the preset's printer then gets PNG stacks only)
UNWRITTEN = "*"


def _written(fmt: str) -> bool:
    from ..raster.outputs import RESIN_FORMATS

    return fmt in RESIN_FORMATS


def _shown(fmt: str) -> str:
    return fmt if _written(fmt) else f"{fmt} (not written by gpuslice)"


def _row(p) -> tuple[str, ...]:
    px = f"{p.pixel * 1000:g}" if p.pixel_y is None else f"{p.pixel * 1000:g}x{p.py * 1000:g}"
    x, y, z = p.build_mm
    fmt = p.native_format or "any"
    if p.native_format and p.format_version is not None:
        fmt += f" v{p.format_version}"
    if p.native_format and not _written(p.native_format):
        fmt += f" {UNWRITTEN}"
    return (p.name, f"{p.resolution[0]}x{p.resolution[1]}", px, f"{x:g} x {y:g} x {z:g}", p.orientation, fmt)


def _table(rows: list[tuple[str, ...]]) -> str:
    widths = [max(len(r[k]) for r in rows) for k in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows)


def _details(p) -> str:
    x, y, z = p.build_mm
    px = f"{p.pixel * 1000:g} x {p.py * 1000:g} um"
    lines = [f"{p.name}: {p.title}",
             f"  display   {p.resolution[0]} x {p.resolution[1]} px, {px}, {p.orientation}",
             f"  build     {x:g} x {y:g} x {z:g} mm",
             f"  formats   {', '.join(_shown(f) for f in p.formats) or 'any'}"
             + (f" (native {p.native_format} version {p.format_version})" if p.format_version is not None else ""),
             f"  machine   {p.machine or '-'}"]
    if p.settings:
        lines.append("  settings  " + ", ".join(f"{k} = {v}" for k, v in p.settings.items()))
    if p.notes:
        lines.append(f"  notes     {p.notes}")
    if p.source:
        lines.append(f"  source    {p.source}")
    return "\n".join(lines)


@click.command()
@click.argument("name", required=False)
@click.option("--json", "as_json", is_flag=True, help="Print JSON (a list of presets, sorted by name) for scripts.")
def printers(name: str | None, as_json: bool) -> None:
    """List the resin printer presets that --printer takes: display pixels, pixel size (x by y, um), build size
    (mm), display orientation and native archive format. With NAME (a preset, or a .toml/.json preset file of your
    own), show that one in full: every format it reads, its machine name, default settings and sources."""
    from ..raster.printers import PRINTERS, find_printer

    chosen = [find_printer(name)] if name is not None else [PRINTERS[n] for n in sorted(PRINTERS)]
    if as_json:
        click.echo(json.dumps([p.to_dict() for p in chosen], indent=1))
    elif name is not None:
        click.echo(_details(chosen[0]))
    else:
        rows = [_row(p) for p in chosen]
        click.echo(_table([COLUMNS, *rows]))
        if any(r[-1].endswith(UNWRITTEN) for r in rows):
            click.echo(f"{UNWRITTEN} a format gpuslice does not write: a PNG stack (-o DIR/) is all it gives that "
                       "printer")
