"""Parameters with their metadata, and the named model extensions ("effects").

A :class:`ParamSpec` carries everything a fit, a filter or a report needs to
know about one parameter: SI unit, bounds, category (geometric, physical,
phenomenological, or the extension it belongs to), a one-line meaning and the
unit people read it in (``wn`` lives in rad/s and is shown in Hz), and, for
a parameter the online twin tracks, its :class:`Tracking`: the healthy band,
the expected drift rate, the physical range and the signal that excites it.
That is the one home of what the product knows of a parameter.

A :class:`ParameterSet` is an immutable, validated assignment of values to the
specs of one model with a set of switched-on effects.  It is converted to the
flat ``float64`` vector the compiled right-hand side reads by
:meth:`ParameterSet.vector`; effects that are off take their neutral values
there, so the nominal model is exactly the extended model with every effect off.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping


from fpdd.errors import ParameterError

CATEGORIES = ("geometric", "physical", "phenomenological", "extension", "initial")
#: what can excite a tracked parameter (the filter freezes it while its signal is quiet)
EXCITATION = ("rod_motion", "valve_command", "pressure_difference")


@dataclasses.dataclass(frozen=True)
class Tracking:
    """What the online twin needs of a parameter it tracks.

    ``band``: the healthy band by default, a relative half-width: ``value / (1 + band)`` to
    ``value * (1 + band)``.  ``drift_rate``: the expected drift, a random-walk intensity in log units per
    sqrt(second) (the filter's process noise on the parameter).  ``bounds``: the physical range of the
    tracked value as factors of the rig's value (the filter moves the parameter through a logit between
    them).  ``excited_by``: the signal whose excitation makes the parameter observable (:data:`EXCITATION`).
    """

    band: float
    drift_rate: float
    bounds: tuple[float, float]
    excited_by: str

    def __post_init__(self) -> None:
        if not (self.band > 0 and self.drift_rate > 0 and 0 < self.bounds[0] < 1 < self.bounds[1]):
            raise ValueError(f"tracking {self}: band and drift rate > 0, bounds (lo < 1 < hi) expected")
        if self.excited_by not in EXCITATION:
            raise ValueError(f"tracking: excited_by {self.excited_by!r} not in {EXCITATION}")


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """Metadata of one parameter (SI unit inside)."""

    name: str
    unit: str
    lo: float
    hi: float
    category: str
    meaning: str
    display_unit: str | None = None
    display_scale: float = 1.0  # value_in_display_unit = value * display_scale
    typical: float | None = None  # a physically sensible magnitude (starts, screening)
    tracking: Tracking | None = None  # what the online twin needs, for a parameter it can track

    def __post_init__(self) -> None:
        if self.category not in CATEGORIES:
            raise ValueError(f"{self.name}: category {self.category!r} not in {CATEGORIES}")
        if not self.lo <= self.hi:
            raise ValueError(f"{self.name}: bounds [{self.lo}, {self.hi}] are empty")

    @property
    def log_scaled(self) -> bool:
        """Whether a fit should move this parameter in log coordinates (wide positive range)."""
        return self.lo > 0.0 and self.hi / self.lo > 100.0

    def check(self, value: float | str) -> float:
        """Return ``value`` as float or raise a :class:`ParameterError` naming the parameter; a string may carry
        a unit (``"2000mm^2"``, ``"43Hz"``: converted to SI as ``--set`` does)."""
        if isinstance(value, str):
            from fpdd.units import text_to_si
            from twin.units import bare_number

            try:
                si = text_to_si(self.name, value, self.unit)
            except ParameterError as exc:
                reason = str(exc).removeprefix(f"{self.name}: ")
                raise ParameterError(f"{self.name} (={value!r}) must be a number in {self.unit} or a value with a "
                                     f"unit: {reason}") from None
            if _is_number(value):  # a bare number in text: refused where the display unit is not SI
                bare_number(self.name, si, unit=(self.unit, self.display_unit or self.unit, self.display_scale))
            value = si
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ParameterError(f"{self.name} (={value!r}) must be a number in {self.unit}") from None
        if not math.isfinite(v):
            raise ParameterError(f"{self.name} (={v}) must be finite, in [{self.lo:g} ... {self.hi:g}] {self.unit}")
        if not (self.lo <= v <= self.hi):
            raise ParameterError(
                f"{self.name} (={v:g} {self.unit}) must be in [{self.lo:g} ... {self.hi:g}] {self.unit}"
                f" ({self.meaning})"
            )
        return v

    def show(self, value: float) -> str:
        """``value`` in the unit people read, e.g. ``43 Hz`` for ``wn``."""
        unit = self.display_unit or self.unit
        return f"{value * self.display_scale:.6g}" + ("" if unit == "1" else f" {unit}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class Effect:
    """A named physical effect that extends a model without editing its core.

    ``params`` are the effect's own parameters; ``neutral`` their values that make
    the effect vanish (the nominal model); ``signature`` says how a residual
    looks when the effect is present but not modelled (used by the diagnosis).
    """

    name: str
    description: str
    params: tuple[ParamSpec, ...]
    neutral: tuple[float, ...]
    signature: str
    typical: tuple[float, ...]  # a plausible magnitude when present (starts and tests)
    #: free parameters that mimic the effect (to within what a record resolves) while they are fitted: the
    #: effect can be told from them only when they are held at known values (``mimicry`` says how)
    mimicked_by: tuple[str, ...] = ()
    mimicry: str = ""
    #: effects this one contains as a special case, each with the map of its parameters onto this one's (the
    #: static supply droop's resistance is the supply line's at zero compliance and inertance): the diagnosis tries
    #: this effect in place of a named special case, nested, and never the special case beside it
    generalises: tuple[tuple[str, tuple[tuple[str, str], ...]], ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)


@dataclasses.dataclass(frozen=True)
class ParameterSet:
    """Validated values of a model's parameters with a set of switched-on effects.

    Construct through :meth:`twin.models.base.Model.params`; ``values`` holds one
    value per spec of ``specs`` (base parameters first, then each active effect's).
    """

    model: str
    specs: tuple[ParamSpec, ...]
    values: tuple[float, ...]
    effects: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if len(self.specs) != len(self.values):
            raise ParameterError(f"{self.model}: {len(self.values)} values for {len(self.specs)} parameters")
        checked = tuple(s.check(v) for s, v in zip(self.specs, self.values))
        object.__setattr__(self, "values", checked)

    # --- access ------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    def spec(self, name: str) -> ParamSpec:
        for s in self.specs:
            if s.name == name:
                return s
        raise ParameterError(f"{self.model} has no parameter {name!r}; known: {', '.join(self.names)}")

    def __getitem__(self, name: str) -> float:
        return self.values[self.names.index(self.spec(name).name)]

    def __contains__(self, name: str) -> bool:
        return name in self.names

    def as_dict(self) -> dict[str, float]:
        return dict(zip(self.names, self.values))

    def replace(self, **values: float | str) -> ParameterSet:
        """A copy with some values changed (validated)."""
        return self.update(values)

    def update(self, values: Mapping[str, float | str]) -> ParameterSet:
        for k in values:
            self.spec(k)  # raises for unknown names
        new = tuple(s.check(values[s.name]) if s.name in values else v for s, v in zip(self.specs, self.values))
        return dataclasses.replace(self, values=new)

    def by_category(self, *categories: str) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs if s.category in categories)

    def changed(self) -> dict[str, float]:
        """The values that differ from the model's nominal ones (same effects): what makes this set this rig."""
        try:
            from twin.models import get_model

            nominal = get_model(self.model).params(effects=self.effects)
        except Exception:  # a model not in the registry: every value is its own
            return self.as_dict()
        return {n: v for n, v in zip(self.names, self.values) if n not in nominal or nominal[n] != v}

    def __repr__(self) -> str:
        """One line: the model, its effects and the values that differ from its nominal ones, in display units
        (``table()`` lists them all)."""
        changed = self.changed()
        shown = ", ".join(f"{n}={self.spec(n).show(v).replace(' ', '')}" for n, v in list(changed.items())[:8])
        more = f", ... {len(changed) - 8} more" if len(changed) > 8 else ""
        effects = f", effects={list(self.effects)}" if self.effects else ""
        what = f"changed: {shown}{more}" if changed else "nominal"
        return f"ParameterSet(model={self.model!r}{effects}, {what}; {len(self.values)} parameters)"

    def table(self) -> str:
        rows = [f"{'parameter':<12} {'value':>16}  {'category':<16} meaning"]
        for s, v in zip(self.specs, self.values):
            rows.append(f"{s.name:<12} {s.show(v):>16}  {s.category:<16} {s.meaning}")
        return "\n".join(rows)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def check_names(known: Iterable[str], asked: Iterable[str], what: str) -> None:
    """Raise :class:`ParameterError` if any of ``asked`` is not in ``known``."""
    known = tuple(known)
    bad = [a for a in asked if a not in known]
    if bad:
        raise ParameterError(f"unknown {what} {', '.join(map(repr, bad))}; known: {', '.join(known)}")
