"""Values with units on the way in, by name: ``wn=43Hz``, ``CdAleak=3.3mm^2``, ``Ffric=50N``, ``x=2um``.

The unit of a name is looked up among every model's parameters and the rig signals; the conversion is
:func:`fpdd.units.text_to_si` (pint, with ``Hz`` read as cycles per second for an angular frequency).
"""

from __future__ import annotations

import functools

from fpdd.units import SIGNAL_UNITS, text_to_si


@functools.lru_cache(maxsize=1)
def _known_units() -> dict[str, str]:
    """SI unit of every parameter name of every model, and of the signals."""
    from twin.models import MODELS, get_model

    out = dict(SIGNAL_UNITS)
    for name in MODELS:
        for s in get_model(name).kernel_specs:
            out.setdefault(s.name, s.unit)
    return out


def to_si(name: str, text: str, unit: str | None = None) -> float:
    """``text`` (a number, or a number with a unit) as a float in the SI unit of ``name``.

    ``unit``: the SI unit to convert to (default: looked up by ``name`` among the
    models' parameters and the signals).
    """
    try:
        float(text)
    except ValueError:  # a value with a unit: the models are asked for the unit of the name only then
        unit = unit or _known_units().get(name)
    return text_to_si(name, text, unit)
