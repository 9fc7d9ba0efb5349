"""``twin track``: in-memory records and streams, a CSV log through the CLI, MCAP topics that validate
against the event schemas, alarm sequence numbers, times from the start of the record."""

from __future__ import annotations

import json
import os

import pytest
from mcap.reader import make_reader

from replay.csvio import CsvSink
from twin import cli
from fpdd.errors import DataError
from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent
from twin.models import msp25 as M
from twin.models.scenario import Drift, simulate_wear
from fpdd.units import NOMINAL_NOISE
from twin.models.simulate import excite
from twin.service.track import track

NOISE = {k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}
STEP = Drift("Ffric", 3.0, 5.0, shape="step")  # 50 -> 150 N at 5 s


@pytest.fixture(scope="module")
def friction_step():
    _, xr = excite(M.MODEL, 12.0, 1e-3, seed=31)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [STEP], noise=NOISE, seed=31)
    return rec


def test_track_a_record_in_memory(friction_step):
    twin = track(friction_step, rig_name="bench-3")
    alarms = [a for a in twin.alarms if a.level == "alarm"]
    assert alarms and {a.parameter for a in twin.alarms} == {"Ffric"}
    assert 5.0 <= alarms[0].t_s <= 7.0  # the band's top (75 N) is crossed at the step
    assert [a.seq for a in twin.alarms] == list(range(1, len(twin.alarms) + 1))
    assert all(a.rig == "bench-3" for a in twin.alarms)
    final = twin.final_estimates()
    assert set(final) == set(M.PHENOMENOLOGICAL)
    assert abs(final["Ffric"]["value"] - 150.0) < 3 * final["Ffric"]["std"] + 5.0
    hist = twin.history_arrays()
    assert hist["values"].shape == (len(hist["t_s"]), 5) and hist["t_s"][-1] == pytest.approx(12.0, abs=0.06)


def test_a_stream_of_blocks_gives_the_same_alarms(friction_step):
    s = friction_step.to_samples()
    blocks = (s.slice(i, i + 777) for i in range(0, len(s), 777))
    a = track(friction_step, tracked=("Ffric", "Cd"))
    b = track(blocks, tracked=("Ffric", "Cd"))
    assert [(e.parameter, e.level, e.kind, e.t_ns) for e in a.alarms] == \
           [(e.parameter, e.level, e.kind, e.t_ns) for e in b.alarms]
    assert set(a.final_estimates()) == {"Ffric", "Cd"}


def test_track_rejects_what_it_cannot_read():
    with pytest.raises(DataError, match="not int"):
        track(42)


def test_cli_on_a_csv_log_writes_mcap_png_and_json(friction_step, tmp_path, capsys):
    log = tmp_path / "rig.csv"
    with CsvSink(log) as sink:
        sink.write(friction_step.to_samples())
    out_dir = tmp_path / "out"
    rc = cli.main(["track", str(log), "--track", "Ffric,Cd,wn", "--rig", "bench-3", "--out", str(out_dir),
                   "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["final"]) == {"Ffric", "Cd", "wn"}
    assert all({"value", "std"} <= set(v) and v["std"] > 0 for v in doc["final"].values())
    alarms = [a for a in doc["alarms"] if a["level"] == "alarm"]
    assert alarms and {a["parameter"] for a in doc["alarms"]} == {"Ffric"}
    assert all({"parameter", "level", "t", "seq", "estimate", "std"} <= set(a) for a in doc["alarms"])
    assert 5.0 <= alarms[0]["t"] <= 7.0  # seconds from the start of the record (the CSV starts at t = 0)
    assert doc["status"]["Ffric"] == "alarm"
    assert os.path.getsize(doc["files"]["trends_png"]) > 1000
    with open(doc["files"]["mcap"], "rb") as f:
        msgs = [(ch.topic, json.loads(m.data)) for _, ch, m in make_reader(f, validate_crcs=True).iter_messages()]
    kinds = {"/twin/alarm": AlarmEvent, "/twin/estimate": EstimateEvent, "/twin/status": StatusEvent}
    for topic, payload in msgs:  # every message validates against its event schema (alarms need seq >= 1)
        if topic in kinds:  # the live view's /rig/signals and /twin/alarm_log: tests/test_recorded_layout.py
            kinds[topic].from_dict(payload)
    mcap_alarms = [p for t, p in msgs if t == "/twin/alarm"]
    assert [a["seq"] for a in mcap_alarms] == [a["seq"] for a in doc["alarms"]]
    estimates = [p for t, p in msgs if t == "/twin/estimate"]
    assert len(estimates) >= 200 and set(estimates[-1]["params"]) == {"Ffric", "Cd", "wn"}
    assert {t for t, _ in msgs} == set(kinds) | {"/rig/signals", "/twin/alarm_log"}
    with open(doc["files"]["mcap"], "rb") as f:  # each channel carries its event's schema, for Foxglove
        summary = make_reader(f).get_summary()
    assert summary is not None
    for ch in (c for c in summary.channels.values() if c.topic in kinds):
        schema = json.loads(summary.schemas[ch.schema_id].data)
        assert schema["title"] == kinds[ch.topic].SCHEMA["title"]
        assert set(kinds[ch.topic].SCHEMA["required"]) <= set(schema["required"])


@pytest.mark.slow
def test_cli_commissions_from_a_fit_file_with_noise_and_timing(tmp_path, capsys):
    """An analog-controller rig of the reference simulator with twice the nominal noise, commissioned from a
    fit file (values near the truth, its noise levels, continuous timing): nothing raised, the noise as the
    fit said (and learnt), the timing the fit's; the flags override the file; bad flags are one line."""
    from tests.track_reference import record, to_samples

    rec, _ = record("analog", 4, 30.0)
    log = tmp_path / "analog.csv"
    with CsvSink(log) as sink:
        sink.write(to_samples(rec, t0_ns=0))
    truth = {n: float(rec.truth[n]) for n in M.PHENOMENOLOGICAL}
    fit = {"model": "msp25", "effects": [], "params": {n: v * 1.05 for n, v in truth.items()},
           "std": {n: 0.01 * v for n, v in truth.items()}, "timing": {"controller": "continuous"},
           "noise": {"x": 2.1e-6, "pA": 1.9e4, "pB": 2.0e4}}
    path = tmp_path / "fit.json"
    path.write_text(json.dumps(fit))
    rc = cli.main(["track", str(log), "--params", str(path), "--out", str(tmp_path / "o"), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["alarms"] == [] and doc["timing"] == "continuous"
    assert doc["noise"]["x"]["nominal"] == pytest.approx(2.1e-6)
    assert set(doc["sensors"].values()) == {"ok"}
    rc = cli.main(["track", str(log), "--params", str(path), "--noise-levels", "x=4um", "--controller",
                   "digital:5000", "--out", str(tmp_path / "o"), "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert doc["noise"]["x"]["nominal"] == pytest.approx(4e-6) and doc["timing"] == "digital:5000"
    assert cli.main(["-q", "track", str(log), "--params", str(path), "--out", str(tmp_path / "o")]) == 0
    out, err = capsys.readouterr()
    said = err.splitlines()  # where its report is, for a person
    wn = next(line for line in out.splitlines() if line.strip().startswith("wn "))
    assert __import__("re").match(r"\s+wn\s+[\d.]+ Hz \+- (\d(\.\d)?|0\.0*[1-9]\d?)(e-\d+)? Hz ", wn), wn  # std rounded in Hz
    assert f"report: {tmp_path / 'o' / 'track_report.html'}" in said and (tmp_path / "o" / "track_report.html").exists()
    rc = cli.main(["track", str(log), "--noise-levels", "y=1", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and err == ["twin track: error: --noise-levels: expected positive standard deviations of x, pA, "
                               "pB (e.g. x=2um,pA=20kPa), got 'y=1'"]
    path.write_text(json.dumps({**fit, "noise": {"x": -1.0}}))
    rc = cli.main(["track", str(log), "--params", str(path), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "fit.json: noise.x must be a positive standard deviation" in err[0]


@pytest.mark.slow
def test_cli_confirm_tests_each_parameter_and_never_holds_the_filters_alarm_silently(tmp_path, capsys):
    """``--confirm``: a warning or alarm only from a confirmed window; on the product's own record the
    filter's friction alarm is confirmed by the windows (never a silent ``ok``); each parameter carries the
    record time of its last window re-fit."""
    _, xr = excite(M.MODEL, 24.0, 1e-3, seed=32)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [STEP], noise=NOISE, seed=32)
    log = tmp_path / "rig.csv"
    with CsvSink(log) as sink:
        sink.write(rec.to_samples())
    assert cli.main(["track", str(log), "--out", str(tmp_path / "f"), "--json"]) == 0
    plain = json.loads(capsys.readouterr().out)
    assert plain["status"]["Ffric"] == "alarm"  # the filter's own drift test alarms the step
    assert cli.main(["track", str(log), "--confirm", "--out", str(tmp_path / "o"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert all(a["t"] >= 5.0 for a in doc["alarms"])  # nothing before the step at 5 s
    assert {a["parameter"] for a in doc["alarms"]} <= {"Ffric"}
    # the product's own exact record (white noise outside the loop): every window represents the rig, the step
    # is confirmed, nothing else moves
    assert doc["status"]["Ffric"] == "alarm" and doc["consistency"] == "consistent", doc["status"]
    assert all(doc["status"][n] == "ok" for n in doc["status"] if n != "Ffric"), doc["status"]
    assert set(doc["status"]) == set(plain["status"])
    with open(doc["files"]["mcap"], "rb") as f:
        statuses = [json.loads(m.data) for _, ch, m in make_reader(f).iter_messages() if ch.topic == "/twin/status"]
    assert statuses and all(set(s["parameters"]) == set(doc["status"]) for s in statuses)
    tested = statuses[-1].get("tested", {})  # a window that could test a parameter: its record time
    assert set(tested) <= set(doc["status"]) and all(0.0 < t <= 24.0 for t in tested.values())
    assert tested["Ffric"] >= 24.0 - 20.0 - 4.0  # tested within the last period and window
