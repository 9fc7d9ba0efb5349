"""Event dataclasses: round trips, schema-driven validation, messages that name the field."""

from __future__ import annotations

import json
import math

import pytest

from fpdd.errors import DataError
from twin.online.events import (
    AlarmEvent,
    EstimateEvent,
    ParamEstimate,
    StatusEvent,
    event_to_json,
    validate,
)

T0_NS = 1_740_000_000_000_000_000


def make_alarm(**changes: object) -> AlarmEvent:
    fields: dict[str, object] = dict(
        rig="msp25",
        parameter="Kleak",
        level="alarm",
        kind="raised",
        t_ns=T0_NS,
        t_s=12.5,
        estimate=3.1e-12,
        std=2.0e-13,
        baseline=1.0e-12,
        band_lo=0.5e-12,
        band_hi=2.0e-12,
        statistic=14.2,
        message="leakage above band",
        seq=4,
    )
    fields.update(changes)
    return AlarmEvent(**fields)  # type: ignore[arg-type]


def make_estimate() -> EstimateEvent:
    return EstimateEvent(
        rig="msp25",
        t_ns=T0_NS,
        t_s=1.25,
        params={
            "Fc": {"value": 51.0, "std": 2.5, "unit": "N"},
            "Kleak": ParamEstimate(1.1e-12, 1.4e-13, "m^3/(s*Pa)"),
        },
        nis=2.7,
        status="ok",
    )


def make_status() -> StatusEvent:
    return StatusEvent(
        rig="msp25",
        t_ns=T0_NS,
        state="running",
        parameters={"Fc": "ok", "Kleak": "unresolved", "omega_v": "frozen"},
        counters={"samples": 1000, "gated": 3},
        message="tracking",
    )


@pytest.mark.parametrize("make", [make_alarm, make_estimate, make_status])
def test_round_trip_through_json(make) -> None:
    event = make()
    decoded = json.loads(event_to_json(event))
    again = type(event).from_dict(decoded)
    assert again == event
    assert again.to_dict() == event.to_dict()


@pytest.mark.parametrize("cls", [AlarmEvent, EstimateEvent, StatusEvent])
def test_schema_lists_every_serialised_field(cls) -> None:
    sample = {AlarmEvent: make_alarm, EstimateEvent: make_estimate, StatusEvent: make_status}[cls]()
    schema = cls.SCHEMA
    # in the payload only when set: a signature, an announced epoch, the owner's term, the times of confirmed tests
    optional = {AlarmEvent: {"signature", "epoch", "term"}, EstimateEvent: {"term"},
                StatusEvent: {"epoch", "signature", "tested", "term"}}.get(cls, set())
    assert set(schema["required"]) == set(sample.to_dict()) == set(schema["properties"]) - optional
    json.dumps(schema)  # the schema itself is plain JSON
    validate(sample.to_dict(), schema, cls.__name__)


def test_estimate_params_are_converted_and_read_only() -> None:
    event = make_estimate()
    assert event.params["Fc"] == ParamEstimate(51.0, 2.5, "N")
    with pytest.raises(TypeError):
        event.params["Fc"] = ParamEstimate(1.0, 1.0, "N")  # type: ignore[index]


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("level", "alrm", "AlarmEvent.level: 'alrm' is not one of ['ok', 'warning', 'alarm', 'early']"),
        ("kind", "gone", "AlarmEvent.kind: 'gone' is not one of"),
        ("seq", 0, "AlarmEvent.seq: 0 must be >= 1"),
        ("seq", "3", "AlarmEvent.seq: '3' must be an integer"),
        ("seq", True, "AlarmEvent.seq: True must be an integer"),
        ("t_ns", 1.5, "AlarmEvent.t_ns: 1.5 must be an integer"),
        ("std", -1.0, "AlarmEvent.std: -1.0 must be >= 0"),
        ("estimate", math.nan, "AlarmEvent.estimate: nan must be a finite number"),
        ("rig", "a/b", "AlarmEvent.rig: 'a/b' does not match"),
        ("rig", "*", "AlarmEvent.rig: '*' does not match"),
        ("parameter", "", "AlarmEvent.parameter: '' does not match"),
    ],
)
def test_alarm_from_dict_names_the_bad_field(field: str, value: object, message: str) -> None:
    data = make_alarm().to_dict()
    data[field] = value
    with pytest.raises(DataError) as info:
        AlarmEvent.from_dict(data)
    assert message in str(info.value)


def test_missing_field_is_named() -> None:
    data = make_alarm().to_dict()
    del data["baseline"]
    with pytest.raises(DataError, match=r"AlarmEvent\.baseline: missing"):
        AlarmEvent.from_dict(data)


def test_not_an_object() -> None:
    with pytest.raises(DataError, match="AlarmEvent: expected a JSON object, got list"):
        AlarmEvent.from_dict([1, 2])


def test_unknown_fields_are_ignored_for_forward_compatibility() -> None:
    data = {**make_alarm().to_dict(), "added_in_a_later_version": 1}
    assert AlarmEvent.from_dict(data) == make_alarm()


def test_construction_validates_cross_field_rules() -> None:
    with pytest.raises(DataError, match=r"AlarmEvent\.band_lo: .* must be <= band_hi"):
        make_alarm(band_lo=3.0, band_hi=1.0)
    with pytest.raises(DataError, match="'ok' is not a possible level for kind 'raised'"):
        make_alarm(level="ok")
    with pytest.raises(DataError, match="must be 'alarm' for kind 'escalated'"):
        make_alarm(level="warning", kind="escalated")
    assert make_alarm(level="ok", kind="returned").level == "ok"
    with pytest.raises(DataError, match=r"AlarmEvent\.seq: -1 must be >= 1"):
        make_alarm(seq=-1)


def test_unjournaled_alarm_has_seq_zero() -> None:
    event = make_alarm(seq=0)
    assert event.seq == 0
    assert event.with_seq(7).seq == 7


def test_estimate_and_status_validation_messages() -> None:
    data = make_estimate().to_dict()
    data["params"]["Fc"]["std"] = -2.0
    with pytest.raises(DataError, match=r"EstimateEvent\.params\.Fc\.std: -2\.0 must be >= 0"):
        EstimateEvent.from_dict(data)
    data = make_estimate().to_dict()
    del data["params"]["Kleak"]["unit"]
    with pytest.raises(DataError, match=r"EstimateEvent\.params\.Kleak\.unit: missing"):
        EstimateEvent.from_dict(data)
    data = {**make_estimate().to_dict(), "nis": None}
    assert EstimateEvent.from_dict(data).nis is None
    data = {**make_status().to_dict(), "state": "sleeping"}
    with pytest.raises(DataError, match=r"StatusEvent\.state: 'sleeping' is not one of"):
        StatusEvent.from_dict(data)
    data = make_status().to_dict()
    data["counters"]["samples"] = -1
    with pytest.raises(DataError, match=r"StatusEvent\.counters\.samples: -1 must be >= 0"):
        StatusEvent.from_dict(data)
    data = make_status().to_dict()
    data["parameters"]["bad name"] = "ok"
    with pytest.raises(DataError, match=r"StatusEvent\.parameters key: 'bad name' does not match"):
        StatusEvent.from_dict(data)


def test_json_never_carries_nan() -> None:
    event = make_estimate()
    text = event_to_json(event)
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text)["params"]["Kleak"]["unit"] == "m^3/(s*Pa)"


def test_estimate_from_tracker_arrays_equals_the_validated_event_and_refuses_what_it_would() -> None:
    names, units = ("Fc", "Kleak"), ("N", "m^3/(s*Pa)")
    fast = EstimateEvent.of_tracker("msp25", T0_NS, 1.25, names, [51.0, 1.1e-12], [2.5, 1.4e-13], units, 2.7, "ok")
    slow = EstimateEvent("msp25", T0_NS, 1.25, {"Fc": {"value": 51.0, "std": 2.5, "unit": "N"},
                                                 "Kleak": {"value": 1.1e-12, "std": 1.4e-13, "unit": units[1]}},
                         2.7, "ok")
    assert fast == slow and event_to_json(fast) == event_to_json(slow)
    with pytest.raises(DataError, match=r"EstimateEvent\.params\.Fc\.std: -1\.0 must be >= 0"):
        EstimateEvent.of_tracker("msp25", T0_NS, 1.25, names, [51.0, 1e-12], [-1.0, 1e-13], units, None, "ok")
    with pytest.raises(DataError, match=r"EstimateEvent\.params\.Kleak\.value: nan must be a finite number"):
        EstimateEvent.of_tracker("msp25", T0_NS, 1.25, names, [51.0, math.nan], [1.0, 1e-13], units, None, "ok")


def test_alarm_names_the_si_unit_of_its_values_and_reads_older_payloads_without_it():
    from twin.online.events import AlarmEvent

    ev = AlarmEvent(rig="r", parameter="wn", level="alarm", kind="raised", t_ns=5, t_s=0.005, estimate=190.0,
                    std=2.0, baseline=270.0, band_lo=235.0, band_hi=310.0, statistic=11.0, seq=1)
    assert ev.to_dict()["unit"] == "rad/s"
    old = {k: v for k, v in ev.to_dict().items() if k != "unit"}  # journaled before units were named
    assert AlarmEvent.from_dict(old).unit == "rad/s"
    assert AlarmEvent.from_dict(ev.to_dict()) == ev


def test_each_parameter_carries_its_numbers_in_its_display_unit_the_same_by_event_encoder_and_json() -> None:
    from twin.online.events import EstimateEncoder

    names, units = ("wn", "CdAleak"), ("rad/s", "m^2")
    bands = {"CdAleak": (2.1e-9, 5.2e-9, 3.4e-9)}
    vals, stds = [2 * math.pi * 47.5, 3.9e-9], [2.0, 4e-10]
    ev = EstimateEvent.of_tracker("msp25", T0_NS, 1.25, names, vals, stds, units, None, "ok", bands)
    d = ev.to_dict()["params"]
    assert d["wn"]["display"]["unit"] == "Hz" and d["wn"]["display"]["value"] == pytest.approx(47.5)
    assert d["wn"]["display"]["hi95"] == pytest.approx(d["wn"]["hi95"] / (2 * math.pi))
    assert d["wn"]["display"]["band_lo"] is None and d["wn"]["display"]["baseline"] is None  # null stays null
    cd = d["CdAleak"]["display"]
    assert cd["unit"] == "mm^2" and cd["value"] == pytest.approx(3.9e-3) and cd["lo95"] < cd["value"] < cd["hi95"]
    assert (cd["band_lo"], cd["band_hi"], cd["baseline"]) == pytest.approx((2.1e-3, 5.2e-3, 3.4e-3))
    text = event_to_json(ev)
    assert EstimateEncoder("msp25", names, units, bands)(T0_NS, 1.25, vals, stds, math.nan, "ok") == text
    assert event_to_json(EstimateEvent.from_dict(json.loads(text))) == text  # read back: the same text
    si = json.loads(text)["params"]["wn"]
    other = {**si, "display": {"unit": "rad/s", **{f: si[f] for f in ("value", "lo95", "hi95")}}}  # its own unit
    assert EstimateEvent("msp25", T0_NS, 1.25, {"wn": other}).to_dict()["params"]["wn"]["display"]["value"] == vals[0]
    with pytest.raises(DataError, match=r"EstimateEvent\.params\.wn\.display\.unit: 7 must be a string"):
        EstimateEvent("msp25", T0_NS, 1.25, {"wn": {**other, "display": {**other["display"], "unit": 7}}})
