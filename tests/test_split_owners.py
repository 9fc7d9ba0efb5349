"""Two services running one rig at once (the two sides of a split network): every alarm, estimate and status
carries its owner's term, and while two terms publish the owners' statuses, ``AlarmSubscriber`` /
``twin alarms`` and a plain Zenoh subscriber see it in one line. Loopback, explicit endpoints, scouting off."""

from __future__ import annotations

import argparse
import json
import threading
import time
from pathlib import Path

import zenoh

from event_helpers import T0_NS, alarm
from net_helpers import connected
from twin.cli import main as twin_main
from twin.commands.alarms import add_arguments, run
from twin.online.events import EstimateEvent, StatusEvent, event_to_json
from twin.service.bus import TwinPublisher
from twin.service.journal import AlarmJournal
from twin.service.ownership import new_term
from twin.service.subscriber import AlarmSubscriber

WAIT_S = 10.0


def _estimate() -> str:
    return event_to_json(EstimateEvent.of_tracker("r1", T0_NS, 1.0, ["Kleak"], [1e-12], [1e-13], ["m^3/(s Pa)"],
                                                  None, "ok"))


class Statuses:
    """Statuses, alarms and estimates of r1 as a plain Zenoh subscriber gets them."""

    def __init__(self, session: zenoh.Session) -> None:
        self.got: dict[str, list[dict]] = {"status": [], "alarm": [], "estimate": []}
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber("fpdd/r1/*", self._keep)

    def _keep(self, sample: zenoh.Sample) -> None:
        kind = str(sample.key_expr).rsplit("/", 1)[-1]
        if kind in self.got:
            with self._lock:
                self.got[kind].append(json.loads(sample.payload.to_string()))

    def of(self, kind: str) -> list[dict]:
        with self._lock:
            return list(self.got[kind])


def test_two_owners_at_once_are_said_by_their_statuses_and_the_subscriber(hub, endpoint, tmp_path: Path) -> None:
    plain = Statuses(hub)
    first = new_term()
    terms = (first, first + 2500)  # the second side claimed the rig 2.5 s later
    # one side in the listening peer, the other connected to it (peers do not relay for each other)
    with connected(endpoint) as b_session, AlarmJournal(tmp_path / "a.db") as ja, \
            AlarmJournal(tmp_path / "b.db") as jb:
        ja.begin_term("r1", terms[0])
        jb.begin_term("r1", terms[1])
        with TwinPublisher(hub, "r1", ja, term=terms[0]) as a, \
                TwinPublisher(b_session, "r1", jb, term=terms[1]) as b, AlarmSubscriber(hub, "r1") as sub:
            assert a.wait_for_alarm_subscribers(WAIT_S) and b.wait_for_alarm_subscribers(WAIT_S)
            raised = [a.publish_alarm(alarm("r1", 1)), b.publish_alarm(alarm("r1", 2))]
            deadline = time.monotonic() + WAIT_S
            while sub.splits == 0 or not any(s["message"].startswith("split: ") for s in plain.of("status")):
                assert time.monotonic() < deadline, (sub.reports, plain.of("status")[-2:])
                for side in (a, b):
                    side.publish_status(StatusEvent(rig="r1", t_ns=T0_NS, state="running"))
                    side.put_payload("estimate", _estimate())
                try:
                    sub.recv(timeout=0.1)
                except TimeoutError:
                    pass
        plain.sub.undeclare()
    assert [e.term for e in raised] == list(terms)  # journaled with the owner's term
    assert {a["term"] for a in plain.of("alarm")} == set(terms)
    assert {e["term"] for e in plain.of("estimate")} == set(terms)
    assert {s["term"] for s in plain.of("status")} == set(terms)
    said = [s["message"] for s in plain.of("status") if s["message"].startswith("split: ")]
    assert said[0].startswith(f"split: rig r1 is run by two owners at once (terms {terms[0]} and {terms[1]}; "
                              "this one: term ")
    splits = [r for r in sub.reports if r.startswith("split: ")]
    assert splits == [f"split: rig r1 is published by two owners at once (terms {terms[0]} and {terms[1]}): the "
                      "network was split; alarms of both are shown, a number claimed by both is a conflict"]


def test_a_takeover_is_no_split(hub, endpoint, tmp_path: Path) -> None:
    """The old owner's last status, then the new owner's: one owner at a time, nothing said."""
    with AlarmSubscriber(hub, "r1") as sub:
        for i, term in enumerate((new_term(), new_term() + 1000)):
            with connected(endpoint) as s, AlarmJournal(tmp_path / f"{i}.db") as j, \
                    TwinPublisher(s, "r1", j, term=term) as twin:
                for _ in range(3):
                    twin.publish_status(StatusEvent(rig="r1", t_ns=T0_NS, state="running"))
                    time.sleep(0.05)
                deadline = time.monotonic() + WAIT_S
                while term not in sub._terms.get("r1", {}):
                    assert time.monotonic() < deadline
                    try:
                        sub.recv(timeout=0.05)
                    except TimeoutError:
                        pass
    assert sub.splits == 0 and not [r for r in sub.reports if r.startswith("split")]


def test_alarms_cli_says_split_in_one_line(hub, endpoint, tmp_path: Path, capsys) -> None:
    parser = add_arguments(argparse.ArgumentParser(prog="twin alarms"))
    first = new_term()
    stop = threading.Event()
    with AlarmJournal(tmp_path / "a.db") as ja, AlarmJournal(tmp_path / "b.db") as jb, \
            TwinPublisher(hub, "r1", ja, term=first) as a, TwinPublisher(hub, "r1", jb, term=first + 700) as b:

        def publish() -> None:
            while not stop.is_set():
                for side in (a, b):
                    side.publish_status(StatusEvent(rig="r1", t_ns=T0_NS, state="running"))
                stop.wait(0.1)

        feeder = threading.Thread(target=publish, daemon=True)
        feeder.start()
        try:
            assert run(parser.parse_args(["--rig", "r1", "--connect", endpoint, "--for", "2"])) == 0
            err = capsys.readouterr().err.splitlines()
            assert twin_main(["top", "--rig", "r1", "--connect", endpoint, "--once", "--json"]) == 0
            shown = json.loads(capsys.readouterr().out)
        finally:
            stop.set()
            feeder.join(WAIT_S)
    text = json.dumps(shown)
    assert f"split: rig r1 is run by two owners at once (terms {first} and {first + 700}" in text  # twin top
    split = [line for line in err if line.startswith("split: ")]
    assert len(split) == 1 and split[0].startswith(f"split: rig r1 is published by two owners at once (terms {first} "
                                                   f"and {first + 700})")
