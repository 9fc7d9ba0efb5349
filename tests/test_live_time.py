"""Time on a live input: a block stamped in the future costs only itself (also after a restart), and a
held stream does not leave the rig behind real time for good. Real Zenoh sessions on loopback."""

from __future__ import annotations

import json
import queue
import threading
import time

import zenoh

from net_helpers import free_port
from replay.base import Samples
from replay.live import ZenohSampleSink
from fpdd.zenohconf import zenoh_config
from twin.models import msp25 as M
from twin.models.scenario import simulate_wear
from fpdd.units import NOMINAL_NOISE
import pytest
from twin.models.simulate import excite
from twin.online.events import StatusEvent
from twin.service.config import parse_config
from twin.service.journal import AlarmJournal
from twin.service.live_time import CLOCK_STEP_SAMPLES, TIME_JUMP_S
from twin.service.serve import serve
from twin.service.checkpoint_file import checkpoint_path, read_checkpoints

RIG = "rig-t"
KEY = f"fpdd/{RIG}/samples"
HOUR_NS = 3600 * 10**9


def _samples(seconds: float, seed: int) -> Samples:
    """A rig record at 1 kHz stamped in UNIX time, as a rig on a synchronised clock does, starting a minute ago."""
    _, xr = excite(M.MODEL, seconds, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, (), noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=seed)
    s = rec.to_samples()
    start = (time.time_ns() // 10**6 - 60_000) * 10**6
    return Samples(s.t_ns + start, s.signals)


def _config(tmp_path, port: int, **service):
    return parse_config({
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"]},
        "service": {"journal_dir": str(tmp_path / "journal"), "stale_s": 0.3, "estimate_every": 100, **service},
        "rig": [{"name": RIG, "source": f"zenoh://{KEY}"}],
    }, "<live-time>")


class Watch:
    """Statuses and estimates of the rig as they are published."""

    def __init__(self, session) -> None:
        self.statuses: queue.Queue[StatusEvent] = queue.Queue()
        self.estimates: list[int] = []  # t_ns of each estimate received
        self.t_s: list[float] = []  # and its record time
        self._lock = threading.Lock()
        self.subs = [
            session.declare_subscriber(f"fpdd/{RIG}/status", lambda s: self.statuses.put(
                StatusEvent.from_dict(json.loads(s.payload.to_string())))),
            session.declare_subscriber(f"fpdd/{RIG}/estimate", self._estimate),
        ]

    def _estimate(self, sample) -> None:
        doc = json.loads(sample.payload.to_string())
        with self._lock:
            self.estimates.append(doc["t_ns"])
            self.t_s.append(doc["t_s"])

    def count(self, after_ns: int = 0) -> int:
        """Estimates received of samples after ``after_ns``."""
        with self._lock:
            return sum(t > after_ns for t in self.estimates)

    def until(self, predicate, timeout: float = 60.0) -> StatusEvent:
        deadline = time.monotonic() + timeout
        while True:
            status = self.statuses.get(timeout=max(0.01, deadline - time.monotonic()))
            if predicate(status):
                return status

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()


def _run(cfg, feed, max_block: int = 100):
    """The service in a thread while ``feed(watch, sink)`` publishes; returns (summary, feed's result)."""
    stop = threading.Event()
    summaries: dict = {}
    th = threading.Thread(target=serve, args=(cfg, stop), kwargs={"summaries": summaries})
    th.start()
    try:
        with zenoh.open(zenoh_config("peer", connect=list(cfg.listen))) as session:
            watch = Watch(session)
            try:
                with ZenohSampleSink(KEY, session=session, end_marker=False, max_block=max_block) as sink:
                    assert sink.wait_for_subscriber(20.0), "the service did not subscribe to its input"
                    result = feed(watch, sink)
            finally:
                watch.close()
    finally:
        stop.set()
        th.join(timeout=60.0)
    assert not th.is_alive()
    return summaries[RIG], result


def _write(sink, block: Samples, speed: float = 5.0) -> None:
    """``block`` in payloads of 0.1 s of samples, at ``speed`` times real time (estimates are put on the bus
    with congestion control DROP: a burst of them may lose some)."""
    start = time.monotonic()
    for i in range(0, len(block), 100):
        sink.write(block.slice(i, i + 100))
        time.sleep(max(0.0, start + (i + 100) * 1e-3 / speed - time.monotonic()))


def _ahead(block: Samples, ns: int) -> Samples:
    return Samples(block.t_ns + ns, {k: v.copy() for k, v in block.signals.items()})


@pytest.mark.slow
def test_a_block_stamped_an_hour_ahead_costs_only_itself_also_after_a_restart(tmp_path):
    samples = _samples(12.0, seed=1021)
    cfg = _config(tmp_path, free_port())
    bad = samples.slice(4000, 4500)

    def first_run(watch, sink):
        _write(sink, samples.slice(0, 4000))
        watch.until(lambda s: s.counters.get("samples") == 4000)
        before = watch.count()
        _write(sink, _ahead(bad, HOUR_NS))  # one block a clock glitch stamped an hour ahead
        _write(sink, samples.slice(4000, 8000))  # then the correct samples, those of the bad block included
        status = watch.until(lambda s: s.counters.get("samples") == 8000)
        return before, watch.count(after_ns=int(samples.t_ns[3999])), status

    s1, (before, after, status) = _run(cfg, first_run)
    assert before >= 20  # one estimate per 100 samples (40); the bus may drop some (congestion control DROP)
    assert after >= 20, "estimates keep coming after the future block"
    assert s1.stats.estimates == 80
    assert status.counters["time_jump"] == len(bad) and s1.time_jump == len(bad)
    assert "time_backwards" not in status.counters and s1.time_backwards == 0
    assert s1.samples == 8000 and s1.state == "stopped"
    saved = read_checkpoints(checkpoint_path(tmp_path / "journal" / f"{RIG}.db"))
    cp = saved[1].get(RIG) if saved is not None else None
    assert cp is not None and cp.t_ns == int(samples.t_ns[7999]), "the future time never reaches a checkpoint"

    def second_run(watch, sink):  # the first block after the restart is from the future
        _write(sink, _ahead(samples.slice(8000, 8200), HOUR_NS))
        said = watch.until(lambda s: s.counters.get("time_jump") == 200 and s.state == "running")
        _write(sink, samples.slice(8000, 12000))
        watch.until(lambda s: s.counters.get("samples") == 12000)
        return watch.count(after_ns=int(samples.t_ns[7999])), said

    s2, (after, status) = _run(cfg, second_run)
    assert s2.resumed_samples == 8000
    assert after >= 20, "estimates come after a restart whose first block is from the future"
    assert s2.stats.estimates == 40
    assert s2.time_jump == 200 and s2.time_backwards == 0
    assert "time_jump 200" in status.message and "after the rig's present" in status.message
    assert s2.samples == 4000


def test_a_fresh_rig_whose_first_block_is_from_the_future_is_not_blinded(tmp_path):
    samples = _samples(3.0, seed=1026)
    cfg = _config(tmp_path, free_port())

    def feed(watch, sink):
        _write(sink, _ahead(samples.slice(0, 300), HOUR_NS))
        _write(sink, samples.slice(0, 3000))
        return watch.until(lambda s: s.counters.get("samples") == 3000)

    summary, status = _run(cfg, feed)
    assert summary.time_jump == 300 and summary.time_backwards == 0 and summary.samples == 3000
    assert summary.stats.estimates == 30


@pytest.mark.slow
def test_samples_ahead_by_less_than_the_tolerance_are_not_a_jump(tmp_path):
    """A block half the tolerance ahead is processed; the correct samples after it are behind it: about
    CLOCK_STEP_SAMPLES of them are dropped, then the rig's clock is re-based on them (not blinded for 2.5 s)."""
    samples = _samples(4.0, seed=1022)
    cfg = _config(tmp_path, free_port())
    lead = int(TIME_JUMP_S / 2 * 1e9)

    def feed(watch, sink):
        _write(sink, samples.slice(0, 2000))
        watch.until(lambda s: s.counters.get("samples") == 2000)
        _write(sink, _ahead(samples.slice(2000, 2100), lead))
        _write(sink, samples.slice(2100, 4000))
        return watch.until(lambda s: s.counters.get("clock_steps") == 1
                           and s.counters["samples"] + s.counters["time_backwards"] == 4000)

    summary, status = _run(cfg, feed)
    assert summary.time_jump == 0 and 0 < summary.time_backwards <= 2 * CLOCK_STEP_SAMPLES
    assert summary.samples == 4000 - summary.time_backwards and "time_jump" not in status.counters
    assert "the input's clock stepped back 2.5 s" in status.message


def test_a_sender_faster_than_real_time_is_no_jump(tmp_path):
    """8 s of 100 Hz samples in one payload, sent at once (one block of the rig, reaching 8 s past the rig's
    present): they run on from the last processed sample without a gap, so they are processed."""
    full = _samples(9.0, seed=1024)
    samples = Samples(full.t_ns[::10], {k: v[::10] for k, v in full.signals.items()})
    cfg = _config(tmp_path, free_port())

    def feed(watch, sink):
        sink.write(samples.slice(0, 100))
        watch.until(lambda s: s.counters.get("samples") == 100)
        sink.write(samples.slice(100, 900))
        return watch.until(lambda s: s.counters.get("samples") == 900)

    summary, status = _run(cfg, feed, max_block=1000)
    assert summary.time_jump == 0 and summary.time_backwards == 0 and "time_jump" not in status.counters


def _step_noted(tmp_path, way: str) -> list[str]:
    """The clock steps the rig's journal noted."""
    with AlarmJournal(tmp_path / "journal" / f"{RIG}.db") as journal:
        notes = journal.notes(RIG)
    assert all(kind == "clock_step" for _, kind, _ in notes)
    return [text for _, _, text in notes if f"clock stepped {way}" in text]


@pytest.mark.slow
def test_a_clock_that_stays_ahead_is_adopted(tmp_path):
    """A sender whose clock stepped an hour ahead and stays there: after CLOCK_STEP_SAMPLES samples in a row from
    the future its time is adopted (counted, said in the status and the journal), and the rig goes on."""
    samples = _samples(6.0, seed=1025)
    cfg = _config(tmp_path, free_port())

    def feed(watch, sink):
        _write(sink, samples.slice(0, 1000), speed=1.0)
        watch.until(lambda s: s.counters.get("samples") == 1000)
        _write(sink, _ahead(samples.slice(1000, 6000), HOUR_NS), speed=1.0)
        return watch.until(lambda s: s.counters.get("clock_steps") == 1
                           and s.counters["samples"] + s.counters["time_jump"] == 6000)

    summary, status = _run(cfg, feed)
    assert summary.clock_steps == 1 and 0 < summary.time_jump <= 2 * CLOCK_STEP_SAMPLES and summary.samples > 5000
    assert summary.samples + summary.time_jump == 6000 and summary.input_gaps == 1
    assert "clock step #1: the input's clock stepped forward 3600.0 s" in status.message
    assert len(_step_noted(tmp_path, "forward")) == 1


@pytest.mark.slow
@pytest.mark.parametrize("step_ns", [30 * 10**9, HOUR_NS])
def test_a_clock_that_stepped_back_is_adopted_and_the_record_time_runs_on(tmp_path, step_ns):
    """A rig controller that restarts its clock 30 s or an hour back: after CLOCK_STEP_SAMPLES samples in a row
    before the last processed one, its time is adopted; the rig keeps tracking and the events' record time t_s
    runs on; the status and the journal say so."""
    samples = _samples(6.0, seed=1027)
    cfg = _config(tmp_path, free_port())

    def feed(watch, sink):
        _write(sink, samples.slice(0, 1000), speed=1.0)
        watch.until(lambda s: s.counters.get("samples") == 1000)
        _write(sink, _ahead(samples.slice(1000, 6000), -step_ns), speed=1.0)
        status = watch.until(lambda s: s.counters.get("clock_steps") == 1
                             and s.counters["samples"] + s.counters["time_backwards"] == 6000)
        with watch._lock:
            return list(watch.estimates), list(watch.t_s), status

    summary, (t_ns, t_s, status) = _run(cfg, feed)
    assert summary.clock_steps == 1 and 0 < summary.time_backwards <= 2 * CLOCK_STEP_SAMPLES and summary.samples > 5000
    assert summary.samples + summary.time_backwards == 6000 and summary.time_jump == 0
    assert summary.stats.estimates == summary.samples // 100
    later = [s for t, s in zip(t_ns, t_s) if t < int(samples.t_ns[0])]  # estimates on the new clock
    assert later and min(later) > max(s for t, s in zip(t_ns, t_s) if t >= int(samples.t_ns[0]))
    assert all(b > a for a, b in zip(t_s, t_s[1:])), "the record time runs on across the step"
    said = f"the input's clock stepped back {step_ns * 1e-9:.1f} s"
    assert f"clock step #1: {said}" in status.message
    noted = _step_noted(tmp_path, "back")
    assert len(noted) == 1 and noted[0].startswith(said)


@pytest.mark.slow
def test_after_a_held_stream_the_lag_is_re_based(tmp_path):
    """A sender that holds its stream for 4 s and goes on where it stopped: the rig waited, it is not behind."""
    samples = _samples(3.0, seed=1023)
    cfg = _config(tmp_path, free_port(), lag_warn_s=2.0)
    hold_s = 4.0

    def feed(watch, sink):
        _write(sink, samples.slice(0, 1500), speed=1.0)  # as a rig sends them
        watch.until(lambda s: s.counters.get("samples") == 1500)
        time.sleep(hold_s)
        _write(sink, samples.slice(1500, 3000), speed=1.0)
        return watch.until(lambda s: s.counters.get("samples") == 3000)

    summary, status = _run(cfg, feed)
    assert summary.samples == 3000
    assert status.counters["lag_ms"] < hold_s * 1000 / 2, status.counters
    assert "behind real time" not in status.message and status.state != "degraded"
