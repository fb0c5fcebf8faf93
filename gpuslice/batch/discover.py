"""Batch discovery: folders (recursive, filtered by a glob), list files (``.txt``/``.list``: one path a line, ``#``
comments, relative to the list file) and single paths become :class:`Model` s. Outputs mirror the input tree under
the output folder: a model's relative path is taken from the deepest folder holding every input (a single folder
argument is that folder), and its suffix is replaced by the output's (``.npz`` by default).
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import BatchError

__all__ = ["Model", "MESH_SUFFIXES", "LIST_SUFFIXES", "discover"]

#: suffixes a folder search picks up when no glob is given (any case)
MESH_SUFFIXES = (".stl", ".3mf", ".obj", ".ply", ".off")
#: list files: one model path a line
LIST_SUFFIXES = (".txt", ".list", ".lst")


@dataclass(frozen=True)
class Model:
    """One model of a batch: ``src`` the file as found (named so in messages), ``rel`` its path relative to the
    batch's base folder (POSIX), ``out`` its output path relative to the output folder (POSIX), ``path`` the absolute
    path workers read (``src`` when not given)."""

    src: str
    rel: str
    out: str
    path: str = ""

    @property
    def location(self) -> str:
        return self.path or self.src


def _glob_regex(pattern: str) -> re.Pattern:
    """A case-insensitive regex for a glob over relative POSIX paths: ``**/`` any folders (or none), ``*`` and
    ``?`` within one name, ``[...]`` a character class; a pattern without ``/`` matches the file name only."""
    if "/" not in pattern:
        pattern = "**/" + pattern
    out, i = [], 0
    while i < len(pattern):
        c = pattern[i]
        if pattern.startswith("**/", i):
            out.append("(?:.*/)?")
            i += 3
            continue
        if pattern.startswith("**", i):
            out.append(".*")
            i += 2
            continue
        if c == "*":
            out.append("[^/]*")
        elif c == "?":
            out.append("[^/]")
        elif c == "[":
            j = pattern.find("]", i + 1)
            if j < 0:
                out.append(re.escape(c))
            else:
                body = pattern[i + 1 : j]
                out.append("[" + ("^" + body[1:] if body.startswith("!") else body) + "]")
                i = j
        else:
            out.append(re.escape(c))
        i += 1
    return re.compile("".join(out) + r"\Z", re.IGNORECASE)


def _walk(folder: Path, pattern: str | None) -> list[Path]:
    rx = _glob_regex(pattern) if pattern else None
    found = []
    seen: set[str] = set()  # real folders walked: links that loop back (a/up -> ..) are followed once
    for root, dirs, files in os.walk(folder, followlinks=True):
        real = os.path.realpath(root)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.startswith("."):
                continue
            p = Path(root) / name
            rel = p.relative_to(folder).as_posix()
            if (rx.match(rel) if rx else name.lower().endswith(MESH_SUFFIXES)):
                found.append(p)
    return found


def _read_list(path: Path) -> list[Path]:
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise BatchError(f"{path}: cannot read the list file ({exc.strerror or exc})") from None
    out = []
    for n, line in enumerate(lines, 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        p = Path(line)
        p = p if p.is_absolute() else path.parent / p
        if not p.is_file():
            raise BatchError(f"{path}:{n}: {line}: no such model file")
        out.append(p)
    return out


def discover(inputs: Sequence[str | os.PathLike], glob: str | None = None, suffix: str = ".npz",
             out_dir: str | os.PathLike | None = None) -> list[Model]:
    """The models named by ``inputs`` (folders searched recursively, list files, model files), in sorted order.

    Parameters
    ----------
    inputs : folders, list files (``.txt``, ``.list``, ``.lst``) or model files.
    glob : in folders, keep the files whose path relative to the folder matches this pattern (case-insensitive;
        ``**/`` spans folders; a pattern without ``/`` matches names at any depth). Default: every file ending in
        one of :data:`MESH_SUFFIXES`. Hidden files and folders (names starting with ``.``) are skipped.
    suffix : the output suffix that replaces each model's suffix (``""``: none, e.g. a PNG-stack folder).
    out_dir : the output folder: files inside it are never models (a batch's own outputs, e.g. ``.3mf`` slice
        stacks, are not read back as inputs; when it is the input folder itself, the files its batch journal lists),
        and a model whose output would replace it is refused.

    Raises
    ------
    BatchError
        An input does not exist, nothing was found, or two models would write the same output.
    """
    if not inputs:
        raise BatchError("no inputs given")
    files: list[Path] = []
    roots: list[Path] = []
    for item in inputs:
        p = Path(os.fspath(item))
        if p.is_dir():
            roots.append(p.resolve())
            files += _walk(p, glob)
        elif p.is_file() and p.suffix.lower() in LIST_SUFFIXES:
            listed = _read_list(p)
            files += listed
            roots += [q.resolve().parent for q in listed]
        elif p.is_file():
            files.append(p)
            roots.append(p.resolve().parent)
        else:
            raise BatchError(f"{p}: no such file or folder")
    if not files:
        what = f"matching '{glob}'" if glob else f"ending in {', '.join(MESH_SUFFIXES)}"
        raise BatchError(f"{', '.join(map(str, inputs))}: no model files {what}")
    out_root = Path(os.fspath(out_dir)).resolve() if out_dir is not None else None
    if out_root is not None:  # (an output folder that is the input folder itself: only the batch's own files go)
        from .journal import read_journal, unchanged

        made = read_journal(out_root) or {}
        files = [f for f in files if not f.resolve().is_relative_to(out_root)] or \
            [f for f in files if not unchanged(out_root, [f.resolve().relative_to(out_root).as_posix()], made)]
    base = Path(os.path.commonpath([str(r) for r in roots]))
    models: dict[str, Model] = {}
    outputs: dict[str, str] = {}
    seen: set[Path] = set()
    for f in files:
        resolved = f.resolve()
        if resolved in seen:
            continue  # the same file named twice (or reached through links)
        seen.add(resolved)
        if resolved.is_relative_to(base):
            rel = resolved.relative_to(base).as_posix()
        else:  # a link to a file outside the inputs: named by the link's place, else by the file's name
            here = Path(os.path.abspath(f))
            rel = here.relative_to(base).as_posix() if here.is_relative_to(base) else resolved.name
        stem = rel[: -len(Path(rel).suffix)] if Path(rel).suffix else rel
        out = stem + suffix
        if out.lower() in outputs:
            raise BatchError(f"{f}: its output {out} clashes with that of {outputs[out.lower()]}")
        if out_root is not None and (out_root / out).resolve() == resolved:
            raise BatchError(f"{f}: its output would replace it; give another output folder")
        outputs[out.lower()] = str(f)
        models[rel] = Model(src=str(f), rel=rel, out=out, path=str(resolved))
    if not suffix:  # folder outputs (PNG stacks): a.stl's out/a/ must not hold a/b.stl's out/a/b/
        for b in sorted(outputs):
            parts = b.split("/")
            for k in range(1, len(parts)):
                a = "/".join(parts[:k])
                if a in outputs:
                    raise BatchError(f"{outputs[b]}: its output {b} would lie inside that of {outputs[a]} ({a}/)")
    return [models[k] for k in sorted(models)]
