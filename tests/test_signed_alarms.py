"""Signed alarms on a plain Zenoh peer bus (no router, no access control): loopback, explicit endpoints,
multicast scouting off.

One session listens on ``tcp/127.0.0.1:<free port>`` and relays; the twin, the forger and the
subscribers connect to it. Every key is made by ``twin keys init`` (or its library function) in the
test's directory. Waits are on queues and events with timeouts; nothing sleeps a fixed time.
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import re
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import pytest
import zenoh

from event_helpers import T0_NS
from event_helpers import alarm as make_alarm
from net_helpers import connected
from twin.cli import main as twin_main
from twin.commands.alarms import add_arguments as add_alarms_arguments
from twin.commands.alarms import run as run_alarms_cli
from fpdd.errors import ConfigError
from twin.online.events import AlarmEvent, StatusEvent, event_to_json
from twin.service.bus import TwinPublisher
from twin.service.subscriber import AlarmSubscriber
from twin.service.config import parse_config
from twin.service.fleet import BusFront
from twin.service.journal import AlarmJournal
from twin.service.signing import (FORGED, STATUS_DOMAIN, UNVERIFIED, VERIFIED, TrustStore, canonical, init_keys,
                                  load_signer)

WAIT_S = 10.0  # upper bound of every wait; the happy path takes milliseconds


def alarm(rig: str, i: int, seq: int = 0, level: str = "") -> AlarmEvent:
    return make_alarm(rig, i, seq, level=level or ("alarm" if i % 2 else "warning"))


def unsigned(events: list[AlarmEvent]) -> list[AlarmEvent]:
    return [replace(e, signature="") for e in events]


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    """r1's key pair, made as an operator makes it; the directory is also the subscribers' trust store."""
    directory = tmp_path / "keys"
    init_keys("r1", directory)
    return directory


@pytest.fixture
def journal(tmp_path: Path) -> Iterator[AlarmJournal]:
    with AlarmJournal(tmp_path / "alarms.db") as j:
        yield j


def wait_matching(publisher: zenoh.Publisher) -> None:
    matched = threading.Event()
    listener = publisher.declare_matching_listener(lambda s: matched.set() if s.matching else None)
    try:
        assert publisher.matching_status.matching or matched.wait(WAIT_S), "no subscriber matched"
    finally:
        listener.undeclare()


def pump_until(sub: AlarmSubscriber, done: Callable[[], bool]) -> list[AlarmEvent]:
    """Let the subscriber process what arrives until ``done()``; returns what it delivered meanwhile."""
    got: list[AlarmEvent] = []
    deadline = time.monotonic() + WAIT_S
    while not done():
        assert time.monotonic() < deadline, f"condition not reached within {WAIT_S} s; reports: {sub.reports}"
        try:
            got.append(sub.recv(timeout=0.05))
        except TimeoutError:
            pass
    return got


def foreign_signature(event: AlarmEvent, tmp_path: Path) -> AlarmEvent:
    """``event`` signed with a key that is not the rig's (someone made their own key for 'r1')."""
    other = tmp_path / "other"
    if not (other / "r1.key").exists():
        init_keys("r1", other)
    return load_signer(other / "r1.key", "r1").sign(event)


# --------------------------------------------------------------------------- signatures, no network


def test_every_field_of_a_signed_alarm_is_covered(keys: Path) -> None:
    signer, trust = load_signer(keys / "r1.key", "r1"), TrustStore(keys)
    event = replace(alarm("r1", 3, seq=3), epoch="18ed2f6e4b1c0a00" + "0123456789abcdef")
    payload = json.loads(event_to_json(signer.sign(event)))
    assert trust.check(payload).status == VERIFIED
    assert signer.sign(event).signature == payload["signature"]  # deterministic: live = history
    changed = {"rig": "r2", "parameter": "Ffric", "level": "warning", "kind": "returned", "t_ns": payload["t_ns"] + 1,
               "t_s": 3.5, "estimate": 4e-12, "std": 1e-13, "baseline": 2e-12, "band_lo": 1e-13, "band_hi": 3e-12,
               "seq": 4, "statistic": 99.0, "message": "fine", "unit": "N", "wall_ns": 1_700_000_000_000_000_000,
               "epoch": "18ed2f6e4b1c0a01" + "0123456789abcdef"}
    assert set(changed) == set(payload) - {"signature"}  # a field added to the payload must be tried here too
    for field, value in changed.items():
        tampered = {**payload, field: value}
        verdict = trust.check(tampered)
        expected = UNVERIFIED if field == "rig" else FORGED  # r2 has no key in this trust store
        assert verdict.status == expected, field
    assert trust.check({**payload, "extra": 1}).status == FORGED  # nothing can be added either
    no_sig = {k: v for k, v in payload.items() if k != "signature"}
    assert trust.check(no_sig).reason == "unsigned, but rig 'r1' signs its alarms"
    assert trust.check({**payload, "signature": "%%%"}).reason == "the signature is not base64"
    raw = bytearray(base64.b64decode(payload["signature"]))
    raw[0] ^= 1
    assert trust.check({**payload, "signature": base64.b64encode(bytes(raw)).decode()}).status == FORGED
    assert canonical(payload).startswith(b"fpdd-alarm-v1\n{")
    assert TrustStore().check(payload).status == UNVERIFIED  # no keys: nothing to check against


def test_keys_command_files_modes_and_refusals(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    directory = tmp_path / "etc" / "keys"
    assert twin_main(["keys", "init", "--rig", "r1", "--rig", "r2", "--dir", str(directory), "--json"]) == 0
    made = json.loads(capsys.readouterr().out)["keys"]
    assert [k["rig"] for k in made] == ["r1", "r2"]
    for rig in ("r1", "r2"):
        assert stat.S_IMODE(os.stat(directory / f"{rig}.key").st_mode) == 0o600
        assert stat.S_IMODE(os.stat(directory / f"{rig}.pub").st_mode) == 0o644
    before = (directory / "r1.key").read_bytes()
    assert twin_main(["keys", "init", "--rig", "r1", "--dir", str(directory)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.endswith("r1.key: exists already; a new key would orphan every subscriber's copy of the old one "
                        "(use --force to replace it)") and "\n" not in err
    assert (directory / "r1.key").read_bytes() == before
    assert twin_main(["keys", "show", str(directory / "r1.key"), str(directory / "r1.pub"), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)["keys"]
    assert [k["kind"] for k in shown] == ["private", "public"]
    assert shown[0]["fingerprint"] == shown[1]["fingerprint"] == made[0]["fingerprint"] != made[1]["fingerprint"]
    os.chmod(directory / "r1.key", 0o644)
    with pytest.raises(ConfigError, match=r"r1\.key: signing key of rig 'r1' is readable by others \(mode 0644\)"):
        load_signer(directory / "r1.key", "r1")
    (directory / "bad.pub").write_text("not a key\n")
    with pytest.raises(ConfigError, match=r"bad\.pub: not a PEM public key"):
        TrustStore(directory)
    with pytest.raises(ConfigError, match="no <rig>.pub public key in the trust store"):
        TrustStore(tmp_path)
    capsys.readouterr()
    bad = {("keys", "init", "--rig", "a/b", "--dir", str(directory)): "--rig: 'a/b' is not a valid rig id",
           ("keys", "show", str(tmp_path / "none.pub")): "none.pub: cannot read the key (No such file or directory)",
           ("keys", "show", str(directory / "bad.pub")): "bad.pub: not a PEM key",
           ("alarms", "--keys", str(tmp_path / "none"), "--connect", "tcp/127.0.0.1:1"):
               "none: cannot read the trust store (No such file or directory)"}
    for argv, message in bad.items():
        assert twin_main(list(argv)) == 2, argv
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and message in err and "Traceback" not in err, (argv, err)


def test_the_deploy_readme_key_commands_run_as_written(tmp_path: Path) -> None:
    readme = (Path(__file__).parent.parent / "deploy" / "README.md").read_text(encoding="utf-8")
    section = readme.split("## Signed alarms", 1)[1].split("\n## ", 1)[0]
    script = "\n".join(re.findall(r"```sh\n(.*?)```", section, re.DOTALL))
    env = {**os.environ, "PATH": str(Path(sys.executable).parent) + os.pathsep + os.environ["PATH"]}
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    shown = done.stdout.splitlines()[-2:]  # twin keys show: the private and the public file
    assert [line.split(", ")[-1] for line in shown][0] == [line.split(", ")[-1] for line in shown][1]
    assert shown[0].startswith("keys/msp25-hall1-a.key: rig msp25-hall1-a, private key, SHA256:")
    assert TrustStore(tmp_path / "keys").rigs == ["msp25-hall1-a", "msp25-hall1-b"]


def test_rigs_toml_signing_keys(keys: Path, tmp_path: Path) -> None:
    config = tmp_path / "rigs.toml"
    doc = {"service": {"signing_keys": "keys"},
           "rig": [{"name": "r1", "source": "r1.mcap"}, {"name": "r2", "source": "r2.mcap"}]}
    with pytest.raises(ConfigError, match=r"keys/r2\.key: cannot read the signing key of rig 'r2'"):
        parse_config(doc, str(config))  # a directory of keys: every rig is expected to have one
    init_keys("r2", tmp_path / "more")
    doc["rig"][1]["signing_key"] = "more/r2.key"  # a rig's own key wins over the directory
    cfg = parse_config(doc, str(config))
    assert [r.signing_key for r in cfg.rigs] == [str(keys / "r1.key"), str(tmp_path / "more" / "r2.key")]
    cfg = parse_config({"rig": [{"name": "r1", "source": "r1.mcap"}]}, str(config))
    assert cfg.rigs[0].signing_key is None  # no keys configured: alarms go out unsigned


# --------------------------------------------------------------------------- live alarms


def test_forged_alarm_with_the_next_seq_is_reported_and_all_real_alarms_arrive(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, keys: Path, tmp_path: Path
) -> None:
    signer = load_signer(keys / "r1.key", "r1")
    with connected(endpoint) as twin_session, connected(endpoint) as forger_session, \
            AlarmSubscriber(hub, "r1", trust=TrustStore(keys)) as sub, \
            TwinPublisher(twin_session, "r1", journal, signer=signer) as twin:
        assert twin.wait_for_alarm_subscribers(WAIT_S)
        real = [twin.publish_alarm(alarm("r1", 1))]
        first = sub.recv(timeout=WAIT_S)
        forger = forger_session.declare_publisher("fpdd/r1/alarm")
        wait_matching(forger)
        # Before the real seq 2: an unsigned alarm, one signed by another key, a real one with a field changed.
        forger.put(event_to_json(alarm("r1", 50, seq=2)))
        forger.put(event_to_json(foreign_signature(alarm("r1", 51, seq=2), tmp_path)))
        tampered = replace(signer.sign(replace(real[0], seq=2)), seq=2, level="ok", kind="returned")
        forger.put(event_to_json(tampered))
        got = pump_until(sub, lambda: sub.forged == 3)
        assert got == []  # nothing forged was delivered, and no number moved
        real += [twin.publish_alarm(alarm("r1", i)) for i in (2, 3, 4, 5)]
        got = [first, *(sub.recv(timeout=WAIT_S) for _ in range(4))]
        # Nothing else (no forged alarm, no duplicate), whatever the machine's speed: the forger's puts were all
        # handled above, and a later real alarm is the next one delivered.
        marker = twin.publish_alarm(alarm("r1", 6))
        assert unsigned([sub.recv(timeout=WAIT_S)]) == [marker]
        forger.undeclare()
    assert unsigned(got) == real
    assert all(sub.verification[("r1", e.seq)] == VERIFIED for e in got)
    assert sub.missed == [] and sub.forged == 3 and sub.rejected == 3
    forged_lines = [r for r in sub.reports if r.startswith("forged: ")]
    assert len(forged_lines) == 3 and all("rig r1 seq 2 on fpdd/r1/alarm" in r for r in forged_lines)
    assert "unsigned, but rig 'r1' signs its alarms" in forged_lines[0]
    assert "does not verify with the key of rig 'r1'" in forged_lines[1] and forged_lines[1] == forged_lines[2]


def test_without_keys_a_forged_next_seq_is_checked_against_the_live_twins_history(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    """No keys anywhere: the live twin's history (journaled before put) still tells the forged number."""
    with connected(endpoint) as twin_session, connected(endpoint) as forger_session, \
            AlarmSubscriber(hub, "r1") as sub, TwinPublisher(twin_session, "r1", journal) as twin:
        assert twin.wait_for_alarm_subscribers(WAIT_S)
        real = [twin.publish_alarm(alarm("r1", 1))]
        got = [sub.recv(timeout=WAIT_S)]
        forger = forger_session.declare_publisher("fpdd/r1/alarm")
        wait_matching(forger)
        forger.put(event_to_json(alarm("r1", 50, seq=2)))  # before the real seq 2
        got += pump_until(sub, lambda: sub.forged == 1)
        real += [twin.publish_alarm(alarm("r1", i)) for i in (2, 3, 4, 5)]
        forger.put(event_to_json(alarm("r1", 51, seq=6)))  # the next number again, after the real ones
        got += [sub.recv(timeout=WAIT_S) for _ in range(4)]
        pump_until(sub, lambda: sub.forged == 2)
        forger.undeclare()
    assert got == real and {sub.verification[("r1", e.seq)] for e in got} == {UNVERIFIED}
    assert sub.reports == [f"forged: rig r1 seq {n} on fpdd/r1/alarm: not in the history of the rig's live twin "
                           "(not journaled by it); not accepted" for n in (2, 6)]
    assert sub.missed == []


def test_without_keys_a_different_alarm_under_a_delivered_number_is_a_conflict(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal
) -> None:
    """The documented limit of an unsigned bus: the first alarm of a number wins, a second one is reported."""
    with connected(endpoint) as forger_session, AlarmSubscriber(hub, "r1") as sub, \
            TwinPublisher(hub, "r1", journal) as twin:
        real = twin.publish_alarm(alarm("r1", 1))
        assert sub.recv(timeout=WAIT_S) == real and sub.verification[("r1", 1)] == UNVERIFIED
        forger = forger_session.declare_publisher("fpdd/r1/alarm")
        wait_matching(forger)
        forger.put(event_to_json(real))  # the very alarm again: a replay, not delivered twice
        forger.put(event_to_json(alarm("r1", 9, seq=1)))
        pump_until(sub, lambda: sub.conflicts == 1)
        forger.undeclare()
    assert sub.reports == [f"replayed: rig r1 seq 1 on fpdd/r1/alarm: received live before (epoch {real.epoch}); "
                           "not delivered again",
                           "conflict: rig r1 seq 1: a different alarm under a number already delivered "
                           "(Kleak alarm raised delivered, Kleak alarm raised now); not delivered"]
    assert sub.replayed == 1 and sub.epochs == {"r1": real.epoch}


# --------------------------------------------------------------------------- history


@contextmanager
def forged_history(session: zenoh.Session, seqs: range, tmp_path: Path) -> Iterator[None]:
    """A second queryable on r1's history, answering ``seqs`` with alarms of its own (signed with its own key)."""
    forged = [event_to_json(foreign_signature(alarm("r1", 100 + s, seq=s), tmp_path)) for s in seqs]

    def answer(query: zenoh.Query) -> None:
        with query:
            for payload in forged:
                query.reply("fpdd/r1/alarm/history", payload, encoding=zenoh.Encoding.APPLICATION_JSON)

    queryable = session.declare_queryable("fpdd/r1/alarm/history", answer)
    try:
        yield
    finally:
        queryable.undeclare()


def has_two_queryables(session: zenoh.Session) -> bool:
    repliers = {str(r.replier_id) for r in session.get("fpdd/r1/alarm/history", target=zenoh.QueryTarget.ALL,
                                                        consolidation=zenoh.ConsolidationMode.NONE, timeout=WAIT_S)}
    return len(repliers) == 2


def test_a_second_history_queryable_is_a_conflict_and_only_real_alarms_are_delivered(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, keys: Path, tmp_path: Path
) -> None:
    signer = load_signer(keys / "r1.key", "r1")
    with connected(endpoint) as twin_session, TwinPublisher(twin_session, "r1", journal, signer=signer) as twin:
        real = [twin.publish_alarm(alarm("r1", i)) for i in range(1, 6)]
        with connected(endpoint) as forger, forged_history(forger, range(1, 9), tmp_path):
            deadline = time.monotonic() + WAIT_S
            while not has_two_queryables(hub):  # both queryables reached the late subscriber's session
                assert time.monotonic() < deadline
            with AlarmSubscriber(hub, "r1", trust=TrustStore(keys)) as sub:
                got = [sub.recv(timeout=WAIT_S) for _ in range(5)]
                # No 6..8 of the forger's, whatever the machine's speed: the twin's real 6, put live after
                # the history was judged, is the next alarm delivered.
                assert twin.wait_for_alarm_subscribers(WAIT_S)
                marker = twin.publish_alarm(alarm("r1", 6))
                assert unsigned([sub.recv(timeout=WAIT_S)]) == [marker]
    assert unsigned(got) == real
    assert {sub.verification[("r1", e.seq)] for e in [*got, marker]} == {VERIFIED}
    forged = [r for r in sub.reports if r.startswith("forged: ")]
    conflict = [r for r in sub.reports if r.startswith("conflict: ")]
    assert sub.forged == 8 and sub.conflicts == len(conflict)
    assert len(forged) == 1 and forged[0].startswith("forged: rig r1 seq 1..8 in replies of queryable ")
    assert "answered differently by 2 repliers" in conflict[0] and "seq 1..5)" in conflict[0]
    # Reported once. When the twin's liveliness is handled after the real 6 is journaled, the history is asked
    # from 6 and the two repliers disagree on 6 as well: that is the one other conflict there may be.
    assert len(conflict) == 1 or (len(conflict) == 2 and "answered differently by 2 repliers" in conflict[1]
                                  and "seq 6)" in conflict[1])


def test_without_keys_disagreeing_queryables_are_never_merged(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, tmp_path: Path
) -> None:
    with connected(endpoint) as twin_session, TwinPublisher(twin_session, "r1", journal) as twin:
        for i in range(1, 6):
            twin.publish_alarm(alarm("r1", i))
        with connected(endpoint) as forger, forged_history(forger, range(1, 9), tmp_path):
            deadline = time.monotonic() + WAIT_S
            while not has_two_queryables(hub):
                assert time.monotonic() < deadline
            with AlarmSubscriber(hub, "r1") as sub:
                # Neither version of 1..5, none of the forger's 6..8, whatever the machine's speed: the twin's
                # real 6, put live after the history was judged, is the first alarm delivered (unverifiable
                # but maybe real, so delivered, with 1..5 recorded missed).
                assert twin.wait_for_alarm_subscribers(WAIT_S)
                marker = twin.publish_alarm(alarm("r1", 6))
                assert sub.recv(timeout=WAIT_S) == marker
    assert sub.missed == [("r1", 1, 5)]
    assert sub.conflicts == 1 and sub.forged == 0
    assert sub.reports[0].startswith("conflict: rig r1: the history on fpdd/r1/alarm/history is answered "
                                     "differently by 2 repliers")


# --------------------------------------------------------------------------- the command and the service


def test_alarms_cli_marks_verification_and_prints_only_real_alarms(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, keys: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str]
) -> None:
    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms"))
    signer = load_signer(keys / "r1.key", "r1")
    # Both queryables in the listening peer that the command connects to (peers do not relay for each other);
    # the forger's first, so that the command knows it once it sees the twin's token.
    with forged_history(hub, range(1, 9), tmp_path), TwinPublisher(hub, "r1", journal, signer=signer) as twin:
        real = [twin.publish_alarm(alarm("r1", i)) for i in range(1, 6)]
        common = ["--rig", "r1", "--connect", endpoint, "--timeout", "1"]
        assert run_alarms_cli(parser.parse_args([*common, "--keys", str(keys), "--json"])) == 0
        verified = capsys.readouterr()
        assert run_alarms_cli(parser.parse_args([*common, "--count", "1"])) == 1
        unkeyed = capsys.readouterr()
    lines = [json.loads(line) for line in verified.out.splitlines()]
    assert [line["verification"] for line in lines] == [VERIFIED] * 5
    assert unsigned([AlarmEvent.from_dict(line) for line in lines]) == real
    assert all(line["signature"] for line in lines)
    err = verified.err.splitlines()
    assert len(err) == 2 and err[0].startswith("forged: rig r1 seq 1..8") and err[1].startswith("conflict: rig r1")
    assert unkeyed.out == ""  # no keys: the disagreeing queryables are not merged, nothing printed
    assert unkeyed.err.startswith("conflict: rig r1")
    with pytest.raises(ConfigError, match="--require-signed: needs --keys DIR"):
        run_alarms_cli(parser.parse_args(["--connect", endpoint, "--require-signed"]))


def test_alarms_cli_unsigned_rig_is_unverified_or_refused(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, keys: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms"))
    with TwinPublisher(hub, "r2", journal) as twin:  # r2 has no key: it publishes unsigned
        twin.publish_alarm(alarm("r2", 1))
        common = ["--rig", "r2", "--connect", endpoint, "--keys", str(keys)]
        assert run_alarms_cli(parser.parse_args([*common, "--count", "1", "--timeout", str(WAIT_S)])) == 0
        out = capsys.readouterr().out.splitlines()
        # the line starts with the wall-clock time the journal recorded the alarm, then the record's time
        assert len(out) == 1 and re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z r2 #1 t=1\.000 s ", out[0]) \
            and out[0].endswith(" [unverified]"), out
        assert run_alarms_cli(parser.parse_args([*common, "--require-signed", "--timeout", "1"])) == 0
        refused = capsys.readouterr()
    assert refused.out == ""
    line = refused.err.strip()
    assert "\n" not in line and line.startswith("unverified: rig r2 seq 1 in replies of queryable ")
    assert line.endswith(" on fpdd/r2/alarm/history: no public key of rig 'r2' in the trust store; not accepted")


def test_the_service_front_signs_live_alarms_and_history(
    hub: zenoh.Session, endpoint: str, journal: AlarmJournal, keys: Path
) -> None:
    """What ``twin serve`` declares (BusFront with rigs.toml's signing keys): both paths verify."""
    first = journal.append(alarm("r1", 1))
    with connected(endpoint) as s:
        front = BusFront(s, {"r1": journal}, None, {"r1": str(keys / "r1.key")})
        try:
            with AlarmSubscriber(hub, "r1", trust=TrustStore(keys)) as sub:
                got = [sub.recv(timeout=WAIT_S)]  # from the history
                assert front._pubs["r1"].wait_for_alarm_subscribers(WAIT_S)
                second = journal.append(alarm("r1", 2))
                front.handle("r1", [("alarm", second)])  # live
                got.append(sub.recv(timeout=WAIT_S))
        finally:
            front.close()
    assert unsigned(got) == [first, second]
    assert [sub.verification[("r1", s)] for s in (1, 2)] == [VERIFIED, VERIFIED] and sub.reports == []


# --------------------------------------------------------------------------- replays of another campaign


def earlier_campaign(hub: zenoh.Session, tmp_path: Path, keys: Path, endpoint: str) -> list[str]:
    """Five alarms of r1 as they went over the bus in an earlier campaign (journal ``a.db``), recorded off the
    bus by a plain Zenoh subscriber (in the listening peer): signed, valid for ever."""
    recorded: list[str] = []
    arrived = threading.Event()
    signer = load_signer(keys / "r1.key", "r1")

    def keep(sample: zenoh.Sample) -> None:
        recorded.append(sample.payload.to_string())
        if len(recorded) == 5:
            arrived.set()

    with connected(endpoint) as twin_session, AlarmJournal(tmp_path / "a.db") as journal_a:
        listener = hub.declare_subscriber("fpdd/r1/alarm", keep)
        with TwinPublisher(twin_session, "r1", journal_a, signer=signer) as twin:
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            for i in range(1, 6):
                twin.publish_alarm(replace(alarm("r1", i), parameter="Ffric", unit=""))
            assert arrived.wait(WAIT_S)
        listener.undeclare()
    return recorded


def test_alarms_of_an_earlier_epoch_put_again_are_refused_and_the_real_ones_arrive(
    hub: zenoh.Session, endpoint: str, keys: Path, tmp_path: Path
) -> None:
    old = earlier_campaign(hub, tmp_path, keys, endpoint)
    trust = TrustStore(keys)
    assert {trust.check(json.loads(p)).status for p in old} == {VERIFIED}  # still validly signed
    statuses: list[str] = []
    signer = load_signer(keys / "r1.key", "r1")
    with connected(endpoint) as twin_session, connected(endpoint) as attacker_session, \
            AlarmJournal(tmp_path / "b.db") as journal_b:
        status_listener = hub.declare_subscriber("fpdd/r1/status", lambda s: statuses.append(s.payload.to_string()))
        twin = TwinPublisher(twin_session, "r1", journal_b, signer=signer)
        twin.publish_status(StatusEvent(rig="r1", t_ns=T0_NS, state="running"))  # announces the new epoch
        with AlarmSubscriber(hub, "r1", trust=trust) as sub:
            assert sub.epochs == {"r1": journal_b.epoch("r1")}  # from the owner's latest status, before anything
            attacker = attacker_session.declare_publisher("fpdd/r1/alarm")
            wait_matching(attacker)
            for payload in old:
                attacker.put(payload)
            assert pump_until(sub, lambda: sub.replayed == 5) == []
            assert twin.wait_for_alarm_subscribers(WAIT_S)
            real = twin.publish_alarm(replace(alarm("r1", 7, level="warning"), parameter="CdAleak", unit=""))
            got = sub.recv(timeout=WAIT_S)  # the real seq 1 of this campaign: not taken by the replayed seq 1
            twin.close()  # the rig's twin is gone: the replays are still told by their epoch
            for payload in old:
                attacker.put(payload)
            assert pump_until(sub, lambda: sub.replayed == 10) == []
            attacker.undeclare()
        deadline = time.monotonic() + WAIT_S
        while not statuses:
            assert time.monotonic() < deadline, "the plain subscriber got no status"
            time.sleep(0.01)
        status_listener.undeclare()
    assert unsigned([got]) == [real] and real.seq == 1 and sub.verification[("r1", 1)] == VERIFIED
    epoch_a, epoch_b = json.loads(old[0])["epoch"], real.epoch
    assert epoch_a < epoch_b
    lines = [r for r in sub.reports if r.startswith("replayed: ")]
    assert len(lines) == 10 and lines[0] == (f"replayed: rig r1 seq 1 on fpdd/r1/alarm: of epoch {epoch_a}, earlier "
                                             f"than the rig's epoch {epoch_b}; not accepted")
    assert sub.forged == 0 and sub.conflicts == 0 and sub.missed == []
    # What a plain Zenoh subscriber sees is enough to tell the same: the status announces the epoch under the
    # rig's key, and the replayed alarms carry an earlier one that cannot be changed without breaking them.
    status = json.loads(statuses[-1])
    assert status["epoch"] == epoch_b and trust.check(status, STATUS_DOMAIN).status == VERIFIED
    assert trust.check(status).status == FORGED  # a status signature is no alarm signature
    assert trust.check({**status, "epoch": epoch_a}, STATUS_DOMAIN).status == FORGED
    assert all(json.loads(p)["epoch"] == epoch_a for p in old)
    assert trust.check({**json.loads(old[0]), "epoch": epoch_b}).status == FORGED


def test_alarms_cli_refuses_a_history_of_an_earlier_epoch_in_one_line(
    hub: zenoh.Session, endpoint: str, keys: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A second history queryable answering with the rig's alarms of another campaign (validly signed): the
    command prints the real alarm only and says in one line what it refused."""
    old = earlier_campaign(hub, tmp_path, keys, endpoint)
    parser = add_alarms_arguments(argparse.ArgumentParser(prog="twin alarms"))
    signer = load_signer(keys / "r1.key", "r1")

    def answer(query: zenoh.Query) -> None:
        with query:
            for payload in old:
                query.reply("fpdd/r1/alarm/history", payload, encoding=zenoh.Encoding.APPLICATION_JSON)

    with AlarmJournal(tmp_path / "b.db") as journal_b:
        replayer = hub.declare_queryable("fpdd/r1/alarm/history", answer)
        try:
            with TwinPublisher(hub, "r1", journal_b, signer=signer) as twin:
                twin.publish_status(StatusEvent(rig="r1", t_ns=T0_NS, state="running"))
                common = ["--rig", "r1", "--connect", endpoint, "--keys", str(keys), "--json", "--timeout", "1"]
                assert run_alarms_cli(parser.parse_args(common)) == 0  # the new campaign has no alarm yet
                before = capsys.readouterr()
                real = twin.publish_alarm(replace(alarm("r1", 7, level="warning"), parameter="CdAleak", unit=""))
                assert run_alarms_cli(parser.parse_args(common)) == 0
                after = capsys.readouterr()
        finally:
            replayer.undeclare()
    assert before.out == ""
    epoch_a = json.loads(old[0])["epoch"]
    for err in (before.err, after.err):
        replayed = [line for line in err.splitlines() if line.startswith("replayed: ")]
        assert len(replayed) == 1 and replayed[0].startswith("replayed: rig r1 seq 1..5 in replies of queryable ")
        assert replayed[0].endswith(f": of epoch {epoch_a}, earlier than the rig's epoch {real.epoch}; not accepted")
        assert "Traceback" not in err
    lines = [json.loads(line) for line in after.out.splitlines()]
    assert len(lines) == 1 and lines[0]["verification"] == VERIFIED and lines[0]["epoch"] == real.epoch
    assert unsigned([AlarmEvent.from_dict(lines[0])]) == [real]


def test_a_later_epoch_starts_the_numbers_afresh(hub: zenoh.Session, endpoint: str, keys: Path, tmp_path: Path) -> None:
    """The rig's journal was replaced (a new campaign): a subscriber running across it gets the new alarms 1, 2."""
    signer = load_signer(keys / "r1.key", "r1")
    delivered: list[AlarmEvent] = []
    with AlarmSubscriber(hub, "r1", trust=TrustStore(keys)) as sub:
        for name in ("a.db", "b.db"):
            with connected(endpoint) as s, AlarmJournal(tmp_path / name) as j, \
                    TwinPublisher(s, "r1", j, signer=signer) as twin:
                assert twin.wait_for_alarm_subscribers(WAIT_S)
                sent = [twin.publish_alarm(alarm("r1", i + (10 if name == "b.db" else 0))) for i in (1, 2)]
                got = [sub.recv(timeout=WAIT_S) for _ in sent]
                assert unsigned(got) == sent and [e.seq for e in got] == [1, 2]
                delivered += got
    first, second = delivered[0].epoch, delivered[2].epoch
    assert first < second and sub.epochs == {"r1": second}
    assert [r for r in sub.reports if r.startswith("epoch: ")] == [
        f"epoch: rig r1 numbers its alarms in a new epoch {second} (was {first}), announced by alarm seq 1 on "
        "fpdd/r1/alarm; its alarms from 1 are delivered"]
