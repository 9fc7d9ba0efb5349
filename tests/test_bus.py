"""The Zenoh layer on real sessions: loopback, explicit endpoints, multicast scouting off.

One session listens on ``tcp/127.0.0.1:<free port>``, the others connect to it.
Every wait is on a queue or an event with a timeout; nothing sleeps a fixed time.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import queue
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from zenoh import ext as zext

from twin.service.bus import RigKeys, TwinPublisher, format_alarm
from twin.service.queries import fetch_latest, live_twins
from twin.service.subscriber import AlarmSubscriber
from fpdd.zenohconf import zenoh_config
from twin.commands.alarms import add_arguments as add_alarms_arguments
from twin.commands.alarms import parse_since
from twin.commands.alarms import run as run_alarms_cli
from fpdd.errors import ConfigError, DataError, SourceError
from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent, event_to_json
from twin.service.journal import AlarmJournal
from twin.service.store import Store
from net_helpers import connected
from event_helpers import T0_NS
from event_helpers import alarm as make_alarm

WAIT_S = 10.0  # upper bound of every wait; the happy path takes milliseconds
START_S = 300.0  # upper bound of a child process's start (imports, Zenoh session): only a hang reaches it


def alarm(rig: str, i: int, seq: int = 0) -> AlarmEvent:
    return make_alarm(rig, i, seq, level="alarm" if i % 2 else "warning")


@pytest.fixture
def journal(tmp_path: Path) -> Iterator[AlarmJournal]:
    with AlarmJournal(tmp_path / "alarms.db") as j:
        yield j


def receive(sub: AlarmSubscriber, n: int) -> list[AlarmEvent]:
    return [sub.recv(timeout=WAIT_S) for _ in range(n)]


def wait_matching(publisher: zenoh.Publisher) -> None:
    matched = threading.Event()
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None
    )
    try:
        assert publisher.matching_status.matching or matched.wait(WAIT_S), "no subscriber matched"
    finally:
        listener.undeclare()


# --------------------------------------------------------------------------- config and keys


def test_zenoh_config_has_explicit_endpoints() -> None:
    config = zenoh_config(listen=["tcp/127.0.0.1:7447"], connect=["tcp/10.0.0.1:7447"])
    assert json.loads(config.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447"]
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("mode")) == "peer"
    with pytest.raises(ConfigError, match="a client cannot listen"):
        zenoh_config(mode="client", listen=["tcp/127.0.0.1:7447"])
    with pytest.raises(ConfigError, match="mode: 'server'"):
        zenoh_config(mode="server")
    with pytest.raises(ConfigError, match=r"connect: 'nonsense' is not an endpoint \(expected PROTOCOL/HOST:PORT"):
        zenoh_config(connect=["nonsense"])
    with pytest.raises(ConfigError, match=r"listen: 'tcp/127.0.0.1:99999': port '99999' is not in 0..65535"):
        zenoh_config(listen=["tcp/127.0.0.1:99999"])


def test_a_zenoh_file_is_overridden_only_by_what_is_given(tmp_path: Path) -> None:
    file = tmp_path / "client.json5"
    file.write_text('{mode: "client", connect: {endpoints: ["tcp/10.1.2.3:7447"]}, '
                    'scouting: {multicast: {enabled: false}}}')
    config = zenoh_config(config_file=file)  # no defaults forced on the file
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/10.1.2.3:7447"]
    config = zenoh_config("peer", connect=["tcp/127.0.0.1:7447"], config_file=file)
    assert json.loads(config.get_json("mode")) == "peer"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    with pytest.raises(ConfigError, match="a client cannot listen"):
        zenoh_config(listen=["tcp/127.0.0.1:7447"], config_file=file)
    with pytest.raises(ConfigError, match=r"missing\.json5: cannot read the Zenoh configuration: does not exist"):
        zenoh_config(config_file=tmp_path / "missing.json5")


def test_key_space() -> None:
    keys = RigKeys("msp25")
    assert (keys.estimate, keys.status, keys.alarm, keys.history, keys.twin) == (
        "fpdd/msp25/estimate",
        "fpdd/msp25/status",
        "fpdd/msp25/alarm",
        "fpdd/msp25/alarm/history",
        "fpdd/msp25/twin",
    )
    assert RigKeys("*").alarm == "fpdd/*/alarm"
    assert RigKeys.rig_of("fpdd/msp25/alarm/history") == "msp25"
    with pytest.raises(ConfigError, match="rig: 'a/b' is not a valid rig id"):
        RigKeys("a/b")
    with pytest.raises(DataError):
        RigKeys.rig_of("other/msp25")


# --------------------------------------------------------------------------- alarms


def test_alarms_received_live(hub: zenoh.Session, endpoint: str, journal: AlarmJournal) -> None:
    with connected(endpoint) as sub_session, AlarmSubscriber(sub_session, "r1", history=False) as sub:
        with TwinPublisher(hub, "r1", journal) as twin:
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            sent = [twin.publish_alarm(alarm("r1", i)) for i in range(1, 4)]
            got = receive(sub, 3)
    assert got == sent
    assert [e.seq for e in got] == [1, 2, 3]
    assert sub.missed == []


def test_alarm_is_journaled_before_it_is_published(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    on_disk: queue.Queue[bool] = queue.Queue()

    def check(sample: zenoh.Sample) -> None:
        seq = json.loads(sample.payload.to_string())["seq"]
        with Store(journal.path, writer=False) as reader:  # what another process sees in the file
            on_disk.put(any(e.seq == seq for e in reader.alarms("r1")))

    with connected(endpoint) as sub_session:
        raw = sub_session.declare_subscriber("fpdd/r1/alarm", check)
        with TwinPublisher(hub, "r1", journal) as twin:
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            twin.publish_alarm(alarm("r1", 1))
            assert on_disk.get(timeout=WAIT_S) is True
        raw.undeclare()


def test_late_subscriber_gets_every_missed_alarm(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    with TwinPublisher(hub, "r1", journal) as twin:
        sent = [twin.publish_alarm(alarm("r1", i)) for i in range(1, 6)]
        with connected(endpoint) as sub_session, AlarmSubscriber(sub_session, "*") as sub:
            history = receive(sub, 5)
            assert history == sent
            assert [e.seq for e in history] == [1, 2, 3, 4, 5]
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            live = twin.publish_alarm(alarm("r1", 6))
            assert sub.recv(timeout=WAIT_S) == live
            # no duplicates of anything: a later alarm is the next one delivered, whatever the machine's speed
            marker = twin.publish_alarm(alarm("r1", 7))
            assert sub.recv(timeout=WAIT_S) == marker
            assert sub.missed == []


def test_history_since_seq_and_since_t_ns(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    with TwinPublisher(hub, "r1", journal) as twin:
        for i in range(1, 6):
            twin.publish_alarm(alarm("r1", i))
        with connected(endpoint) as s:
            with AlarmSubscriber(s, "r1", since_seq=3) as sub:
                assert [e.seq for e in receive(sub, 3)] == [3, 4, 5]
            with AlarmSubscriber(s, "r1", since_t_ns=T0_NS + 4_000_000_000) as sub:
                assert [e.seq for e in receive(sub, 2)] == [4, 5]
            replies = list(
                s.get("fpdd/r1/alarm/history?since_seq=abc", consolidation=zenoh.ConsolidationMode.NONE)
            )
            assert len(replies) == 1 and replies[0].err is not None
            assert "since_seq: 'abc' must be an integer" in replies[0].err.payload.to_string()


def test_gap_is_detected_and_filled_from_history(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    with connected(endpoint) as sub_session, AlarmSubscriber(sub_session, "r1") as sub:
        with TwinPublisher(hub, "r1", journal) as twin:
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            first = twin.publish_alarm(alarm("r1", 1))
            assert sub.recv(timeout=WAIT_S) == first
            queries = sub.history_queries
            lost = [journal.append(alarm("r1", i)) for i in (2, 3)]  # journaled, lost in transit
            fourth = twin.publish_alarm(alarm("r1", 4))
            assert receive(sub, 3) == [*lost, fourth]
            assert sub.history_queries > queries
            assert sub.missed == []


def test_lost_last_alarm_is_caught_by_the_status_counter(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    with connected(endpoint) as sub_session, AlarmSubscriber(sub_session, "r1") as sub:
        with TwinPublisher(hub, "r1", journal) as twin:
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            first = twin.publish_alarm(alarm("r1", 1))
            assert sub.recv(timeout=WAIT_S) == first
            lost = journal.append(alarm("r1", 2))  # the last alarm, lost in transit
            status = twin.publish_status(StatusEvent(rig="r1", t_ns=T0_NS, state="running"))
            assert status.counters["alarm_seq"] == 2
            assert sub.recv(timeout=WAIT_S) == lost


def test_gap_the_history_cannot_fill_is_reported(hub: zenoh.Session, endpoint: str) -> None:
    with connected(endpoint) as sub_session, AlarmSubscriber(sub_session, "ghost") as sub:
        raw = hub.declare_publisher("fpdd/ghost/alarm")  # no twin, no history behind it
        wait_matching(raw)
        raw.put(event_to_json(alarm("ghost", 1, seq=1)))
        raw.put(event_to_json(alarm("ghost", 3, seq=3)))
        raw.put(event_to_json(alarm("ghost", 3, seq=3)))  # a duplicate
        raw.put(b"{not json")
        got = receive(sub, 2)
        raw.put(event_to_json(alarm("ghost", 4, seq=4)))
        got.append(sub.recv(timeout=WAIT_S))
        raw.undeclare()
    assert [e.seq for e in got] == [1, 3, 4]
    assert sub.missed == [("ghost", 2, 2)]
    assert sub.rejected == 1


def test_twin_coming_up_later_delivers_its_journal(
    hub: zenoh.Session, endpoint: str, tmp_path: Path
) -> None:
    path = tmp_path / "offline.jsonl"
    with AlarmJournal(path) as offline:  # alarms journaled while the bus was unreachable
        for i in range(1, 4):
            offline.append(alarm("late", i))
    with AlarmSubscriber(hub, "late") as sub:
        assert sub.history_queries == 1
        with connected(endpoint) as twin_session, AlarmJournal(path) as j, TwinPublisher(
            twin_session, "late", j
        ):
            assert [e.seq for e in receive(sub, 3)] == [1, 2, 3]


def test_journal_survives_a_restart_of_the_service(
    hub: zenoh.Session, endpoint: str, tmp_path: Path
) -> None:
    path = tmp_path / "alarms.db"
    for run in range(2):  # two lives of the service on the same journal, the second raising its alarms again
        with connected(endpoint) as s, AlarmJournal(path) as j, TwinPublisher(s, "r1", j) as twin:
            assert twin.publish_alarm(alarm("r1", 1)).seq == 1
            twin.publish_alarm(alarm("r1", 2 * run + 2))
    with connected(endpoint) as s, AlarmJournal(path) as j, TwinPublisher(s, "r1", j) as twin:
        assert twin.publish_alarm(alarm("r1", 5)).seq == 4
        with AlarmSubscriber(hub, "r1") as sub:
            assert [(e.seq, e.message) for e in receive(sub, 4)] == [
                (1, "alarm 1"), (2, "alarm 2"), (3, "alarm 4"), (4, "alarm 5")]


# --------------------------------------------------------------------------- forged and unverifiable alarms


def test_a_forged_jump_is_checked_against_the_history_and_no_real_alarm_is_dropped(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    """An alarm with seq 100 put by someone else on the rig's key while its twin is alive."""
    # The listening session stands in for the router: it relays between the twin and the forger.
    with AlarmSubscriber(hub, "r1") as sub, connected(endpoint) as twin_session, \
            connected(endpoint) as forger_session:
        with TwinPublisher(twin_session, "r1", journal) as twin:
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            real = [twin.publish_alarm(alarm("r1", i)) for i in (1, 2)]
            assert receive(sub, 2) == real
            forger = forger_session.declare_publisher("fpdd/r1/alarm")
            wait_matching(forger)
            forger.put(event_to_json(alarm("r1", 100, seq=100)))
            forger.put(event_to_json(alarm("r1", 77, seq=2)))  # a different payload under a number seen
            real += [twin.publish_alarm(alarm("r1", i)) for i in (3, 4, 5, 6)]
            assert receive(sub, 4) == real[2:]
            marker = twin.publish_alarm(alarm("r1", 7))  # nothing of the forger's before the next real one
            assert sub.recv(timeout=WAIT_S) == marker
            forger.undeclare()
    assert sub.missed == [] and sub.rejected == 1  # seq 100: not in the twin's history; seq 2: a duplicate


def test_an_unverifiable_jump_is_delivered_and_the_real_alarms_follow_when_the_twin_is_back(
    hub: zenoh.Session, endpoint: str, tmp_path: Path
) -> None:
    path = tmp_path / "alarms.db"
    with AlarmJournal(path) as j:  # the twin journaled 1..3 while it was unreachable
        real = [j.append(alarm("r1", i)) for i in (1, 2, 3)]
    with AlarmSubscriber(hub, "r1") as sub, connected(endpoint) as other:
        raw = other.declare_publisher("fpdd/r1/alarm")  # no twin alive: nothing can be checked
        wait_matching(raw)
        raw.put(event_to_json(alarm("r1", 100, seq=100)))
        assert sub.recv(timeout=WAIT_S).seq == 100  # delivered: it may be real
        assert sub.missed == [("r1", 1, 99)]
        with connected(endpoint) as twin_session, AlarmJournal(path) as j, TwinPublisher(twin_session, "r1", j):
            assert receive(sub, 3) == real  # the twin is back: its history fills the gap
        raw.undeclare()
    assert sub.recovered == 3


def _child_publisher(endpoint: str, journal_path: str, n: int, done: object, ready: object) -> None:
    """Runs in a spawned process: a twin connecting to the test's session."""
    with zenoh.open(zenoh_config(connect=[endpoint])) as session, AlarmJournal(
        journal_path
    ) as journal, TwinPublisher(session, "child", journal) as twin:
        ready.set()  # type: ignore[attr-defined]
        twin.wait_for_alarm_subscribers(WAIT_S)
        for i in range(1, n + 1):
            twin.publish_alarm(alarm("child", i))
        done.wait(WAIT_S)  # type: ignore[attr-defined]  # keep the history up until read


def test_second_process_publishes_to_this_one(
    hub: zenoh.Session, endpoint: str, tmp_path: Path
) -> None:
    ctx = multiprocessing.get_context("spawn")
    done, ready = ctx.Event(), ctx.Event()
    child = ctx.Process(
        target=_child_publisher, args=(endpoint, str(tmp_path / "child.jsonl"), 4, done, ready)
    )
    with AlarmSubscriber(hub, "child") as sub:
        child.start()
        try:
            # a Python process that imports the product starts in a second on a quiet machine and in tens of seconds
            # on a loaded one: the wait for the alarms starts once the child's session is open
            assert ready.wait(START_S), f"the child process did not open its session within {START_S} s"
            got = receive(sub, 4)
        finally:
            done.set()
            child.join(WAIT_S)
    assert child.exitcode == 0
    assert [(e.rig, e.seq, e.message) for e in got] == [("child", i, f"alarm {i}") for i in range(1, 5)]


# --------------------------------------------------------------------------- estimates, status


def test_late_subscribers_get_latest_estimate_and_status(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    with TwinPublisher(hub, "r1", journal) as twin:
        twin.publish_alarm(alarm("r1", 1))
        old = EstimateEvent("r1", T0_NS, 0.0, {"Fc": {"value": 40.0, "std": 9.0, "unit": "N"}}, None, "ok")
        new = EstimateEvent("r1", T0_NS + 10**6, 0.001, {"Fc": {"value": 50.0, "std": 2.0, "unit": "N"}}, 1.1, "ok")
        twin.publish_estimate(old)
        twin.publish_estimate(new)
        status = twin.publish_status(
            StatusEvent("r1", T0_NS, "running", {"Fc": "ok"}, {"samples": 2}, "tracking")
        )
        with connected(endpoint) as s:
            assert live_twins(s) == ["r1"]
            # a plain get on the key, answered by the latest-value queryable
            assert fetch_latest(s, "estimate") == [new]
            assert fetch_latest(s, "status", "r1") == [status]
            assert status.counters == {"samples": 2, "alarm_seq": 1}
            # an advanced subscriber, answered by the advanced publisher's cache
            got: queue.Queue[str] = queue.Queue()
            adv = zext.declare_advanced_subscriber(
                s,
                "fpdd/*/estimate",
                lambda sample: got.put(sample.payload.to_string()),
                history=zext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            )
            try:
                assert EstimateEvent.from_dict(json.loads(got.get(timeout=WAIT_S))) == new
            finally:
                adv.undeclare()
    with TwinPublisher(hub, "r1", journal) as twin:
        with pytest.raises(DataError, match="published through the twin of rig 'r1'"):
            twin.publish_alarm(alarm("r2", 1))


# --------------------------------------------------------------------------- CLI


def test_alarms_cli_json_count(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms"))
    args = parser.parse_args(
        ["--rig", "r1", "--connect", endpoint, "--json", "--count", "3", "--timeout", str(WAIT_S)]
    )
    with TwinPublisher(hub, "r1", journal) as twin:
        sent = [twin.publish_alarm(alarm("r1", i)) for i in (1, 2)]
        result: list[int] = []
        cli = threading.Thread(target=lambda: result.append(run_alarms_cli(args)))
        cli.start()
        sent.append(twin.publish_alarm(alarm("r1", 3)))  # live or history: printed once either way
        cli.join(WAIT_S + 5)
    assert result == [0]
    lines = capsys.readouterr().out.splitlines()
    assert [AlarmEvent.from_dict(json.loads(line)) for line in lines] == sent


def test_alarms_cli_times_out_without_enough_alarms(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms"))
    args = parser.parse_args(["--connect", endpoint, "--count", "1", "--timeout", "0.3", "--no-history"])
    with TwinPublisher(hub, "r1", journal):
        assert run_alarms_cli(args) == 1
    assert capsys.readouterr().out == ""


def test_alarms_cli_without_a_twin_gives_up_naming_the_endpoint(endpoint: str) -> None:
    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms"))
    with zenoh.open(zenoh_config(listen=[endpoint])):  # something answers, but no twin
        args = parser.parse_args(["--connect", endpoint, "--wait", "0.5"])
        with pytest.raises(SourceError, match=rf"no twin reachable through {endpoint} within 0.5 s"):
            run_alarms_cli(args)
    args = parser.parse_args(["--connect", endpoint, "--mode", "client"])
    with pytest.raises(SourceError, match=rf"cannot reach {endpoint}: nothing answers there"):
        run_alarms_cli(args)


def test_cli_argument_parsing_and_human_format() -> None:
    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms", exit_on_error=False))
    now = T0_NS
    assert parse_since("90s", now_ns=now) == now - 90 * 10**9
    assert parse_since("2h", now_ns=now) == now - 7200 * 10**9
    assert parse_since("2025-02-19T21:20:00Z") == 1_740_000_000 * 10**9
    assert parse_since(str(T0_NS)) == T0_NS
    with pytest.raises(ValueError, match="is not an ISO 8601 time"):
        parse_since("yesterday")
    with pytest.raises(argparse.ArgumentError):
        parser.parse_args(["--count", "0"])
    args = parser.parse_args(["--since", "15m", "--since-seq", "4", "--rig", "msp25"])
    assert args.since_seq == 4 and args.rig == "msp25" and args.since > 0
    line = format_alarm(alarm("msp25", 3, seq=7))
    assert line.startswith("2025-02-19T21:20:03.000Z msp25 #7 t=3.000 s ALARM")
    assert "Kleak = 3e-12 ± 2e-13" in line and line.endswith("alarm 3")


def test_alarms_of_a_replayed_log_carry_wall_clock_time_and_since_takes_both_clocks(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, capsys: pytest.CaptureFixture[str]
) -> None:
    """A replayed log's alarms are in its own (1970) time; the journal stamps when each was raised, so
    ``--since 1h`` (wall clock) finds them, and ``--since t=SECONDS`` picks by the record's time."""
    import dataclasses
    import time

    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms"))
    before = time.time_ns()
    with TwinPublisher(hub, "r1", journal) as twin:
        sent = [twin.publish_alarm(dataclasses.replace(alarm("r1", i), t_ns=i * 10**9, t_s=float(i)))
                for i in (1, 2, 3)]
        assert all(before <= a.wall_ns <= time.time_ns() for a in sent)
        args = parser.parse_args(["--rig", "r1", "--connect", endpoint, "--json", "--count", "3", "--timeout",
                                  str(WAIT_S), "--since", "1h"])
        assert run_alarms_cli(args) == 0
        got = [AlarmEvent.from_dict(json.loads(line)) for line in capsys.readouterr().out.splitlines()]
        assert got == sent
        args = parser.parse_args(["--rig", "r1", "--connect", endpoint, "--count", "1", "--timeout",
                                  str(WAIT_S), "--since", "t=2.5"])
        assert run_alarms_cli(args) == 0
        lines = capsys.readouterr().out.splitlines()
        assert len(lines) == 1 and " r1 #3 t=3.000 s " in lines[0]
        assert lines[0].startswith(time.strftime("%Y-", time.gmtime()))  # the wall-clock time first
        args = parser.parse_args(["--rig", "r1", "--connect", endpoint, "--count", "1", "--timeout", "0.5",
                                  "--since", "2099-01-01T00:00:00Z"])
        assert run_alarms_cli(args) == 1 and capsys.readouterr().out == ""
