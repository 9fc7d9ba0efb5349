"""Values with units on the way in, by name: ``wn=43Hz``, ``CdAleak=3.3mm^2``, ``Ffric=50N``, ``x=2um``.

The unit of a name is looked up among every model's parameters and the rig signals (:func:`known_units`; a
parameter's display unit: :func:`display_of`); the conversion is
:func:`fpdd.units.text_to_si` (pint, with ``Hz`` read as cycles per second for an angular frequency).
"""

from __future__ import annotations

import functools

from fpdd.units import SIGNAL_UNITS, text_to_si


@functools.cache
def parameter_units() -> dict[str, tuple[str, str, float]]:
    """Parameter name -> (SI unit, display unit, display scale) over every model's parameters (the first model
    that names it wins)."""
    from twin.models import MODELS, get_model

    out: dict[str, tuple[str, str, float]] = {}
    for name in MODELS:
        for s in get_model(name).kernel_specs:
            out.setdefault(s.name, (s.unit, s.display_unit or s.unit, float(s.display_scale)))
    return out


@functools.cache
def known_units() -> dict[str, str]:
    """SI unit of every signal, and of every parameter name of every model."""
    out = dict(SIGNAL_UNITS)
    for name, (si, _, _) in parameter_units().items():
        out.setdefault(name, si)
    return out


def display_of(parameter: str, si_unit: str) -> tuple[str, float]:
    """``(display unit, scale)`` of a parameter known to the models with this SI unit (value in the display
    unit = SI value x scale, e.g. ``("Hz", 1/(2 pi))`` for ``wn``); ``(si_unit, 1.0)`` otherwise."""
    known = parameter_units().get(parameter)
    return (known[1], known[2]) if known is not None and known[0] == si_unit else (si_unit, 1.0)


def to_si(name: str, text: str, unit: str | None = None) -> float:
    """``text`` (a number, or a number with a unit) as a float in the SI unit of ``name``.

    ``unit``: the SI unit to convert to (default: looked up by ``name`` among the
    models' parameters and the signals).
    """
    try:
        float(text)
    except ValueError:  # a value with a unit: the models are asked for the unit of the name only then
        unit = unit or known_units().get(name)
    return text_to_si(name, text, unit)
