"""After a split network joins again, the owner that stands down hands the alarms it raised over to the owner
that stays (twin.service.handover): that owner journals and puts those it does not hold under its next numbers,
marked with the term and number they had; the one that stood down takes the owner's numbering; a plain Zenoh
subscriber receives the marked alarms, and ``AlarmSubscriber`` / ``twin alarms`` say in one line which alarm of
the split was the losing side's and end with the owner's alarm under every number. Loopback, explicit
endpoints, scouting off."""

from __future__ import annotations

import argparse
import json
import threading
import time
from dataclasses import replace
from pathlib import Path

import zenoh

from event_helpers import alarm
from net_helpers import connected
from twin.commands.alarms import add_arguments, run
from twin.online.events import AlarmEvent
from twin.service.bus import SPLIT_MARK, TwinPublisher
from twin.service.handover import hand_over
from twin.service.journal import AlarmJournal
from twin.service.ownership import new_term
from twin.service.subscriber import AlarmSubscriber

WAIT_S = 10.0


class PlainAlarms:
    """Alarms of r1 as a plain Zenoh subscriber gets them."""

    def __init__(self, session: zenoh.Session) -> None:
        self.got: list[dict] = []
        self._lock = threading.Lock()
        self.sub = session.declare_subscriber("fpdd/r1/alarm", self._keep)

    def _keep(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.got.append(json.loads(sample.payload.to_string()))

    def wait(self, n: int) -> list[dict]:
        deadline = time.monotonic() + WAIT_S
        while True:
            with self._lock:
                if len(self.got) >= n:
                    return list(self.got)
            assert time.monotonic() < deadline, self.got
            time.sleep(0.02)


def _content(e: AlarmEvent) -> tuple:
    """What a number holds (the signature aside)."""
    return tuple(sorted(replace(e, signature="").to_dict().items()))


def _ident(e: AlarmEvent | dict) -> tuple:
    d = e.to_dict() if isinstance(e, AlarmEvent) else e
    return d["parameter"], d["level"], d["kind"], d["t_ns"]


def test_the_owner_that_stands_down_hands_its_alarms_over_and_no_number_holds_two_alarms(
        hub, endpoint, tmp_path: Path, capsys) -> None:
    plain = PlainAlarms(hub)
    stays = new_term()
    leaves = stays + 2500  # the other side claimed the rig 2.5 s into the split
    with connected(endpoint) as other, AlarmJournal(tmp_path / "a.db") as ja, AlarmJournal(tmp_path / "b.db") as jb:
        ja.begin_term("r1", stays)
        for i in (1, 2):  # before the split: the owner's alarms, replicated to the standby under its numbers
            jb.record(ja.append(alarm("r1", i)))
        jb.begin_term("r1", leaves)
        sub = AlarmSubscriber(hub, "r1")
        with TwinPublisher(hub, "r1", ja, term=stays) as a:
            with TwinPublisher(other, "r1", jb, term=leaves) as b:
                assert a.wait_for_alarm_subscribers(WAIT_S) and b.wait_for_alarm_subscribers(WAIT_S)
                # the split: each side numbers after seq 2
                ours = [a.publish_alarm(alarm("r1", i)) for i in (3, 4)]
                theirs = [b.publish_alarm(alarm("r1", 3)),  # the same alarm, raised there later (another time)
                          b.publish_alarm(alarm("r1", 5, level="warning")), b.publish_alarm(alarm("r1", 6))]
                assert [e.seq for e in ours] == [3, 4] and [e.seq for e in theirs] == [3, 4, 5]
                assert theirs[0].wall_ns != ours[0].wall_ns and theirs[0].term == leaves
                plain.wait(5)
            # the other side stood down (its twin closed): it hands its term's alarms over
            done = hand_over(other, jb, "r1", leaves)
            assert (done.raised, done.adopted, done.replaced) == (3, 2, 3), done
            got = plain.wait(7)[5:]
            # the owner that stayed journaled and put the two it did not hold, under its next numbers, marked
            final = ja.read(rig="r1")
            assert [e.seq for e in final] == [1, 2, 3, 4, 5, 6]
            assert [_ident(e) for e in final[4:]] == [_ident(theirs[1]), _ident(theirs[2])]
            for e, was in zip(final[4:], theirs[1:], strict=True):
                m = SPLIT_MARK.match(e.message)
                assert m is not None and (int(m[1]), int(m[2]), int(m[3])) == (leaves, was.seq, stays), e.message
                assert e.term == leaves and e.wall_ns == was.wall_ns and e.epoch == final[0].epoch
            assert [(d["seq"], _ident(d), d["term"]) for d in got] == [(e.seq, _ident(e), leaves) for e in final[4:]]
            # the side that stood down holds the owner's alarm under every number now; its own are in its notes
            assert [_content(e) for e in jb.read(rig="r1")] == [_content(e) for e in final]
            kept = [AlarmEvent.from_dict(json.loads(text)) for _, kind, text in jb.notes("r1") if kind == "superseded"]
            assert [_content(e) for e in kept] == [_content(e) for e in theirs]
            again = hand_over(other, jb, "r1", leaves)  # asked again: the owner holds them all, nothing changes
            assert (again.raised, again.adopted, again.replaced) == (2, 0, 0), again
            assert len(jb.notes("r1")) == 3 and [_content(e) for e in ja.read(rig="r1")] == [_content(e) for e in final]
            # the subscriber that saw both sides ends with the owner's alarm under every number
            latest: dict[int, AlarmEvent] = {}
            deadline = time.monotonic() + WAIT_S
            while [_content(latest.get(e.seq, e)) for e in final] != [_content(e) for e in final] \
                    or len(latest) < len(final):
                assert time.monotonic() < deadline, (sorted(latest), sub.reports)
                try:
                    ev = sub.recv(timeout=0.2)
                    latest[ev.seq] = ev
                except TimeoutError:
                    pass
            said = [r for r in sub.reports if r.startswith("superseded: ")]
            assert said == [f"superseded: rig r1 seq {was.seq} of term {leaves} was the losing side's of a split "
                            f"network (two owners at once): that alarm is seq {e.seq} now, in term {stays}'s "
                            "numbering" for e, was in zip(final[4:], theirs[1:], strict=True)]
            sub.close()
            # twin alarms joining now: every number once, the owner's, and the same lines on stderr
            capsys.readouterr()
            parser = add_arguments(argparse.ArgumentParser(prog="twin alarms"))
            assert run(parser.parse_args(["--rig", "r1", "--connect", endpoint, "--for", "1", "--json"])) == 0
            out, err = capsys.readouterr()
        plain.sub.undeclare()
    shown = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert [(d["seq"], _ident(d)) for d in shown] == [(e.seq, _ident(e)) for e in final], out
    assert [line for line in err.splitlines() if line.startswith("superseded: ")] == said


def test_nothing_is_handed_over_without_an_owner_and_a_bad_or_forged_handover_is_refused(
        hub, endpoint, tmp_path: Path) -> None:
    from twin.service.signing import init_keys, load_signer

    stays, leaves = new_term(), new_term() + 1000
    with AlarmJournal(tmp_path / "b.db") as jb:
        jb.begin_term("r1", leaves)
        jb.append(alarm("r1", 1))
        done = hand_over(hub, jb, "r1", leaves, timeout=0.5)  # no owner answers: the journal stays as it was
        assert (done.raised, done.adopted, done.replaced) == (1, 0, 0)
        assert "not handed over (no owner answered" in done.note and "\n" not in done.note
        assert [e.seq for e in jb.read(rig="r1")] == [1] and jb.notes("r1") == []
    signer = load_signer(init_keys("r1", tmp_path / "keys")[0], "r1")
    other_key = load_signer(init_keys("r1", tmp_path / "other")[0], "r1")
    with connected(endpoint) as other, AlarmJournal(tmp_path / "a.db") as ja, \
            TwinPublisher(hub, "r1", ja, term=stays, signer=signer):
        ja.begin_term("r1", stays)
        forged = json.loads(other_key.payload(replace(alarm("r1", 2, seq=1), term=leaves)))
        unsigned = replace(alarm("r1", 2, seq=1), term=leaves).to_dict()
        for bad, why in (('{"rig": "r2", "term": 5, "alarms": []}', "expected"), ("not json", "Expecting value"),
                         (json.dumps({"rig": "r1", "term": stays, "alarms": []}), "this owner's own"),
                         (json.dumps({"rig": "r1", "term": leaves, "alarms": [unsigned]}), "does not verify"),
                         (json.dumps({"rig": "r1", "term": leaves, "alarms": [forged]}), "does not verify")):
            replies = list(other.get("fpdd/r1/alarm/handover", payload=bad, timeout=WAIT_S))
            assert [r.ok for r in replies] == [None], bad
            text = replies[0].err.payload.to_string()
            assert text.startswith('{"error": "fpdd/r1/alarm/handover: ') and why in text, text
        assert ja.read(rig="r1") == []  # nothing journaled
        signed = json.loads(signer.payload(replace(alarm("r1", 2, seq=1), term=leaves)))
        (reply,) = other.get("fpdd/r1/alarm/handover", payload=json.dumps({"rig": "r1", "term": leaves,
                                                                            "alarms": [signed]}), timeout=WAIT_S)
        assert json.loads(reply.ok.payload.to_string())["alarms"] == [{"seq": 1, "now": 1, "held": False}]
        (kept,) = ja.read(rig="r1")
        assert kept.term == leaves and kept.message.startswith(f"split: raised by term {leaves} as seq 1 ")
