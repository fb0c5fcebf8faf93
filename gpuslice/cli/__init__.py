"""The ``gpuslice`` command line: one module per command, imported only when that command runs."""

from .main import cli, main

__all__ = ["cli", "main"]
