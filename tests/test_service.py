"""The service end to end: demo, twin track, twin serve with a journal that survives restarts, late subscribers."""

from __future__ import annotations

import json
import os
import threading

import pytest
import zenoh

from mcap.reader import make_reader

from replay.mcapio import McapSink
from twin import cli
from twin.bus import AlarmSubscriber, zenoh_config
from twin.config import parse_config
from twin.demo import free_port
from twin.demo import run as run_demo
from twin.models import msp25 as M
from twin.scenario import Drift, simulate_wear
from twin.service import serve
from twin.simulate import DEFAULT_NOISE, excite

NOISE = {k: DEFAULT_NOISE[k] for k in ("x", "pA", "pB")}


def _log(path, duration, drifts, seed=0):
    _, xr = excite(M.MODEL, duration, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, drifts, noise=NOISE, seed=seed)
    with McapSink(str(path)) as sink:
        sink.write(rec.to_samples())
    return rec


def test_demo_end_to_end(tmp_path):
    lines = []
    s = run_demo(str(tmp_path / "demo"), duration_s=40.0, speed=0.0, t_start=10.0, t_end=30.0, say=lines.append)
    leak = [a for a in s["alarms"] if a["parameter"] == "CdAleak" and a["level"] == "alarm"]
    assert leak and 0.0 <= s["detection_delay_s"] <= 5.0
    assert s["false_alarms"] == []
    assert s["received_by_subscriber"] == len(s["alarms"]) > 0
    assert any("subscriber: seq  1" in line for line in lines)
    for key in ("html", "trends_png", "rig_mcap", "twin_mcap"):
        assert os.path.getsize(s["files"][key]) > 1000, key
    with open(s["files"]["twin_mcap"], "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        alarms = [json.loads(m.data) for _, ch, m in reader.iter_messages(topics=["/twin/alarm"])]
        f.seek(0)
        topics = {ch.topic for _, ch, _ in make_reader(f).iter_messages()}
    assert {"/twin/estimate", "/twin/alarm", "/twin/status"} <= topics
    assert [a["seq"] for a in alarms] == [a["seq"] for a in s["alarms"]]


def test_twin_track_json_names_the_fault_and_its_time(tmp_path, capsys):
    log = tmp_path / "rig.mcap"
    _log(log, 15.0, [Drift("Ffric", 3.0, 6.0, shape="step")], seed=2)
    rc = cli.main(["track", str(log), "--out", str(tmp_path / "out"), "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    alarms = [a for a in out["alarms"] if a["level"] == "alarm"]
    assert alarms and {a["parameter"] for a in out["alarms"]} == {"Ffric"}
    assert 6.0 <= alarms[0]["t"] <= 8.0
    assert out["final"]["Ffric"]["value"] == pytest.approx(150.0, rel=0.15)
    assert set(out["final"]["Cd"]) >= {"value", "std"}
    assert os.path.getsize(tmp_path / "out" / "parameter_trends.png") > 1000


def _config(tmp_path, log, port, speed=0.0):
    return parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "estimate_every": 100},
        "rig": [{"name": "rig-a", "source": str(log), "speed": speed}],
    }, str(tmp_path / "rigs.toml"))


def test_journal_survives_a_restart_and_a_late_subscriber_gets_every_alarm(tmp_path):
    log = tmp_path / "rig.mcap"
    _log(log, 12.0, [Drift("Ffric", 3.0, 4.0, shape="step")], seed=3)
    first = serve(_config(tmp_path, log, free_port()))
    assert first["rig-a"].alarms >= 1
    n1 = first["rig-a"].alarms
    # restart on the same journal, now replayed in real time so that a subscriber can join late
    cfg = _config(tmp_path, log, free_port(), speed=2.0)
    stop = threading.Event()
    alarmed = threading.Event()
    result = {}
    th = threading.Thread(target=lambda: result.update(serve(cfg, stop, on_alarm=lambda ev: alarmed.set())))
    th.start()
    try:
        assert alarmed.wait(timeout=30.0), "the restarted service raised no alarm"
        with zenoh.open(zenoh_config("peer", connect=list(cfg.listen))) as session, \
                AlarmSubscriber(session, rig="rig-a") as sub:
            got = [sub.recv(timeout=10.0) for _ in range(n1 + 1)]
    finally:
        stop.set()
        th.join(timeout=30.0)
    seqs = [e.seq for e in got]
    assert seqs == list(range(1, n1 + 2))  # the first run's alarms, then the restarted run's first
    assert all(e.parameter == "Ffric" for e in got)
    with open(tmp_path / "journal" / "rig-a.alarms.jsonl") as f:
        journal = [json.loads(line) for line in f]
    assert [j["seq"] for j in journal] == list(range(1, len(journal) + 1)) and len(journal) >= n1 + 1


def test_serve_reports_a_bad_configuration_without_a_traceback(tmp_path, capsys):
    p = tmp_path / "rigs.toml"
    p.write_text('[[rig]]\nname = "a"\nsource = "x.mcap"\ntrack = ["mass"]\n')
    assert cli.main(["serve", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert "rigs.toml" in err and "mass" in err and "Traceback" not in err


def test_serve_tracks_a_live_zenoh_input(tmp_path):
    from replay.live import ZenohSampleSink

    port = free_port()
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "service": {"journal_dir": str(tmp_path / "journal")},
        "rig": [{"name": "rig-z", "source": "zenoh://fpdd/rig-z/samples"}],
    }, "<live>")
    _, xr = excite(M.MODEL, 12.0, 1e-3, seed=4)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("Ffric", 3.0, 4.0, shape="step")],
                           noise=NOISE, seed=4)
    result: dict = {}
    th = threading.Thread(target=lambda: result.update(serve(cfg)))
    th.start()
    try:
        with zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{port}"])) as rig_session:
            with ZenohSampleSink("fpdd/rig-z/samples", session=rig_session) as sink:
                assert sink.wait_for_subscriber(10.0), "the service did not subscribe to its input"
                sink.write(rec.to_samples())
    finally:
        th.join(timeout=60.0)
    assert not th.is_alive()
    assert result["rig-z"].samples == len(rec)
    with open(tmp_path / "journal" / "rig-z.alarms.jsonl") as f:
        alarms = [json.loads(line) for line in f]
    assert alarms and {a["parameter"] for a in alarms} == {"Ffric"}


def test_one_process_serves_several_rigs_each_with_its_own_journal(tmp_path):
    logs = {"rig-f": [Drift("Ffric", 3.0, 3.0, shape="step")], "rig-w": [Drift("wn", 0.7, 2.0, 8.0, "ramp")]}
    for name, drifts in logs.items():
        _log(tmp_path / f"{name}.mcap", 10.0, drifts, seed=6)
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "service": {"journal_dir": str(tmp_path / "journal")},
        "rig": [{"name": n, "source": str(tmp_path / f"{n}.mcap"), "speed": 0.0} for n in logs],
    }, "<two rigs>")
    stats = serve(cfg)
    assert set(stats) == set(logs) and all(s.samples == 10000 for s in stats.values())
    for name, drifts in logs.items():
        with open(tmp_path / "journal" / f"{name}.alarms.jsonl") as f:
            params = {json.loads(line)["parameter"] for line in f}
        assert params == {drifts[0].parameter}, (name, params)
