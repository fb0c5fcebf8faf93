"""JSON reports (``--report``): ``indent=1``, sorted keys, numpy values made plain, written atomically."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    pass

from .atomic import atomic_write_text

PathLike = str | os.PathLike

__all__ = ["plain", "write_report"]


def plain(obj: Any) -> Any:
    """``obj`` with numpy values, tuples, sets and paths turned into JSON's own types, recursively."""
    if isinstance(obj, Mapping):
        return {plain_key(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj]
    if isinstance(obj, set | frozenset):
        return sorted((plain(v) for v in obj), key=repr)
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj


def plain_key(key: Any) -> str:
    if isinstance(key, str):
        return key
    if isinstance(key, np.generic):
        key = key.item()
    return json.dumps(key) if isinstance(key, bool | None | float) else str(key)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def write_report(report: Mapping[str, Any], path: PathLike) -> None:
    """Write ``report`` as JSON, atomically.

    The text is ``json.dumps(report, indent=1, sort_keys=True)`` plus a final newline, UTF-8. Numpy arrays
    become (nested) lists, numpy integers/floats/bools plain ``int``/``float``/``bool``, tuples lists,
    sets sorted lists, paths strings, and dictionary keys strings (so keys of mixed types still sort).
    Non-finite floats are written as ``NaN``/``Infinity`` as Python's :mod:`json` does.

    Raises
    ------
    TypeError
        A value has no JSON form.
    """
    text = json.dumps(plain(report), indent=1, sort_keys=True, ensure_ascii=False, default=_json_default)
    atomic_write_text(path, text + "\n")

