"""The window's evidence against the baseline is its likelihood ratio (twin.online.confirm), on records of the
independent reference simulator: where the leakage's effect is linear, the ratio's z is the one of a Wald test
in the leakage itself, not in its logarithm (whose standard error shrinks as the estimate grows); a baseline that
fits the window as well as its estimate is no evidence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from track_reference import to_samples
from reference import msp25_spec
from reference.tables import MSP25_FREE
from twin.online.baseline import Baseline, default_baseline
from twin.online.confirm import ConfirmedDrift, Verdict, critical_z, fit_window, window_record
from twin.online.tracker import OnlineTracker

LEAK = MSP25_FREE["CdAleak"]


@pytest.fixture(scope="module")
def window(reference_records):
    """A leaking rig (5 times Table 9's leakage): the last 4 s of an 8 s record, the tracker at Table 9, and the
    window's fit started at the baseline."""
    (rec,) = reference_records([msp25_spec(31, duration=8.0, truth={"CdAleak": 5.0 * LEAK})])
    samples = to_samples(rec)
    k = int(np.searchsorted(samples.t_ns, samples.t_ns[-1] - 4_000_000_000))
    tr = OnlineTracker()
    w = window_record(samples.slice(k, len(samples)), tr)
    names = list(tr.tracked)
    res = fit_window(w, tr, names, {n: b.value for n, b in default_baseline("msp25").items()})
    assert res is not None
    return tr, w, names, res


def _wald(res, base: float) -> Verdict:
    v, sd = float(res.estimate["CdAleak"]), float(res.std["CdAleak"])
    return Verdict("CdAleak", "high", v, sd / v, math.log(v / base) / (sd / v))


def test_the_ratio_tests_the_leakage_in_its_own_scale_not_its_logarithm(window):
    tr, w, names, res = window
    bands = default_baseline("msp25")
    cd = ConfirmedDrift("r", bands, "msp25")
    v, sd = float(res.estimate["CdAleak"]), float(res.std["CdAleak"])
    assert 3.5 * LEAK < v < 6.5 * LEAK  # the window finds the leak
    wald = _wald(res, bands["CdAleak"].value)
    out = cd._likelihood_ratio(wald, res, w, tr, names)
    assert out.state == "high" and out.why.startswith("likelihood ratio")
    linear = (v - bands["CdAleak"].value) / sd  # the Wald z in the leakage itself, which acts linearly
    assert out.z == pytest.approx(linear, rel=0.25)
    assert out.z < 0.75 * wald.z  # the log scale's curvature overstates it (here by log(5) / (1 - 1/5) = 2x)


def test_a_baseline_that_fits_the_window_as_well_is_no_evidence(window):
    tr, w, names, res = window
    v, sd = float(res.estimate["CdAleak"]), float(res.std["CdAleak"])
    # a baseline half a standard error below the estimate, its band narrow enough to leave the estimate outside:
    # the Wald test of a made-up tiny standard error says "high", the window's likelihood ratio does not
    near = v - 0.5 * sd
    bands = {**default_baseline("msp25"), "CdAleak": Baseline(near, 0.99 * near, 1.01 * near)}
    cd = ConfirmedDrift("r", bands, "msp25")
    claimed = Verdict("CdAleak", "high", v, 1e-3, math.log(v / near) / 1e-3)
    out = cd._likelihood_ratio(claimed, res, w, tr, names)
    assert out.state == "unresolved" and abs(out.z) < critical_z()
    assert "nearly as well" in out.why


def test_a_replicating_window_is_judged_by_its_likelihood_ratio_too(window):
    """A window the Wald test leaves ``unresolved`` may replicate an earlier confirmation on its side: it gets the
    same restricted fit, and its ratio, not its Wald z, decides (here the ratio rejects the baseline outright)."""
    tr, w, names, res = window
    bands = default_baseline("msp25")
    base = bands["CdAleak"]
    cd = ConfirmedDrift("r", bands, "msp25")
    v = float(res.estimate["CdAleak"])
    weak = Verdict("CdAleak", "unresolved", v, 0.6, math.log(v / base.value) / 0.6)  # a wide Wald error: z ~2.7
    assert not cd._may_replicate("CdAleak", weak)  # nothing confirmed yet: nothing to replicate
    cd.count["CdAleak"], cd.side["CdAleak"] = 1, "low"
    assert not cd._may_replicate("CdAleak", weak)  # confirmed on the other side
    cd.side["CdAleak"] = "high"
    assert cd._may_replicate("CdAleak", weak)
    inside = Verdict("CdAleak", "unresolved", base.hi * 0.99, 0.6, 1.0)
    assert not cd._may_replicate("CdAleak", inside)  # inside its band: no replication
    out = cd._likelihood_ratio(weak, res, w, tr, names)
    assert out.state == "high" and out.z > critical_z() > weak.z
    assert "nearly as well" not in out.why
