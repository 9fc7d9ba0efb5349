"""An alarm journaled but not yet put when the service is killed (``kill -9``), or put a moment before the kill
and still in the dead process's transmit queue, is put when it starts again, so a plain Zenoh subscriber gets
every alarm, at least once, each copy the same (loopback, explicit endpoints, scouting off)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

from fpdd.zenohconf import zenoh_config
from twin.service.bus import StoreHistory
from twin.service.fleet import BusFront
from twin.service.put_mark import put_mark_path
from twin.service.subscriber import AlarmSubscriber

WAIT_S = 10.0

CHILD = r"""
import os, signal, sys
sys.path.insert(0, sys.argv[3])
import zenoh
from event_helpers import alarm
from fpdd.zenohconf import zenoh_config
from twin.service.bus import TwinPublisher
from twin.service.journal import AlarmJournal
from twin.service.put_mark import put_mark_path

path, endpoint = sys.argv[1], sys.argv[2]
session = zenoh.open(zenoh_config(connect=[endpoint]))
journal = AlarmJournal(path)
twin = TwinPublisher(session, "r1", journal, put_mark=put_mark_path(path))
assert twin.wait_for_alarm_subscribers(10.0)
twin.publish_alarm(alarm("r1", 1))
twin.publish_alarm(alarm("r1", 2))  # put: in the session's transmit queue, perhaps not yet sent
journal.record(alarm("r1", 3))  # journaled, in the main file; the put would come next
print("journaled", flush=True)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_an_alarm_journaled_but_not_put_before_a_kill_is_put_at_the_restart(
    hub: zenoh.Session, endpoint: str, tmp_path: Path
) -> None:
    received: list[dict] = []
    lock = threading.Lock()

    def keep(sample: zenoh.Sample) -> None:
        with lock:
            received.append(json.loads(sample.payload.to_string()))

    def wait_for(n: int) -> None:
        deadline = time.monotonic() + WAIT_S
        while True:
            with lock:
                if len({a["seq"] for a in received}) >= n:
                    return
            assert time.monotonic() < deadline, f"{sorted({a['seq'] for a in received})}: not {n} alarms"
            time.sleep(0.01)

    plain = hub.declare_subscriber("fpdd/r1/alarm", keep)  # a plain Zenoh subscriber: no history, no gap filling
    # `twin alarms` (a session of its own, live only), reading its messages only after the restarts: the twin that
    # put alarm 2 is dead by then and its history cannot vouch for it (it was called "forged" before)
    alarms_session = zenoh.open(zenoh_config(connect=[endpoint]))
    twin_alarms = AlarmSubscriber(alarms_session, "r1", history=False)
    try:
        path = tmp_path / "r1.db"
        child = subprocess.Popen([sys.executable, "-c", CHILD, str(path), endpoint, str(Path(__file__).parent)],
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        out, err = child.communicate(timeout=120)
        assert child.returncode == -9 and out == "journaled\n", err
        assert json.loads(put_mark_path(path).read_text())["seq"] < 2  # killed within a second of the puts
        for _ in range(2):  # the service starts again (and once more: the mark is settled, nothing is put again)
            history = StoreHistory(path)
            front = BusFront(hub, {"r1": history})
            front.close()
            history.close()
            assert json.loads(put_mark_path(path).read_text())["seq"] == 3
        wait_for(3)
        delivered = []
        try:
            for _ in range(3):
                delivered.append(twin_alarms.recv(WAIT_S))
        except TimeoutError:
            raise AssertionError(f"delivered {[e.seq for e in delivered]}; {twin_alarms.reports}") from None
    finally:
        plain.undeclare()
        twin_alarms.close()
        alarms_session.close()
    assert [e.seq for e in delivered] == [1, 2, 3]  # each once, in order; a copy is said, not delivered
    assert all(line.startswith("replayed: ") and "received live before" in line for line in twin_alarms.reports), \
        twin_alarms.reports
    seqs = [a["seq"] for a in received]
    assert sorted(set(seqs)) == [1, 2, 3] and seqs.index(3) > max(seqs.index(1), seqs.index(2))
    for seq in (1, 2, 3):  # at least once, at most the child's put and the restart's; every copy the same alarm
        copies = [a for a in received if a["seq"] == seq]
        assert 1 <= len(copies) <= 2 and all(c == copies[0] for c in copies)
    assert len({a["epoch"] for a in received}) == 1


def test_a_put_is_marked_only_once_the_process_has_outlived_it(tmp_path: Path) -> None:
    from twin.service.put_mark import SETTLE_S, PutMark

    path = tmp_path / "r1.db.put.json"
    mark = PutMark(path, "r1")
    mark.done(0, "e1")
    mark.put(1, "e1", now=100.0)
    mark.put(2, "e1", now=100.0 + SETTLE_S / 2)
    assert json.loads(path.read_text())["seq"] == 0 and mark.pending == 2
    mark.settle(100.0 + SETTLE_S)  # the first outlived, the second not yet
    assert json.loads(path.read_text())["seq"] == 1 and mark.pending == 1
    assert PutMark(path, "r1").unsent(2, "e1") == 2  # a restart now would put the second again
    mark.settle(100.0 + 2 * SETTLE_S)
    assert json.loads(path.read_text()) == {"rig": "r1", "epoch": "e1", "seq": 2} and mark.pending == 0
