"""Units by name: values with units on the way in (``wn=43Hz``, ``CdAleak=3.3mm^2``, ``Ffric=50N``, ``x=2um``),
and the display unit of a parameter or a signal of a model on the way out (:func:`param_spec`, :func:`signal_unit`,
which the estimation and the reports share).

The unit of a name is looked up among every model's parameters and the rig signals (:func:`known_units`; a
parameter's display unit: :func:`display_of`); the conversion is
:func:`fpdd.units.text_to_si` (pint, with ``Hz`` read as cycles per second for an angular frequency).
"""

from __future__ import annotations

import functools

from fpdd.units import SIGNAL_UNITS, display, text_to_si

#: quantities shown beside the logged signals, not logged themselves: (display unit, factor from SI)
DERIVED_SIGNALS: dict[str, tuple[str, float]] = {"force": display("N"), "v": display("m/s")}


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


def signal_unit(name: str, model: str | None = None) -> tuple[str, float]:
    """(display unit, factor from SI) of a logged signal of ``model``'s records
    (:func:`twin.models.records.signal_specs`: the oscillator's ``u`` is a force in N); SI and factor 1 when
    unknown."""
    from twin.models.records import signal_specs

    spec = signal_specs(model or "").get(name)
    return spec.display if spec is not None else DERIVED_SIGNALS.get(name, ("", 1.0))


@functools.cache
def _specs(model: str) -> dict:
    from twin.models import get_model

    m = get_model(model)
    out = {s.name: s for s in m.params().specs}
    for e in m.EFFECTS.values():
        for s in e.params:
            out.setdefault(s.name, s)
    return out


def param_spec(model: str | None, name: str):
    """The :class:`~twin.params.ParamSpec` of a parameter of ``model`` (effects included), or ``None``."""
    if not model:
        return None
    try:
        return _specs(model).get(name)
    except Exception:  # an unknown model name: shown in SI
        return None
