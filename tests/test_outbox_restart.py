"""An alarm journaled but not yet put when the service is killed (``kill -9``) is put when it starts again, so a
plain Zenoh subscriber gets every alarm once (loopback, explicit endpoints, scouting off)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import zenoh

from twin.service.bus import StoreHistory
from twin.service.fleet import BusFront
from twin.service.put_mark import put_mark_path

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
twin.publish_alarm(alarm("r1", 2))
print("put", flush=True)
sys.stdin.readline()  # the subscriber has both: what is tested is the third, journaled and never put
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
                if len(received) >= n:
                    return
            assert time.monotonic() < deadline, f"{len(received)} of {n} alarms arrived"
            time.sleep(0.01)

    plain = hub.declare_subscriber("fpdd/r1/alarm", keep)  # a plain Zenoh subscriber: no history, no gap filling
    path = tmp_path / "r1.db"
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path), endpoint, str(Path(__file__).parent)],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert child.stdout is not None and child.stdin is not None
    assert child.stdout.readline() == "put\n"
    # a put still in the child's transmit queue at a kill -9 is lost with it, its put mark written (a limit noted
    # in issue 38): the child dies only once the first two have arrived
    wait_for(2)
    child.stdin.write("go\n")
    child.stdin.flush()
    out, err = child.communicate(timeout=120)
    assert child.returncode == -9 and out == "journaled\n", err
    assert json.loads(put_mark_path(path).read_text())["seq"] == 2
    for _ in range(2):  # the service starts again (and once more: nothing is put twice)
        history = StoreHistory(path)
        front = BusFront(hub, {"r1": history})
        front.close()
        history.close()
    wait_for(3)
    plain.undeclare()
    assert [a["seq"] for a in received] == [1, 2, 3]
    assert len({a["epoch"] for a in received}) == 1
    assert json.loads(put_mark_path(path).read_text())["seq"] == 3
