"""Live sources: python-can's virtual bus in-process, Zenoh on loopback (two sessions, two processes)."""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import socket
import threading
import time

import can
import numpy as np
import pytest
import zenoh

from replay.base import Samples
from benchmarks.can import msp25_samples
from replay.can.bus import CanBusSink, CanBusSource, parse_can_uri
from replay.live import ZenohCanSink, ZenohSampleSink, ZenohSource, frames_to_payload, payload_to_frames
from fpdd.zenohconf import zenoh_config
from replay.live import samples_to_json as samples_json
from replay.can.encode import FrameScheduler
from replay.can.codec import VectorCodec
from fpdd.errors import SourceError

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


def _consume(src, *, until, timeout_s: float = 20.0, size: int = 65536):
    """Iterate ``src.chunks`` in a thread; ``until(blocks)`` is polled after every block and may
    close the source.  Returns (blocks, thread); the thread must end by itself once closed."""
    blocks: list[Samples] = []
    done = threading.Event()

    def run():
        try:
            for block in src.chunks(size):
                blocks.append(block)
                until(blocks)
        finally:
            done.set()

    th = threading.Thread(target=run, daemon=True)
    th.start()
    if not done.wait(timeout_s):
        src.close()
        pytest.fail(f"the live source did not end within {timeout_s} s")
    th.join(timeout_s)
    return blocks


def _read_to_end(src, timeout_s: float = 30.0) -> Samples:
    """Everything up to the sender's end marker (the source is closed, and the test fails, on timeout)."""
    return Samples.concat(_consume(src, until=lambda b: None, timeout_s=timeout_s))


def test_can_bus_source_probes_signals_and_stays_open_when_quiet():
    """Without signals= the source looks at the first frames; a quiet bus makes it stale (empty
    blocks, stale_events) but does not end it: only close() does, from another thread."""
    samples = msp25_samples(0.5, seed=6)
    with can.Bus(interface="virtual", channel="live2") as rx, \
            can.Bus(interface="virtual", channel="live2", preserve_timestamps=True) as tx:
        with CanBusSink(tx) as sink:
            sink.write(samples)
        t_end = samples.t_ns[-1] / 1e9 + 1e-4
        tx.send(can.Message(arbitration_id=0x555, is_extended_id=False, data=b"\x01", timestamp=t_end))
        src = CanBusSource(rx, timeout_s=0.1, poll_s=0.02)
        assert src.signals == ("x_ref", "u", "x", "pA", "pB", "T_oil", "pP")

        def until(blocks):
            if sum(map(len, blocks)) == len(samples) and src.stale and len(blocks[-1]) == 0:
                threading.Thread(target=src.close).start()

        blocks = _consume(src, until=until)
        assert sum(map(len, blocks)) == len(samples)
        assert src.stale_events == 1 and any("still waiting" in str(p) for p in src.report.problems)
        assert src.report.skipped == {"unknown_id 0x555": 1}
        assert src.health()["closed"] and src.health()["samples_out"] == len(samples)
        assert not rx._is_shutdown  # not owned: the caller closes it


def test_silent_bus_waits_and_says_so():
    src = CanBusSource("can://virtual/silent", timeout_s=0.05, poll_s=0.02)
    with pytest.raises(SourceError, match="no CAN frame of a rig message within 0.05 s"):
        src.signals  # noqa: B018
    blocks = _consume(src, until=lambda b: src.close() if src.stale and len(b) >= 3 else None)
    assert len(blocks) >= 3 and all(len(b) == 0 for b in blocks) and src.stale_events == 1
    assert src.idle() >= 0.05


def test_can_bus_flood_is_dropped_and_counted(caplog):
    """Frames beyond max_frames_per_s are dropped as 'flood', counted and logged once."""
    samples = msp25_samples(0.4, seed=12)
    caplog.set_level(logging.WARNING, logger="replay.live")
    with can.Bus(interface="virtual", channel="fl1") as rx, \
            can.Bus(interface="virtual", channel="fl1", preserve_timestamps=True) as tx:
        src = CanBusSource(rx, timeout_s=0.1, poll_s=0.02, max_frames_per_s=300,
                           signals=("x_ref", "u", "x", "pA", "pB"))
        with CanBusSink(tx) as sink:
            sink.write(samples)  # about 1000 frames at once
        blocks = _consume(src, until=lambda b: src.close() if src.stale else None)
    dropped = src.report.skipped["flood"]
    assert 600 <= dropped <= 1000 - 250, src.report.skipped
    assert sum(map(len, blocks)) < len(samples)
    assert len([r for r in caplog.records if "flood" in r.getMessage()]) == 1  # rate-limited


# --- Zenoh -------------------------------------------------------------------------------------------

def test_zenoh_json_samples_two_sessions():
    ep = _endpoint()
    samples = msp25_samples(0.3, seed=8)
    samples.signals["pA"][5] = np.nan  # NaN travels as null
    with ZenohSource("zenoh://fpdd/test/samples", config=zenoh_config(listen=[ep]), timeout_s=5.0) as src:
        with ZenohSampleSink("zenoh://fpdd/test/samples", config=zenoh_config(connect=[ep]), max_block=128) as sink:
            assert sink.wait_for_subscriber(5.0)
            sink.write(samples)
        back = _read_to_end(src)
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
        back = _read_to_end(src)
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
    from benchmarks.can import msp25_samples as make
    from replay.live import ZenohCanSink as Sink
    from fpdd.zenohconf import zenoh_config as conf

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
            back = _read_to_end(src)
        finally:
            child.join(20.0)
    assert child.exitcode == 0
    ref = msp25_samples(0.5, seed=11)
    assert len(back) == len(ref)
    np.testing.assert_array_equal(back.t_ns, ref.t_ns)
    assert np.abs(back["x"] - ref["x"]).max() <= LSB_X / 2 + 1e-15


def test_zenoh_source_stays_open_without_publisher():
    ep = _endpoint()
    with ZenohSource("fpdd/none", config=zenoh_config(listen=[ep]), timeout_s=0.1, poll_s=0.02,
                     signals=("x",)) as src:
        blocks = _consume(src, until=lambda b: threading.Thread(target=src.close).start()
                          if src.stale and len(b) >= 5 else None)
        assert all(len(b) == 0 for b in blocks) and src.stale_events == 1
        assert "no data for 0.1 s; still waiting" in str(src.report.problems[-1])
    with ZenohSource("fpdd/none", config=zenoh_config(listen=[_endpoint()]), timeout_s=0.05) as src:
        with pytest.raises(SourceError, match="nothing received within 0.05 s"):
            src.signals  # noqa: B018


def test_samples_json_single_sample_form():
    from replay.live import json_to_samples

    s, bad = json_to_samples(b'{"format":"fpdd.samples/1","t_ns":5,"signals":{"x":0.25,"u":null}}', "p")
    assert isinstance(s, Samples) and s.t_ns.tolist() == [5] and s["x"][0] == 0.25 and np.isnan(s["u"][0])
    assert not bad.any()  # null is a missing value, not a bad one


def _payload(t, **signals) -> bytes:
    return json.dumps({"format": "fpdd.samples/1", "t_ns": t, "signals": signals}).encode()


def test_zenoh_bad_payloads_are_dropped_counted_per_cause_and_logged(caplog):
    """Every kind of bad message on a live key: dropped, counted per cause, logged once per
    cause; the good samples around them all arrive; nothing raises out of the source."""
    caplog.set_level(logging.WARNING, logger="replay.live")
    ep = _endpoint()
    good = msp25_samples(0.3, seed=21)
    rng = np.random.default_rng(21)
    bar = {k: (v / 1e5 if k in ("pA", "pB") else v).tolist() for k, v in good.slice(0, 200).signals.items()}
    bad_payloads = [
        (b"{not json", "bad_json"),
        (bytes(rng.integers(0, 256, 300, dtype=np.uint8)), "bad_json"),
        (b'{"t_ns":5,"signals":[1,2]}', "bad_schema"),
        (b'{"format":"fpdd.samples/1","t_ns":5,"signals":[1,2]}', "bad_schema"),
        (b'{"format":"fpdd.samples/1","t_ns":[1,2],"signals":{"x":[1.0]}}', "bad_schema"),
        (b'{"format":"fpdd.samples/1","t_ns":[1],"signals":{"x":["abc"]}}', "bad_schema"),
        (_payload([2 ** 70], x=[0.0]), "bad_time"),
        (_payload([1.5], x=[0.0]), "bad_time"),
        (b'{"format":"fpdd.samples/1","t_ns":[9],"signals":{"x":[NaN]}}', "non_finite"),
        (b'{"format":"fpdd.samples/1","t_ns":[9],"signals":{"x":[1e999]}}', "non_finite"),
        (_payload((good.t_ns[:200] + 10**9).tolist(), **bar), "wrong_unit"),
        (b"x" * (9 << 20), "oversized"),
    ]
    with ZenohSource("fpdd/bad", config=zenoh_config(listen=[ep]), timeout_s=10.0, poll_s=0.05,
                     signals=good.names) as src:
        with zenoh.open(zenoh_config(connect=[ep])) as session:
            pub = session.declare_publisher("fpdd/bad", congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + 10.0
            while not pub.matching_status.matching:
                assert time.monotonic() < deadline, "no subscriber matched"
                threading.Event().wait(0.01)
            pub.put(samples_json(good.slice(0, 100)))
            for payload, _ in bad_payloads:
                pub.put(payload)
            pub.put(samples_json(good.slice(100, len(good))))
            pub.put(b'{"format":"fpdd.samples/1","end":true}')
            back = _read_to_end(src)
    np.testing.assert_array_equal(back.t_ns, good.t_ns)
    want = {}
    for _, cause in bad_payloads:
        want[cause] = want.get(cause, 0) + 1
    want["wrong_unit"] = 200  # the samples of the block in bar
    assert dict(src.report.skipped) == want
    text = "\n".join(map(str, src.report.problems))
    for needle in ("payload is not JSON", "\"signals\" is list", "beyond the int64 range",
                   "is a float, expected an integer number of ns", "not finite", "look like bar",
                   "9437184 bytes, at most 8388608 accepted"):
        assert needle in text, (needle, text)
    logged = [r.getMessage() for r in caplog.records]
    assert len(logged) == len(want) and all("dropped" in m for m in logged), logged


def test_zenoh_flood_is_dropped_and_counted():
    ep = _endpoint()
    good = msp25_samples(0.2, seed=22)
    with ZenohSource("fpdd/flood", config=zenoh_config(listen=[ep]), timeout_s=10.0, poll_s=0.05,
                     signals=good.names, max_queue=4) as src:
        with ZenohSampleSink("fpdd/flood", config=zenoh_config(connect=[ep]), max_block=10) as sink:
            assert sink.wait_for_subscriber(5.0)
            sink.write(good)  # 20 payloads, nobody consuming yet: 4 queued, 16 dropped
            deadline = time.monotonic() + 10.0
            while src.report.skipped["flood"] < 16:
                assert time.monotonic() < deadline, src.report.skipped
                threading.Event().wait(0.01)
            it = src.chunks()
            kept = [next(it) for _ in range(4)]
        rest = list(it)  # the end marker came after the queue had room again
    assert src.report.skipped == {"flood": 16}
    assert sum(map(len, kept)) == 40 and sum(map(len, rest)) == 0


def test_a_consumer_loop_stops_on_a_quiet_live_input():
    """A service reads a live source with `for block in src.chunks(): if stop.is_set(): break`:
    the empty blocks of a quiet input hand control back, so its stop event ends it promptly."""
    ep = _endpoint()
    stop = threading.Event()
    got: list[int] = []
    ended = threading.Event()

    def service(src):
        for block in src.chunks(100):
            if stop.is_set():
                break
            got.append(len(block))
        ended.set()

    with ZenohSource("fpdd/quiet/samples", config=zenoh_config(listen=[ep]), timeout_s=0.5, poll_s=0.02) as src:
        th = threading.Thread(target=service, args=(src,), daemon=True)
        th.start()
        deadline = time.monotonic() + 10.0
        while len(got) < 3:  # heartbeats arrive
            assert time.monotonic() < deadline and th.is_alive()
            threading.Event().wait(0.01)
        stop.set()
        assert ended.wait(5.0)
    assert set(got) == {0} and not src.stale  # 3 heartbeats well before the staleness threshold
