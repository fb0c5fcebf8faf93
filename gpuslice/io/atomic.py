"""Writing files atomically: every output of gpuslice goes through :func:`atomic_path`.

The output is written under a temporary name in the destination's directory and renamed over the final name only
once it is complete, so an interrupted run (an exception, Ctrl-C, a full disk) never leaves a truncated file under
the name the user asked for. Folders (a PNG stack) are written the same way, as a whole.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import secrets
import shutil
import stat
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import ParameterError

if TYPE_CHECKING:
    pass

PathLike = str | os.PathLike

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "atomic_write_tree", "remove_path",
           "refuse_special", "utf8", "committed_together"]

#: the outputs whose renames wait for the end of the innermost :func:`committed_together` block (None: none open)
_GROUP: contextvars.ContextVar[list | None] = contextvars.ContextVar("gpuslice_atomic_group", default=None)


def remove_path(path: Path) -> None:
    """Remove a file, link or directory tree at ``path`` if there is one; never raises."""
    with contextlib.suppress(OSError):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


def _fsync_file(path: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _fsync_dir(path: Path) -> None:
    # Makes the rename itself durable on POSIX; directories cannot be opened on Windows, hence best effort.
    with contextlib.suppress(OSError, AttributeError):
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


#: the buffer (bytes) of a file that a resin archive writer fills layer by layer: the writer's thread also feeds
#: the encoder threads, and every system call makes it wait for the GIL again behind them (with the default 8 KiB
#: buffer, one wait per layer: the armadillo 12K GOO job ran 1.10x longer)
WRITE_BUFFER = 1 << 22


def refuse_special(path: str | os.PathLike) -> None:
    """:class:`ParameterError` when ``path`` exists (through symbolic links) and is neither a regular file nor a
    folder: a device such as ``/dev/null``, a FIFO or a socket, which an atomic write would replace by a regular file
    (for every program on the machine, in ``/dev``'s case); or a write-protected file (no write permission for
    anyone, as ``chmod a-w`` leaves it), which the rename would replace without a word where ``cp`` and a shell's
    ``>`` refuse."""
    p = Path(os.fspath(path))
    try:
        mode = p.stat().st_mode
    except OSError:  # does not exist (or a dangling link, replaced as a file is): nothing to protect
        return
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        raise ParameterError(f"{p}: not a regular file (a device, FIFO or socket); gpuslice writes files: name one")
    if stat.S_ISREG(mode) and not mode & 0o222:
        raise ParameterError(f"{p}: is write-protected; make it writable (chmod u+w) to replace it, or name another "
                             "file")


def _target(path: Path) -> Path:
    """Where an output named ``path`` goes: through a symbolic link to the file it names (the rename replaced the
    link itself with a file and left its target stale), else ``path``."""
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextlib.contextmanager
def atomic_path(path: PathLike, *, fsync: bool = True) -> Iterator[Path]:
    """Context manager giving a temporary path that replaces ``path`` when the block succeeds.

    The temporary path lies in the same directory as ``path`` (so the final rename never crosses file
    systems) and is named ``.{name}.tmp-{pid}-{random}{suffix}`` (``.gpuslice.tmp-…`` for a name over 200 bytes,
    so that the temporary's name fits where the final one does): hidden, unique, and ending with the final
    name's suffix for writers that look at it (``np.savez`` appends ``.npz`` otherwise). The block creates
    whatever it wants at that path, a file or a directory. When the block completes, the temporary is
    flushed to disk (``fsync=True``) and renamed over ``path`` with :func:`os.replace`; when the block
    raises anything, ``KeyboardInterrupt`` and ``SystemExit`` included, the temporary (file or directory
    tree) is removed and the exception propagates. Either way no partial output is ever visible under
    ``path`` and no temporary is left behind.

    Parameters
    ----------
    path
        The final output path. Its directory must exist.
    fsync
        Flush the written file and the directory entry to stable storage, so a power cut right after the
        rename cannot leave an empty file under ``path``.

    Yields
    ------
    Path
        The temporary path to write to (nothing exists there yet).

    Raises
    ------
    ParameterError
        The directory of ``path`` does not exist, or ``path`` is an existing directory and the block wrote
        a file.
    FileNotFoundError
        The block completed without creating anything at the temporary path.

    Notes
    -----
    A directory written by the block replaces an existing directory at ``path`` by two renames (the old
    tree is moved aside, the new one moved in, the old one deleted); readers see either the complete old
    tree or the complete new one, though there is an instant where ``path`` does not exist.

    Examples
    --------
    >>> with atomic_path("out.bin") as tmp:  # doctest: +SKIP
    ...     with open(tmp, "wb") as fh:
    ...         fh.write(data)
    """
    final = _target(Path(os.fspath(path)))
    directory = final.parent
    if not directory.is_dir():
        raise ParameterError(f"{final}: directory {directory} does not exist")
    refuse_special(final)
    stem = final.name if len(os.fsencode(final.name)) <= 200 else "gpuslice"  # (a long name fits; its temporary too)
    tmp = directory / f".{stem}.tmp-{os.getpid()}-{secrets.token_hex(4)}{final.suffix}"
    with _removing(tmp, final):
        yield tmp
        if not tmp.exists() and not tmp.is_symlink():
            raise FileNotFoundError(f"{final}: nothing was written to the temporary path {tmp}")
    group = _GROUP.get()
    if group is not None:  # renamed with the others at the end of the committed_together block
        group.append((tmp, final, fsync))
        return
    _commit(tmp, final, fsync)


def _commit(tmp: Path, final: Path, fsync: bool) -> None:
    """Rename the complete temporary ``tmp`` over ``final`` (:func:`atomic_path`); ``tmp`` is removed on failure."""
    with _removing(tmp, final):
        refuse_special(final)  # (again: the path may have been made while the block ran)
        if tmp.is_dir() and not tmp.is_symlink():
            _replace_dir(tmp, final)
        else:
            if final.is_dir() and not final.is_symlink():
                raise ParameterError(f"{final}: is a directory")
            with contextlib.suppress(OSError):  # a file replaced keeps its permissions (a 0600 output stays private;
                os.chmod(tmp, final.stat().st_mode & 0o777)  # not setuid, setgid or sticky bits)
            if fsync:
                _fsync_file(tmp)
            os.replace(tmp, final)
        if fsync:
            _fsync_dir(final.parent)


@contextlib.contextmanager
def _removing(tmp: Path, final: Path) -> Iterator[None]:
    """Remove ``tmp`` when the block raises anything; an :class:`OSError` is raised again named after the output
    ``final``, not its hidden temporary ("No space left on device" from a writer named no file at all), unless it
    names another file."""
    try:
        yield
    except OSError as exc:
        remove_path(tmp)
        if exc.errno is not None and (exc.filename is None or os.fspath(exc.filename).startswith(os.fspath(tmp))):
            raise type(exc)(exc.errno, exc.strerror or str(exc), os.fspath(final)) from None
        raise
    except BaseException:
        remove_path(tmp)
        raise


@contextlib.contextmanager
def committed_together() -> Iterator[None]:
    """Context manager under which the outputs of :func:`atomic_path` (in this thread's context) are complete but
    not yet renamed: all of them are renamed into place, in the order they were written, when the block succeeds,
    and none when it raises (their temporaries are removed, the previous files left as they were). A command that
    writes an output and then a report about it (``slice -o … --report …``) thus never leaves a new output beside
    a failed report. Only a failing rename itself (rare: the temporaries lie in the outputs' own folders) can
    leave the earlier outputs renamed; the later ones are then removed. Nested blocks join the outermost."""
    if _GROUP.get() is not None:
        yield
        return
    group: list[tuple[Path, Path, bool]] = []
    token = _GROUP.set(group)
    try:
        yield
    except BaseException:
        for tmp, _final, _fsync in group:
            remove_path(tmp)
        raise
    finally:
        _GROUP.reset(token)
    for k, (tmp, final, fsync) in enumerate(group):
        try:
            _commit(tmp, final, fsync)
        except BaseException:
            for later, _final, _fsync in group[k + 1 :]:
                remove_path(later)
            raise


def _replace_dir(tmp: Path, final: Path) -> None:
    if not final.exists() and not final.is_symlink():
        os.replace(tmp, final)
        return
    if not final.is_dir() or final.is_symlink():
        os.replace(tmp, final)  # raises NotADirectoryError on POSIX: a directory cannot replace a file
        return
    old = final.parent / f".{final.name}.old-{os.getpid()}-{secrets.token_hex(4)}"
    os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        os.replace(old, final)
        raise
    remove_path(old)


def atomic_write_bytes(path: PathLike, data: bytes | bytearray | memoryview) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)


def utf8(text: str) -> bytes:
    """``text`` as UTF-8; a file name's bytes that are not UTF-8 (which Python keeps as lone surrogates, U+DC80 to
    U+DCFF) become U+FFFD instead of an encoding error."""
    try:
        return text.encode("utf-8")
    except UnicodeEncodeError:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "replace").encode("utf-8", "replace")


def atomic_write_text(path: PathLike, text: str, *, encoding: str = "utf-8") -> None:
    """Write ``text`` to ``path`` atomically, encoded with ``encoding`` (UTF-8: :func:`utf8`), newlines written as
    given."""
    atomic_write_bytes(path, utf8(text) if encoding.lower().replace("-", "") == "utf8" else text.encode(encoding))


def atomic_write_tree(path: PathLike, payload: bytes | dict[str, bytes]) -> None:
    """Write ``payload`` at ``path`` atomically, making its parent folders: a file (bytes), or a folder of files
    (relative path -> bytes; a PNG stack's layers), built under a temporary name and renamed whole."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(payload, bytes):
        atomic_write_bytes(target, payload)
        return
    with atomic_path(target) as tmp:
        tmp.mkdir()
        for rel, data in payload.items():
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp / rel).write_bytes(data)
