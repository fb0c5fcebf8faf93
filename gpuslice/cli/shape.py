"""``gpuslice shape``: write a built-in test solid as a binary STL."""

from __future__ import annotations

import click

from ..mesh.shapes import SHAPES, write_stl

__all__ = ["shape"]


@click.command()
@click.argument("name", type=click.Choice(sorted(SHAPES)))
@click.option("-o", "--output", type=click.Path(path_type=str), required=True, help="Binary STL to write.")
def shape(name: str, output: str) -> None:
    """Write a built-in test solid NAME (mm, closed, outward-wound) as a binary STL, e.g. for a first run."""
    from pathlib import Path

    from .options import check_output_file, fail

    check_output_file(output)  # (a folder, a device or a FIFO first: said as for every command)
    if Path(output).suffix.lower() != ".stl":  # (a .obj got STL bytes, which nothing then read)
        fail(f"{output}: shape writes binary STL; name the output .stl")
    tri = SHAPES[name]()
    write_stl(tri, output, header=f"gpuslice shape {name}".encode())
    click.echo(f"wrote {output}: {name}, {len(tri)} facets")
