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

from event_helpers import alarm as make_alarm
from net_helpers import connected
from twin.cli import main as twin_main
from twin.commands.alarms import add_arguments as add_alarms_arguments
from twin.commands.alarms import run as run_alarms_cli
from fpdd.errors import ConfigError
from twin.online.events import AlarmEvent, event_to_json
from twin.service.bus import TwinPublisher
from twin.service.subscriber import AlarmSubscriber
from twin.service.config import parse_config
from twin.service.fleet import BusFront
from twin.service.journal import AlarmJournal
from twin.service.signing import FORGED, UNVERIFIED, VERIFIED, TrustStore, canonical, init_keys, load_signer

WAIT_S = 10.0  # upper bound of every wait; the happy path takes milliseconds


def alarm(rig: str, i: int, seq: int = 0) -> AlarmEvent:
    return make_alarm(rig, i, seq, level="alarm" if i % 2 else "warning")


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
    payload = json.loads(event_to_json(signer.sign(alarm("r1", 3, seq=3))))
    assert trust.check(payload).status == VERIFIED
    assert signer.sign(alarm("r1", 3, seq=3)).signature == payload["signature"]  # deterministic: live = history
    changed = {"rig": "r2", "parameter": "Ffric", "level": "warning", "kind": "returned", "t_ns": payload["t_ns"] + 1,
               "t_s": 3.5, "estimate": 4e-12, "std": 1e-13, "baseline": 2e-12, "band_lo": 1e-13, "band_hi": 3e-12,
               "seq": 4, "statistic": 99.0, "message": "fine", "unit": "N", "wall_ns": 1_700_000_000_000_000_000}
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
        with pytest.raises(TimeoutError):
            sub.recv(timeout=0.3)  # nothing else: no forged alarm, no duplicate
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
        forger.put(event_to_json(real))  # a plain duplicate: nothing to say
        forger.put(event_to_json(alarm("r1", 9, seq=1)))
        pump_until(sub, lambda: sub.conflicts == 1)
        forger.undeclare()
    assert sub.reports == ["conflict: rig r1 seq 1: a different alarm under a number already delivered "
                           "(Kleak alarm raised delivered, Kleak alarm raised now); not delivered"]


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
                with pytest.raises(TimeoutError):
                    sub.recv(timeout=0.3)  # no 6..8
    assert unsigned(got) == real
    assert {sub.verification[("r1", e.seq)] for e in got} == {VERIFIED}
    assert sub.forged == 8 and sub.conflicts == 1
    forged = [r for r in sub.reports if r.startswith("forged: ")]
    conflict = [r for r in sub.reports if r.startswith("conflict: ")]
    assert len(forged) == 1 and forged[0].startswith("forged: rig r1 seq 1..8 in replies of queryable ")
    assert len(conflict) == 1 and "answered differently by 2 repliers" in conflict[0] and "seq 1..5" in conflict[0]


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
                with pytest.raises(TimeoutError):
                    sub.recv(timeout=0.3)  # neither version of 1..5, none of the forger's 6..8
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
