"""Live sources: python-can's virtual bus in-process, Zenoh on loopback (two sessions, two processes)."""

from __future__ import annotations

import multiprocessing as mp
import socket

import can
import numpy as np
import pytest

from replay.base import Samples
from replay.bench_can import msp25_samples
from replay.live import (CanBusSink, CanBusSource, ZenohCanSink, ZenohSampleSink, ZenohSource, frames_to_payload,
                         parse_can_uri, payload_to_frames, zenoh_config)
from replay.canio import FrameScheduler
from replay.dbc import VectorCodec
from twin.errors import SourceError

LSB_X = 1e-7


def _endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


# --- CAN bus -------------------------------------------------------------------------------------

def test_can_uri():
    assert parse_can_uri("can://virtual/rig1") == ("virtual", "rig1")
    assert parse_can_uri("can://socketcan/can0") == ("socketcan", "can0")
    with pytest.raises(SourceError, match="can://INTERFACE/CHANNEL"):
        parse_can_uri("can://virtual")


def test_can_bus_source_decodes_live_frames():
    samples = msp25_samples(0.4, seed=5)
    with can.Bus(interface="virtual", channel="live1", preserve_timestamps=True) as tx, \
            CanBusSource("can://virtual/live1", timeout_s=0.2,
                         signals=("x_ref", "u", "x", "pA", "pB")) as src, \
            CanBusSink(tx) as sink:
        sink.write(samples)
        got = []
        for sample in src:  # sample by sample, as the live service reads
            got.append(sample)
            if len(got) == len(samples):
                break
    t = np.array([g.t_ns for g in got])
    np.testing.assert_array_equal(t, samples.t_ns)
    x = np.array([g.values["x"] for g in got])
    assert np.abs(x - samples["x"]).max() <= LSB_X / 2 + 1e-15
    assert src.report.skipped == {}


def test_can_bus_source_probes_signals_and_times_out():
    """Without signals= the source looks at the first frames; a silent bus ends the stream."""
    samples = msp25_samples(0.5, seed=6)
    with can.Bus(interface="virtual", channel="live2") as rx, \
            can.Bus(interface="virtual", channel="live2", preserve_timestamps=True) as tx:
        with CanBusSink(tx) as sink:
            sink.write(samples)
        t_end = samples.t_ns[-1] / 1e9 + 1e-4
        tx.send(can.Message(arbitration_id=0x555, is_extended_id=False, data=b"\x01", timestamp=t_end))
        with CanBusSource(rx, timeout_s=0.1) as src:
            assert src.signals == ("x_ref", "u", "x", "pA", "pB", "T_oil", "pP")
            back = src.read_all()
        assert len(back) == len(samples)
        assert src.report.skipped == {"unknown_id 0x555": 1}
        assert "no CAN frame for 0.1 s" in str(src.report.problems[-1])
        assert not rx._is_shutdown  # not owned: the caller closes it


def test_silent_bus_is_an_error():
    with pytest.raises(SourceError, match="no CAN frame within 0.05 s"):
        CanBusSource("can://virtual/silent", timeout_s=0.05)


# --- Zenoh -------------------------------------------------------------------------------------------

def test_zenoh_json_samples_two_sessions():
    ep = _endpoint()
    samples = msp25_samples(0.3, seed=8)
    samples.signals["pA"][5] = np.nan  # NaN travels as null
    with ZenohSource("zenoh://fpdd/test/samples", config=zenoh_config(listen=[ep]), timeout_s=5.0) as src:
        with ZenohSampleSink("zenoh://fpdd/test/samples", config=zenoh_config(connect=[ep]), max_block=128) as sink:
            assert sink.wait_for_subscriber(5.0)
            sink.write(samples)
        back = src.read_all()
    assert back.names == samples.names
    np.testing.assert_array_equal(back.t_ns, samples.t_ns)
    for k in samples.names:
        np.testing.assert_array_equal(back[k], samples[k])
    assert src.report.records_read == 3 and src.report.samples_out == len(samples)


def test_zenoh_can_frames_two_sessions_and_bad_payload():
    ep = _endpoint()
    samples = msp25_samples(0.3, seed=9)
    with ZenohSource("fpdd/test/can", config=zenoh_config(listen=[ep]), timeout_s=5.0) as src:
        with ZenohCanSink("fpdd/test/can", config=zenoh_config(connect=[ep])) as sink:
            assert sink.wait_for_subscriber(5.0)
            sink.write(samples.slice(0, 100))
            sink._put(b"FCAN\x07\x00\x18\x00")  # a version nobody speaks
            sink.write(samples.slice(100, len(samples)))
        back = src.read_all()
    assert len(back) == len(samples)
    assert np.abs(back["x"] - samples["x"]).max() <= LSB_X / 2 + 1e-15
    assert src.report.skipped["bad_payload"] == 1
    assert "fpdd.can version 7" in str(src.report.problems[0])


def test_can_payload_round_trip():
    codec = VectorCodec()
    fr = FrameScheduler(codec).frames(msp25_samples(0.1))
    back = payload_to_frames(frames_to_payload(fr), "test")
    for f in ("t_ns", "key", "dlc", "data", "kind"):
        np.testing.assert_array_equal(getattr(back, f), getattr(fr, f))


def _publish_can_in_child(endpoint: str, key: str, seconds: float, seed: int) -> None:
    """Another process: encode samples to MSP25 frames and publish them raw on Zenoh."""
    from replay.bench_can import msp25_samples as make
    from replay.live import ZenohCanSink as Sink, zenoh_config as conf

    with Sink(key, config=conf(connect=[endpoint])) as sink:
        if not sink.wait_for_subscriber(10.0):
            raise SystemExit(2)
        sink.write(make(seconds, seed=seed))


def test_zenoh_can_frames_across_processes():
    ep = _endpoint()
    ctx = mp.get_context("spawn")  # forked children hang on close with zenoh
    with ZenohSource("fpdd/proc/can", config=zenoh_config(listen=[ep]), timeout_s=20.0) as src:
        child = ctx.Process(target=_publish_can_in_child, args=(ep, "fpdd/proc/can", 0.5, 11))
        child.start()
        try:
            back = src.read_all()
        finally:
            child.join(20.0)
    assert child.exitcode == 0
    ref = msp25_samples(0.5, seed=11)
    assert len(back) == len(ref)
    np.testing.assert_array_equal(back.t_ns, ref.t_ns)
    assert np.abs(back["x"] - ref["x"]).max() <= LSB_X / 2 + 1e-15


def test_zenoh_source_times_out_without_publisher():
    ep = _endpoint()
    with ZenohSource("fpdd/none", config=zenoh_config(listen=[ep]), timeout_s=0.1,
                     signals=("x",)) as src:
        assert len(src.read_all()) == 0
        assert "no payload for 0.1 s" in str(src.report.problems[-1])
    with ZenohSource("fpdd/none", config=zenoh_config(listen=[_endpoint()]), timeout_s=0.05) as src:
        with pytest.raises(SourceError, match="nothing received within 0.05 s"):
            src.signals  # noqa: B018


def test_samples_json_single_sample_form():
    from replay.live import json_to_samples

    s = json_to_samples(b'{"format":"fpdd.samples/1","t_ns":5,"signals":{"x":0.25,"u":null}}', "p")
    assert isinstance(s, Samples) and s.t_ns.tolist() == [5] and s["x"][0] == 0.25 and np.isnan(s["u"][0])
