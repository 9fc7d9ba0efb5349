"""The units of the parameters an event carries: the SI unit and the display unit with its scale, over every
model's parameters."""

from __future__ import annotations

import functools


def parameter_si_unit(parameter: str) -> str:
    """The SI unit of a parameter of any model (``"1"`` if unknown)."""
    from twin.units import _known_units

    return _known_units().get(parameter, "1")


@functools.cache
def known_displays() -> dict[str, tuple[str, str, float]]:
    """Parameter name -> (SI unit, display unit, display scale) over every model's parameters."""
    from twin.models import MODELS, get_model

    out: dict[str, tuple[str, str, float]] = {}
    for name in MODELS:
        for s in get_model(name).kernel_specs:
            out.setdefault(s.name, (s.unit, s.display_unit or s.unit, float(s.display_scale)))
    return out


def display_of(parameter: str, si_unit: str) -> tuple[str, float]:
    """``(display unit, scale)`` of a parameter known to the models with this SI unit (value in the display
    unit = SI value x scale, e.g. ``("Hz", 1/(2 pi))`` for ``wn``); ``(si_unit, 1.0)`` otherwise."""
    known = known_displays().get(parameter)
    return (known[1], known[2]) if known is not None and known[0] == si_unit else (si_unit, 1.0)


def scaled(x: float | None, scale: float) -> float | None:
    return None if x is None else x * scale

