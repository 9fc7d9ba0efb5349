"""Strict JSON, one writer for every output of the project: MCAP payloads, ``--json``, ``--save``, reports.

Strict means what RFC 8259 allows: no ``NaN`` or ``Infinity`` (they become ``null``), numpy scalars and
arrays as plain numbers and lists.  An unwritable file is a one-line :class:`~fpdd.errors.DataError` naming
it, never a traceback.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from fpdd.errors import DataError

__all__ = ["default", "finite_or_none", "dumps", "compact", "write"]


def default(obj: Any) -> Any:
    """``json`` fallback: numpy arrays as lists, numpy scalars as Python numbers."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def finite_or_none(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None, recursively (strict JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {k: finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_none(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_or_none(obj.tolist())
    if isinstance(obj, np.generic):
        return finite_or_none(obj.item())
    return obj


def dumps(obj: Any, indent: int | None = 2, sort_keys: bool = False) -> str:
    """Strict JSON text of ``obj`` (indented for people by default)."""
    seps = None if indent is not None else (",", ":")
    try:
        return json.dumps(obj, indent=indent, separators=seps, sort_keys=sort_keys, allow_nan=False, default=default)
    except ValueError:  # a NaN or an infinity somewhere: the slow path only then
        return json.dumps(finite_or_none(obj), indent=indent, separators=seps, sort_keys=sort_keys,
                          allow_nan=False, default=default)


def compact(obj: Any, sort_keys: bool = False) -> bytes:
    """Compact strict JSON bytes (payloads on the bus and in MCAP)."""
    return dumps(obj, indent=None, sort_keys=sort_keys).encode()


def write(path: str | os.PathLike, obj: Any) -> str:
    """Write ``obj`` as strict, indented JSON to ``path``; returns the path.  An unwritable path is a one-line
    :class:`DataError` naming the file."""
    text = dumps(obj)
    try:
        with open(path, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    except OSError as exc:
        raise DataError(f"{os.fspath(path)}: cannot write ({exc.strerror or exc})") from None
    return os.fspath(path)
