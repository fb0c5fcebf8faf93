"""The files a batch finished, kept beside its manifest: one JSON line per finished model in ``.gpuslice-batch.done``,
``{"files": {name: [size, mtime_ns]}}`` (its output and, with ``--check``, its check report, named relative to the
output folder), appended by the batch's own process once the files are in place.

A re-run skips a model only when its files are still the ones the journal lists (same size and modification time);
an output that is not (a file put there later, a model that failed before and whose name someone filled, a file
changed since) is refused by name, before any model, unless ``--force`` remakes it. A folder a batch wrote before the
journal existed (a manifest and no journal) keeps the older rule: its existing outputs are taken as finished.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

__all__ = ["JOURNAL_NAME", "record_finished", "record_written_since", "read_journal", "unchanged", "forget_journal"]

#: the journal in the output folder, beside the manifest
JOURNAL_NAME = ".gpuslice-batch.done"


def _stamp(path: Path) -> list[int] | None:
    """``[size, mtime_ns]`` of the file ``path``, or None when it is not there."""
    try:
        st = path.stat()
    except OSError:
        return None
    return [st.st_size, st.st_mtime_ns]


def record_finished(folder: Path, names: list[str]) -> None:
    """Append the files ``names`` (relative to ``folder``) of a finished model to the journal. A journal that cannot
    be written (a full disk) leaves the model unrecorded: a re-run then refuses its files by name instead of
    skipping them (``--force`` remakes them)."""
    files = {name: _stamp(folder / name) for name in names}
    if any(v is None for v in files.values()):
        return
    line = json.dumps({"files": files}, separators=(",", ":")) + "\n"
    with contextlib.suppress(OSError):
        fd = os.open(folder / JOURNAL_NAME, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line.encode("utf-8"))  # (one write of one line: appended whole)
        finally:
            os.close(fd)


def record_written_since(folder: Path, names: list[str], since_ns: int) -> None:
    """Journal ``names`` when every one of them was put in place at or after ``since_ns`` (a worker renames an
    output whole when it is complete): a model finished as a batch was stopped, its result never back."""
    stamps = [_stamp(folder / name) for name in names]
    if all(s is not None and s[1] >= since_ns for s in stamps):
        record_finished(folder, names)


def forget_journal(folder: Path) -> None:
    """Empty the journal (the options changed, ``--force``: its files were made with the old ones). An empty journal,
    not none: the folder's remaining outputs are then refused by name, not taken as finished by the older rule."""
    from ..io.atomic import atomic_write_text

    atomic_write_text(folder / JOURNAL_NAME, "")


def read_journal(folder: Path) -> dict[str, list[int]] | None:
    """The journal of ``folder``: each file's latest ``[size, mtime_ns]``; None when there is no journal (or it
    cannot be read). Lines that do not parse (a write cut short) are passed over."""
    try:
        text = (folder / JOURNAL_NAME).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None
    out: dict[str, list[int]] = {}
    for line in text.splitlines():
        try:
            files = json.loads(line)["files"]
            out.update({str(k): [int(v[0]), int(v[1])] for k, v in files.items()})
        except (ValueError, KeyError, TypeError, IndexError, AttributeError):
            continue
    return out


def unchanged(folder: Path, names: list[str], journal: dict[str, list[int]]) -> bool:
    """Whether each of ``names`` is the file the journal recorded (same size and modification time)."""
    return all(journal.get(name) is not None and journal[name] == _stamp(folder / name) for name in names)


def remove_journaled(folder: Path, names: list[str], journal: dict[str, list[int]]) -> None:
    """Remove those of ``names`` that are the files ``journal`` recorded (a batch's own outputs, unchanged since);
    a file the journal does not list as it is, the user's, stays."""
    from ..io.atomic import remove_path

    for name in names:
        if unchanged(folder, [name], journal):
            remove_path(folder / name)
