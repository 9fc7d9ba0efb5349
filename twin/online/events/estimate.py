"""Parameter estimates (:class:`EstimateEvent`, :class:`ParamEstimate`) and :class:`EstimateEncoder`, the service's
fast path that writes the very text of an estimate's JSON from the tracker's numbers."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any, ClassVar, Self

from fpdd.errors import DataError
from twin.online.events.schema import (INT64_MAX, NAME_PATTERN, RIG_PATTERN, STATUS_PATTERN, FromJson, check, num,
                                       validate)
from twin.units import display_of


def _scaled(x: float | None, scale: float) -> float | None:
    return None if x is None else x * scale


_PARAM_ESTIMATE_SCHEMA: dict[str, Any] = {
    "type": "object",
    "required": ["value", "std", "unit"],
    "properties": {
        "value": num("estimate in the SI unit given by 'unit'"),
        "std": num("standard deviation of the estimate's error while the parameter holds still, same unit",
                    minimum=0),
        "unit": {"type": "string", "description": "SI unit of every number of the parameter, e.g. 'N', "
                                                  "'m^3/(s*Pa)', '1', 'rad/s'"},
        "lo95": num("lower end of the 95 % interval, same unit (log-normal for a positive value: "
                     "value*exp(-1.96 std/value), else value - 1.96 std)"),
        "hi95": num("upper end of the 95 % interval, same unit"),
        "band_lo": {"type": ["number", "null"], "description": "lower edge of the healthy band, same unit "
                                                               "(null: no band)"},
        "band_hi": {"type": ["number", "null"], "description": "upper edge of the healthy band, same unit"},
        "baseline": {"type": ["number", "null"], "description": "healthy baseline value, same unit"},
        "display": {
            "type": "object",
            "required": ["unit", "value", "lo95", "hi95"],
            "description": "the same numbers in the display unit people read (twin params: wn in Hz, CdAleak in "
                           "mm^2): SI value x the parameter's display scale; null stays null",
            "properties": {
                "unit": {"type": "string", "description": "display unit, e.g. 'Hz', 'mm^2', '1'"},
                "value": num("estimate, display unit"),
                "lo95": num("lower end of the 95 % interval, display unit"),
                "hi95": num("upper end of the 95 % interval, display unit"),
                "band_lo": {"type": ["number", "null"], "description": "lower edge of the healthy band, display unit"},
                "band_hi": {"type": ["number", "null"], "description": "upper edge of the healthy band, display unit"},
                "baseline": {"type": ["number", "null"], "description": "healthy baseline value, display unit"},
            },
        },
    },
}

Z95 = 1.959963984540054
"""The two-sided 95 % quantile of the standard normal."""


def interval95(value: float, std: float) -> tuple[float, float]:
    """The 95 % interval of an estimate: log-normal for a positive value (the tracker works in log coordinates),
    ``value*exp(+-1.96 std/value)``; symmetric ``value +- 1.96 std`` otherwise (and for std > 25 value)."""
    if value > 0 and std <= 25.0 * value:  # beyond, exp(1.96 std/value) says nothing and overflows soon
        rel = Z95 * std / value
        return value * math.exp(-rel), value * math.exp(rel)
    return value - Z95 * std, value + Z95 * std


def _band(band: Any) -> tuple[float | None, float | None, float | None]:
    """``(lo, hi, baseline)`` of a band given as a Baseline, ``(lo, hi)``, ``(lo, hi, baseline)`` or ``None``."""
    if band is None:
        return None, None, None
    if hasattr(band, "lo"):
        return float(band.lo), float(band.hi), float(band.value)
    lo, hi, *rest = band
    return (None if lo is None else float(lo), None if hi is None else float(hi),
            float(rest[0]) if rest and rest[0] is not None else None)


_ESTIMATE_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "fpdd-twin/estimate-event.schema.json",
    "title": "EstimateEvent",
    "description": "The tracked parameters of one rig at one instant (key fpdd/<rig>/estimate).",
    "type": "object",
    "required": ["rig", "t_ns", "t_s", "params", "nis", "status"],
    "properties": {
        "rig": {"type": "string", "pattern": RIG_PATTERN},
        "t_ns": {"type": "integer", "minimum": 0, "maximum": INT64_MAX, "description": "ingest time [ns]"},
        "t_s": num("time from the start of the record [s]"),
        "params": {
            "type": "object",
            "propertyNames": {"pattern": NAME_PATTERN},
            "additionalProperties": _PARAM_ESTIMATE_SCHEMA,
            "description": "parameter name -> {value, std, lo95, hi95, band_lo, band_hi, baseline, unit} (SI) "
                           "and display {unit, value, lo95, hi95, band_lo, band_hi, baseline} (display unit)",
        },
        "nis": {"type": ["number", "null"], "minimum": 0, "description": "normalised innovation squared of this step, null before the first update"},
        "status": {"type": "string", "pattern": STATUS_PATTERN, "description": "filter status: ok, gated, repaired_covariance, stale_input, ..."},
        "term": {"type": "integer", "minimum": 1, "maximum": INT64_MAX,
                 "description": "optional: the ownership term of the service that published it (fencing: a "
                                "later owner has a larger term; two terms at once: a split network)"},
    },
}


@dataclass(frozen=True, slots=True)
class ParamEstimate:
    """One tracked parameter: value and standard deviation in SI ``unit``, and the rig's healthy band
    (``band_lo``, ``band_hi``, ``baseline``; ``None`` when the twin has none). Its 95 % interval is
    :func:`interval95` of value and std (:attr:`lo95`, :attr:`hi95`). ``display_unit`` and ``display_scale``
    (default: the parameter's own, :func:`display_of`) give the ``display`` copy of the numbers."""

    value: float
    std: float
    unit: str
    band_lo: float | None = None
    band_hi: float | None = None
    baseline: float | None = None
    name: str = field(default="", compare=False)
    display_unit: str = ""
    display_scale: float = 1.0

    def __post_init__(self) -> None:
        if not self.display_unit:
            du, sc = display_of(self.name, self.unit) if self.name else (self.unit, 1.0)
            object.__setattr__(self, "display_unit", du)
            object.__setattr__(self, "display_scale", sc)
        check("ParamEstimate", _PARAM_ESTIMATE_SCHEMA, self.to_dict())

    @property
    def lo95(self) -> float:
        return interval95(self.value, self.std)[0]

    @property
    def hi95(self) -> float:
        return interval95(self.value, self.std)[1]

    def to_dict(self) -> dict[str, Any]:
        """``{"value", "std", "lo95", "hi95", "band_lo", "band_hi", "baseline", "unit"}`` (SI, ``unit`` names it)
        and ``display``: ``{"unit", "value", "lo95", "hi95", "band_lo", "band_hi", "baseline"}`` in the display
        unit (SI x ``display_scale``)."""
        lo, hi = interval95(self.value, self.std)
        k = self.display_scale
        return {"value": self.value, "std": self.std, "lo95": lo, "hi95": hi, "band_lo": self.band_lo,
                "band_hi": self.band_hi, "baseline": self.baseline, "unit": self.unit,
                "display": {"unit": self.display_unit, "value": self.value * k, "lo95": lo * k, "hi95": hi * k,
                            "band_lo": _scaled(self.band_lo, k), "band_hi": _scaled(self.band_hi, k),
                            "baseline": _scaled(self.baseline, k)}}


@dataclass(frozen=True, slots=True)
class EstimateEvent(FromJson):
    """The parameter estimates of one rig at one instant.

    :ivar rig: rig id.
    :ivar t_ns: ingest time [ns].
    :ivar t_s: time from the start of the record [s].
    :ivar params: parameter name -> :class:`ParamEstimate` (read-only mapping;
        plain ``{"value", "std", "unit"}`` dicts, with ``band_lo``, ``band_hi``, ``baseline`` if known, are
        accepted and converted; ``lo95``/``hi95`` and the ``display`` numbers in them are ignored: they follow
        from value, std and the display unit).
    :ivar nis: normalised innovation squared of the step, ``None`` before the first update.
    :ivar status: filter status (``ok``, ``gated``, ``repaired_covariance``, ``stale_input``, ...).
    """

    rig: str
    t_ns: int
    t_s: float
    params: Mapping[str, ParamEstimate]
    nis: float | None = None
    status: str = "ok"

    SCHEMA: ClassVar[dict[str, Any]] = _ESTIMATE_SCHEMA

    def __post_init__(self) -> None:
        if not isinstance(self.params, Mapping):
            raise DataError(f"EstimateEvent.params: {self.params!r} must be an object")
        converted: dict[str, ParamEstimate] = {}
        for name, item in self.params.items():
            if isinstance(item, ParamEstimate):
                converted[name] = item
            elif isinstance(item, Mapping):
                validate(item, _PARAM_ESTIMATE_SCHEMA, f"EstimateEvent.params.{name}")
                du, sc = _display_of_dict(name, item)
                converted[name] = ParamEstimate(item["value"], item["std"], item["unit"], item.get("band_lo"),
                                                item.get("band_hi"), item.get("baseline"), name, du, sc)
            else:
                raise DataError(f"EstimateEvent.params.{name}: {item!r} must be an object")
        object.__setattr__(self, "params", MappingProxyType(converted))
        check("EstimateEvent", self.SCHEMA, self.to_dict())

    @classmethod
    def of_tracker(cls, rig: str, t_ns: int, t_s: float, names: tuple[str, ...], values, stds,
                   units: tuple[str, ...], nis: float | None, status: str, bands: Mapping | None = None,
                   displays: tuple[tuple[str, float], ...] | None = None) -> Self:
        """An estimate from the tracker's arrays, built without the schema walk when every number is finite.

        ``bands``: parameter name -> its healthy band (a Baseline, ``(lo, hi)`` or ``(lo, hi, baseline)``, SI).
        ``displays``: per parameter ``(display unit, scale)`` (the tracker's ``displays``; default
        :func:`display_of`).

        The service builds one per published estimate of every rig (20 per
        second per rig by default); the full validation of ``__init__`` is kept
        for anything unusual (a non-finite value, a negative std), which then
        raises as usual.
        """
        vals = [float(v) for v in values]
        sds = [float(v) for v in stds]
        bs = [_band((bands or {}).get(n)) for n in names]
        ds = tuple(displays) if displays is not None else tuple(display_of(n, u) for n, u in zip(names, units))
        if (not all(math.isfinite(v) for v in vals) or not all(math.isfinite(v) and v >= 0 for v in sds)
                or not 0 <= t_ns <= INT64_MAX or not math.isfinite(t_s)
                or (nis is not None and not (math.isfinite(nis) and nis >= 0))):
            plain: dict[str, Any] = {}
            for n, v, sd, u, b, d in zip(names, vals, sds, units, bs, ds):
                item = {"value": v, "std": sd, "unit": u, "band_lo": b[0], "band_hi": b[1], "baseline": b[2]}
                validate(item, _PARAM_ESTIMATE_SCHEMA, f"EstimateEvent.params.{n}")  # named as the event would
                plain[n] = ParamEstimate(v, sd, u, b[0], b[1], b[2], n, d[0], d[1])
            return cls(rig, t_ns, t_s, plain, nis, status)
        ev = object.__new__(cls)
        params = {}
        for n, v, sd, u, b, d in zip(names, vals, sds, units, bs, ds):
            p = object.__new__(ParamEstimate)
            for field_name, x in (("value", v), ("std", sd), ("unit", u), ("band_lo", b[0]), ("band_hi", b[1]),
                                  ("baseline", b[2]), ("name", n), ("display_unit", d[0]),
                                  ("display_scale", float(d[1]))):
                object.__setattr__(p, field_name, x)
            params[n] = p
        for name, value in (("rig", rig), ("t_ns", int(t_ns)), ("t_s", float(t_s)),
                            ("params", MappingProxyType(params)), ("nis", nis), ("status", status)):
            object.__setattr__(ev, name, value)
        return ev

    def to_dict(self) -> dict[str, Any]:
        """The event as a JSON-ready dict (the payload of ``fpdd/<rig>/estimate``)."""
        return {
            "rig": self.rig,
            "t_ns": self.t_ns,
            "t_s": self.t_s,
            "params": {name: p.to_dict() for name, p in self.params.items()},
            "nis": self.nis,
            "status": self.status,
        }

    def with_bands(self, bands: Mapping) -> Self:
        """A copy whose parameters without a band take theirs from ``bands`` (name -> Baseline or
        ``(lo, hi[, baseline])``, SI)."""
        params = {}
        for name, p in self.params.items():
            b = _band(bands.get(name)) if p.band_lo is None and p.band_hi is None else None
            params[name] = replace(p, band_lo=b[0], band_hi=b[1], baseline=b[2]) if b and b[0] is not None else p
        return replace(self, params=params)


def _display_of_dict(name: str, item: Mapping[str, Any]) -> tuple[str, float]:
    """``(display unit, scale)`` of a parameter's dict: its ``display.unit`` with the parameter's own scale for
    that unit (1 for the SI unit; else the ratio of the dict's display value to its value); the parameter's
    own (:func:`display_of`) when the dict has none."""
    own = display_of(name, item["unit"])
    d = item.get("display")
    if not isinstance(d, Mapping) or not isinstance(d.get("unit"), str) or not d["unit"]:
        return own
    unit = d["unit"]
    if unit == own[0]:
        return own
    if unit == item["unit"]:
        return unit, 1.0
    v, dv = item["value"], d.get("value")
    if isinstance(dv, (int, float)) and not isinstance(dv, bool) and math.isfinite(dv) and v != 0:
        return unit, float(dv) / float(v)
    return unit, 1.0


def _json_number(x: float | None) -> str:
    """A number as ``json.dumps`` of a finite float writes it; ``null`` for ``None`` or non-finite."""
    return "null" if x is None or not math.isfinite(x) else repr(float(x))


class EstimateEncoder:
    """The ``EstimateEvent`` payload of one rig's tracker written straight from its numbers: the very text of
    ``event_to_json(EstimateEvent.of_tracker(rig, ..., bands=bands))`` (sorted keys, compact, floats by
    ``repr``, intervals and bands included) without building the event, for the service's hot path."""

    def __init__(self, rig: str, names: tuple[str, ...], units: tuple[str, ...], bands: Mapping | None = None,
                 displays: tuple[tuple[str, float], ...] | None = None):
        """``displays``: per parameter ``(display unit, scale)`` as :meth:`EstimateEvent.of_tracker` takes them."""
        import json

        def text(v: str) -> str:  # a JSON string constant inside a %-format
            return json.dumps(v).replace("%", "%%")

        self.names = tuple(names)
        self._order = sorted(range(len(names)), key=lambda j: names[j])
        ds = tuple(displays) if displays is not None else tuple(display_of(n, u) for n, u in zip(names, units))
        self._scales = [float(ds[j][1]) for j in self._order]
        parts = []
        for j in self._order:
            lo, hi, base = _band((bands or {}).get(names[j]))
            k = float(ds[j][1])
            shown = (f'"display":{{"band_hi":{_json_number(_scaled(hi, k))},"band_lo":{_json_number(_scaled(lo, k))},'
                     f'"baseline":{_json_number(_scaled(base, k))},"hi95":%r,"lo95":%r,"unit":{text(ds[j][0])},'
                     '"value":%r}')
            parts.append(f'{text(names[j])}:{{"band_hi":{_json_number(hi)},"band_lo":{_json_number(lo)},'
                         f'"baseline":{_json_number(base)},{shown},"hi95":%r,"lo95":%r,"std":%r,'
                         f'"unit":{text(units[j])},"value":%r}}')
        self._fmt = ('{"nis":%s,"params":{' + ",".join(parts)
                     + f'}},"rig":{text(rig)},"status":"%s","t_ns":%d,"t_s":%r}}')

    def __call__(self, t_ns: int, t_s: float, values, stds, nis: float, status: str) -> str | None:
        """The payload; ``None`` for anything the schema checks would refuse (the event path then runs)."""
        vals = values.tolist() if hasattr(values, "tolist") else list(values)
        sds = stds.tolist() if hasattr(stds, "tolist") else list(stds)
        if not (all(map(math.isfinite, vals)) and all(math.isfinite(v) and v >= 0 for v in sds) and t_ns >= 0
                and math.isfinite(t_s) and not nis < 0):
            return None
        nums: list[Any] = ["null" if not math.isfinite(nis) else repr(nis)]
        for j, k in zip(self._order, self._scales):
            lo, hi = interval95(vals[j], sds[j])
            v = vals[j]
            shown = (hi * k, lo * k, v * k)
            if not (math.isfinite(lo) and math.isfinite(hi) and all(map(math.isfinite, shown))):
                return None
            nums += [*shown, hi, lo, sds[j], v]
        return self._fmt % (*nums, status, t_ns, t_s)

