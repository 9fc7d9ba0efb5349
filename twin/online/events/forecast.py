"""The forecast's messages: :class:`Forecast` (one parameter's exit time and its interval), the
``/twin/forecast`` and ``fpdd/<rig>/forecast`` payload (:data:`FORECAST_SCHEMA`, :func:`forecast_message`, SI
with the unit of each field in :data:`FORECAST_UNITS`) and its wording for people (:func:`describe`); the
degradation models that make them are :mod:`twin.online.forecast`."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

@dataclasses.dataclass
class Forecast:
    """One parameter's forecast at record time ``t`` [s]: exit time (record seconds, median and 90 % interval; ``None``:
    beyond the grid), probability of leaving the band within the horizon, the exponential model's weight, and the
    trend's evidence (BIC difference to a flat line)."""

    parameter: str
    t: float
    t_ns: int
    t_exit: float | None
    t_exit_lo: float | None
    t_exit_hi: float | None
    p_within_horizon: float
    w_exp: float
    evidence: float
    edge: str

    def to_dict(self) -> dict[str, Any]:
        """The ``twin track --json`` entry (record seconds)."""
        return {"parameter": self.parameter, "t": self.t, "t_exit": self.t_exit, "t_exit_lo": self.t_exit_lo,
                "t_exit_hi": self.t_exit_hi, "p_within_horizon": self.p_within_horizon}


_NUM_OR_NULL = {"type": ["number", "null"]}

FORECAST_SCHEMA: dict[str, Any] = {
    "title": "fpdd.Forecast", "type": "object",
    "description": "When each tracked parameter of a rig leaves its healthy band (record seconds; null: not "
                   "within 1000 horizons); one message per second of record",
    "properties": {
        "rig": {"type": "string"}, "t_ns": {"type": "integer", "description": "ingest time [ns]"},
        "t_s": {"type": "number", "description": "record time of the forecast [s]"},
        "horizon_s": {"type": "number", "description": "horizon of p_within_horizon [s]"},
        "forecasts": {"type": "object", "description": "parameter name -> its forecast (the parameters that have one)",
                      "propertyNames": {"pattern": "^[A-Za-z_][A-Za-z0-9_]*$"}, "additionalProperties": {
            "type": "object",
            "properties": {"parameter": {"type": "string", "description": "the parameter (its key)"},
                           "t": {"type": "number", "description": "record time of the forecast [s]"},
                           "t_exit": {**_NUM_OR_NULL, "description": "median exit time, record seconds [s]"},
                           "t_exit_lo": {**_NUM_OR_NULL, "description": "5 % quantile of the exit time [s]"},
                           "t_exit_hi": {**_NUM_OR_NULL, "description": "95 % quantile of the exit time [s]"},
                           "remaining_s": {**_NUM_OR_NULL, "description": "median remaining time [s]"},
                           "remaining_lo_s": {**_NUM_OR_NULL, "description": "5 % quantile [s]"},
                           "remaining_hi_s": {**_NUM_OR_NULL, "description": "95 % quantile [s]"},
                           "p_within_horizon": {"type": "number", "description": "probability [1]"},
                           "edge": {"type": "string", "enum": ["low", "high"]}},
            "required": ["parameter", "t", "t_exit", "t_exit_lo", "t_exit_hi", "p_within_horizon", "remaining_s", "remaining_lo_s",
                         "remaining_hi_s", "edge"]}},
        "units": {"type": "object", "description": "field name -> its unit (s: seconds, 1: a probability)",
                  "additionalProperties": {"type": "string"}},
        "maintenance": {"type": "object", "description": "parameter name -> its last recorded maintenance (its "
                        "forecast started afresh then); absent when none was recorded",
                        "additionalProperties": {
                            "type": "object",
                            "properties": {"t": {**_NUM_OR_NULL, "description": "record time it was applied [s]"},
                                           "seq": {"type": "integer", "description": "the event's number"},
                                           "note": {"type": "string"},
                                           "wall_ns": {"type": ["integer", "null"],
                                                       "description": "when it was recorded [ns]"}},
                            "required": ["t", "seq", "note"]}},
    },
    "required": ["rig", "t_ns", "t_s", "horizon_s", "forecasts", "units"],
}


#: The unit of each field of a forecast message (``units`` in it): SI seconds, and a probability.
FORECAST_UNITS = {"t_s": "s", "horizon_s": "s", "t": "s", "t_exit": "s", "t_exit_lo": "s", "t_exit_hi": "s",
                  "remaining_s": "s", "remaining_lo_s": "s", "remaining_hi_s": "s", "p_within_horizon": "1"}


def forecast_message(rig: str, fcs: Sequence[Forecast], horizon_s: float,
                     maintained: Mapping[str, Mapping[str, Any]] | None = None) -> list[dict[str, Any]]:
    """The ``/twin/forecast`` (and ``fpdd/<rig>/forecast``) payloads of forecasts: one per instant, SI;
    ``maintained`` (:attr:`ForecastMonitor.maintained`): each parameter's last recorded maintenance, as
    ``maintenance`` in every message (left out when there is none)."""
    by_t: dict[int, list[Forecast]] = {}
    for f in fcs:
        by_t.setdefault(f.t_ns, []).append(f)

    def rem(v: float | None, t: float) -> float | None:
        return None if v is None else max(0.0, v - t)

    return [{"rig": rig, "t_ns": t_ns, "t_s": fs[0].t, "horizon_s": horizon_s,
             "forecasts": {f.parameter: {"parameter": f.parameter, "t": f.t, "t_exit": f.t_exit, "t_exit_lo": f.t_exit_lo, "t_exit_hi": f.t_exit_hi,
                                         "p_within_horizon": f.p_within_horizon, "remaining_s": rem(f.t_exit, f.t),
                                         "remaining_lo_s": rem(f.t_exit_lo, f.t),
                                         "remaining_hi_s": rem(f.t_exit_hi, f.t), "edge": f.edge} for f in fs},
             "units": dict(FORECAST_UNITS), **maintenance_field(maintained)}
            for t_ns, fs in sorted(by_t.items())]


def maintenance_field(maintained: Mapping[str, Mapping[str, Any]] | None) -> dict[str, Any]:
    """``{"maintenance": {parameter: {"t", "seq", "note", "wall_ns"}}}`` of a forecast message, or ``{}``."""
    if not maintained:
        return {}
    return {"maintenance": {n: {"t": m.get("t"), "seq": m.get("seq"), "note": m.get("note", ""),
                                "wall_ns": m.get("wall_ns")} for n, m in sorted(maintained.items())}}


def fmt_duration(seconds: float) -> str:
    """A duration for people: ``45 s``, ``6.1 min``, ``3.2 h``, ``4.5 d``."""
    s = float(seconds)
    if s < 100:
        return f"{s:.0f} s"
    if s < 6000:
        return f"{s / 60:.1f} min"
    if s < 172800:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.1f} d"


def describe(fc: Forecast) -> str:
    """``in 6.1 min [4.0, 9.5]`` (the median and the 90 % interval of the remaining time, in the median's unit)."""
    if fc.t_exit is None:
        return "not within the forecast grid"
    rem = max(0.0, fc.t_exit - fc.t)
    if rem < 1.0:
        return "now (its trend is at the band's edge or beyond)"
    text = fmt_duration(rem)
    unit = text.split()[-1]
    div = {"s": 1.0, "min": 60.0, "h": 3600.0, "d": 86400.0}[unit]

    def num(v: float | None) -> str:
        if v is None:
            return "never"
        x = max(0.0, v - fc.t) / div
        return f"{x:.0f}" if unit == "s" else f"{x:.1f}"

    return f"in {text} [{num(fc.t_exit_lo)}, {num(fc.t_exit_hi)}]"
