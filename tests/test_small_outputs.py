"""What a user sees in passing: top lists parameters in the model's order, a closed pipe ends a command quietly."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import pytest

HERE = pathlib.Path(__file__).parent / "data"


def test_top_lists_parameters_in_the_models_order_not_alphabetically():
    from twin.commands.top import TopState
    from twin.models import get_model

    state = TopState()
    order = list(get_model("msp25").PHENOMENOLOGICAL)
    # the estimate payload carries its keys sorted (JSON with sort_keys), as the bus sends it
    params = {n: {"value": 1.0, "std": 0.1, "unit": "1"} for n in sorted(order)}
    assert list(params) != order
    state.put("estimate", {"rig": "r", "t_s": 1.0, "status": "ok", "params": params})
    assert list(state.snapshot()["r"]["params"]) == order


def _closed_pipe(cmd: list[str]) -> subprocess.CompletedProcess:
    """Run ``cmd`` with its stdout closed before it writes (``cmd | head -0``: the reader went away)."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert p.stdout is not None and p.stderr is not None
    p.stdout.close()
    err = p.stderr.read()
    p.stderr.close()
    p.wait(timeout=120)
    return subprocess.CompletedProcess(cmd, p.returncode, b"", err)


def test_a_closed_pipe_ends_replay_and_twin_quietly():
    for cmd in ([sys.executable, "-m", "replay.cli", "info", str(HERE / "msp25_short.asc"), "--json"],
                [sys.executable, "-m", "twin.cli", "params", "--json"]):
        done = _closed_pipe(cmd)
        assert b"Broken pipe" not in done.stderr and b"BrokenPipeError" not in done.stderr, done.stderr
        assert done.returncode == 0, (cmd, done.stderr)


@pytest.mark.slow
def test_the_diagnose_caption_names_no_extended_model_when_there_is_none(tmp_path):
    sys.path.insert(0, str(pathlib.Path(__file__).parent))
    from diag_helpers import OSC, record
    from twin.estimation.diagnose import diagnose
    from twin.reports import diagnose_report

    rec = record(OSC, (), seed=3, duration_s=3.0)  # the nominal model is the truth: nothing to add
    diag = diagnose(OSC, [rec], seed=0, candidates=["coulomb_friction"])
    assert diag.causes == []
    page = pathlib.Path(diagnose_report(diag, str(tmp_path / "d"))).read_text(encoding="utf-8")
    assert "no effect was found, so there is no extended model" in page
    assert "extended model (orange" not in page


def test_a_trend_plot_takes_its_range_from_the_converged_estimates():
    """The start-up samples, whose +-2 sigma is wider than the healthy band, do not set the y-range."""
    import numpy as np

    from twin.online.baseline import Baseline
    from twin.reports.plots import settled_mask

    band = Baseline(50.0, 40.0, 60.0)
    stds = np.array([80.0, 30.0, 6.0, 4.0, 2.0, 2.5, 1.0])  # 4 std <= 20 first at index 3
    assert settled_mask(stds, band).tolist() == [False, False, False, True, True, True, True]
    assert settled_mask(np.full(6, 50.0), band).tolist() == [False] * 3 + [True] * 3  # never converged: later half
