"""The ``gpuslice`` command line: one module per command, imported only when that command runs."""

from .main import cli, entry, main

__all__ = ["cli", "entry", "main"]
