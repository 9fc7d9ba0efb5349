"""What a user sees in passing: top lists parameters in the model's order, a closed pipe ends a command quietly."""

from __future__ import annotations

import pathlib
import subprocess
import sys

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
