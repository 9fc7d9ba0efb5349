"""A rig's twin publishes through the Publisher protocol only: the Zenoh publisher (a real loopback session),
the runner's outbox, the live view's tee and the offline track each receive the same estimate text (written
by the one estimate encoder, or the event whose JSON is that text), and the status counters a publisher
adds (the outbox's ``alarm_seq``) reach the status."""

from __future__ import annotations

import json
import queue
import threading

import pytest
import zenoh

from net_helpers import free_port
from fpdd.zenohconf import zenoh_config
from twin.online.events import EstimateEvent, event_to_json
from twin.service.bus import TwinPublisher
from twin.service.config import parse_config
from twin.service.journal import AlarmJournal
from twin.service.outbox import Outbox
from twin.service.publisher import Publisher
from twin.service.rig import RigTwin
from twin.service.track import SequenceNumbers

WAIT_S = 10.0
EVERY = 100
PROBE = '{"probe":true}'


@pytest.fixture(scope="module")
def samples():
    from twin.models import msp25 as M
    from twin.models.scenario import simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite

    _, xr = excite(M.MODEL, 1.0, 1e-3, seed=1031)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [], noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=1031)
    return rec.to_samples()


def _rig(name: str):
    return parse_config({"rig": [{"name": name, "source": "x.mcap"}]}, "rigs.toml").rigs[0]


class _Events(Publisher):
    """Takes estimates as events (the protocol's default for the JSON payload), keeps their JSON."""

    def __init__(self) -> None:
        self.estimates: list[str] = []

    def publish_alarm(self, event):
        return event

    def publish_estimate(self, event: EstimateEvent) -> None:
        self.estimates.append(event_to_json(event))

    def publish_status(self, event):
        return event


def test_every_publisher_gets_the_same_estimate_text(samples, tmp_path):
    rig = _rig("rig-p")
    # the event path: a publisher that keeps the protocol's default (no JSON payloads)
    events = _Events()
    RigTwin(rig, events, estimate_every=EVERY).write(samples)
    assert len(events.estimates) == len(samples) // EVERY == 10
    # the runner's outbox: the payloads, batched for the service's process
    out: queue.Queue = queue.Queue()
    with AlarmJournal(tmp_path / "outbox.db") as journal:
        box = Outbox(rig.name, journal, out)
        twin = RigTwin(rig, box, estimate_every=EVERY)
        twin.write(samples)
        twin.publish_status(force=True)
        box.flush()
    batched: list[tuple] = []
    while not out.empty():
        kind, name, batch = out.get_nowait()
        assert (kind, name) == ("batch", rig.name)
        batched += batch
    assert [item[1] for item in batched if item[0] == "estimate"] == events.estimates
    status = json.loads([item[1] for item in batched if item[0] == "status"][-1])
    assert status["counters"]["alarm_seq"] == 0  # the outbox's own counter, through status_counters()
    # the offline track's publisher takes the payload (nothing to publish) and counts every estimate
    offline = RigTwin(rig, SequenceNumbers(), estimate_every=EVERY)
    offline.write(samples)
    assert offline.stats.estimates == len(events.estimates)
    for text in events.estimates:
        assert text == event_to_json(EstimateEvent.from_dict(json.loads(text)))


def test_a_twin_on_a_zenoh_publisher_puts_the_encoders_text(samples, tmp_path):
    """RigTwin -> TwinPublisher (publish_estimate_json) -> Zenoh loopback -> a subscriber: the very text."""
    rig = _rig("rig-z")
    events = _Events()
    RigTwin(rig, events, estimate_every=EVERY).write(samples)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got: list[str] = []
    heard, done = threading.Event(), threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        text = sample.payload.to_string()
        if text == PROBE:  # the subscription has reached the publisher
            heard.set()
            return
        got.append(text)
        if len(got) == len(events.estimates):
            done.set()

    with zenoh.open(zenoh_config(listen=[endpoint])) as hub, zenoh.open(zenoh_config(connect=[endpoint])) as s, \
            AlarmJournal(tmp_path / "j.db") as journal, TwinPublisher(hub, rig.name, journal) as pub:
        sub = s.declare_subscriber(f"fpdd/{rig.name}/estimate", on_sample)
        try:
            for _ in range(int(WAIT_S / 0.1)):  # the subscription may take a moment to propagate
                pub.put_payload("estimate", PROBE)
                if heard.wait(0.1):
                    break
            else:
                pytest.fail(f"the subscriber heard nothing within {WAIT_S} s")
            twin = RigTwin(rig, pub, estimate_every=EVERY)
            twin.write(samples)
            assert done.wait(WAIT_S), f"{len(got)} of {len(events.estimates)} estimates arrived"
        finally:
            sub.undeclare()
    assert got == events.estimates
