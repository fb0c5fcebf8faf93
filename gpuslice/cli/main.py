"""The ``gpuslice`` command group: one module per command in this package, imported only when that command runs
(start-up stays short), and the one place errors become exit codes.

Results go to stdout (or files), progress and errors to stderr. A user error (bad file, bad option) prints one line
``gpuslice: error: <file>: <problem>`` and exits with status 2; the library's errors name option fields
(``max_gap``), shown here as their flags (``--max-gap``). Ctrl-C exits with 130; SIGTERM (``kill``, ``timeout``)
and SIGHUP (a closed terminal) stop a command the same way, exiting with 128 + the signal's number (143, 129).
Outputs are written under a temporary name and renamed when complete, so an interrupted run leaves no partial
file. ``--debug`` shows tracebacks.

The installed ``gpuslice`` command (and ``python -m gpuslice.cli``) enters through :func:`entry`, which ends the
process without the interpreter's teardown once the command is over (see :func:`exit_now`); :func:`main` returns
the exit code and is what scripts and tests call in-process.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import shutil
import signal
import sys
import threading

import click

from .. import __version__
from ..errors import GpusliceError, ParameterError, flatten, one_line
from .options import EXIT_USAGE

__all__ = ["main", "entry", "exit_now", "cli", "COMMANDS"]

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
        with _stop_on_terminate(), _named_stdout():
            cli.main(args=args, prog_name="gpuslice", standalone_mode=False)
    except click.exceptions.Abort as exc:
        _INTERRUPTED.set()
        if isinstance(exc.__cause__, Terminated):
            click.echo(f"gpuslice: {exc.__cause__}", err=True)
            return 128 + exc.__cause__.signum
        click.echo("gpuslice: interrupted", err=True)
        return 130
    except click.ClickException as exc:
        click.echo(f"gpuslice: error: {exc.format_message()}", err=True)
        return EXIT_USAGE
    except GpusliceError as exc:
        if debug:
            raise
        click.echo(f"gpuslice: error: {flatten(_message(exc), 2000)}", err=True)  # (a file's text in it: bounded)
        return EXIT_USAGE
    except KeyboardInterrupt as exc:
        _INTERRUPTED.set()
        if isinstance(exc, Terminated):
            click.echo(f"gpuslice: {exc}", err=True)
            return 128 + exc.signum
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
        where = exc.filename  # ("standard output" where it could not take a write: _NamedStream)
        click.echo(f"gpuslice: error: {where}: {reason}" if where else f"gpuslice: error: {reason}", err=True)
        return EXIT_USAGE
    except Exception as exc:  # never a traceback for users; --debug shows it
        if debug:
            raise
        click.echo(f"gpuslice: internal error: {one_line(exc)} (run with --debug)", err=True)
        return 1
    return 0


class _NamedStream:
    """``sys.stdout`` (and its ``buffer``) for the length of a command, naming itself in the OSErrors of its writes:
    a summary or a table printed to a full disk says "standard output: No space left on device" (the OSError names
    no file, and the data it could not write is gone, so it cannot be asked later)."""

    NAME = "standard output"

    def __init__(self, stream) -> None:
        self._stream = stream

    def _named(self, call, *args):
        try:
            return call(*args)
        except OSError as exc:
            if exc.filename is None:
                exc.filename = self.NAME
            raise

    def write(self, data):
        return self._named(self._stream.write, data)

    def writelines(self, lines):
        return self._named(self._stream.writelines, lines)

    def flush(self):
        return self._named(self._stream.flush)

    @property
    def buffer(self):
        return _NamedStream(self._stream.buffer)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


@contextlib.contextmanager
def _named_stdout():
    """:class:`_NamedStream` in place of ``sys.stdout`` while a command runs (left as found afterwards; where click
    wrapped it on a closed pipe, its wrapper keeps the wrapping, around the stream found)."""
    real = sys.stdout
    named = _NamedStream(real) if real is not None else None
    if named is not None:
        sys.stdout = named
    try:
        yield
    finally:
        if sys.stdout is named:
            sys.stdout = real
        elif getattr(sys.stdout, "wrapped", None) is named:  # (click's PacifyFlushWrapper, on a broken pipe)
            sys.stdout.wrapped = real


def entry() -> None:
    """Console-script entry point: :func:`main` on ``sys.argv``, then :func:`exit_now` with its exit code.

    Before numpy loads (``import gpuslice`` and this module import none), ``OPENBLAS_NUM_THREADS`` is set to 1 unless
    the user set it: nothing here runs a threaded BLAS call, and numpy's OpenBLAS otherwise starts a thread per core
    at import that spins for ≈ 0.1 s waiting for work, taking a core from start-up (measured: a 0.05 mm nefertiti
    slice 7 % slower on 2 cores). The variable is inherited by the PNG and batch worker processes. For ``raster``,
    the process's threads share one malloc arena (:func:`gpuslice.allocator.one_malloc_arena`), for ``slice`` and
    ``view`` they also keep what they free (:func:`gpuslice.allocator.keep_freed_memory`), unless the user tunes malloc
    (``MALLOC_*``, ``GLIBC_TUNABLES``) or sets ``GPUSLICE_PLAIN_MALLOC`` (any non-empty value)."""
    if "numpy" not in sys.modules:
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    sys.unraisablehook = _unraisable
    command = _command(sys.argv[1:])
    if command == "raster":  # slicing, then the layers on other threads: what one frees, the next uses
        from ..allocator import resin_arena

        resin_arena()
    elif command in ("slice", "view"):  # their big arrays, freed batch after batch, reused instead of mapped afresh
        from ..allocator import slice_heap

        slice_heap()
    exit_now(main())


def _command(args: list[str]) -> str | None:
    """The subcommand named by ``args`` (the first word that is not an option: the group's options take no value)."""
    return next((a for a in args if not a.startswith("-")), None)


#: set once the command was interrupted (Ctrl-C): see :func:`_unraisable`
_INTERRUPTED = threading.Event()


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP while a command runs, raised in the main thread as Ctrl-C's KeyboardInterrupt is: every
    ``with`` block unwinds as for Ctrl-C (an output's temporary file removed, encoder threads and workers stopped)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = int(signum)

    def __str__(self) -> str:
        return f"terminated ({signal.Signals(self.signum).name})"


@contextlib.contextmanager
def _stop_on_terminate():
    """While the command runs, SIGTERM and SIGHUP raise :class:`Terminated` in the main thread instead of killing
    the process on the spot, which would leave an output's hidden temporary file (``.part.goo.tmp-…``) behind.
    Only signals left at their default action are taken (``nohup`` keeps SIGHUP ignored); a second one while the
    command unwinds ends the process at once, as without this handler. Ctrl-C (SIGINT, when at Python's default)
    raises KeyboardInterrupt as always, but a second one while the first unwinds is let go (it used to interrupt the
    clean-up: a traceback from a thread's wait, or an output's empty temporary file left), and a third ends the
    process at once. The previous handlers come back afterwards. Nothing is done outside the main thread
    (``signal.signal`` is refused there)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pid = os.getpid()
    seen: list[int] = []

    def die(signum) -> None:  # as the signal asks, as without these handlers
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    def handler(signum, frame):
        if os.getpid() == pid and not seen:
            seen.append(signum)
            _INTERRUPTED.set()
            raise Terminated(signum)
        die(signum)  # a second one while the first unwinds, or a forked child that inherited the handler

    interrupts: list[int] = []

    def on_interrupt(signum, frame):
        if os.getpid() != pid:  # a forked child that inherited the handler: as Python's own
            raise KeyboardInterrupt
        interrupts.append(signum)
        _INTERRUPTED.set()  # (before anything unwinds: see _unraisable)
        if len(interrupts) == 1:
            raise KeyboardInterrupt
        if len(interrupts) > 2:  # a third: end at once, as Python's default would not
            die(signum)
        # the second is let go while the first unwinds (removing a temporary file, stopping threads): `timeout -s INT`
        # sends one to the process and one to its group, and a user may press twice

    previous = {}
    for name in ("SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)
        if signum is not None and signal.getsignal(signum) == signal.SIG_DFL:
            previous[signum] = signal.signal(signum, handler)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:  # (not when the caller ignores Ctrl-C)
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, on_interrupt)
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def _unraisable(info) -> None:
    """The command line's ``sys.unraisablehook``: Python's own report, except after Ctrl-C. An interrupt can land
    inside a library's constructor (an import of PyOpenCL builds pytools' cache objects), whose finaliser then fails
    on the half-made object and Python prints "Exception ignored ... Traceback" after "gpuslice: interrupted"; the
    user asked to stop, and the one line has said so."""
    if not _INTERRUPTED.is_set():
        sys.__unraisablehook__(info)


def exit_now(code: int) -> None:
    """End the process with ``code`` once the command is over, skipping the interpreter's teardown when that is safe.

    Tearing down an interpreter that has imported numpy, pyopencl and PoCL costs 50–110 ms (freeing every module and
    array, the OpenCL objects' finalisers, PoCL's threads), as much as slicing a 100k-facet mesh; a finished command
    needs none of it. So the standard streams are flushed and the process ends with :func:`os._exit`, provided
    nothing could still be owed work: no thread other than the main one is alive that is not a daemon, no
    :mod:`multiprocessing` child is running, no Dask client or cluster was imported (``batch``), and no coverage or
    profiler hook is installed (``sys.gettrace``/``sys.getprofile``, ``coverage`` imported). Every output file was
    already written and renamed into place by then (:mod:`gpuslice.io.atomic`). ``GPUSLICE_SLOW_EXIT=1`` (any
    non-empty value) keeps the ordinary exit. Otherwise this is ``sys.exit(code)``.
    """
    flushed = True
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):  # a closed pipe (``| head``): nothing more can be said on it
            flushed = False
    if flushed and _nothing_pending():
        _remove_multiprocessing_tempdir()
        os._exit(code)
    sys.exit(code)


def _remove_multiprocessing_tempdir() -> None:
    """Do what :mod:`multiprocessing`'s exit handler would, which :func:`os._exit` skips: its finalisers of priority
    >= 0 (the semaphores of the executors' queues, unregistered from the resource tracker, which otherwise warned of
    "leaked semaphore objects" on stderr after an interrupted ``batch -j N``), and remove the ``pymp-*`` folder it made
    in ``$TMPDIR`` for this process (a forkserver's socket: ``batch -j N``, the PNG encoder processes; every such
    command left it behind, with its dead socket)."""
    process = sys.modules.get("multiprocessing.process")
    if process is None:
        return
    util = sys.modules.get("multiprocessing.util")
    if util is not None:
        with contextlib.suppress(Exception):
            util._run_finalizers(0)
    tempdir = getattr(process.current_process(), "_config", {}).get("tempdir")
    if tempdir:
        shutil.rmtree(tempdir, ignore_errors=True)


def _nothing_pending() -> bool:
    if os.environ.get("GPUSLICE_SLOW_EXIT") or sys.gettrace() is not None or sys.getprofile() is not None:
        return False
    if any(name in sys.modules for name in ("coverage", "distributed", "dask.distributed")):
        return False
    main_thread = threading.main_thread()
    if any(t is not main_thread and t.is_alive() and not t.daemon for t in threading.enumerate()):
        return False
    mp = sys.modules.get("multiprocessing")
    return mp is None or not mp.active_children()
