"""The Foxglove live view on a real WebSocket connection (loopback).

A client speaks the documented Foxglove WebSocket protocol itself (``websockets``;
subprotocol ``foxglove.websocket.v1`` alone, as Foxglove offers it; the view also
accepts foxglove-sdk's own name ``foxglove.sdk.v1``): it receives ``serverInfo``
and ``advertise``, subscribes, and decodes the binary message frames (opcode 1:
subscription id, log time, JSON payload), which must validate against the
schema the channel advertised.  Every wait is bounded; nothing sleeps a fixed time.
"""

from __future__ import annotations

import json
import os
import struct
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from websockets.sync.client import connect

from replay.base import Samples
from twin.service.bus import TwinPublisher
from fpdd.zenohconf import zenoh_config
from twin.online.baseline import default_baseline
from net_helpers import free_port
from twin.online.events import EstimateEvent, StatusEvent, validate
from twin.service.journal import AlarmJournal
from twin.reports.units import signal_unit
from twin.service.live_view import TOPICS, LiveView, foxglove_layout

sys.path.insert(0, os.path.dirname(__file__))
from event_helpers import T0_NS, wear_forecasts  # noqa: E402

WAIT_S = 10.0
#: the documented protocol name, the one Foxglove offers
SUBPROTOCOLS = ["foxglove.websocket.v1"]
ROOT = Path(__file__).resolve().parents[1]


class Client:
    """A minimal foxglove.websocket.v1 client."""

    def __init__(self, url: str, subprotocols=SUBPROTOCOLS) -> None:
        self._conn = connect(url, subprotocols=subprotocols, open_timeout=WAIT_S, max_size=None)
        self.ws = self._conn.__enter__()
        assert self.ws.subprotocol == subprotocols[0]
        self.info = self.recv_json("serverInfo")
        self.channels: dict[str, dict] = {}
        while set(self.channels) != {t for t, _ in TOPICS.values()}:
            for ch in self.recv_json("advertise")["channels"]:
                self.channels[ch["topic"]] = ch
        self.sub_of: dict[int, str] = {}

    def recv_json(self, op: str) -> dict:
        while True:
            msg = self.ws.recv(timeout=WAIT_S)
            if isinstance(msg, str):
                d = json.loads(msg)
                if d["op"] == op:
                    return d

    def subscribe(self, topics) -> None:
        subs = []
        for i, topic in enumerate(topics, start=1):
            subs.append({"id": i, "channelId": self.channels[topic]["id"]})
            self.sub_of[i] = topic
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def messages(self, want: dict[str, int], timeout: float = WAIT_S) -> dict[str, list[tuple[int, dict]]]:
        """Message data frames until ``want[topic]`` of each arrived: topic -> [(log time ns, payload)]."""
        got: dict[str, list] = {t: [] for t in want}
        while any(len(got[t]) < n for t, n in want.items()):
            msg = self.ws.recv(timeout=timeout)
            if isinstance(msg, bytes):
                assert msg[0] == 0x01, f"opcode {msg[0]}"
                sub, log_time = struct.unpack_from("<IQ", msg, 1)
                topic = self.sub_of[sub]
                if topic in got:
                    got[topic].append((log_time, json.loads(msg[13:])))
        return got

    def close(self) -> None:
        self._conn.__exit__(None, None, None)


def schema_of(ch: dict) -> dict:
    assert ch["encoding"] == "json" and ch["schemaEncoding"] == "jsonschema"
    return json.loads(ch["schema"])


def check(payload: dict, ch: dict) -> None:
    validate(payload, schema_of(ch), ch["schemaName"])


@pytest.fixture
def view():
    with LiveView(port=0, bands={"rig-1": default_baseline("msp25")}, signal_rate_hz=100.0) as v:
        yield v


def estimate(rig: str, i: int) -> EstimateEvent:
    return EstimateEvent(rig=rig, t_ns=T0_NS + i * 50_000_000, t_s=i * 0.05,
                         params={"CdAleak": {"value": 3.3e-9 * (1 + 0.1 * i), "std": 3e-10, "unit": "m^2"},
                                 "wn": {"value": 2 * np.pi * 43.0, "std": 1.0, "unit": "rad/s"},
                                 "zeta": {"value": 0.37, "std": 0.002, "unit": "1"}},
                         nis=1.2, status="ok")


def test_messages_arrive_with_their_schemas(view, tmp_path):
    client = Client(view.url)
    try:
        assert client.info["name"] == "fpdd-twin"
        names = {t: ch["schemaName"] for t, ch in client.channels.items()}
        assert names == {"/rig/signals": "fpdd.live.Signals", "/twin/estimate": "EstimateEvent",
                         "/twin/status": "StatusEvent", "/twin/forecast": "fpdd.Forecast", "/twin/alarm": "AlarmEvent",
                         "/twin/alarm_log": "foxglove.Log"}
        client.subscribe(list(client.channels))
        for topic in client.channels:
            assert view.wait_subscribed(topic, WAIT_S), topic
        # a second of 1 kHz samples: decimated to 100 per second
        n = 1000
        t_ns = T0_NS + np.arange(n, dtype=np.int64) * 1_000_000
        sig = {"x": 1e-3 * np.sin(np.arange(n) / 50), "x_ref": np.zeros(n), "u": np.full(n, 0.5),
               "pA": np.full(n, 10e6), "pB": np.full(n, 9e6)}
        assert view.signals("rig-1", Samples(t_ns, sig)) == 100
        # a twin's publisher wrapped by the view: whatever it publishes is shown
        with AlarmJournal(tmp_path / "alarms.db") as journal:
            from event_helpers import alarm

            tee = view.tee(_Recorder(journal))
            tee.publish_estimate(estimate("rig-1", 1))
            tee.publish_status(StatusEvent(rig="rig-1", t_ns=T0_NS, state="running",
                                           parameters={"CdAleak": "alarm"}, counters={"samples": 1000}))
            published = tee.publish_alarm(alarm("rig-1", 2))
            assert published.seq == 1
        got = client.messages({"/rig/signals": 100, "/twin/estimate": 1, "/twin/status": 1, "/twin/alarm": 1,
                               "/twin/alarm_log": 1})
    finally:
        client.close()
    for topic, msgs in got.items():
        for log_time, payload in msgs:
            check(payload, client.channels[topic])
            ts = payload["timestamp"]
            assert ts["sec"] * 1_000_000_000 + ts["nsec"] == log_time  # Foxglove time = the sample's t_ns
    sig0 = got["/rig/signals"][0][1]  # SI with the unit named, as in the rig's MCAP; display units under display
    assert sig0["rig"] == "rig-1" and sig0["pA"] == pytest.approx(10e6) and sig0["u"] == 0.5 and sig0["x"] == 0.0
    assert sig0["units"] == {"x": "m", "x_ref": "m", "u": "V", "pA": "Pa", "pB": "Pa"}
    assert sig0["display"]["units"] == {"x": "mm", "x_ref": "mm", "u": "V", "pA": "MPa", "pB": "MPa"}
    assert sig0["display"]["pA"] == pytest.approx(10.0) and sig0["display"]["pB"] == pytest.approx(9.0)
    sig5 = got["/rig/signals"][5][1]  # a sample 50 ms in: x = 1 mm sin(50/50)
    assert sig5["x"] == pytest.approx(1e-3 * np.sin(1.0), rel=1e-12)
    assert sig5["display"]["x"] == pytest.approx(np.sin(1.0), rel=1e-12)
    described = json.loads(client.channels["/rig/signals"]["schema"])["properties"]
    assert described["x"]["description"].endswith(", m") and described["pA"]["description"].endswith(", Pa")
    assert described["display"]["properties"]["pA"]["description"].endswith(", MPa")
    assert [m["t_s"] for _, m in got["/rig/signals"][:3]] == pytest.approx([0.0, 0.01, 0.02])
    est = got["/twin/estimate"][0][1]["params"]
    assert est["wn"]["value"] == pytest.approx(2 * np.pi * 43.0) and est["wn"]["unit"] == "rad/s"  # SI, unit named
    assert est["CdAleak"]["unit"] == "m^2" and est["CdAleak"]["value"] == pytest.approx(3.63e-9)
    assert est["CdAleak"]["lo95"] < est["CdAleak"]["value"] < est["CdAleak"]["hi95"]
    band = default_baseline("msp25")["CdAleak"]
    assert est["CdAleak"]["band_lo"] == pytest.approx(band.lo) and est["zeta"]["unit"] == "1"
    a = got["/twin/alarm"][0][1]
    assert a["seq"] == 1 and a["level"] == "alarm" and a["rig"] == "rig-1"
    assert a == {**published.to_dict(), "timestamp": a["timestamp"]}  # the AlarmEvent, as on Zenoh and in MCAP
    assert got["/twin/alarm_log"][0][1]["level"] == 4 and "ALARM" in got["/twin/alarm_log"][0][1]["message"]
    assert got["/twin/status"][0][1]["parameters"] == {"CdAleak": "alarm"}


class _Recorder:
    """A publisher as the service's: journals alarms (numbering them), keeps the rest."""

    def __init__(self, journal: AlarmJournal) -> None:
        self.journal = journal

    def publish_alarm(self, ev):
        return self.journal.record(ev).event

    def publish_estimate(self, ev):
        return None

    def publish_status(self, ev):
        return ev


def test_follows_a_twin_over_zenoh(view, tmp_path):
    """What a real TwinPublisher puts on Zenoh (loopback, scouting off) reaches the Foxglove client."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    client = Client(view.url)
    try:
        client.subscribe(["/twin/estimate", "/twin/alarm"])
        assert view.wait_subscribed("/twin/estimate", WAIT_S) and view.wait_subscribed("/twin/alarm", WAIT_S)
        with zenoh.open(zenoh_config(listen=[endpoint])) as hub, zenoh.open(zenoh_config(connect=[endpoint])) as s, \
                AlarmJournal(tmp_path / "j.db") as journal, TwinPublisher(hub, "rig-2", journal) as pub:
            view.follow(s, "*")
            from event_helpers import alarm

            # the subscription may take a moment to propagate: publish until the view has shown one
            for i in range(int(WAIT_S / 0.2)):
                pub.publish_estimate(estimate("rig-2", i))
                try:
                    first = client.messages({"/twin/estimate": 1}, timeout=0.2)
                    break
                except TimeoutError:
                    continue
            else:
                pytest.fail(f"no estimate reached the Foxglove client within {WAIT_S} s")
            pub.publish_alarm(alarm("rig-2", 5))
            got = client.messages({"/twin/alarm": 1})
    finally:
        client.close()
    assert first["/twin/estimate"][0][1]["rig"] == "rig-2"
    check(got["/twin/alarm"][0][1], client.channels["/twin/alarm"])
    assert got["/twin/alarm"][0][1]["seq"] == 1


def test_the_shipped_layout_plots_every_parameter_with_its_band_and_lists_the_alarms():
    shipped = json.loads((ROOT / "deploy" / "foxglove-layout.json").read_text(encoding="utf-8"))
    assert shipped == foxglove_layout(), "regenerate: python -m twin.service.live_view --layout deploy/foxglove-layout.json"
    fields = {topic: set(schema["properties"]) for topic, schema in TOPICS.values()}
    param_fields = set(json.loads(json.dumps(TOPICS["estimate"][1]))["properties"]["params"]
                       ["additionalProperties"]["properties"])
    display_fields = set(json.loads(json.dumps(TOPICS["estimate"][1]))["properties"]["params"]
                         ["additionalProperties"]["properties"]["display"]["properties"])
    signal_display_fields = set(TOPICS["signals"][1]["properties"]["display"]["properties"])
    paths = [p["value"] for c in shipped["configById"].values() for p in c.get("paths", [])]
    for name in ("x", "x_ref", "pA", "pB"):  # the rig's signals in display units (mm, MPa), SI in the message
        assert f"/rig/signals{{rig==$rig}}.display.{name}" in paths
    for name in ("Ffric", "CdAleak", "Cd", "zeta", "wn"):  # in display units, as `twin params` shows them
        for f in ("value", "lo95", "hi95", "band_lo", "band_hi"):
            assert f"/twin/estimate{{rig==$rig}}.params.{name}.display.{f}" in paths
    forecast_fields = set(json.loads(json.dumps(TOPICS["forecast"][1]))["properties"]["forecasts"]
                          ["additionalProperties"]["properties"])
    for name in ("Ffric", "CdAleak", "Cd", "zeta", "wn"):  # the remaining time with its 90 % interval
        for f in ("remaining_s", "remaining_lo_s", "remaining_hi_s"):
            assert f"/twin/forecast{{rig==$rig}}.forecasts.{name}.{f}" in paths
    for p in paths:
        topic, rest = p.split("{", 1)
        field = rest.split("}.", 1)[1].split(".")
        assert field[0] in fields[topic] and (field[0] != "params" or field[2] in param_fields), p
        assert field[0] != "params" or field[2] != "display" or field[3] in display_fields, p
        assert field[0] != "forecasts" or field[2] in forecast_fields, p
        assert topic != "/rig/signals" or (field[0] == "display" and field[1] in signal_display_fields), p
    titles = [c.get("title", "") for c in shipped["configById"].values()]
    assert any("leaves its band" in t and "[s]" in t for t in titles)
    assert {"wn [Hz]", "CdAleak [mm²]", "Ffric [N]", "zeta"} <= set(titles)
    assert any(c.get("topicToRender") == "/twin/alarm_log" for c in shipped["configById"].values())
    assert shipped["globalVariables"]["rig"]


@pytest.mark.parametrize("subprotocol", ["foxglove.websocket.v1", "foxglove.sdk.v1"])
def test_both_subprotocol_names_are_accepted(view, subprotocol):
    """Foxglove offers the documented name; foxglove-sdk's own name works too; the same messages either way."""
    client = Client(view.url, [subprotocol])
    try:
        assert client.ws.subprotocol == subprotocol and client.info["name"] == "fpdd-twin"
        client.subscribe(["/twin/estimate"])
        assert view.wait_subscribed("/twin/estimate", WAIT_S)
        view.estimate(estimate("rig-1", 3))
        got = client.messages({"/twin/estimate": 1})
    finally:
        client.close()
    assert got["/twin/estimate"][0][1]["t_s"] == pytest.approx(0.15)


def test_an_estimate_is_the_same_message_in_the_twins_mcap_and_live(tmp_path):
    """A rig's twin records its estimates to MCAP and shows them live: equal messages (SI with units, 95 %
    intervals and bands in both), and equal to what it puts on Zenoh."""
    from mcap.reader import make_reader

    from replay.mcapio import McapSink
    from twin.models import msp25 as M
    from twin.models.scenario import simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite
    from twin.online.events import event_to_json
    from twin.service.config import parse_config
    from twin.service.rig import RigTwin

    rig = parse_config({"rig": [{"name": "rig-m", "source": "x.mcap"}]}, "rigs.toml").rigs[0]
    _, xr = excite(M.MODEL, 2.0, 1e-3, seed=1001)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [], noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=1001)
    path = tmp_path / "twin.mcap"
    with LiveView(port=0) as view:
        client = Client(view.url)
        try:
            client.subscribe(["/twin/estimate"])
            assert view.wait_subscribed("/twin/estimate", WAIT_S)
            with McapSink(str(path)) as recorder:
                twin = RigTwin(rig, view.tee(None), recorder, estimate_every=200)
                twin.write(rec.to_samples())
                n = twin.stats.estimates
            live = [m for _, m in client.messages({"/twin/estimate": n})["/twin/estimate"]]
        finally:
            client.close()
    with open(path, "rb") as f:
        recorded = [(ch.schema_id, json.loads(m.data)) for _, ch, m in
                    make_reader(f).iter_messages(topics=["/twin/estimate"])]
    assert n == 10 and len(recorded) == n
    assert [m for _, m in recorded] == live
    first = live[0]
    assert set(first["params"]) == set(rig.track)
    for name, p in first["params"].items():
        b = rig.baseline[name]
        assert p["lo95"] < p["value"] < p["hi95"] and p["unit"]
        assert (p["band_lo"], p["band_hi"], p["baseline"]) == pytest.approx((b.lo, b.hi, b.value))
        spec = M.MODEL.params().spec(name)
        assert p["display"]["unit"] == (spec.display_unit or spec.unit)
        for f in ("value", "lo95", "hi95", "band_lo", "band_hi", "baseline"):
            assert p["display"][f] == pytest.approx(p[f] * spec.display_scale, rel=1e-12), (name, f)
    # the service's Zenoh payload of the same numbers is that message too (without the Foxglove time)
    values = np.array([first["params"][n]["value"] for n in twin.tracker.tracked])
    stds = np.array([first["params"][n]["std"] for n in twin.tracker.tracked])
    text = twin._estimate_json(first["t_ns"], first["t_s"], values, stds, first["nis"], first["status"])
    assert json.loads(text) == {k: v for k, v in first.items() if k != "timestamp"}
    assert text == event_to_json(EstimateEvent.from_dict(json.loads(text)))


def _field(msg: dict, path: list[str]):
    for key in path:
        assert isinstance(msg, dict) and key in msg, f"{'.'.join(path)} not in {sorted(msg)}"
        msg = msg[key]
    return msg


@pytest.mark.slow
def test_twin_serve_feeds_every_topic_and_field_of_its_layout_and_stops_cleanly_with_a_client(tmp_path):
    """``twin serve --foxglove 0``: a Foxglove client (documented subprotocol) receives the rig's signals,
    estimates, statuses and alarms, with every field the written layout's panels read, for the layout's rig
    (the first served); Ctrl-C with the client connected ends the service cleanly (exit 0, no traceback)."""
    import queue
    import re
    import signal
    import subprocess
    import threading

    from mcap.reader import make_reader  # noqa: F401  (the log below is an MCAP file)

    from replay.mcapio import McapSink
    from twin.models import msp25 as M
    from twin.models.scenario import Drift, simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite

    log = tmp_path / "rig.mcap"
    _, xr = excite(M.MODEL, 12.0, 1e-3, seed=1002)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("Ffric", 3.0, 5.0, shape="step")],
                           noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}, seed=1002)
    with McapSink(str(log)) as sink:
        sink.write(rec.to_samples())
    cfg = tmp_path / "rigs.toml"
    cfg.write_text(f"""[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{free_port()}"]
[service]
journal_dir = "{tmp_path / 'journal'}"
estimate_every = 100
[[rig]]
name = "rig-a"
source = "{log}"
speed = 1.0
[[rig]]
name = "idle"
source = "zenoh://fpdd/idle/samples"
""", encoding="utf-8")
    proc = subprocess.Popen([sys.executable, "-m", "twin.cli", "serve", "--config", str(cfg), "--foxglove", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: queue.Queue[str] = queue.Queue()
    seen: list[str] = []
    reader = threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True)  # type: ignore[union-attr]
    reader.start()
    try:
        while True:
            line = lines.get(timeout=60.0)
            seen.append(line)
            m = re.search(r"Foxglove live view on (ws://\S+) \(layout for rig (\S+): (.+)\)$", line.strip())
            if m:
                break
        url, rig, layout_path = m.groups()
        assert rig == "rig-a"
        layout = json.loads(Path(layout_path).read_text(encoding="utf-8"))
        assert layout["globalVariables"]["rig"] == "rig-a"
        client = Client(url)
        try:
            client.subscribe(list(client.channels))
            try:
                got = client.messages({"/rig/signals": 20, "/twin/estimate": 2, "/twin/status": 1,
                                       "/twin/alarm": 1, "/twin/alarm_log": 1}, timeout=60.0)
            except Exception as exc:  # the live view went away: say what the service printed, and whether it ran
                time.sleep(1.0)
                said = "".join(seen) + "".join(lines.get() for _ in range(lines.qsize()))
                raise AssertionError(f"{exc!r}; the service's exit code {proc.poll()}, its output:\n"
                                     f"{said[-3000:]}") from exc
            proc.send_signal(signal.SIGINT)  # Ctrl-C with the client still connected
            assert proc.wait(timeout=60.0) == 0
        finally:
            client.close()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        reader.join(timeout=WAIT_S)
        proc.stdout.close()  # type: ignore[union-attr]
    out = "".join(seen)
    while not lines.empty():
        out += lines.get()
    assert "Traceback" not in out and "Error" not in out, out[-3000:]
    for topic, msgs in got.items():
        for _, payload in msgs:
            check(payload, client.channels[topic])
    ours = {t: [m for _, m in msgs if m.get("rig", m.get("name")) == "rig-a"] for t, msgs in got.items()}
    assert ours["/rig/signals"][0]["x"] is not None and ours["/rig/signals"][0]["pA"] > 1e6  # SI: Pa
    for panel in layout["configById"].values():
        paths = [p["value"] for p in panel.get("paths", [])] + ([panel["topicPath"]] if "topicPath" in panel else [])
        for p in paths:
            topic, rest = p.split("{", 1)
            assert rest.startswith("rig==$rig}"), p
            field = [f for f in rest.split("}", 1)[1].split(".") if f]
            if topic == "/twin/forecast":  # only a wearing parameter has one: test_forecasts_are_shown_...
                continue
            assert ours[topic], f"no message of rig-a on {topic}"
            for msg in ours[topic]:
                value = _field(msg, field)
                assert field == [] or isinstance(value, (int, float)) or value is None, p
                if topic == "/twin/estimate" and field[0] == "params":  # display unit: SI x the spec's scale
                    assert field[2] == "display", p
                    spec = M.MODEL.params().spec(field[1])
                    si = _field(msg, field[:2] + field[3:])
                    assert _field(msg, field[:3] + ["unit"]) == (spec.display_unit or spec.unit)
                    assert (value is None) == (si is None), p
                    assert value is None or value == pytest.approx(si * spec.display_scale, rel=1e-12), p
                    assert value is not None or field[3] not in ("value", "lo95", "hi95"), p
                if topic == "/rig/signals":  # the display unit (the one in the panel's title): SI x its scale
                    assert field[0] == "display", p
                    unit, scale = signal_unit(field[1], M.MODEL.name)
                    assert msg["display"]["units"][field[1]] == unit and f"[{unit}]" in panel["title"], p
                    assert msg["units"][field[1]] == {"x": "m", "x_ref": "m", "pA": "Pa", "pB": "Pa"}[field[1]]
                    assert value == pytest.approx(msg[field[1]] * scale, rel=1e-12), p
        if "topicToRender" in panel:
            assert ours[panel["topicToRender"]], panel["topicToRender"]
    assert ours["/twin/alarm"][0]["parameter"] == "Ffric"


def test_forecasts_are_shown_with_their_schema_from_a_twin_and_over_zenoh(view, tmp_path):
    """``/twin/forecast``: what a rig's twin hands its publisher (through :meth:`LiveView.tee`) and what a real
    TwinPublisher puts on ``fpdd/<rig>/forecast`` (loopback, scouting off) reach the Foxglove client as the
    same message with its Foxglove time: the remaining time and its 90 % interval in seconds, units named."""
    msgs = wear_forecasts("rig-1", seed=1202)
    assert len(msgs) > 100
    client = Client(view.url)
    try:
        client.subscribe(["/twin/forecast"])
        assert view.wait_subscribed("/twin/forecast", WAIT_S)
        tee = view.tee(None)
        for m in msgs[-5:]:
            tee.publish_forecast(m)
        shown = client.messages({"/twin/forecast": 5})["/twin/forecast"]
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        with zenoh.open(zenoh_config(listen=[endpoint])) as hub, zenoh.open(zenoh_config(connect=[endpoint])) as s, \
                AlarmJournal(tmp_path / "j.db") as journal, TwinPublisher(hub, "rig-2", journal) as pub:
            view.follow(s, "*")
            other = wear_forecasts("rig-2", 300.0, seed=1202)[-1]
            for _ in range(int(WAIT_S / 0.2)):  # the subscription may take a moment to propagate
                from twin.service.bus import ForecastGate

                pub._forecast_gate = ForecastGate()  # each try is a first message: put
                assert pub.put_forecast(other)
                try:
                    followed = client.messages({"/twin/forecast": 1}, timeout=0.2)["/twin/forecast"]
                    break
                except TimeoutError:
                    continue
            else:
                pytest.fail(f"no forecast reached the Foxglove client within {WAIT_S} s")
    finally:
        client.close()
    for (log_time, payload), made in zip(shown, msgs[-5:]):
        check(payload, client.channels["/twin/forecast"])
        assert log_time == made["t_ns"] and {k: v for k, v in payload.items() if k != "timestamp"} == made
    last = shown[-1][1]["forecasts"]["CdAleak"]
    assert last["remaining_lo_s"] <= last["remaining_s"] <= last["remaining_hi_s"]
    assert 60.0 < last["remaining_s"] < 300.0  # the wear leaves the band at 560 s, forecast at 400 s
    assert shown[-1][1]["units"]["remaining_s"] == "s"
    log_time, payload = followed[0]
    check(payload, client.channels["/twin/forecast"])
    assert payload["rig"] == "rig-2" and {k: v for k, v in payload.items() if k != "timestamp"} == other


def test_a_port_in_use_is_one_line(view):
    from fpdd.errors import SourceError

    with pytest.raises(SourceError, match=rf"Foxglove live view: cannot listen on 127.0.0.1:{view.port}: "):
        LiveView(port=view.port)
