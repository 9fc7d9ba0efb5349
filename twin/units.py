"""Values with units on the way in: ``wn=43Hz``, ``CdAleak=3.3mm^2``, ``Ffric=50N``, ``x=2um``.

The product's convention: inside and in machine outputs (JSON, MCAP, Zenoh)
everything is SI with the unit named beside the value; human outputs show each
parameter in its display unit (``twin params``); inputs accept a number with
any unit of the right dimension, converted by pint, and a bare number means SI.

One trap is handled explicitly: pint (rightly, for it) treats ``Hz`` as ``1/s``,
so ``43 Hz`` would become ``43 rad/s``.  An angular frequency given in a unit
without an angle (Hz, kHz) is read as cycles per second: ``43 Hz`` is
``2 pi 43 rad/s``.  pint is imported only when a value carries a unit.
"""

from __future__ import annotations

import functools
import math

from fpdd.errors import ParameterError

#: SI units of the logged signals (noise levels, quantisation steps)
SIGNAL_UNITS = {"x": "m", "x_ref": "m", "y": "m", "pA": "Pa", "pB": "Pa", "u": "V"}


@functools.lru_cache(maxsize=1)
def _registry():
    import pint

    return pint.UnitRegistry()


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
    text = text.strip()
    try:
        value = float(text)
    except ValueError:
        pass
    else:
        if not math.isfinite(value):
            raise ParameterError(f"{name}: {text!r} is not a finite number")
        return value
    target = unit or _known_units().get(name)
    if target is None:
        raise ParameterError(f"{name}: {text!r} is not a number, and {name!r} has no known unit to convert to")
    import pint

    ureg = _registry()
    try:
        q = ureg.Quantity(text.replace("²", "^2").replace("³", "^3").replace("µ", "u"))
        si = ureg.Unit("dimensionless" if target == "1" else target)
        if (str(si) == "radian / second" and q.check("1/[time]")
                and not any(a in str(q.units) for a in ("radian", "revolution", "degree", "turn"))):
            value = float(q.to("Hz").magnitude) * 2.0 * math.pi  # Hz: cycles per second
        else:
            value = float(q.to(si).magnitude)
    except pint.errors.DimensionalityError:
        raise ParameterError(f"{name}: {text!r} is not in a unit of {target} "
                             f"(expected e.g. {_example(target)})") from None
    except (pint.errors.PintError, ValueError, TypeError, AttributeError, AssertionError):
        raise ParameterError(f"{name}: cannot read {text!r} as a value with a unit "
                             f"(expected e.g. {_example(target)})") from None
    if not math.isfinite(value):
        raise ParameterError(f"{name}: {text!r} is not a finite value")
    return value


def _example(unit: str) -> str:
    return {"rad/s": "43Hz or 270rad/s", "m^2": "3.3mm^2", "N": "50N", "m": "2um", "Pa": "20kPa",
            "1": "a plain number"}.get(unit, f"1{unit.replace(' ', '*')}")
