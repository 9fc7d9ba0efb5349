"""Failover between ``twin serve`` processes over Zenoh (loopback, separate processes: a router, two or three
services sharing a rig, an alarm subscriber): the owner killed with SIGKILL at a seeded random moment, a standby
takes the rig over from the replicated checkpoint; what the subscriber received and the journals hold together
equal an uninterrupted run's alarms exactly (seq 1..n, none lost, none twice)."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import threading
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from net_helpers import connected, free_port
from twin.service.store import Store
from twin.models.scenario import Drift

from benchmarks.failover import (ALARM_LINE, CLAIM_S, CLAIMING, ENV, LEASE_S, RIG, ROOT, RUNNING, TOOK_OVER, WAIT_S,
                                 Estimates, Proc, journal, key, received, router, serve_proc, service_config,
                                 subscriber, wear_log)

#: The issue's bound: a standby takes a rig within this long of its owner's token going [s].
TAKEOVER_S = 5.0
#: The wear log's length [s of record].
LOG_S = 24.0


@pytest.fixture(autouse=True)
def no_process_left_running():
    yield
    Proc.cleanup()


@pytest.fixture(scope="module")
def wear(tmp_path_factory) -> tuple[Path, list]:
    """A 24 s log of a rig whose friction steps at 3 s and whose valve frequency ramps down from 12 s, and the
    alarms of one uninterrupted run of it (the reference)."""
    log, reference = wear_log(tmp_path_factory.mktemp("wear"), LOG_S,
                              [Drift("Ffric", 3.0, 3.0, shape="step"), Drift("wn", 0.6, 12.0, 18.0, "ramp")], 1011)
    assert len(reference) >= 3 and reference[0].t_ns < 9e9 < reference[-1].t_ns
    return log, reference


def estimate_after_kill(session, owner: Proc, after_s: float) -> float:
    """Kill ``owner`` after ``after_s``; the time from the kill to the rig's next estimate (published by the
    service that took it over) [s]."""
    est = Estimates(session)
    try:
        time.sleep(after_s)
        killed = time.monotonic()
        owner.kill()
        return est.first_after(killed)[0] - killed
    finally:
        est.close()


@pytest.mark.slow
def test_owner_killed_at_a_random_moment_a_standby_takes_over_and_no_alarm_is_lost_or_repeated(tmp_path, wear):
    log, reference = wear
    rng = np.random.default_rng(1001)
    ep = router(tmp_path)
    sub = subscriber(ep)
    started = time.monotonic()
    a = serve_proc(service_config(tmp_path, "svc-a", ep, str(log), priority=0, speed=1.5))
    a.wait_for(CLAIMING)
    startup_s = time.monotonic() - started  # what a service's start takes on this machine now
    # svc-b must still be running the log when the returning owner has started: its play lasts at least six of
    # this machine's start-ups (1.5x real time on a quiet machine, slower on a busy one; alarms are in record time)
    speed_b = min(1.5, LOG_S / (6.0 * startup_s))
    a.wait_for(ALARM_LINE)  # svc-a runs the rig and raised its first alarm; svc-b starts late
    b = serve_proc(service_config(tmp_path, "svc-b", ep, str(log), priority=1, speed=speed_b))
    b.wait_for(RUNNING)
    with connected(ep) as session:
        took = estimate_after_kill(session, a, CLAIM_S + float(rng.uniform(0.0, 2.0)))  # seeded random moment
    assert b.wait_for(TOOK_OVER)[1] == "svc-a"
    assert took < LEASE_S + TAKEOVER_S, f"took over {took:.2f} s after the kill"
    back = serve_proc(service_config(tmp_path, "svc-a", ep, str(log), priority=0, speed=speed_b))  # the owner returns
    assert b.finish() == 0, "\n".join(b.seen[-20:])
    assert back.finish() == 0, "\n".join(back.seen[-20:])
    # the returning owner stood by: it never claimed the rig, and learnt that its log ended on svc-b
    assert not any(CLAIMING.match(line) for line in back.seen), "\n".join(back.seen)
    assert any(re.match(r"^twin serve: summary rig-f: finished.*run to its end by svc-b", line) for line in back.seen)
    time.sleep(0.5)
    sub.kill(signal.SIGTERM)
    got = {(d["seq"], d["parameter"], d["level"], d["kind"], d["t_ns"]) for d in received(sub)}
    ja, jb = journal(tmp_path, "svc-a"), journal(tmp_path, "svc-b")
    union = got | {key(x) for x in ja} | {key(x) for x in jb}
    assert sorted(union) == [key(x) for x in reference]  # seq 1..n, none lost, none twice
    # who watched when: svc-a ran the rig from the start, svc-b from svc-a's checkpoint to the end of the log
    owners = {n: [json.loads(x) for x in (tmp_path / n / f"{RIG}.owners.jsonl").read_text().splitlines()]
              for n in ("svc-a", "svc-b")}
    assert [(o["event"], o.get("previous")) for o in owners["svc-a"]] == [("runs", None)]  # killed: no end
    assert [(o["event"], o.get("previous")) for o in owners["svc-b"]] == [("runs", "svc-a"), ("finished", None)]
    assert owners["svc-a"][0]["wall_ns"] < owners["svc-b"][0]["wall_ns"] and owners["svc-b"][0]["resumed_t_ns"] > 0
    # the late standby caught up: the first alarm in its journal is svc-a's own (same raise time), not raised again
    assert jb[0].wall_ns == ja[0].wall_ns and key(jb[0]) == key(ja[0])
    print(f"took over {took:.2f} s after the kill; {len(reference)} alarms")


@pytest.mark.slow
def test_live_input_taken_over_from_now_unwatched_time_within_the_takeover_and_a_preferred_owner_takes_it_back(
        tmp_path, wear):

    log, _ = wear
    rng = np.random.default_rng(1002)
    ep = router(tmp_path)
    source = f"zenoh://fpdd/{RIG}/samples"
    a = serve_proc(service_config(tmp_path, "svc-a", ep, source, priority=0, speed=1.0))
    a.wait_for(CLAIMING)
    b = serve_proc(service_config(tmp_path, "svc-b", ep, source, priority=1, speed=1.0))
    b.wait_for(RUNNING)
    with connected(ep) as session:
        est = Estimates(session)
        try:
            Proc(["-m", "replay.cli", "play", str(log), "--to", "zenoh", "--key", f"fpdd/{RIG}/samples",
                  "--zenoh-connect", ep, "--speed", "1", "--wait-s", "10", "-q"], stdout=True)
            a.wait_for(ALARM_LINE)
            time.sleep(float(rng.uniform(0.3, 1.5)))  # a random moment (seeded)
            killed = time.monotonic()
            a.kill()
            unwatched = float(b.wait_for(re.compile(r"^twin serve: rig rig-f: ([0-9.]+) s of input not watched"))[1])
            first = est.first_after(killed)  # the rig watched again: the new owner's estimate
            last = est.last_before(killed)  # the old owner's last
            took = first[0] - killed
            # nobody watched between the old owner's last estimate and the new owner's first (record time):
            # what the new owner says it did not watch lies within that gap
            gap = (first[1] - last[1]) * 1e-9
            assert unwatched <= gap + 0.005, (unwatched, gap)
            assert took < LEASE_S + TAKEOVER_S
            time.sleep(1.5)  # a status or two of the new owner
            status = next(r.ok for r in session.get(f"fpdd/{RIG}/status", timeout=5.0) if r.ok is not None)
            st = json.loads(status.payload.to_string())
            # running (or degraded while it catches up with the live input after its start)
            assert st["state"] in ("running", "degraded") and st["message"].startswith("took over from svc-a "), st
            assert st["counters"]["unwatched_ms"] == int(unwatched * 1000 + 0.5) or \
                abs(st["counters"]["unwatched_ms"] - unwatched * 1000) <= 10
            assert 0 <= st["counters"]["took_over_ms"] <= took * 1000 + 10
            top = subprocess.run([sys.executable, "-m", "twin.cli", "top", "--once", "--json", "--connect", ep,
                                  "--mode", "client", "--rig", RIG], env=ENV, capture_output=True, text=True,
                                 timeout=WAIT_S)
            assert top.returncode == 0, top.stderr
            shown = json.loads(top.stdout)["rigs"][RIG]
            assert shown["owner"] == ["svc-b"] and shown["standby"] == [], shown
            # svc-a comes back told to take its rig back: svc-b stands down, svc-a runs the rig from now
            back = serve_proc(service_config(tmp_path, "svc-a", ep, source, priority=0, speed=1.0, prefer=True))
            assert back.wait_for(TOOK_OVER)[1] == "svc-b"
            b.wait_for(re.compile(r"^twin serve: rig rig-f: standing down for svc-a"))
            b.wait_for(re.compile(r"^twin serve: rig rig-f: stood down; standing by"))
        finally:
            est.close()
    back.kill(signal.SIGTERM)
    b.kill(signal.SIGTERM)
    # both had taken the rig over; told to stop, each closes its session and exits cleanly
    assert (back.proc.returncode, b.proc.returncode) == (0, 0), "\n".join(back.drain()[-10:] + b.drain()[-10:])
    ja, jb = journal(tmp_path, "svc-a"), journal(tmp_path, "svc-b")
    seqs = {}
    for x in ja + jb:  # one alarm per number on every service, numbers 1..n
        assert seqs.setdefault(x.seq, key(x)) == key(x)
    assert sorted(seqs) == list(range(1, len(seqs) + 1)) and len(set(seqs.values())) == len(seqs)
    print(f"live: took over {took:.2f} s after the kill, {unwatched:.2f} s unwatched within a gap of {gap:.2f} s "
          f"between estimates; {len(seqs)} alarms")


@pytest.mark.slow
def test_a_frozen_owner_is_taken_over_at_its_lease_and_when_it_thaws_the_rule_keeps_one_owner(tmp_path, wear):
    """A host that hangs (SIGSTOP) looks like a split network: its tokens go when its lease expires, a standby
    takes the rig; when it comes back both run the rig until they see each other, and the one the rule ranks
    after stands down. The journals agree alarm for alarm."""
    log, reference = wear
    ep = router(tmp_path)
    a = serve_proc(service_config(tmp_path, "svc-a", ep, str(log), priority=0, speed=1.5))
    a.wait_for(CLAIMING)
    b = serve_proc(service_config(tmp_path, "svc-b", ep, str(log), priority=1, speed=1.5))
    b.wait_for(RUNNING)
    with connected(ep) as session:
        est = Estimates(session)
        try:
            est.first_after(time.monotonic())
            time.sleep(1.0)
            frozen = time.monotonic()
            a.proc.send_signal(signal.SIGSTOP)
            took = est.first_after(frozen)[0] - frozen
        finally:
            est.close()
    assert b.wait_for(TOOK_OVER)[1] == "svc-a"
    assert LEASE_S <= took < LEASE_S + TAKEOVER_S, f"took over {took:.2f} s after the freeze (lease {LEASE_S:g} s)"
    raised = int(b.wait_for(ALARM_LINE)[1])  # svc-b raised an alarm svc-a, frozen, has not reached yet
    a.proc.send_signal(signal.SIGCONT)  # back: svc-a ranks first, svc-b stands down
    b.wait_for(re.compile(r"^twin serve: rig rig-f: standing down for svc-a \(it runs the rig too"))
    b.wait_for(re.compile(r"^twin serve: rig rig-f: stood down; standing by"))
    assert a.finish() == 0 and b.finish() == 0
    ja, jb = journal(tmp_path, "svc-a"), journal(tmp_path, "svc-b")
    assert [key(x) for x in ja] == [key(x) for x in jb] == [key(x) for x in reference]
    # svc-b handed the alarms of its term over: svc-a journaled (marked) those it did not hold yet, and svc-b took
    # svc-a's numbering; raised again by svc-a from the same data, they were recognised, not journaled twice
    owners = [json.loads(x) for x in (tmp_path / "svc-b" / f"{RIG}.owners.jsonl").read_text().splitlines()]
    handed = [o for o in owners if o["event"] == "handed_over"]
    assert len(handed) == 1 and handed[0]["raised"] >= 1 and handed[0]["replaced"] >= 1, owners
    marked = [x for x in ja if x.message.startswith("split: raised by term ")]
    assert len(marked) == handed[0]["adopted"] and (handed[0]["adopted"] == 0 or marked[0].seq >= raised), marked
    assert [(x.seq, x.message, x.term) for x in ja] == [(x.seq, x.message, x.term) for x in jb]


def test_the_lab_configurations_load_and_differ_only_where_a_site_must():
    import zenoh

    from twin.service.config import load_config

    lab = ROOT / "deploy" / "lab"
    for name in ("router-site-a", "router-site-b", "twin-site-a", "twin-site-b"):
        zenoh.Config.from_file(str(lab / f"{name}.json5"))  # zenoh refuses unknown keys and message names
    a, b = (load_config(str(lab / f"rigs-site-{s}.toml")) for s in "ab")
    assert a.failover is not None and b.failover is not None and a.failover.service_id != b.failover.service_id
    same = ("journal_dir", "out_dir", "path", "failover")
    assert {k: v for k, v in vars(a).items() if k not in same} == {k: v for k, v in vars(b).items() if k not in same}
    assert {k: v for k, v in vars(a.failover).items() if k != "service_id"} == \
           {k: v for k, v in vars(b.failover).items() if k != "service_id"}


@pytest.mark.slow
def test_the_lab_router_lets_the_twins_of_both_sites_share_a_rig_over_mtls(tmp_path, wear):
    """deploy/lab's router (mTLS, access control) with the two sites' twin certificates: the owner of site A
    runs the rig, site B stands by (replica, tokens, history) and takes the rig over when site A's service
    stops; B's journal ends with exactly the uninterrupted run's alarms."""
    import zenoh

    from test_deploy import readme_certificate_script
    from twin.service.config import parse_config
    from twin.service.serve import serve

    log, reference = wear
    certs = tmp_path / "tls"
    certs.mkdir()
    subprocess.run(["bash", "-euo", "pipefail", "-c", readme_certificate_script()
                    + 'issue router-local fpdd-router-site-a "IP:127.0.0.1"\n'
                    + 'issue lab-a fpdd-twin-lab-a "DNS:lab-a"\nissue lab-b fpdd-twin-lab-b "DNS:lab-b"\n'],
                   cwd=certs, check=True, capture_output=True, timeout=60)
    lab = ROOT / "deploy" / "lab"
    endpoint = f"tls/127.0.0.1:{free_port()}"

    def config(file: str, name: str, router: bool = False) -> zenoh.Config:
        conf = zenoh.Config.from_file(str(lab / file))
        tls = {"root_ca_certificate": "ca.pem", "connect_certificate": f"{name}.pem",
               "connect_private_key": f"{name}.key"}
        if router:
            conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
            conf.insert_json5("connect/endpoints", "[]")  # site B's router is not part of this test
            tls |= {"listen_certificate": f"{name}.pem", "listen_private_key": f"{name}.key"}
        else:
            conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        for k, file_ in tls.items():
            conf.insert_json5(f"transport/link/tls/{k}", json.dumps(str(certs / file_)))
        return conf

    def rigs(name: str, priority: int):
        return parse_config({"service": {"journal_dir": str(tmp_path / name), "checkpoint_s": 0.3},
                             "failover": {"service_id": name, "priority": priority, "lease_s": LEASE_S,
                                          "claim_s": CLAIM_S},
                             "rig": [{"name": "msp25-lab-1", "source": str(log), "speed": 3.0}]}, name)

    first_alarm = threading.Event()
    stops = {"lab-a": threading.Event(), "lab-b": threading.Event()}
    results: dict = {}

    def run(name: str, priority: int, session) -> None:
        results[name] = serve(rigs(name, priority), stops[name], on_alarm=lambda ev: first_alarm.set(),
                              session=session)

    with zenoh.open(config("router-site-a.json5", "router-local", router=True)), \
            zenoh.open(config("twin-site-a.json5", "lab-a")) as sa, zenoh.open(config("twin-site-b.json5", "lab-b")) as sb:
        ta = threading.Thread(target=run, args=("lab-a", 0, sa))
        ta.start()
        assert first_alarm.wait(WAIT_S)  # site A runs the rig
        tb = threading.Thread(target=run, args=("lab-b", 1, sb))
        tb.start()
        time.sleep(1.0)  # site B stands by: its replica follows
        stopped_ns = time.time_ns()
        stops["lab-a"].set()  # site A's service stops: its last checkpoint goes to site B, which takes over
        ta.join(WAIT_S)
        tb.join(WAIT_S)
        assert not ta.is_alive() and not tb.is_alive()
    assert results["lab-b"]["msp25-lab-1"].samples > 0
    owners = [json.loads(x) for x in (tmp_path / "lab-b" / "msp25-lab-1.owners.jsonl").read_text().splitlines()]
    assert [(o["event"], o.get("previous")) for o in owners] == [("runs", "lab-a"), ("finished", None)]
    assert owners[0]["wall_ns"] > stopped_ns  # site B saw site A's owner token until then
    with Store(tmp_path / "lab-b" / "msp25-lab-1.db", writer=False) as store:
        got = store.alarms("msp25-lab-1")
    assert [key(x) for x in got] == [key(x) for x in reference]


def test_a_replica_message_is_data_only_and_a_damaged_one_is_refused_with_one_line():
    from fpdd.errors import DataError
    from twin.service.checkpoint_file import Checkpoint
    from twin.service.replication import decode_replica, encode_replica

    state = {"x": np.arange(3.0), "n": 4, "flags": np.array([True, False]), "name": "ukf", "nan": float("nan")}
    payload = encode_replica(Checkpoint("rig-r", 5_000_000, 5000, "fp", state, 1.5e9, 3), "finished", "svc-a")
    cp, rig_state, owner = decode_replica(payload, "rig-r")
    assert (cp.t_ns, cp.samples, cp.alarm_seq, rig_state, owner) == (5_000_000, 5000, 3, "finished", "svc-a")
    assert np.array_equal(cp.state["x"], state["x"]) and cp.state["flags"].tolist() == [True, False]
    assert cp.state["n"] == 4 and np.isnan(cp.state["nan"])
    doc = json.loads(payload)
    doc["body"]["alarm_seq"] = 2  # changed on the way
    for bad, what in ((json.dumps(doc), "SHA-256"), ("not json", "not JSON"), ('{"format": "x"}', "not a replica"),
                      (payload, "rig")):
        with pytest.raises(DataError) as err:
            decode_replica(bad, "rig-r" if what != "rig" else "rig-s")
        assert what in str(err.value) and "\n" not in str(err.value) and "fpdd/" in str(err.value)


@pytest.mark.parametrize("table, message", [
    ({"service_id": "a/b"}, "failover.service_id: 'a/b' must be"),
    ({"priority": -1}, "failover.priority: -1; expected 0..1000000"),
    ({"lease_s": 0.1}, "failover.lease_s: 0.1 seconds; expected 0.5 to 60"),
    ({"prefr": True}, "failover: unknown key 'prefr' (did you mean 'prefer'?)"),
    ({"prefer": "yes"}, "failover.prefer: expected true or false"),
])
def test_a_bad_failover_table_is_refused_with_one_line_naming_the_key(table, message):
    from fpdd.errors import ConfigError
    from twin.service.config import parse_config

    with pytest.raises(ConfigError) as err:
        parse_config({"failover": table, "rig": [{"name": "r", "source": "r.mcap"}]}, "rigs.toml")
    assert str(err.value).startswith(f"rigs.toml: {message}"), str(err.value)


@pytest.mark.slow
def test_a_replica_closed_while_the_owner_does_not_answer_leaves_no_thread_inside_zenoh(hub, endpoint, tmp_path,
                                                                                        monkeypatch):
    """A standby takes a rig over while its replica still queries the owner that just died (each history query
    waits its timeout): closing the replica stops its thread, so no thread is inside a Zenoh call when the
    service closes its session and exits (one was: 'FATAL: exception not rethrown', SIGABRT at the exit)."""
    from event_helpers import alarm
    from twin.online.events import event_to_json
    from twin.service import replication
    from twin.service.config import parse_config

    monkeypatch.setattr(replication, "FETCH_S", 0.4)
    cfg = parse_config({"service": {"journal_dir": str(tmp_path / "svc-b")},
                        "failover": {"service_id": "svc-b", "priority": 1},
                        "rig": [{"name": "r1", "source": str(tmp_path / "r1.mcap")}]}, "rigs.toml")
    held: list = []  # the owner's history: its queries are kept, never answered (a host that hangs)
    history = hub.declare_queryable("fpdd/r1/alarm/history", held.append)
    try:
        with connected(endpoint) as session:
            replica = replication.Replica(session, cfg, cfg.rigs[0])
            for i in range(10):  # alarms after a gap: each makes the replica ask the history first (0.4 s each)
                hub.put("fpdd/r1/alarm", event_to_json(alarm("r1", i, seq=5 + i)))
            time.sleep(0.5)
            started = time.monotonic()
            replica.close()
            assert not replica._thread.is_alive(), f"the replica's thread still runs {time.monotonic() - started:.1f} s " \
                "after close()"
            assert replica.journal.closed
    finally:
        history.undeclare()
        held.clear()
