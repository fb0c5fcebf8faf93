"""The ``gpuslice`` command group: one module per command in this package, imported only when that command runs
(start-up stays short), and the one place errors become exit codes.

Results go to stdout (or files), progress and errors to stderr. A user error (bad file, bad option) prints one line
``gpuslice: error: <file>: <problem>`` and exits with status 2; the library's errors name option fields
(``max_gap``), shown here as their flags (``--max-gap``). Ctrl-C exits with 130. Outputs are written under a
temporary name and renamed when complete, so an interrupted run leaves no partial file. ``--debug`` shows
tracebacks.
"""

from __future__ import annotations

import importlib
import sys

import click

from .. import __version__
from ..errors import GpusliceError, ParameterError, flatten, one_line
from .options import EXIT_USAGE

__all__ = ["main", "cli", "COMMANDS"]

#: command name -> "module:attribute" under gpuslice.cli, imported on first use
COMMANDS = {
    "batch": "batch:batch",
    "bench": "bench:bench",
    "check": "check:check",
    "devices": "devices:devices",
    "info": "info:info",
    "plot": "bench:plot",
    "printers": "printers:printers",
    "raster": "raster:raster",
    "shape": "shape:shape",
    "slice": "slice:slice_cmd",
    "view": "view:view",
}


class LazyGroup(click.Group):
    """A click group whose commands live in their own modules and are imported when used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(COMMANDS))

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name in COMMANDS and cmd_name not in self.commands:
            module, attr = COMMANDS[cmd_name].split(":")
            name = f"{__package__}.{module}"
            try:
                mod = importlib.import_module(name)
            except ModuleNotFoundError as exc:
                if exc.name != name:  # a missing dependency inside the module: say so
                    raise
                return None
            self.add_command(getattr(mod, attr), cmd_name)
        return super().get_command(ctx, cmd_name)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, message=f"gpuslice %(version)s (Python {sys.version.split()[0]})")
@click.option("--debug", is_flag=True, help="Show tracebacks on errors.")
@click.pass_context
def cli(ctx: click.Context, debug: bool) -> None:
    """Slice triangle meshes (STL) into closed, nested layer contours on any OpenCL device."""
    ctx.obj = {"debug": debug}


def _message(exc: GpusliceError) -> str:
    if isinstance(exc, ParameterError) and exc.params:
        from .options import cli_message

        return cli_message(exc)
    return str(exc)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (0 ok, 2 user error, 130 interrupted)."""
    args = sys.argv[1:] if argv is None else list(argv)
    debug = "--debug" in args
    try:
        cli.main(args=args, prog_name="gpuslice", standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("gpuslice: interrupted", err=True)
        return 130
    except click.ClickException as exc:
        click.echo(f"gpuslice: error: {exc.format_message()}", err=True)
        return EXIT_USAGE
    except GpusliceError as exc:
        if debug:
            raise
        click.echo(f"gpuslice: error: {flatten(_message(exc))}", err=True)
        return EXIT_USAGE
    except KeyboardInterrupt:
        click.echo("gpuslice: interrupted", err=True)
        return 130
    except SystemExit as exc:
        return int(exc.code or 0) if not isinstance(exc.code, str) else 1
    except MemoryError:
        click.echo("gpuslice: error: out of memory", err=True)
        return 1
    except OSError as exc:  # an output that cannot be written (disk full, permission denied): the user's to fix
        if debug:
            raise
        reason = exc.strerror or flatten(str(exc)) or type(exc).__name__
        click.echo(f"gpuslice: error: {exc.filename}: {reason}" if exc.filename else f"gpuslice: error: {reason}",
                   err=True)
        return EXIT_USAGE
    except Exception as exc:  # never a traceback for users; --debug shows it
        if debug:
            raise
        click.echo(f"gpuslice: internal error: {one_line(exc)} (run with --debug)", err=True)
        return 1
    return 0
