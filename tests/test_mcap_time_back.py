"""An MCAP whose log time jumps back (a logger's clock stepped back mid-record): the samples are read in the
file's order and the jump is counted and reported as input lost, never sorted away into a record that looks
whole (with the chunk index, as without it); ``twin fit`` on it says so in one line and exits 3."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from replay.base import Samples
from replay.factory import open_source
from replay.mcapio import McapSink
from twin.cli import main as twin_main

DATA = Path(__file__).parent / "data"


def _stepped_back(path: Path, samples: Samples, at: int, back_s: float, block: int = 20) -> None:
    t = samples.t_ns.copy()
    t[at:] -= int(back_s * 1e9)
    stepped = Samples(t, samples.signals)
    with McapSink(str(path), flush_messages=block * 4) as sink:  # several chunks on each side of the step
        for i in range(0, len(stepped), block):
            sink.write(stepped.slice(i, min(i + block, len(stepped))))


@pytest.mark.parametrize("back_s", [0.05, 10.0])  # into the samples before it, and before the record began
def test_a_log_time_that_jumps_back_is_read_in_file_order_and_reported(tmp_path: Path, back_s: float) -> None:
    with open_source(DATA / "reference.mcap") as src:
        good = src.read_all()
    t = good.t_ns - int(good.t_ns[0]) + 100 * 10**9
    good = Samples(t, good.signals)
    path = tmp_path / "back.mcap"
    half = len(good) // 2
    _stepped_back(path, good, half, back_s)
    with open_source(path) as src:
        got = src.read_all()
        report = src.report
    lost = report.skipped["time_backwards"] + report.skipped["time_repeated"]
    assert lost > 0 and len(got) + lost == len(good)
    assert np.array_equal(got.t_ns[:half], good.t_ns[:half])  # the file's first part, first
    assert np.all(np.diff(got.t_ns) > 0)


@pytest.mark.slow
def test_fit_on_an_mcap_whose_log_time_jumps_back_says_so_in_one_line(tmp_path: Path, capsys) -> None:
    from fpdd.units import NOMINAL_NOISE
    from twin.models import msp25 as M
    from twin.models.scenario import simulate_wear
    from twin.models.simulate import excite

    _, xr = excite(M.MODEL, 6.0, 1e-3, seed=1031)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, (), noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=1031)
    s = rec.to_samples()
    path = tmp_path / "back.mcap"
    _stepped_back(path, Samples(s.t_ns + 100 * 10**9, s.signals), 3000, 6.5, block=100)
    code = twin_main(["fit", str(path)])
    err = capsys.readouterr().err
    assert code == 3, err
    lines = [line for line in err.splitlines() if "input lost" in line]
    assert len(lines) == 1 and "time_backwards=3000" in lines[0] and str(path) in lines[0]
    assert "Traceback" not in err and "ValueError" not in err
