"""``twin top`` against a real twin publisher on loopback (explicit endpoints, scouting off).

The live view runs under a pseudo-terminal (``pty``), as on a console; every
wait reads the terminal or the process with a deadline, nothing sleeps a fixed time.
"""

from __future__ import annotations

import json
import os
import pty
import re
import select
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from twin.service.bus import TwinPublisher
from fpdd.zenohconf import zenoh_config
from net_helpers import free_port
from twin.online.events import AlarmEvent, EstimateEvent, StatusEvent
from twin.service.journal import AlarmJournal

sys.path.insert(0, os.path.dirname(__file__))
from event_helpers import T0_NS, wear_forecasts  # noqa: E402

WAIT_S = 30.0  # upper bound of every wait (a Python process starting on a loaded machine)
TWIN = [sys.executable, "-m", "twin.cli"]
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


def wear_forecast(rig: str = "msp25-07", seconds: float = 400.0) -> dict:
    """The wear forecasts of :func:`event_helpers.wear_forecasts` (seed 1201): the last message."""
    return wear_forecasts(rig, seconds, seed=1201)[-1]


@pytest.fixture
def twin_on_bus(tmp_path):
    """A listening session with the twin of rig ``msp25-07``: one estimate, one status, two alarms, a forecast."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config(listen=[endpoint])) as session, AlarmJournal(tmp_path / "j.db") as journal, \
            TwinPublisher(session, "msp25-07", journal) as pub:
        pub.publish_estimate(EstimateEvent(
            rig="msp25-07", t_ns=T0_NS + 12_500_000_000, t_s=12.5, nis=0.9, status="ok",
            params={"CdAleak": {"value": 1.61e-8, "std": 3.0e-9, "unit": "m^2"},
                    "wn": {"value": 2 * np.pi * 43.0, "std": 0.12, "unit": "rad/s"},
                    "zeta": {"value": 0.3699, "std": 0.0021, "unit": "1"}}))
        for i, (level, kind) in enumerate((("warning", "raised"), ("alarm", "escalated")), start=1):
            pub.publish_alarm(AlarmEvent(rig="msp25-07", parameter="CdAleak", level=level, kind=kind,
                                         t_ns=T0_NS + (12 + i) * 1_000_000_000, t_s=12.0 + i, estimate=1.6e-8 + i * 1e-9,
                                         std=3e-9, baseline=3.29e-9, band_lo=1.1e-9, band_hi=9.9e-9, statistic=4.0 * i,
                                         message=f"CdAleak {kind}"))
        pub.publish_status(StatusEvent(rig="msp25-07", t_ns=T0_NS + 12_500_000_000, state="running",
                                       parameters={"CdAleak": "alarm", "wn": "ok", "zeta": "ok"},
                                       counters={"samples": 12500}))
        pub.publish_forecast(wear_forecast())
        yield endpoint, pub


def test_once_json_snapshot(twin_on_bus):
    endpoint, _ = twin_on_bus
    r = subprocess.run([*TWIN, "top", "--connect", endpoint, "--once", "--json", "--wait", "20"],
                       capture_output=True, text=True, timeout=WAIT_S + 30)
    assert r.returncode == 0, r.stderr
    snap = json.loads(r.stdout)
    rig = snap["rigs"]["msp25-07"]
    assert rig["state"] == "running" and rig["samples"] == 12500 and rig["t_s"] == 12.5
    wn = rig["params"]["wn"]
    assert wn["display_unit"] == "Hz" and wn["display_value"] == pytest.approx(43.0) and wn["value"] == pytest.approx(2 * np.pi * 43)
    assert rig["params"]["CdAleak"]["display_unit"] == "mm²" and rig["params"]["CdAleak"]["status"] == "alarm"
    assert rig["params"]["CdAleak"]["shown"] == "0.0161 ± 0.003 mm²"
    assert rig["params"]["zeta"]["display_unit"] == ""  # dimensionless: no unit
    assert rig["last_alarm_event"]["seq"] == 2 and "ALARM escalated CdAleak" in rig["last_alarm"]
    # the early warning: the soonest exit (SI seconds, record time) and the text a person reads
    fc = wear_forecast()["forecasts"]["CdAleak"]
    soon = rig["soonest_exit"]
    assert soon["parameter"] == "CdAleak" and soon["t_exit"] == fc["t_exit"] and soon["t"] == fc["t"]
    assert soon["t_exit_lo"] == fc["t_exit_lo"] and soon["t_exit_hi"] == fc["t_exit_hi"]
    assert soon["remaining_s"] == pytest.approx(fc["t_exit"] - fc["t"]) and soon["horizon_s"] == 600.0
    assert 60.0 < soon["remaining_s"] < 300.0  # the wear leaves the band at 560 s, forecast at 400 s
    minutes = [(fc[k] - fc["t"]) / 60.0 for k in ("t_exit", "t_exit_lo", "t_exit_hi")]
    assert soon["shown"] == f"in {minutes[0]:.1f} min [{minutes[1]:.1f}, {minutes[2]:.1f}]"
    assert rig["params"]["CdAleak"]["forecast"] == soon and "forecast" not in rig["params"]["wn"]


def test_live_view_in_a_terminal(twin_on_bus):
    endpoint, pub = twin_on_bus
    pid, fd = pty.fork()
    if pid == 0:  # the child: twin top on the terminal
        os.environ["COLUMNS"], os.environ["LINES"] = "120", "40"
        # Ctrl-C as a shell gives it to a program in the foreground: a test run started with SIGINT ignored
        # (in the background, under nohup) would hand that on through exec and twin top would never see it.
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.execv(sys.executable, [*TWIN, "top", "--connect", endpoint, "--wait", "20"])
    screen = ""

    def read_until(pattern: str) -> str:
        nonlocal screen
        deadline = time.monotonic() + WAIT_S
        while not re.search(pattern, ANSI.sub("", screen)):
            left = deadline - time.monotonic()
            assert left > 0, f"{pattern!r} not on the terminal within {WAIT_S} s:\n{ANSI.sub('', screen)[-3000:]}"
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                try:
                    screen += os.read(fd, 65536).decode("utf-8", "replace")
                except OSError:  # the child closed the terminal
                    break
        return ANSI.sub("", screen)

    try:
        text = read_until(r"last alarm: #2")
        assert "msp25-07" in text and "running" in text and "CdAleak" in text and "mm²" in text
        assert re.search(r"wn\s+│\s+43\s+│\s+0\.019\s+│\s+Hz", text), text[-2000:]
        assert "leaves band" in text and re.search(r"CdAleak .*│ in \d+\.\d min \[\d+\.\d, \d+\.\d\]", text), text[-2000:]
        assert re.search(r"soonest exit: CdAleak leaves its band in \d+\.\d min \[", text), text[-2000:]
        # a later forecast (the wear slowed: two hours further off) is shown as it comes, in hours
        later = wear_forecast()
        f = later["forecasts"]["CdAleak"]
        later["t_ns"] += 1_000_000_000
        f.update({k: f[k] + 7200.0 for k in ("t_exit", "t_exit_lo", "t_exit_hi")})
        f.update({k: f[k] + 7200.0 for k in ("remaining_s", "remaining_lo_s", "remaining_hi_s")})
        assert pub.put_forecast(later)
        read_until(r"soonest exit: CdAleak leaves its band in 2\.\d h \[2\.\d, 2\.\d\]")
        # a new estimate is shown as it comes
        pub.publish_estimate(EstimateEvent(rig="msp25-07", t_ns=T0_NS + 13_000_000_000, t_s=13.0, nis=1.0,
                                           status="ok", params={"wn": {"value": 2 * np.pi * 41.5, "std": 0.1,
                                                                       "unit": "rad/s"}}))
        read_until(r"wn\s+│\s+41\.5\s+│")
        os.write(fd, b"\x03")  # Ctrl-C: the view ends cleanly
        deadline = time.monotonic() + WAIT_S
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            assert time.monotonic() < deadline, "twin top did not stop on Ctrl-C"
            select.select([fd], [], [], 0.2)
            try:
                os.read(fd, 65536)
            except OSError:
                pass
        assert os.waitstatus_to_exitcode(status) == 0
    finally:
        try:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
        except (ProcessLookupError, ChildProcessError):
            pass
        os.close(fd)


def test_no_twin_is_one_line_naming_the_endpoint():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config(listen=[endpoint])):  # a router-like peer, but no twin behind it
        r = subprocess.run([*TWIN, "top", "--connect", endpoint, "--once", "--wait", "1"], capture_output=True,
                           text=True, timeout=WAIT_S + 30)
    assert r.returncode == 2 and r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and endpoint in lines[0] and "no twin answered" in lines[0], r.stderr


def test_help_and_json_needs_once():
    r = subprocess.run([*TWIN, "top", "--help"], capture_output=True, text=True, timeout=WAIT_S)
    assert r.returncode == 0 and "--once" in r.stdout and "--timeout" in r.stdout
    r = subprocess.run([*TWIN, "top", "--json", "--connect", "tcp/127.0.0.1:9"], capture_output=True, text=True,
                       timeout=WAIT_S)
    assert r.returncode == 2 and "--json needs --once" in r.stderr


SERVING = """
import sys, time, zenoh
from fpdd.zenohconf import zenoh_config
from twin.online.events import StatusEvent
from twin.service.bus import TwinPublisher
from twin.service.journal import AlarmJournal
endpoint, db = sys.argv[1:3]
with zenoh.open(zenoh_config(listen=[endpoint])) as s, AlarmJournal(db) as j, TwinPublisher(s, "rig-k", j) as pub:
    print("serving", flush=True)
    for i in range(100000):  # a twin's statuses, five a second, until killed
        pub.publish_status(StatusEvent(rig="rig-k", t_ns=i * 200_000_000, state="running", counters={"samples": i}))
        time.sleep(0.2)
"""


def test_a_killed_twin_is_shown_gone_within_5_s(tmp_path):
    """kill -9 of the process serving a rig: its liveliness token leaves the bus and twin top marks it GONE
    with the age of its last message, within 5 s."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    twin = subprocess.Popen([sys.executable, "-c", SERVING, endpoint, str(tmp_path / "j.db")], stdout=subprocess.PIPE,
                            text=True)
    pid = fd = None
    try:
        ready, _, _ = select.select([twin.stdout], [], [], WAIT_S)
        assert ready and twin.stdout.readline().strip() == "serving"  # type: ignore[union-attr]
        pid, fd = pty.fork()
        if pid == 0:
            os.environ["COLUMNS"], os.environ["LINES"] = "120", "40"
            os.execv(sys.executable, [*TWIN, "top", "--connect", endpoint, "--wait", "30"])
        screen = ""

        def read_until(pattern: str, within: float = WAIT_S) -> str:
            nonlocal screen
            deadline = time.monotonic() + within
            while not re.search(pattern, ANSI.sub("", screen)):
                left = deadline - time.monotonic()
                assert left > 0, f"{pattern!r} not on the terminal within {within} s:\n{ANSI.sub('', screen)[-3000:]}"
                ready, _, _ = select.select([fd], [], [], left)
                if ready:
                    try:
                        screen += os.read(fd, 65536).decode("utf-8", "replace")
                    except OSError:
                        break
            return ANSI.sub("", screen)

        text = read_until(r"rig rig-k\s+running")
        assert "GONE" not in text and "STALE" not in text
        screen = ""
        twin.kill()  # SIGKILL: no goodbye on the bus
        twin.wait(timeout=WAIT_S)
        read_until(r"rig rig-k\s+running\s+GONE \(twin left the bus; last message \d+ s ago\)", within=5.0)
    finally:
        if twin.poll() is None:
            twin.kill()
            twin.wait()
        twin.stdout.close()  # type: ignore[union-attr]
        if pid:
            try:
                os.kill(pid, 9)
                os.waitpid(pid, 0)
            except (ProcessLookupError, ChildProcessError):
                pass
        if fd is not None:
            os.close(fd)


def test_a_silent_twin_is_stale_with_its_age():
    from twin.commands.top import TopState, render

    state = TopState(stale_s=3.0)
    state.liveliness("rig-s", True)
    state.put("status", {"rig": "rig-s", "t_ns": 0, "state": "running", "parameters": {}, "counters": {}})
    now = state.seen["rig-s"]
    assert state.presence("rig-s", now + 1.0) == ("live", 1.0)
    assert state.presence("rig-s", now + 7.0) == ("stale", 7.0)
    state.liveliness("rig-s", False)
    assert state.presence("rig-s", now + 7.0)[0] == "gone"
    state.seen["rig-s"] = now - 7.0
    snap = state.snapshot()
    assert snap["rig-s"]["presence"] == "gone" and snap["rig-s"]["age_s"] >= 7.0
    from rich.console import Console

    console = Console(width=120, record=True)
    console.print(render(snap, "here", live=False))
    assert "GONE (twin left the bus; last message 7 s ago)" in console.export_text()
