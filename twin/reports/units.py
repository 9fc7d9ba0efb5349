"""Display units, the same in every report, table and axis.

Parameters are shown in their :class:`~twin.params.ParamSpec` display unit
(``wn`` in Hz, ``CdAleak`` in mm^2, ...); signals in the unit a test engineer
reads on the rig (x in mm, pressures in MPa).  A dimensionless value carries no
unit: never ``[1]``, never ``[-]``.
"""

from __future__ import annotations

import math

from fpdd.units import SIGNALS as _SIGNAL_SPECS
from twin.units import DERIVED_SIGNALS, param_spec
from twin.units import signal_unit as signal_unit  # the display unit of a signal, shared with the estimation

#: signal -> (display unit, factor from SI): the unit people read a rig's signals in (:data:`fpdd.units.DISPLAY`,
#: a factor only: the oil temperature stays in kelvin, as a degree Celsius needs an offset)
SIGNALS: dict[str, tuple[str, float]] = {**{n: s.display for n, s in _SIGNAL_SPECS.items()}, **DERIVED_SIGNALS}

DIMENSIONLESS = ("1", "", "-", None)


def pretty_unit(unit: str | None) -> str:
    """``mm^2`` -> ``mm²``, ``m^3/(s Pa)`` -> ``m³/(s Pa)``; dimensionless -> ``""``."""
    if unit in DIMENSIONLESS:
        return ""
    return (unit.replace("^2", "²").replace("^3", "³").replace("^-1", "⁻¹").replace("um", "µm")
            .replace("deg", "°"))


def label(name: str, unit: str | None) -> str:
    """An axis label: ``x [mm]``, or just ``zeta`` for a dimensionless quantity."""
    u = pretty_unit(unit)
    return f"{name} [{u}]" if u else name


class Shown:
    """How one parameter is shown: display unit and scale (from its spec, else the SI unit given)."""

    def __init__(self, name: str, model: str | None = None, si_unit: str | None = None, spec=None) -> None:
        spec = spec if spec is not None else param_spec(model, name)
        self.name = name
        self.si_unit = spec.unit if spec is not None else (si_unit or "")
        self.unit = (spec.display_unit or spec.unit) if spec is not None else (si_unit or "")
        self.scale = float(spec.display_scale) if spec is not None else 1.0

    def __call__(self, value_si: float | None) -> float | None:
        """``value_si`` in the display unit (``None`` stays ``None``)."""
        if value_si is None:
            return None
        return float(value_si) * self.scale

    @property
    def label(self) -> str:
        return label(self.name, self.unit)

    @property
    def unit_text(self) -> str:
        return pretty_unit(self.unit)

    def text(self, value_si: float | None, digits: int = 6, unit: bool = True) -> str:
        """The value in the display unit, e.g. ``43.0051 Hz`` (``n/a`` when missing or not finite)."""
        if value_si is None or not math.isfinite(float(value_si)):
            return "n/a"
        v = self(value_si)
        u = self.unit_text
        return fmt(v, digits) + (f" {u}" if unit and u else "")


def fmt(v: float | None, digits: int = 6) -> str:
    """A number for a table: ``n/a`` for missing or non-finite values, else ``{:.{digits}g}``."""
    if v is None:
        return "n/a"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    if not math.isfinite(f):
        return "n/a"
    return f"{f:.{digits}g}"


def pct(v: float | None, digits: int = 4) -> str:
    """A percentage for a table (``n/a`` when missing)."""
    t = fmt(v, digits)
    return t if t == "n/a" else f"{t} %"
