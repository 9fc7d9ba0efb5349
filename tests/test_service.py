"""The service end to end: demo, twin track, twin serve with a journal that survives restarts, late subscribers."""

from __future__ import annotations

import json
import os
import queue
import threading
import time
from pathlib import Path

import pytest
import zenoh

from mcap.reader import make_reader

from replay.mcapio import McapSink
from twin import cli
from twin.service.subscriber import AlarmSubscriber
from fpdd.zenohconf import zenoh_config
from twin.service.config import parse_config
from net_helpers import free_port
from twin.commands.demo import run as run_demo
from twin.models import msp25 as M
from twin.models.scenario import Drift, simulate_wear
from twin.online.events import StatusEvent
from twin.service.serve import serve
from twin.service.store import Store
from fpdd.units import NOMINAL_NOISE
from twin.models.simulate import excite

NOISE = {k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}


def _log(path, duration, drifts, seed=0):
    _, xr = excite(M.MODEL, duration, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, drifts, noise=NOISE, seed=seed)
    with McapSink(str(path)) as sink:
        sink.write(rec.to_samples())
    return rec


def test_demo_end_to_end(tmp_path):
    lines = []
    s = run_demo(str(tmp_path / "demo"), duration_s=40.0, speed=0.0, factor=30.0, t_start=10.0, t_end=30.0,
                 shape="ramp", say=lines.append)
    leak = [a for a in s["alarms"] if a["parameter"] == "CdAleak" and a["level"] == "alarm"]
    assert leak and 0.0 <= s["detection_delay_s"] <= 5.0
    assert s["false_alarms"] == []
    assert s["received_by_subscriber"] == len(s["alarms"]) > 0
    assert any("subscriber: msp25-demo #1 " in line and "mm^2" in line for line in lines)  # display units
    for key in ("html", "trends_png", "rig_mcap", "twin_mcap"):
        assert os.path.getsize(s["files"][key]) > 1000, key
    html = Path(s["files"]["html"]).read_text(encoding="utf-8")  # a person's page: display units, unit beside
    assert "mm²" in html and "Hz" in html and "raised (UTC)" in html
    assert "e-08" not in html and "e-09" not in html and "rad/s" not in html
    with open(s["files"]["twin_mcap"], "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        alarms = [json.loads(m.data) for _, ch, m in reader.iter_messages(topics=["/twin/alarm"])]
        f.seek(0)
        topics = {ch.topic for _, ch, _ in make_reader(f).iter_messages()}
    assert {"/twin/estimate", "/twin/alarm", "/twin/status"} <= topics
    assert [a["seq"] for a in alarms] == [a["seq"] for a in s["alarms"]]


@pytest.mark.slow
def test_demo_warns_early_and_its_files_fill_the_foxglove_layout(tmp_path):
    """The demo as shipped (150 s, the leakage growing geometrically from 30 s): the forecast's early warning comes
    before the leakage leaves its band, the alarm after; the twin's MCAP fills every panel of the demo's layout,
    the forecast's too."""
    from test_recorded_layout import check_file

    s = run_demo(str(tmp_path / "demo"), speed=0.0, say=lambda _: None)
    cross = s["truth"]["crosses_band_at_s"]
    assert s["early_warning_s"] is not None and s["early_warning_s"] < cross < s["first_alarm_s"]
    fc = s["first_forecast"]
    assert fc["parameter"] == "CdAleak" and fc["t"] < cross and fc["t_exit_lo"] <= cross <= fc["t_exit_hi"]
    assert s["false_alarms"] == [] and s["received_by_subscriber"] == len(s["alarms"])
    layout = json.loads(Path(s["files"]["foxglove_layout"]).read_text(encoding="utf-8"))
    counts = check_file(s["files"]["twin_mcap"], layout)
    assert counts["/twin/forecast"] >= 1 and counts["/twin/alarm_log"] == len(s["alarms"])
    check_file(s["files"]["rig_mcap"], layout, every=500, optional_panels=tuple(
        p for p in layout["configById"] if p not in ("Plot!position", "Plot!pressures")))


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


def _config(tmp_path, log, port, speed=0.0, extra_rigs=(), **service):
    return parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "estimate_every": 100, "stale_s": 0.2, **service},
        "rig": [{"name": "rig-a", "source": str(log), "speed": speed}, *extra_rigs],
    }, str(tmp_path / "rigs.toml"))


def _journal(tmp_path, rig):
    """The rig's journaled alarms (read without the writer's lock, as the bus does)."""
    with Store(tmp_path / "journal" / f"{rig}.db", writer=False) as store:
        return store.alarms(rig)


class StatusWatch:
    """Statuses of a rig as they are published (a plain subscriber on its status key)."""

    def __init__(self, session, rig):
        self.q: queue.Queue[StatusEvent] = queue.Queue()
        self.sub = session.declare_subscriber(
            f"fpdd/{rig}/status", lambda s: self.q.put(StatusEvent.from_dict(json.loads(s.payload.to_string()))))

    def until(self, predicate, timeout=30.0):
        deadline = time.monotonic() + timeout
        while True:
            status = self.q.get(timeout=max(0.01, deadline - time.monotonic()))
            if predicate(status):
                return status

    def close(self):
        self.sub.undeclare()


def _latest_status(session, rig):
    """The state in the rig's latest status, asked of its latest-value queryable (``None``: no answer)."""
    for reply in session.get(f"fpdd/{rig}/status", timeout=5.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_string())["state"]
    return None


IDLE = {"name": "idle", "source": "zenoh://fpdd/idle/samples"}  # a live rig nobody feeds: keeps the service up


@pytest.mark.slow
def test_a_restart_resumes_instead_of_replaying_and_a_late_subscriber_gets_every_alarm(tmp_path):
    log = tmp_path / "rig.mcap"
    _log(log, 12.0, [Drift("Ffric", 3.0, 4.0, shape="step")], seed=3)
    first = serve(_config(tmp_path, log, free_port()))
    n1 = first["rig-a"].alarms
    assert n1 >= 1 and first["rig-a"].samples == 12000
    journaled = _journal(tmp_path, "rig-a")
    assert [e.seq for e in journaled] == list(range(1, n1 + 1))
    # Restart on the same journal with a live rig that keeps the service up: the log rig resumes at
    # its end (nothing processed twice, nothing journaled twice), the idle rig waits ('stale_input').
    cfg = _config(tmp_path, log, free_port(), extra_rigs=[IDLE])
    stop = threading.Event()
    summaries: dict = {}
    th = threading.Thread(target=serve, args=(cfg, stop), kwargs={"summaries": summaries})
    with zenoh.open(zenoh_config("peer", connect=list(cfg.listen))) as session:
        watch = StatusWatch(session, "idle")
        th.start()
        try:
            stale = watch.until(lambda s: s.state == "stale_input" and s.counters.get("stale_ms", 0) > 0)
            assert "no input from zenoh://fpdd/idle/samples" in stale.message
            with AlarmSubscriber(session, rig="rig-a") as sub:
                got = [sub.recv(timeout=10.0) for _ in range(n1)]
                # Nothing else, whatever the machine's speed. The service is no object to publish a marker
                # through; instead: (1) its latest status of rig-a says "finished": the rig's runner has ended,
                # and every alarm it put came before that reply on the same link; (2) a payload put after it
                # from this session on the rig's alarm key is handled (rejected: not an alarm) after anything
                # the subscriber had queued, and nothing is delivered until it is.
                deadline = time.monotonic() + 30.0
                while (state := _latest_status(session, "rig-a")) != "finished":
                    assert time.monotonic() < deadline, f"rig-a not finished within 30 s (state {state})"
                    time.sleep(0.1)
                session.put("fpdd/rig-a/alarm", "end of test")
                late = []
                while sub.rejected == 0:
                    assert time.monotonic() < deadline, "the test's own payload was not handled within 30 s"
                    try:
                        late.append(sub.recv(timeout=0.1))
                    except TimeoutError:
                        pass
                assert late == [] and sub.rejected == 1
            assert th.is_alive(), "a live rig keeps the service running until it is told to stop"
        finally:
            watch.close()
            stop.set()
            th.join(timeout=30.0)
    assert not th.is_alive()
    assert got == journaled
    assert summaries["rig-a"].state == "finished" and summaries["rig-a"].samples == 0
    assert summaries["rig-a"].resumed_samples == 12000
    assert summaries["idle"].state == "stopped"
    assert _journal(tmp_path, "rig-a") == journaled


def test_serve_reports_a_bad_configuration_without_a_traceback(tmp_path, capsys):
    p = tmp_path / "rigs.toml"
    p.write_text('[[rig]]\nname = "a"\nsource = "x.mcap"\ntrack = ["mass"]\n')
    assert cli.main(["serve", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert "rigs.toml" in err and "mass" in err and "Traceback" not in err


def test_a_live_input_that_pauses_or_sends_garbage_is_waited_for_not_ended(tmp_path):
    from replay.live import ZenohSampleSink

    port = free_port()
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "stale_s": 0.2},
        "rig": [{"name": "rig-z", "source": "zenoh://fpdd/rig-z/samples"}],
    }, "<live>")
    _, xr = excite(M.MODEL, 12.0, 1e-3, seed=4)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("Ffric", 3.0, 4.0, shape="step")],
                           noise=NOISE, seed=4)
    samples = rec.to_samples()
    half = len(samples) // 2
    stop = threading.Event()
    summaries: dict = {}
    th = threading.Thread(target=serve, args=(cfg, stop), kwargs={"summaries": summaries})
    th.start()
    try:
        with zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{port}"])) as rig_session:
            watch = StatusWatch(rig_session, "rig-z")
            raw = rig_session.declare_publisher("fpdd/rig-z/samples")
            with ZenohSampleSink("fpdd/rig-z/samples", session=rig_session, end_marker=False) as sink:
                assert sink.wait_for_subscriber(10.0), "the service did not subscribe to its input"
                sink.write(samples.slice(0, half))
                first = watch.until(lambda s: s.state == "stale_input" and s.counters["samples"] == half)
                # garbage that used to kill the rig: a t_ns beyond int64, signals that are not an object
                raw.put(b'{"format":"fpdd.samples/1","t_ns":[99999999999999999999],"signals":{"x":[1.0]}}')
                raw.put(b'{"format":"fpdd.samples/1","t_ns":5,"signals":[1,2]}')
                sink.write(samples.slice(half, len(samples)))
                last = watch.until(lambda s: s.state == "stale_input" and s.counters["samples"] == len(samples))
            raw.undeclare()
            watch.close()
        assert th.is_alive(), "a quiet live input does not end the service"
    finally:
        stop.set()
        th.join(timeout=30.0)
    assert not th.is_alive()
    assert first.counters["stale_ms"] >= 200 and "no input from zenoh://fpdd/rig-z/samples" in first.message
    assert last.counters["samples"] == len(samples)
    s = summaries["rig-z"]
    assert s.state == "stopped" and s.samples == len(samples)
    # the garbage was counted (by the source, or by the rig when the source let it through), not fatal
    assert s.source_errors + s.bad_blocks + s.bad_samples + s.input_dropped >= 2
    if s.input_dropped:
        assert sum(v for k, v in last.counters.items() if k.startswith("dropped_")) == s.input_dropped
    alarms = _journal(tmp_path, "rig-z")
    assert alarms and {a.parameter for a in alarms} == {"Ffric"}


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
        params = {a.parameter for a in _journal(tmp_path, name)}
        assert params == {drifts[0].parameter}, (name, params)


@pytest.mark.slow
def test_worker_processes_run_the_rigs_and_the_bus_answers_from_their_journals(tmp_path):
    """workers = 2: the log rigs run in spawned processes; history queries are answered by the service."""
    logs = {"rig-f": [Drift("Ffric", 3.0, 3.0, shape="step")], "rig-g": [Drift("Ffric", 3.0, 5.0, shape="step")],
            "rig-h": []}
    for name, drifts in logs.items():
        _log(tmp_path / f"{name}.mcap", 8.0, drifts, seed=7)
    port = free_port()
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "workers": 2, "stale_s": 0.2},
        "rig": [*({"name": n, "source": str(tmp_path / f"{n}.mcap"), "speed": 0.0} for n in logs), IDLE],
    }, "<workers>")
    stop = threading.Event()
    summaries: dict = {}
    th = threading.Thread(target=serve, args=(cfg, stop), kwargs={"summaries": summaries})
    th.start()
    try:
        with zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{port}"])) as session:
            watch = StatusWatch(session, "*")
            finished: dict[str, StatusEvent] = {}

            def all_finished(s: StatusEvent) -> bool:
                if s.state == "finished":
                    finished[s.rig] = s
                return set(finished) == set(logs)

            watch.until(all_finished, timeout=120.0)
            done = finished["rig-h"]
            watch.close()
            with AlarmSubscriber(session, rig="rig-g") as sub:
                got = [sub.recv(timeout=10.0) for _ in range(len(_journal(tmp_path, "rig-g")))]
    finally:
        stop.set()
        th.join(timeout=60.0)
    assert not th.is_alive()
    assert done.counters["samples"] == 8000
    assert {n: summaries[n].state for n in logs} == {n: "finished" for n in logs}
    assert all(summaries[n].samples == 8000 for n in logs)
    assert got and got == _journal(tmp_path, "rig-g") and "Ffric" in {a.parameter for a in got}
    assert _journal(tmp_path, "rig-h") == []


def test_a_rig_that_fails_stops_the_service_with_its_name_and_cause(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x\n" + "".join(f"{i * 1e-3:.3f},{1e-3 * (i % 7)}\n" for i in range(2000)))
    good = tmp_path / "good.mcap"
    _log(good, 30.0, [], seed=8)
    p = tmp_path / "rigs.toml"
    p.write_text(f"""
[zenoh]
listen = ["tcp/127.0.0.1:{free_port()}"]
[service]
journal_dir = "{tmp_path / 'journal'}"
[[rig]]
name = "bad"
source = "{bad}"
speed = 0
[[rig]]
name = "good"
source = "{good}"
speed = 1.0
""")
    assert cli.main(["serve", "--config", str(p)]) == 2
    err = capsys.readouterr().err
    assert "twin serve: error: rig bad failed:" in err
    assert "missing a drive (the controller output (servo-valve voltage) 'u' or the demanded rod displacement " \
           "'x_ref'); the record has x" in err  # the model's own words for its signals
    assert "summary bad: failed" in err and "summary good: stopped" in err  # the other rig stopped cleanly
    assert "Traceback" not in err


@pytest.mark.slow
def test_one_thread_paces_several_logs_in_turn_and_a_restart_resumes_each(tmp_path):
    """run_scheduled (a worker's replayed logs on one thread): the rigs advance together, a stop checkpoints
    each one, and a second run continues every rig from its checkpoint to the end of its log."""
    from twin.service.workers import run_scheduled

    names = ("rig-p", "rig-q", "rig-r")
    for i, n in enumerate(names):
        _log(tmp_path / f"{n}.mcap", 6.0, [], seed=20 + i)
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "checkpoint_s": 0.2},
        "rig": [{"name": n, "source": str(tmp_path / f"{n}.mcap"), "speed": 2.0} for n in names],
    }, "<scheduled>")

    def run(stop_after_batches=None):
        out: queue.Queue = queue.Queue()
        stop = threading.Event()
        th = threading.Thread(target=run_scheduled, args=(list(cfg.rigs), cfg, out, stop))
        th.start()
        done, batches = {}, {n: 0 for n in names}
        deadline = time.monotonic() + 120.0
        while len(done) < len(names) and time.monotonic() < deadline:
            try:
                msg = out.get(timeout=1.0)
            except queue.Empty:
                continue
            if msg[0] == "done":
                done[msg[1]] = msg[2]
            elif msg[0] == "batch":
                batches[msg[1]] += 1
                if stop_after_batches and min(batches.values()) >= stop_after_batches:
                    stop.set()
        th.join(timeout=30.0)
        assert not th.is_alive()
        return done

    first = run(stop_after_batches=4)
    assert {n: s.state for n, s in first.items()} == {n: "stopped" for n in names}
    got = [first[n].samples for n in names]
    assert min(got) > 0 and max(got) < 6000
    assert max(got) - min(got) <= 0.5 * max(got), got  # in turn, not one rig after another
    second = run()
    assert {n: s.state for n, s in second.items()} == {n: "finished" for n in names}
    for n in names:  # each went on from its checkpoint: nothing processed twice, nothing skipped
        assert second[n].resumed_samples is not None and second[n].resumed_samples > 0
        assert second[n].resumed_samples + second[n].samples == 6000, (n, second[n])


def test_a_scheduler_stopped_before_it_started_reports_every_rig(tmp_path):
    from twin.service.workers import run_scheduled

    _log(tmp_path / "a.mcap", 1.0, [], seed=30)
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
        "service": {"journal_dir": str(tmp_path / "journal")},
        "rig": [{"name": f"rig-{i}", "source": str(tmp_path / "a.mcap"), "speed": 1.0} for i in range(3)],
    }, "<scheduled>")
    out: queue.Queue = queue.Queue()
    stop = threading.Event()
    stop.set()
    run_scheduled(list(cfg.rigs), cfg, out, stop)
    done = {}
    while not out.empty():
        msg = out.get_nowait()
        if msg[0] == "done":
            done[msg[1]] = msg[2].state
    assert done == {f"rig-{i}": "stopped" for i in range(3)}
