"""Real-time replay: pacing against the log's timestamps.

No fixed millisecond bound: a probe thread sleeps to its own schedule with the same
clock while the replay runs and measures how late *this machine, now* wakes a thread
up; the replay's lateness is asserted against that (it must be within a few times the
probe's, on a quiet machine and on a loaded one alike).
"""

from __future__ import annotations

import argparse
import json
import socket
import threading
import time

import can
import numpy as np
import pytest

from replay.base import Samples
from benchmarks.can import msp25_samples
from replay.can.logs import CanLogSink, CanLogSource
from replay.can.bus import CanBusSink
from replay.live import ZenohSource
from fpdd.zenohconf import zenoh_config
from replay.play import play, register

class JitterProbe:
    """Wakes up every ``period_s`` on the monotonic clock (as the player does) and records how
    late each wake-up was: the scheduling jitter of this machine while the test runs."""

    def __init__(self, period_s: float = 0.002) -> None:
        self.period_s = period_s
        self.late: list[float] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        t0 = time.monotonic()
        k = 0
        while not self._stop.is_set():
            k += 1
            due = t0 + k * self.period_s
            now = time.monotonic()
            if due > now:
                time.sleep(due - now)
            self.late.append(time.monotonic() - due)
            if self.late[-1] > self.period_s:  # fell behind: restart the schedule (no catch-up burst)
                t0, k = time.monotonic(), 0

    def __enter__(self) -> JitterProbe:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(5.0)

    def tolerance(self) -> float:
        """What lateness the machine allows now: 3x the probe's worst wake-up plus 10x its typical one."""
        late = np.maximum(np.array(self.late), 0.0)
        assert late.size >= 1, "the probe did not run"  # on a loaded machine it wakes only a few times
        return 3.0 * float(late.max()) + 10.0 * float(np.median(late))


@pytest.fixture
def log(tmp_path):
    p = tmp_path / "rig.blf"
    with CanLogSink(p) as sink:
        sink.write(msp25_samples(0.3, seed=4))
    return p


def _drain(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (m := bus.recv(timeout=0.0)) is not None:
        out.append(m)
    return out


@pytest.mark.parametrize("speed", [1.0, 3.0])
def test_play_paces_by_timestamps(log, speed):
    with can.Bus(interface="virtual", channel=f"play{speed}") as rx, \
            CanLogSource(log) as src, CanBusSink(f"can://virtual/play{speed}") as sink, JitterProbe() as probe:
        stats = play(src, sink, speed)
        frames = [m for m in _drain(rx) if m.arbitration_id == 0x100]
    tol = probe.tolerance()
    log_t = msp25_samples(0.3, seed=4).t_ns
    assert stats.samples == len(log_t) == len(frames)
    # every frame left at its due time: received time (bus clock) vs. log time / speed; the offset
    # between the two clocks is unknown, so the spread of (received - due) is what must stay small
    recv = np.array([m.timestamp for m in frames])
    want = (log_t - log_t[0]) * 1e-9 / speed
    delay = recv - recv[0] - want
    assert delay.max() - delay.min() < tol, f"spread {np.ptp(delay) * 1e3:.2f} ms, machine allows {tol * 1e3:.2f} ms"
    assert stats.early_max_s == 0.0, "a write went out before its due time"
    assert stats.late_max_s < tol, f"late {stats.late_max_s * 1e3:.2f} ms, machine allows {tol * 1e3:.2f} ms"
    assert abs(stats.wall_s - want[-1]) < tol
    assert stats.log_span_s == pytest.approx((log_t[-1] - log_t[0]) * 1e-9)


def test_play_as_fast_as_possible(log):
    with can.Bus(interface="virtual", channel="fast") as rx, \
            CanLogSource(log) as src, CanBusSink("can://virtual/fast") as sink:
        slept: list[float] = []
        stats = play(src, sink, float("inf"), sleep=slept.append)
        n = len(_drain(rx))
    assert stats.samples == 300 and n == sink.scheduler.frames_out and slept == []  # never waited


def test_play_rejects_bad_speed(log):
    with CanLogSource(log) as src, CanBusSink("can://virtual/bad") as sink:
        with pytest.raises(ValueError, match="speed"):
            play(src, sink, 0.0)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="replay")
    register(ap.add_subparsers(dest="cmd", required=True))
    return ap


def test_cli_play_to_can(log, capsys):
    args = _parser().parse_args(["play", str(log), "--to", "can", "--channel", "can://virtual/cli",
                                 "--speed", "5", "--json"])
    with can.Bus(interface="virtual", channel="cli") as rx, JitterProbe() as probe:
        assert args.func(args) == 0
        n = len(_drain(rx))
    out = json.loads(capsys.readouterr().out)
    assert out["stats"]["samples"] == 300 and out["stats"]["late_max_s"] < probe.tolerance()
    assert out["report"]["samples_out"] == 300 and n == 300 + 300 + 150 + 3



def test_cli_play_to_zenoh(log, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    args = _parser().parse_args(["play", str(log), "--to", "zenoh", "--key", "fpdd/play/samples",
                                 "--zenoh-connect", ep, "--speed", "10", "--json", "--quiet"])
    with ZenohSource("fpdd/play/samples", config=zenoh_config(listen=[ep]), timeout_s=5.0) as src:
        got: list = []
        reader = threading.Thread(target=lambda: got.extend(src.chunks()), daemon=True)
        reader.start()  # consumes while the player sends (a live consumer); ends at the player's end marker
        assert args.func(args) == 0
        reader.join(30.0)
        if reader.is_alive():
            src.close()
            pytest.fail("no end marker within 30 s")
        back = Samples.concat(got)
    ref = msp25_samples(0.3, seed=4)
    np.testing.assert_array_equal(back.t_ns, ref.t_ns)
    assert np.abs(back["x"] - ref["x"]).max() <= 0.5e-7 + 1e-15
    assert json.loads(capsys.readouterr().out)["stats"]["samples"] == 300


def test_cli_play_to_can_needs_an_explicit_channel(log, capsys):
    from replay import cli

    with pytest.raises(SystemExit) as exc:
        cli.main(["play", str(log), "--to", "can"])
    assert exc.value.code == 2
    assert "--to can needs --channel can://INTERFACE/CHANNEL" in capsys.readouterr().err


def test_cli_play_to_a_bus_that_cannot_open_is_one_line(log, capsys):
    """SocketCAN where there is none (this host, CI): one line naming the bus and the cause, exit 1."""
    from replay import cli

    assert cli.main(["play", str(log), "--to", "can", "--channel", "can://socketcan/fpddnone0", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("replay: error: can://socketcan/fpddnone0: cannot open CAN bus: ")


def test_lateness_statistics_take_bounded_memory_and_stay_accurate():
    """The pacer's lateness record is a fixed-size histogram, not a list that grows with the replay."""
    from replay.play import _Lateness

    rng = np.random.default_rng(7)
    lat = _Lateness()
    size0 = lat.counts.nbytes
    parts = [rng.exponential(2e-4, 5000) for _ in range(200)]  # one million writes' lateness
    for p in parts:
        lat.add(p)
    allv = np.concatenate(parts)
    assert lat.counts.nbytes == size0 and lat.n == allv.size
    assert lat.max == allv.max() and lat.min == allv.min()
    assert lat.total / lat.n == pytest.approx(allv.mean(), rel=1e-9)
    exact = np.percentile(allv, 99)
    assert exact <= lat.p99() <= exact * 10 ** (1 / 20) * 1.0001  # the bin holding the 99th percentile
