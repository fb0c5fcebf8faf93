"""``gpuslice devices``: the OpenCL platforms and devices, and which one gpuslice uses."""

from __future__ import annotations

import json

import click

from .options import fail

__all__ = ["devices"]


@click.command()
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
@click.option("--device", default=None, help="Show which device this spec selects.")
def devices(as_json: bool, device: str | None) -> None:
    """List OpenCL platforms and devices, and which one gpuslice uses."""
    from ..device import cpu_unknown_to_pocl, list_devices, resolve

    found = list_devices()
    chosen = resolve(device)["id"] if found else None
    if as_json:
        click.echo(json.dumps({"devices": found, "selected": chosen}, indent=1))
        return
    for d in found:
        mark = "*" if d["id"] == chosen else " "
        click.echo(f"{mark} {d['id']}  {d['platform']} | {d['device']} | {d['type']} | {d['compute_units']} CU | "
                   f"{d['global_mem_mib']} MiB | {d['platform_version']}"
                   + (" | cannot build for this CPU (its LLVM does not know it)" if cpu_unknown_to_pocl(d) else ""))
    if not found:
        fail("no OpenCL device found (pip install pocl-binary-distribution)")
    click.echo("(* = used by default; override with --device or GPUSLICE_DEVICE)")
