"""Units, one home: the rig signals (SI unit, range, nominal sensor noise), the foreign units a log may
carry, the display unit people read each SI unit in, and values with units on the way in.

The product's convention: inside and in machine outputs (JSON, MCAP, Zenoh) everything is SI with the unit
named beside the value; human outputs show a signal in the display unit of its SI unit (:data:`DISPLAY`:
x in mm, pressures in MPa) and a parameter in the display unit of its spec; inputs accept a number with any
unit of the right dimension (:func:`text_to_si`, through pint), and a bare number means SI.

A display unit converts by a factor only, never an offset, because the same unit labels differences
(residuals, noise levels, RMS errors), where an offset would be wrong: the oil temperature reads in kelvin.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re

import numpy as np

from fpdd.errors import DataError, ParameterError

# --- foreign units of logged values ------------------------------------------------------------

#: unit -> (factor, offset, SI unit): ``si = value * factor + offset`` (the units a log's column or a DBC
#: signal may be in; converted to SI at the one boundary where a reader takes them in)
UNITS: dict[str, tuple[float, float, str]] = {
    "m": (1.0, 0.0, "m"),
    "mm": (1e-3, 0.0, "m"),
    "um": (1e-6, 0.0, "m"),
    "µm": (1e-6, 0.0, "m"),
    "Pa": (1.0, 0.0, "Pa"),
    "kPa": (1e3, 0.0, "Pa"),
    "bar": (1e5, 0.0, "Pa"),
    "MPa": (1e6, 0.0, "Pa"),
    "mbar": (1e2, 0.0, "Pa"),
    "psi": (6894.757293168361, 0.0, "Pa"),
    "V": (1.0, 0.0, "V"),
    "mV": (1e-3, 0.0, "V"),
    "N": (1.0, 0.0, "N"),
    "kN": (1e3, 0.0, "N"),
    "K": (1.0, 0.0, "K"),
    "degC": (1.0, 273.15, "K"),
    "°C": (1.0, 273.15, "K"),
    # time, for a foreign time column only
    "s": (1.0, 0.0, "s"),
    "ms": (1e-3, 0.0, "s"),
    "us": (1e-6, 0.0, "s"),
    "ns": (1e-9, 0.0, "s"),
}


def to_si(values: np.ndarray, unit: str, *, what: str = "value") -> np.ndarray:
    """Convert ``values`` given in ``unit`` (a key of :data:`UNITS`) to SI, float64."""
    try:
        factor, offset, _ = UNITS[unit]
    except KeyError:
        raise DataError(f"{what}: unknown unit {unit!r}, known units: {', '.join(UNITS)}") from None
    out = np.asarray(values, dtype=np.float64)
    if factor != 1.0:
        out = out * factor
    if offset != 0.0:
        out = out + offset
    return out


def si_unit(unit: str, *, what: str = "value") -> str:
    """The SI unit a unit of :data:`UNITS` converts to (``"bar"`` -> ``"Pa"``)."""
    try:
        return UNITS[unit][2]
    except KeyError:
        raise DataError(f"{what}: unknown unit {unit!r}, known units: {', '.join(UNITS)}") from None


# --- display units -----------------------------------------------------------------------------

#: SI unit -> (display unit, factor from SI): the unit a test engineer reads a rig quantity in
DISPLAY: dict[str, tuple[str, float]] = {
    "m": ("mm", 1e3), "m/s": ("mm/s", 1e3), "Pa": ("MPa", 1e-6), "K": ("K", 1.0), "V": ("V", 1.0),
    "N": ("N", 1.0), "s": ("s", 1.0),
}


def display(si: str) -> tuple[str, float]:
    """(display unit, factor from SI) of a quantity in SI unit ``si`` (``si`` itself and 1 when it has none)."""
    return DISPLAY.get(si, (si, 1.0))


# --- the rig signals ---------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class SignalSpec:
    """One rig signal: SI unit, plausible physical range in that unit, meaning, nominal sensor noise.

    ``accepts``: other SI units a column mapped onto this signal may be in (``"*"``: any,
    a generic signal such as the oscillator's ``y``); the value is converted to that
    unit's SI unit and kept in it.  ``noise``: the nominal standard deviation of its sensor's
    noise in the SI unit (what a simulation adds and what the tracker assumes when told nothing
    else); ``None`` for a signal without a nominal sensor.
    """

    name: str
    unit: str
    lo: float
    hi: float
    meaning: str
    accepts: tuple[str, ...] = ()
    noise: float | None = None

    def takes(self, si: str) -> bool:
        """True when a column in SI unit ``si`` may be mapped onto this signal."""
        return si == self.unit or si in self.accepts or "*" in self.accepts

    @property
    def display(self) -> tuple[str, float]:
        """(display unit, factor from SI)."""
        return display(self.unit)


#: The signal names every reader recognises, SI units: the readers' common vocabulary.  A model declares its own
#: signals (role, unit, range: ``twin.models.base.Model.SIGNALS``), and the records of a model are read and
#: checked against its table over this one (``twin.models.records.signal_specs``).
SIGNALS: dict[str, SignalSpec] = {
    s.name: s
    for s in (
        SignalSpec("x_ref", "m", -0.5, 0.5, "demanded rod displacement", noise=0.0),
        SignalSpec("u", "V", -15.0, 15.0, "controller output (servo-valve voltage)", noise=0.0),
        SignalSpec("x", "m", -0.5, 0.5, "measured rod displacement (LVDT)", noise=2e-6),
        SignalSpec("pA", "Pa", -1.0e6, 60.0e6, "pressure in chamber A", noise=2e4),
        SignalSpec("pB", "Pa", -1.0e6, 60.0e6, "pressure in chamber B", noise=2e4),
        SignalSpec("F", "N", -1.0e6, 1.0e6, "rod force (load cell)"),
        SignalSpec("T_oil", "K", 233.15, 423.15, "oil temperature"),
        SignalSpec("pP", "Pa", -1.0e6, 60.0e6, "supply pressure"),
        # a generic measured output (a displacement, or any quantity: volts of a circuit)
        SignalSpec("y", "m", -10.0, 10.0, "measured output (displacement, or any quantity: volts "
                   "of a circuit)", accepts=("*",), noise=1e-6),
    )
}

#: The signals a rig record normally carries (any may be missing).
RIG_SIGNALS: tuple[str, ...] = ("x_ref", "u", "x", "pA", "pB")

#: signal -> SI unit
SIGNAL_UNITS: dict[str, str] = {n: s.unit for n, s in SIGNALS.items()}

#: signal -> nominal standard deviation of its sensor's noise (SI): what a simulation adds by default and
#: what the online tracker assumes when neither the configuration nor a commissioning fit says otherwise
NOMINAL_NOISE: dict[str, float] = {n: s.noise for n, s in SIGNALS.items() if s.noise is not None}


# --- values with units on the way in -----------------------------------------------------------

@functools.lru_cache(maxsize=1)
def _registry():
    import pint

    return pint.UnitRegistry()


def text_to_si(name: str, text: str, unit: str | None) -> float:
    """``text`` (a number, or a number with a unit: ``43Hz``, ``3.3mm^2``, ``2um``) as a float in SI ``unit``.

    A bare number is SI.  pint (rightly, for it) treats ``Hz`` as ``1/s``, so ``43 Hz`` would become
    ``43 rad/s``: an angular frequency given in a unit without an angle (Hz, kHz) is read as cycles per
    second, ``2 pi 43 rad/s``.  pint is imported only when a value carries a unit.

    :param name: what the value is (in messages).
    :param unit: the SI unit to convert to; ``None``: only a bare number is accepted.
    :raises ParameterError: one line naming ``name``, the text and the unit expected.
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
    if unit is None:
        raise ParameterError(f"{name}: {text!r} is not a number, and {name!r} has no known unit to convert to")
    fast = _prefixed(text, unit)
    if fast is not None:
        return fast
    import pint

    ureg = _registry()
    try:
        text = text.replace("²", "^2").replace("³", "^3").replace("µ", "u")
        m = _NUMBER_UNIT.match(text)
        if m and unit == "K":  # a temperature: an offset unit (degC, degF) is a number and its unit, never a product
            u = m.group(2).strip()
            q = ureg.Quantity(float(m.group(1)), "degC" if u in ("C", "°C") else "degF" if u in ("F", "°F") else u)
        else:
            q = ureg.Quantity(text)
        si = ureg.Unit("dimensionless" if unit == "1" else unit)
        if (str(si) == "radian / second" and q.check("1/[time]")
                and not any(a in str(q.units) for a in ("radian", "revolution", "degree", "turn"))):
            value = float(q.to("Hz").magnitude) * 2.0 * math.pi  # Hz: cycles per second
        else:
            value = float(q.to(si).magnitude)
    except pint.errors.DimensionalityError:
        raise ParameterError(f"{name}: {text!r} is not in a unit of {unit} "
                             f"(expected e.g. {_example(unit)})") from None
    except (pint.errors.PintError, ValueError, TypeError, AttributeError, AssertionError):
        raise ParameterError(f"{name}: cannot read {text!r} as a value with a unit "
                             f"(expected e.g. {_example(unit)})") from None
    if not math.isfinite(value):
        raise ParameterError(f"{name}: {text!r} is not a finite value")
    return value


_NUMBER_UNIT = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*([^\d\s].*)$")

#: the SI prefixes read without pint (``u`` and ``µ`` for micro)
_PREFIX = {"": 1.0, "G": 1e9, "M": 1e6, "k": 1e3, "c": 1e-2, "m": 1e-3, "u": 1e-6, "n": 1e-9}
_SIMPLE_UNIT = re.compile(r"^([A-Za-z]+)(?:(?:\^|\*\*)([1-9]))?$")


def _prefixed(text: str, unit: str) -> float | None:
    """A number with the SI unit itself or a prefixed one (``0.0098589mm^2`` for ``m^2``, ``20kPa`` for ``Pa``,
    ``43Hz`` for ``rad/s``, cycles per second) without importing pint (about a second of a command's start); any
    other text: ``None``, for pint."""
    m = _NUMBER_UNIT.match(text.replace("²", "^2").replace("³", "^3").replace("µ", "u"))
    if m is None:
        return None
    value, given = float(m.group(1)), m.group(2).strip()
    if unit == "rad/s":
        if given == "rad/s":
            return value
        for p, f in _PREFIX.items():
            if given == p + "Hz":
                return value * f * 2.0 * math.pi
        return None
    target, g = _SIMPLE_UNIT.match(unit), _SIMPLE_UNIT.match(given)
    if target is None or g is None or unit == "K" or (g.group(2) or "1") != (target.group(2) or "1"):
        return None
    base, head = target.group(1), g.group(1)
    if not head.endswith(base) or head[: len(head) - len(base)] not in _PREFIX:
        return None
    return value * _PREFIX[head[: len(head) - len(base)]] ** int(target.group(2) or 1)


def _example(unit: str) -> str:
    return {"rad/s": "43Hz or 270rad/s", "m^2": "3.3mm^2", "N": "50N", "m": "2um", "Pa": "20kPa",
            "K": "313.15K or 40degC", "1": "a plain number"}.get(unit, f"1{unit.replace(' ', '*')}")
