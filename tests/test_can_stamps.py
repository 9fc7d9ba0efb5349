"""The product's CAN logs carry wall-clock time (the record's start, or the time of writing) and the HPU's status
frames of the DBC (oil temperature and supply pressure at 10 Hz), read back by python-can and by the product."""

from __future__ import annotations

import time
from datetime import UTC, datetime

import can
import cantools
import numpy as np
import pytest

from replay.base import Samples
from replay.can.logs import CanLogSink, CanLogSource
from replay.can.codec import DEFAULT_DBC

START = int(datetime(2026, 3, 4, 5, 6, 7, tzinfo=UTC).timestamp()) * 10**9


def _record(n: int = 2000, t_oil: bool = True) -> Samples:
    rng = np.random.default_rng(11)
    t = np.arange(n, dtype=np.int64) * 1_000_000
    x = 0.003 * np.sin(2 * np.pi * 1.3 * t * 1e-9)
    sig = {"x_ref": x, "u": 0.5 * np.tanh(x / 0.003), "x": x + 2e-6 * rng.standard_normal(n),
           "pA": 9e6 + 2e4 * rng.standard_normal(n), "pB": 8e6 + 2e4 * rng.standard_normal(n)}
    if t_oil:
        sig["T_oil"] = 318.0 + 2.0 * t * 1e-9  # warming 2 K/s, 45 degC at the start
    return Samples(t, sig)


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log", ".trc"])
def test_log_starts_at_the_records_start_and_carries_hpu_status(tmp_path, suffix):
    path = tmp_path / f"rig{suffix}"
    rec = _record()
    with CanLogSink(path, start_ns=START) as sink:
        sink.write(rec)
    db = cantools.database.load_file(str(DEFAULT_DBC))
    hpu = db.get_message_by_name("HPU_Status")
    # an ASC file's times count from its header's date unless asked for the absolute ones
    with can.LogReader(str(path), **({"relative_timestamp": False} if suffix == ".asc" else {})) as reader:
        msgs = list(reader)
    assert msgs[0].timestamp == pytest.approx(START * 1e-9, abs=1e-3)
    status = [m for m in msgs if m.arbitration_id == hpu.frame_id]
    assert len(status) == 20  # 2 s of record at the DBC's 100 ms
    gaps = np.diff([m.timestamp for m in status])
    assert gaps == pytest.approx(0.1, abs=1e-3)
    decoded = [hpu.decode(m.data) for m in status]
    t_rel = np.array([m.timestamp for m in status]) - START * 1e-9
    assert [d["T_oil"] for d in decoded] == pytest.approx(318.0 - 273.15 + 2.0 * t_rel, abs=0.051)  # 0.1 degC LSB
    assert {d["pP"] for d in decoded} == {28000}  # kPa: no pP in the record, the frame's nominal supply pressure
    with CanLogSource(path) as src:  # and the product reads its own log: oil temperature in K
        back = Samples.concat(list(src.chunks()))
    assert "T_oil" in back.names and back.t_ns[0] == pytest.approx(START, abs=1e6)
    assert np.nanmax(np.abs(back.signals["T_oil"] - np.interp(back.t_ns - START, rec.t_ns,
                                                               rec.signals["T_oil"]))) < 0.25


def test_a_record_without_status_signals_is_stamped_now_and_gets_no_invented_status(tmp_path):
    path = tmp_path / "rig.blf"
    before = time.time()
    with CanLogSink(path) as sink:
        sink.write(_record(500, t_oil=False))
    with can.LogReader(str(path)) as reader:
        msgs = list(reader)
    assert before - 1.0 <= msgs[0].timestamp <= time.time() + 1.0  # now, not 1970
    assert 0x3A0 not in {m.arbitration_id for m in msgs}


def test_samples_on_the_wall_clock_keep_their_times(tmp_path):
    rec = _record(300, t_oil=False)
    on_wall = Samples(rec.t_ns + START, rec.signals)
    path = tmp_path / "rig.log"
    with CanLogSink(path, start_ns=0) as sink:
        sink.write(on_wall)
    with can.LogReader(str(path)) as reader:
        first = next(iter(reader))
    assert first.timestamp == pytest.approx(START * 1e-9, abs=1e-6)
