"""Resume, don't replay: ``twin serve`` killed with SIGKILL at several moments and restarted ends with
exactly the alarms of an uninterrupted run (same numbers, same identities, same values)."""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from replay.mcapio import McapSink
from twin.service.config import load_config
from net_helpers import free_port
from twin.models import msp25 as M
from twin.models.scenario import Drift, simulate_wear
from twin.service.serve import serve
from fpdd.units import NOMINAL_NOISE
from twin.models.simulate import excite
from twin.service.store import Store

ROOT = Path(__file__).resolve().parent.parent
WAIT_S = 60.0
ALARM_LINE = re.compile(r"^twin serve: rig-k #(\d+) ")


def write_config(path: Path, log: Path, journal: Path, speed: float) -> Path:
    path.write_text(f"""
[zenoh]
listen = ["tcp/127.0.0.1:{free_port()}"]
[service]
journal_dir = "{journal}"
checkpoint_s = 0.3
[[rig]]
name = "rig-k"
source = "{log}"
speed = {speed}
""")
    return path


def alarms(journal: Path) -> list:
    with Store(journal / "rig-k.db", writer=False) as store:
        return store.alarms("rig-k")


class Service:
    """``twin serve`` in its own process; stderr lines on a queue."""

    started: list[Service] = []  # every process a test starts, killed at its end whatever happened

    def __init__(self, config: Path) -> None:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        self.proc = subprocess.Popen([sys.executable, "-m", "twin.cli", "serve", "--config", str(config)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
        Service.started.append(self)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        with self.proc.stderr:
            for line in self.proc.stderr:
                self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def wait_for(self, pattern: re.Pattern) -> re.Match:
        while True:
            line = self.lines.get(timeout=WAIT_S)
            assert line is not None, "twin serve ended before: " + "\n".join(self.seen[-10:])
            self.seen.append(line)
            m = pattern.match(line)
            if m:
                return m

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        assert self.proc.wait(timeout=WAIT_S) == -signal.SIGKILL
        while self.lines.get(timeout=WAIT_S) is not None:  # the pipe is drained and closed
            pass

    def finish(self) -> int:
        while (line := self.lines.get(timeout=WAIT_S)) is not None:
            self.seen.append(line)
        return self.proc.wait(timeout=WAIT_S)


@pytest.fixture(autouse=True)
def no_service_left_running():
    yield
    while Service.started:
        s = Service.started.pop()
        if s.proc.poll() is None:
            s.proc.kill()
        s.proc.wait(timeout=WAIT_S)


@pytest.mark.slow
def test_sigkill_at_several_moments_then_restart_gives_exactly_the_alarms_of_an_uninterrupted_run(tmp_path):
    _, xr = excite(M.MODEL, 16.0, 1e-3, seed=11)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3,
                           [Drift("Ffric", 3.0, 3.0, shape="step"), Drift("wn", 0.6, 6.0, 12.0, "ramp")],
                           noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")}, seed=11)
    log = tmp_path / "rig.mcap"
    with McapSink(str(log)) as sink:
        sink.write(rec.to_samples())
    # the reference: one uninterrupted run, as fast as it goes
    serve(load_config(str(write_config(tmp_path / "ref.toml", log, tmp_path / "ref", 0.0))))
    reference = alarms(tmp_path / "ref")
    assert len(reference) >= 3 and {a.parameter for a in reference} == {"Ffric", "wn"}

    # the same log in (fast) real time, killed right after each of its first two new alarms,
    # then once while it resumes (re-processing what followed its checkpoint)
    config = write_config(tmp_path / "rigs.toml", log, tmp_path / "journal", 6.0)
    kills = []
    for life in range(3):
        svc = Service(config)
        if life:
            svc.wait_for(re.compile(r"^twin serve: rig rig-k: resumed from its checkpoint after \d+ samples"))
        if life < 2:
            kills.append(int(svc.wait_for(ALARM_LINE).group(1)))
        svc.kill()  # the alarm is journaled; the checkpoint may be older: its data are processed again
    svc = Service(config)
    assert svc.finish() == 0, "\n".join(svc.seen)
    # each life printed a new alarm first (the one before was journaled, so never printed again)
    assert kills == sorted(set(kills)) and kills[0] == 1
    summary = next(line for line in svc.seen if line.startswith("twin serve: summary rig-k: finished"))
    assert re.search(r"resumed after \d+ samples", summary)
    got = alarms(tmp_path / "journal")
    assert [(a.seq, a.identity, a.estimate, a.statistic) for a in got] == \
           [(a.seq, a.identity, a.estimate, a.statistic) for a in reference]


@pytest.mark.slow
def test_sigkill_right_after_an_early_alarm_then_restart_journals_each_early_alarm_once(tmp_path):
    """The forecast's early warning resumes like the drift test's alarms: a reference wear record (the leakage
    leaves its band at 180 s; seed >= 1000), killed right after its first early alarm and once while it resumes,
    ends with the journal of an uninterrupted run: each early alarm once, none lost, none twice."""
    from conftest import get_records
    from replay.base import Samples
    from reference import draw_truth, msp25_spec
    from reference.tables import MSP25_FREE

    import numpy as np

    truth = draw_truth(1101, 0.1, "msp25")
    v0, edge = truth["CdAleak"], 3.0 * MSP25_FREE["CdAleak"]
    spec = msp25_spec(1101, duration=240.0, truth=truth, time_varying={
        "CdAleak": {"kind": "ramp", "t0": 0.0, "t1": 240.0, "start": v0, "end": v0 + (edge - v0) * 240.0 / 180.0}})
    rec = get_records([spec], workers=1)[0]
    log = tmp_path / "wear.mcap"
    with McapSink(str(log)) as sink:
        sink.write(Samples(np.round(rec.t * 1e9).astype(np.int64), {k: np.asarray(v, float)
                                                                      for k, v in rec.signals.items()}))
    serve(load_config(str(write_config(tmp_path / "ref.toml", log, tmp_path / "ref", 0.0))))
    reference = alarms(tmp_path / "ref")
    assert [a.parameter for a in reference if a.level == "early"] == ["CdAleak"]

    early_line = re.compile(r"^twin serve: rig-k #(\d+) t=\S+ s EARLY")
    config = write_config(tmp_path / "rigs.toml", log, tmp_path / "journal", 24.0)
    svc = Service(config)
    killed_at = int(svc.wait_for(early_line).group(1))
    svc.kill()  # the early alarm is journaled; the checkpoint may be older: its data are processed again
    svc = Service(config)
    svc.wait_for(re.compile(r"^twin serve: rig rig-k: resumed from its checkpoint after \d+ samples"))
    svc.kill()
    svc = Service(config)
    assert svc.finish() == 0, "\n".join(svc.seen)
    assert not any(early_line.match(line) for line in svc.seen)  # never printed (journaled) again
    got = alarms(tmp_path / "journal")
    assert killed_at == next(a.seq for a in reference if a.level == "early")
    assert [(a.seq, a.identity, a.estimate, a.statistic) for a in got] == \
           [(a.seq, a.identity, a.estimate, a.statistic) for a in reference]
