"""``gpuslice info``: what a mesh file holds, after scaling."""

from __future__ import annotations

import json

import click

from ..mesh.mesh import Placement
from .options import build, click_options, with_options

__all__ = ["info"]


@click.command()
@click.argument("model", type=click.Path(dir_okay=True, path_type=str))
@with_options(click_options(Placement))
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of text.")
def info(model: str, as_json: bool, **kw) -> None:
    """Facets, unique vertices, distinct normals, bbox, watertight, bodies and volume of MODEL (after scaling)."""
    from ..pipeline import Job, load_job_mesh

    mesh = load_job_mesh(Job(source=model, placement=build(Placement, kw)))
    data = mesh.info()
    if as_json:
        click.echo(json.dumps(data, indent=1))
        return
    for key, value in data.items():
        if key == "volume" and value is None:
            value = "n/a (open or inconsistently wound: slice --report's volume_mm3 is what prints)"
        elif isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, list):
            value = " ".join(f"{v:.6g}" for v in value)
        click.echo(f"{key:24s} {value}")
