"""The diagnosis's naming criterion: a held-out gain must be significant against the noise (a
Diebold-Mariano-type test on the relative scale with a HAC variance), whatever share of the excess misfit it
is; and a timing the user stated is not renamed."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.signal import lfilter

from diag_helpers import OSC, record
from twin import cli
from twin.estimation.diagnose import TIMING_EFFECTS
from twin.estimation.diagnose.adequacy import gain_test


def _ar1(rng, n, phi=0.9):
    return lfilter([1.0], [1.0, -phi], rng.standard_normal(n))


def test_equal_held_out_errors_are_rarely_significant():
    """Two models whose held-out errors are the same coloured noise plus their own: the one-sided test's size.
    Measured on 2000 such draws (2000 samples, AR(1) 0.9, lag 40): 0.6 % below 1e-3, 2.5 % below 0.01, 7.1 %
    below 0.05 (the HAC variance of squared coloured errors is underestimated on finite records: the test is
    somewhat liberal, and a name needs the LR test and the AICc besides).  Here 400 draws."""
    rng = np.random.default_rng(7)
    ps = []
    for _ in range(400):
        common = _ar1(rng, 2000)
        q0 = (common + 0.3 * _ar1(rng, 2000)) ** 2
        q1 = (common + 0.3 * _ar1(rng, 2000)) ** 2
        ps.append(gain_test(q0, q1, lag=40)["p"])
    ps = np.array(ps)
    assert np.mean(ps < 1e-3) <= 0.015
    assert 0.02 <= np.mean(ps < 0.05) <= 0.12


def test_a_gain_that_comes_in_bursts_is_significant_and_its_interval_holds_it():
    """An error present in four bursts of a held-out tail, 90 % of it removed: significant at 1e-3 although
    the loss differences alone vary as much as the bursts (the ratio is judged with its denominator)."""
    rng = np.random.default_rng(8)
    n = 2000
    burst = np.zeros(n)
    for c in (200, 700, 1200, 1700):
        burst[c:c + 60] = 30.0 * np.sin(np.linspace(0, np.pi, 60))
    noise = rng.standard_normal(n)
    q0 = (noise + burst) ** 2
    q1 = (noise + 0.1 * burst) ** 2
    t = gain_test(q0, q1, lag=100)
    assert t["gain"] > 0.9 and t["p"] < 1e-3
    assert t["lo"] < t["gain"] < t["hi"] and t["lo"] > 0.5
    worse = gain_test(q1, q0, lag=100)  # the other way round: a loss, never significant
    assert worse["gain"] < 0 and worse["p"] > 0.5


@pytest.mark.slow
def test_a_stated_intersample_rule_is_not_renamed(tmp_path, capsys):
    rec = record(OSC, (), seed=23, kind="multisine")
    path = tmp_path / "osc.csv"
    np.savetxt(path, np.column_stack([rec.t_s, rec["u"], rec["y"]]), delimiter=",", header="t,u,y",
               comments="", fmt="%.17g")
    assert cli.main(["-q", "diagnose", str(path), "--model", "oscillator", "--intersample", "zoh", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    trials = [t["effect"] for ts in out.get("trials", []) for t in ts] if out.get("trials") else []
    assert not set(trials) & set(TIMING_EFFECTS) and not set(out["causes"]) & set(TIMING_EFFECTS)
    assert out["timing_assumed"]["intersample"] == "zoh"
