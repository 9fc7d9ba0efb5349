"""Reading values out of rigs.toml tables: known keys, typed values, bounded numbers, each refusal one line
naming the table, the key and what was expected."""

from __future__ import annotations

import difflib
import math
from typing import Any

from fpdd.errors import ConfigError

__all__ = ["suggest", "unit_number"]

_TYPE_TEXT = {float: "a number", int: "an integer", str: "a string", list: "a list", dict: "a table",
              bool: "true or false"}


def suggest(key: str, known: tuple[str, ...] | list[str]) -> str:
    """`` (did you mean 'x'?)`` for the closest known key, else the list of known keys."""
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else f" (known: {', '.join(known)})"


def _check_keys(d: dict, known: tuple[str, ...], where: str) -> None:
    for key in d:
        if key not in known:
            raise ConfigError(f"{where}: unknown key {key!r}{suggest(key, known)}")


def _get(d: dict, key: str, typ, where: str, default: Any = ...) -> Any:
    """``d[key]`` of type ``typ`` (int accepted for float; numbers finite), or ``default``."""
    if key not in d:
        if default is ...:
            raise ConfigError(f"{where}: missing key {key!r}")
        return default
    v = d[key]
    if typ is float and isinstance(v, int) and not isinstance(v, bool):
        v = float(v)
    if not isinstance(v, typ) or (typ is int and isinstance(v, bool)):
        raise ConfigError(f"{where}.{key}: expected {_TYPE_TEXT.get(typ, typ.__name__)}, got {v!r}")
    if typ is float and not math.isfinite(v):
        raise ConfigError(f"{where}.{key}: expected a finite number, got {v!r}")
    return v


def _number(d: dict, key: str, where: str, default: Any = ..., *, lo: float | None = None,
            lo_open: bool = False, what: str = "") -> float:
    v = _get(d, key, float, where, default)
    if v is None or lo is None:
        return v
    if (lo_open and not v > lo) or (not lo_open and not v >= lo):
        op = ">" if lo_open else ">="
        raise ConfigError(f"{where}.{key}: must be {op} {lo:g}{what}, got {v:g}")
    return v


def unit_number(d: dict, key: str, where: str, name: str, spec=None) -> None:
    """Refuse a bare number at ``d[key]`` for a quantity whose display unit is not its SI unit (``wn``: Hz shown,
    rad/s inside): in rigs.toml such a value is a string with its unit, ``wn = "43Hz"``; the message gives both
    spellings (:func:`twin.units.bare_number`).  ``spec``: the parameter's spec when known (its declared
    display unit), else the name's among every model's parameters and the signals.  A string, a missing key
    and zero pass."""
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return
    from fpdd.errors import ParameterError
    from twin.units import bare_number

    unit = None if spec is None else (spec.unit, spec.display_unit or spec.unit, float(spec.display_scale))
    try:
        bare_number(name, float(v), unit=unit, assign=f'{key} = "{{value}}"')
    except ParameterError as exc:
        raise ConfigError(f"{where}.{key}: {exc}") from None
