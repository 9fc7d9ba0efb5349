"""``replay record``: a live CAN bus or Zenoh key to a log file.

A real CAN interface cannot run here (no SocketCAN in CI containers): the bus is
python-can's ``virtual`` interface, in-process, with the sender in a thread.  Zenoh
runs on loopback with explicit endpoints and multicast scouting off.
"""

from __future__ import annotations

import json
import socket
import threading

import can
import numpy as np
import pytest

from replay import cli
from benchmarks.can import msp25_samples
from replay.can.encode import FrameScheduler, frames_to_messages
from replay.can.codec import VectorCodec
from replay.factory import open_source
from replay.live import ZenohCanSink, ZenohSampleSink
from fpdd.zenohconf import zenoh_config
from replay.record import record

LSB_X = 1e-7


def _endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


class Sender:
    """Sends the rig's frames on a virtual bus, over and over with increasing times, until stopped."""

    def __init__(self, channel: str, seconds: float = 0.2, seed: int = 3) -> None:
        self.frames = list(frames_to_messages(FrameScheduler(VectorCodec()).frames(msp25_samples(seconds, seed=seed))))
        self.sent: list[can.Message] = []
        self.stop = threading.Event()
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        span = self.frames[-1].timestamp - self.frames[0].timestamp + 1e-3
        lap = 0
        while not self.stop.is_set():
            for m in self.frames:
                m2 = can.Message(timestamp=m.timestamp + lap * span, arbitration_id=m.arbitration_id,
                                 is_extended_id=m.is_extended_id, data=m.data, dlc=m.dlc)
                self.bus.send(m2)
                self.sent.append(m2)
            lap += 1
            self.stop.wait(0.005)  # let the recorder breathe between laps

    def __enter__(self) -> Sender:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(10.0)
        self.bus.shutdown()


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log", ".trc"])
def test_record_can_bus_to_a_can_log(tmp_path, capsys, suffix):
    out = tmp_path / f"rec{suffix}"
    with Sender(f"rec{suffix}"):
        code = cli.main(["record", f"can://virtual/rec{suffix}", "--out", str(out), "--limit", "400", "--quiet",
                         "--json", "--duration", "30"])
    assert code == 0, capsys.readouterr().err
    stats = json.loads(capsys.readouterr().out)
    assert stats["count"] == 400 and stats["ended_by"] == "limit" and stats["kind"] == "frames"
    reader = {".asc": can.ASCReader, ".blf": can.BLFReader, ".log": can.CanutilsLogReader, ".trc": can.TRCReader}
    got = list(reader[suffix](str(out)))
    assert len(got) == 400
    ids = [m.arbitration_id for m in got]
    assert set(ids) <= {0x100, 0x101, 0x120, 0x3A0} and 0x100 in ids
    assert all(bytes(m.data) for m in got)


def test_record_can_bus_to_mcap_samples(tmp_path, capsys):
    out = tmp_path / "rec.mcap"
    with Sender("recm", seconds=0.3, seed=5):
        code = cli.main(["record", "can://virtual/recm", "--out", str(out), "--limit", "500", "--quiet",
                         "--duration", "30"])
    assert code == 0, capsys.readouterr().err
    assert "recorded 500 samples from can://virtual/recm" in capsys.readouterr().out
    with open_source(out) as src:
        got = src.read_all()
    ref = msp25_samples(0.3, seed=5)
    assert len(got) == 500 and set(ref.names) >= {"x", "u", "pA"}
    # each recorded sample is one of the sent ones (the lap repeats the same values)
    assert np.isin(np.round(got["x"] / LSB_X), np.round(ref["x"] / LSB_X)).all()


def test_record_zenoh_samples_to_mcap_until_the_end_marker(tmp_path):
    ep = _endpoint()
    out = tmp_path / "z.mcap"
    sent = msp25_samples(0.4, seed=7)
    result: dict = {}
    th = threading.Thread(target=lambda: result.update(stats=record(
        "zenoh://fpdd/rec/samples", str(out), duration_s=60, zenoh_conf=zenoh_config(listen=[ep]))), daemon=True)
    th.start()
    with ZenohSampleSink("fpdd/rec/samples", config=zenoh_config(connect=[ep]), max_block=100) as sink:
        assert sink.wait_for_subscriber(10.0)
        sink.write(sent)
    th.join(30.0)
    assert not th.is_alive()
    stats = result["stats"]
    assert stats.count == len(sent) and stats.ended_by == "end marker"
    with open_source(out) as src:
        got = src.read_all()
    np.testing.assert_array_equal(got.t_ns, sent.t_ns)
    np.testing.assert_array_equal(got["x"], sent["x"])


def test_record_zenoh_can_frames_to_blf(tmp_path):
    ep = _endpoint()
    out = tmp_path / "z.blf"
    sent = msp25_samples(0.2, seed=8)
    result: dict = {}
    th = threading.Thread(target=lambda: result.update(stats=record(
        "zenoh://fpdd/rec/can", str(out), duration_s=60, zenoh_conf=zenoh_config(listen=[ep]))), daemon=True)
    th.start()
    with ZenohCanSink("fpdd/rec/can", config=zenoh_config(connect=[ep])) as sink:
        assert sink.wait_for_subscriber(10.0)
        sink.write(sent)
        frames_out = sink.scheduler.frames_out
    th.join(30.0)
    assert not th.is_alive() and result["stats"].count == frames_out
    with open_source(out) as src:  # the frames decode back to the samples
        got = src.read_all()
    assert len(got) == len(sent) and np.abs(got["x"] - sent["x"]).max() <= LSB_X / 2 + 1e-15


def test_record_shows_progress_and_says_when_nothing_came(tmp_path, capsys):
    out = tmp_path / "quiet.asc"
    code = cli.main(["record", "can://virtual/nobody", "--out", str(out), "--duration", "0.6"])
    err = capsys.readouterr().err
    assert code == 1
    assert "\rrecording can://virtual/nobody -> " in err  # progress on stderr
    assert err.rstrip().endswith(f"replay: error: can://virtual/nobody: nothing received within 0.6 s; "
                                 f"{out} holds no data")
