"""The early warning on Zenoh: ``fpdd/<rig>/forecast`` put on change and every few seconds, ``get`` -> latest.

A real loopback session (explicit endpoints, scouting off) and a plain Zenoh subscriber, as any client would
use: the service (``twin serve``, its runner's outbox relayed to the bus front) tracks a short record of the
independent reference simulator whose leakage wears out of its band, and every forecast put must follow the
schema, name its units, and be one the twin made; ``get`` returns the twin's last one.  When the puts go
out (:class:`twin.service.bus.ForecastGate`) is checked on its own with a clock the test steps.
"""

from __future__ import annotations

import json
import queue
import threading
import time

import pytest
import zenoh

from net_helpers import free_port
from fpdd.zenohconf import zenoh_config
from twin.online.events import validate
from twin.online.events.forecast import FORECAST_SCHEMA, FORECAST_UNITS
from twin.service.bus import FORECAST_S, ForecastGate, RigKeys, TwinPublisher
from twin.service.queries import fetch_forecasts
from twin.service.config import parse_config
from twin.service.journal import AlarmJournal
from twin.service.serve import serve

WAIT_S = 30.0
WEAR_S, EXIT_S = 240.0, 180.0


def _msg(t: float, **fcs: tuple[float | None, float | None, float | None]) -> dict:
    return {"rig": "r1", "t_ns": int(t * 1e9), "t_s": t, "horizon_s": 600.0, "units": dict(FORECAST_UNITS),
            "forecasts": {n: {"parameter": n, "t": t, "t_exit": m, "t_exit_lo": lo, "t_exit_hi": hi,
                              "p_within_horizon": 0.5, "remaining_s": None if m is None else m - t,
                              "remaining_lo_s": None if lo is None else lo - t,
                              "remaining_hi_s": None if hi is None else hi - t, "edge": "high"}
                          for n, (m, lo, hi) in fcs.items()}}


def _wait_finished(statuses: queue.Queue, timeout_s: float = 240.0) -> None:
    """Wait for the rig's status to say finished (or failed), at most ``timeout_s``; assert it finished."""
    deadline = time.monotonic() + timeout_s
    while True:
        st = statuses.get(timeout=max(0.1, deadline - time.monotonic()))
        if st["state"] in ("finished", "failed"):
            break
    assert st["state"] == "finished", st["message"]


def test_the_gate_puts_changes_at_once_and_the_rest_every_period():
    now = [100.0]
    gate = ForecastGate(clock=lambda: now[0])
    assert gate.period_s == FORECAST_S
    assert gate(_msg(60.0, CdAleak=(180.0, 150.0, 220.0)))  # the first
    now[0] += 0.1
    assert not gate(_msg(61.0, CdAleak=(185.0, 160.0, 215.0)))  # the median stays inside the interval put
    now[0] += 0.1
    assert gate(_msg(62.0, CdAleak=(225.0, 190.0, 270.0)))  # it left it: a change
    now[0] += 0.1
    assert gate(_msg(63.0, CdAleak=(225.0, 190.0, 270.0), Ffric=(900.0, 500.0, None)))  # a forecast appears
    now[0] += 0.1
    assert not gate(_msg(64.0, CdAleak=(226.0, 190.0, 270.0), Ffric=(950.0, 520.0, None)))
    now[0] += 0.1
    assert gate(_msg(65.0, CdAleak=(226.0, 190.0, 270.0), Ffric=(950.0, 520.0, 3000.0)))  # a bound became finite
    now[0] += 0.1
    assert gate(_msg(66.0))  # every forecast ended: said at once
    now[0] += 0.1
    assert not gate(_msg(67.0))
    now[0] += FORECAST_S
    assert gate(_msg(68.0))  # a period after the last put: again


def test_a_twin_publisher_keeps_the_latest_and_refuses_another_rigs(tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got: queue.Queue = queue.Queue()
    with zenoh.open(zenoh_config(listen=[endpoint])) as hub, zenoh.open(zenoh_config(connect=[endpoint])) as client, \
            AlarmJournal(tmp_path / "j.db") as journal, TwinPublisher(hub, "r1", journal) as pub:
        sub = client.declare_subscriber(RigKeys("r1").forecast, lambda s: got.put(json.loads(s.payload.to_string())))
        try:
            assert fetch_forecasts(client, "r1", timeout=2.0) == []  # nothing made yet: no reply
            first = _msg(60.0, CdAleak=(180.0, 150.0, 220.0))
            deadline = time.monotonic() + WAIT_S  # the subscription reaches the hub: the first put arrives
            while got.empty():
                assert time.monotonic() < deadline, "no forecast reached the subscriber"
                pub._forecast_gate = ForecastGate()  # each try is a first message
                assert pub.put_forecast(first)
                try:
                    got.put(got.get(timeout=0.2))
                except queue.Empty:
                    continue
            assert got.get() == first
            quiet = _msg(61.0, CdAleak=(181.0, 151.0, 219.0))
            pub._forecast_gate = ForecastGate(clock=lambda: 0.0)
            assert pub.put_forecast(first) and not pub.put_forecast(quiet)
            assert got.get(timeout=WAIT_S) == first
            assert fetch_forecasts(client, "r1", timeout=5.0) == [quiet]  # the latest, put or not
            with pytest.raises(Exception, match="forecast.rig: 'r2'"):
                pub.publish_forecast({**quiet, "rig": "r2"})
        finally:
            sub.undeclare()


@pytest.fixture(scope="module")
def wear_log(tmp_path_factory):
    """240 s of the reference simulator (truth drawn within 10 % of Table 9, seed >= 1000): the leakage grows
    linearly and leaves its default band (3 x Table 9) at 180 s. As a CSV log."""
    from conftest import get_records
    from reference import draw_truth, msp25_spec
    from reference.tables import MSP25_FREE

    truth = draw_truth(1101, 0.1, "msp25")
    v0, edge = truth["CdAleak"], 3.0 * MSP25_FREE["CdAleak"]
    end = v0 + (edge - v0) * WEAR_S / EXIT_S
    spec = msp25_spec(1101, duration=WEAR_S, truth=truth,
                      time_varying={"CdAleak": {"kind": "ramp", "t0": 0.0, "t1": WEAR_S, "start": v0, "end": end}})
    rec = get_records([spec], workers=1)[0]
    path = tmp_path_factory.mktemp("wear") / "wear.csv"
    rec.to_csv(path)
    return path


@pytest.mark.slow
def test_the_service_puts_each_rigs_forecast_and_answers_get_with_the_latest(wear_log, tmp_path):
    port = free_port()
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "workers": 0},
        "rig": [{"name": "rig-w", "source": str(wear_log), "speed": 0.0, "forecast_horizon_s": 600.0},
                {"name": "idle", "source": "zenoh://fpdd/idle/samples"}],  # keeps the service (and its get) up
    }, str(tmp_path / "rigs.toml"))
    stop = threading.Event()
    summaries: dict = {}
    twins: dict = {}
    received: queue.Queue = queue.Queue()
    statuses: queue.Queue = queue.Queue()
    th = threading.Thread(target=serve, args=(cfg, stop), kwargs={"summaries": summaries, "twins": twins})
    with zenoh.open(zenoh_config("peer", connect=[f"tcp/127.0.0.1:{port}"])) as session:
        subs = [session.declare_subscriber("fpdd/*/forecast", lambda s: received.put(
                    (str(s.key_expr), s.encoding, json.loads(s.payload.to_string())))),
                session.declare_subscriber("fpdd/rig-w/status", lambda s: statuses.put(
                    json.loads(s.payload.to_string())))]
        th.start()
        try:
            _wait_finished(statuses)  # the rig finishes its log (the idle rig keeps the service up)
            latest = fetch_forecasts(session, "*", timeout=5.0)
        finally:
            for s in subs:
                s.undeclare()
            stop.set()
            th.join(timeout=60.0)
    assert not th.is_alive()
    puts = []
    while not received.empty():
        puts.append(received.get())
    twin = twins["rig-w"]
    made = _messages(twin)
    assert len(made) >= 100  # one per second of record once the trend shows
    assert puts and {k for k, _, _ in puts} == {"fpdd/rig-w/forecast"}
    assert all(str(e) == "application/json" for _, e, _ in puts)
    msgs = [m for _, _, m in puts]
    for m in msgs:
        validate(m, FORECAST_SCHEMA, "forecast")
        assert m["units"]["t_exit"] == "s" and m["units"]["p_within_horizon"] == "1"
        assert m["rig"] == "rig-w" and m["horizon_s"] == 600.0
    # every put is a message the twin made (in order; one with no forecast left says they ended), fewer than it made
    by_t = {m["t_ns"]: m for m in made}  # the service keeps the last FORECASTS_KEPT forecasts: the messages since
    assert [m["t_ns"] for m in msgs] == sorted(m["t_ns"] for m in msgs)
    kept = [m for m in msgs if m["forecasts"] and m["t_ns"] > made[0]["t_ns"]]
    assert kept and all(by_t[m["t_ns"]] == m for m in kept)
    assert len(msgs) < len(made)
    # get -> the twin's latest: its last forecast, or the message saying they ended
    assert len(latest) == 1 and (latest[0] == made[-1] or (latest[0]["forecasts"] == {} and not twin._forecast_shown
                                                             and latest[0]["t_ns"] > made[-1]["t_ns"]))
    leak = [m["forecasts"]["CdAleak"] for m in msgs if "CdAleak" in m["forecasts"]]
    assert leak and all(f["parameter"] == "CdAleak" and f["edge"] == "high" for f in leak)
    before = [f for f in leak if f["t"] < EXIT_S]  # forecasts put before the leakage left its band
    assert before and all(f["remaining_s"] == pytest.approx(f["t_exit"] - f["t"]) for f in before)
    assert before[0]["t"] <= EXIT_S - 60.0 and abs(before[-1]["t_exit"] - EXIT_S) <= 10.0  # early, then close


def _messages(twin) -> list[dict]:
    """The forecast messages the rig's twin made, as it hands them to its publisher."""
    from twin.online.events.forecast import forecast_message

    return forecast_message(twin.rig.name, list(twin.forecasts), twin.forecast.horizon_s)


@pytest.mark.slow
def test_a_maintenance_sent_with_twin_maintenance_restarts_the_forecast_and_survives_a_restart(wear_log, tmp_path,
                                                                                              capsys):
    """``twin maintenance`` over a real loopback session to the real service: the event is recorded (its reply),
    the rig's standing early alarm returns naming it, the leakage's forecast starts afresh, the latest forecast
    says it was maintained; a refused event is one line. A second run of the service on the same journal resumes
    from the checkpoint without applying it again."""
    from twin import cli
    from twin.service.maintenance import maintenance_path
    from twin.service.store import Store

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg = parse_config({
        "zenoh": {"mode": "peer", "listen": [endpoint]},
        "service": {"journal_dir": str(tmp_path / "journal"), "workers": 0},
        "rig": [{"name": "rig-w", "source": str(wear_log), "speed": 6.0, "forecast_horizon_s": 600.0},
                {"name": "idle", "source": "zenoh://fpdd/idle/samples"}],
    }, str(tmp_path / "rigs.toml"))
    stop = threading.Event()
    twins: dict = {}
    alarms: queue.Queue = queue.Queue()
    statuses: queue.Queue = queue.Queue()
    forecasts: queue.Queue = queue.Queue()
    th = threading.Thread(target=serve, args=(cfg, stop), kwargs={"twins": twins})
    with zenoh.open(zenoh_config("peer", connect=[endpoint])) as session:
        subs = [session.declare_subscriber("fpdd/rig-w/alarm", lambda s: alarms.put(json.loads(s.payload.to_string()))),
                session.declare_subscriber("fpdd/rig-w/status", lambda s: statuses.put(
                    json.loads(s.payload.to_string()))),
                session.declare_subscriber("fpdd/rig-w/forecast", lambda s: forecasts.put(
                    json.loads(s.payload.to_string())))]
        th.start()
        try:
            while True:  # the early alarm of the wearing seal
                a = alarms.get(timeout=600.0)
                if a["level"] == "early":
                    break
            capsys.readouterr()
            assert cli.main(["maintenance", "--rig", "rig-w", "--parameter", "Wn", "--connect", endpoint,
                             "--timeout", "10"]) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "'Wn' not tracked" in err[0] and "Traceback" not in err[0]
            assert cli.main(["maintenance", "--rig", "rig-w", "--parameter", "CdAleak", "--note", "seal replaced",
                             "--connect", endpoint, "--json"]) == 0
            ev = json.loads(capsys.readouterr().out)
            assert ev["rig"] == "rig-w" and ev["seq"] == 1 and ev["parameters"] == ["CdAleak"]
            assert ev["note"] == "seal replaced" and isinstance(ev["wall_ns"], int)
            while True:  # the early alarm returns, naming the maintenance
                a = alarms.get(timeout=WAIT_S)
                if a["parameter"] == "CdAleak" and a["kind"] == "returned" and "maintenance" in a["message"]:
                    break
            assert a["level"] == "ok" and "seal replaced" in a["message"]
            _wait_finished(statuses)
            latest = fetch_forecasts(session, "rig-w", timeout=5.0)
        finally:
            for s in subs:
                s.undeclare()
            stop.set()
            th.join(timeout=60.0)
    assert not th.is_alive()
    twin = twins["rig-w"]
    m = twin.forecast.maintained["CdAleak"]
    assert m["seq"] == 1 and m["note"] == "seal replaced" and twin.forecast.maintenance_seq == 1
    # the forecast started afresh: none of the leakage for the settling time and the least span after it
    after = [f.t for f in twin.forecasts if f.parameter == "CdAleak" and f.t > m["t"]]
    assert not after or after[0] >= m["t"] + twin.forecast.settle_s + twin.forecast.min_span_s
    puts = []
    while not forecasts.empty():
        puts.append(forecasts.get())
    assert any(p.get("maintenance", {}).get("CdAleak", {}).get("seq") == 1 for p in puts)
    for p in puts:
        validate(p, FORECAST_SCHEMA, "forecast")
    assert latest and latest[0]["maintenance"]["CdAleak"]["note"] == "seal replaced"
    assert len(maintenance_path(tmp_path / "journal", "rig-w").read_text().splitlines()) == 1

    def journal() -> list:
        with Store(tmp_path / "journal" / "rig-w.db", writer=False) as store:
            return store.alarms("rig-w")

    first = journal()
    returned = [a for a in first if a.parameter == "CdAleak" and a.kind == "returned" and "maintenance" in a.message]
    assert len(returned) == 1
    # the service again on the same journal: resumed from the checkpoint at the log's end, nothing applied again
    cfg2 = parse_config({"zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
                         "service": {"journal_dir": str(tmp_path / "journal"), "workers": 0},
                         "rig": [{"name": "rig-w", "source": str(wear_log), "speed": 0.0,
                                  "forecast_horizon_s": 600.0}]}, str(tmp_path / "rigs.toml"))
    again: dict = {}
    serve(cfg2, twins=again)
    assert again["rig-w"].forecast.maintenance_seq == 1 and again["rig-w"].forecast.maintained["CdAleak"]["seq"] == 1
    assert [(a.seq, a.identity) for a in journal()] == [(a.seq, a.identity) for a in first]


def test_twin_top_shows_a_parameters_last_maintenance():
    from rich.console import Console

    from twin.commands.top import TopState, render

    state = TopState()
    msg = {**_msg(70.0, Ffric=(900.0, 500.0, 3000.0)),
           "maintenance": {"CdAleak": {"t": 64.0, "seq": 1, "note": "seal replaced", "wall_ns": 1}}}
    validate(msg, FORECAST_SCHEMA, "forecast")
    state.put("forecast", msg)
    snap = state.snapshot()
    assert snap["r1"]["params"]["CdAleak"]["maintenance"]["seq"] == 1
    console = Console(width=160, record=True)
    console.print(render(snap, "test", live=False))
    text = console.export_text()
    assert "maintained #1 (seal replaced)" in text and "Ffric" in text


def test_twin_maintenance_with_no_twin_to_answer_is_one_line_naming_the_key_and_endpoint(capsys):
    from twin import cli

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    assert cli.main(["maintenance", "--rig", "r9", "--parameter", "CdAleak", "--connect", endpoint,
                     "--timeout", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no running twin answered on fpdd/r9/maintenance" in err[0] and endpoint in err[0]
