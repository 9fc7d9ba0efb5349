"""A new rig model, added as one module (twin/models/actuator2.py: a hydraulic actuator whose valve is a static
gain, four states) and registered here: the fit, the diagnosis, the online tracker and its drift monitor run it
end to end with no change anywhere else.  Truth away from the model's defaults, measurement noise through the
loop, fits and the tracker started away from the truth; verification seeds (>= 1000)."""

from __future__ import annotations

import numpy as np
import pytest

import twin.models as registry
from twin.estimation.diagnose import diagnose
from twin.estimation.fit import fit
from twin.models import get_model, trackable_models
from twin.models.simulate import measure
from replay.base import Samples
from twin.online.baseline import Baseline, default_baseline
from twin.online.drift import DriftMonitor
from twin.online.tracker import OnlineTracker

NAME = "actuator2"
TRUTH = {"Ffric": 65.0, "Cl": 3.4e-12, "Kq": 4.3e-5}
NOISE = {"x": 2e-6, "pA": 2e4, "pB": 2e4}
DT = 1e-3


@pytest.fixture
def model(monkeypatch):
    """The model registered under its name for this test only (the registry is the product's one list)."""
    monkeypatch.setitem(registry.REGISTRY, NAME, "twin.models.actuator2")
    monkeypatch.setattr(registry, "MODELS", tuple(registry.REGISTRY))
    return get_model(NAME)


def _demand(duration: float, seed: int) -> np.ndarray:
    """A seeded multisine demand, 0.2-6 Hz, a few millimetres."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(round(duration / DT))) * DT
    f = rng.uniform(0.2, 6.0, 8)
    ph = rng.uniform(0, 2 * np.pi, 8)
    return 4e-3 * np.sum(np.sin(2 * np.pi * f[:, None] * t + ph[:, None]), axis=0) / np.sqrt(8)


def _record(model, duration: float, seed: int, **truth):
    ps = model.params(**{**TRUTH, **truth})
    return measure(model, ps, "x_ref", _demand(duration, seed), DT, noise=NOISE, seed=seed)


def test_the_registry_runs_the_new_model_as_it_runs_any(model):
    assert NAME in trackable_models() and model.CLOSED_LOOP
    assert model.trackable == ("Ffric", "Cl", "Kq") and len(model.STATES) == 4
    assert set(default_baseline(NAME)) == set(model.trackable)


def test_fit_recovers_the_truth_from_a_wrong_start(model):
    rec = _record(model, 8.0, 1001)
    start = {n: v * f for (n, v), f in zip(TRUTH.items(), (1.5, 0.5, 1.3))}
    r = fit(model, rec, free=tuple(TRUTH), start=start, seed=1001)
    assert r.success
    for n, v in TRUTH.items():
        assert abs(r.estimate[n] - v) < 3 * r.std[n] + 1e-12, (n, r.estimate[n], r.std[n])
        if n != "Cl":  # a leak is weakly observable: within its standard errors (as the rig's CdAleak)
            assert abs(r.estimate[n] / v - 1) < 0.05, (n, r.estimate[n])


def test_a_healthy_record_is_diagnosed_healthy_and_a_viscous_friction_is_named(model):
    healthy = diagnose(model, _record(model, 6.0, 1002), free=tuple(TRUTH), seed=1002, test_timing=False)
    assert healthy.causes == [] and not healthy.unexplained, (healthy.causes, healthy.unexplained)
    ps = model.params(("viscous_friction",), **TRUTH, c_visc=4000.0)
    rec = measure(model, ps, "x_ref", _demand(6.0, 1003), DT, noise=NOISE, seed=1003)
    sick = diagnose(model, rec, free=tuple(TRUTH), seed=1003, test_timing=False)
    assert sick.causes == ["viscous_friction"], sick.causes


@pytest.mark.slow
def test_tracker_follows_the_new_model_and_its_drift_monitor_alarms_a_worn_seal(model):
    rec = _record(model, 40.0, 1004)
    s = rec.to_samples()
    start = {n: v * f for (n, v), f in zip(TRUTH.items(), (1.4, 0.6, 1.2))}
    tr = OnlineTracker(NAME, start=start)
    out = tr.process(s)
    assert tr.ns == 4 and out.states.shape[1] == 4
    truth = np.array([TRUTH[n] for n in tr.tracked])
    assert np.all(np.abs(out.estimates[-1] / truth - 1) < 3 * out.log_std[-1] + 0.02), (out.estimates[-1], truth)
    assert (out.guard[-10000:] == "consistent").mean() > 0.9
    # a worn seal: the leak grows tenfold halfway; the model's own drift monitor alarms it, and only it
    xr = _demand(60.0, 1005)
    half = xr.size // 2
    first = measure(model, model.params(**TRUTH), "x_ref", xr[:half], DT, noise=NOISE, seed=1005)
    at = {"x0": float(first["x"][-1]), "pA0": float(first["pA"][-1]), "pB0": float(first["pB"][-1])}
    second = measure(model, model.params(**{**TRUTH, "Cl": 10 * TRUTH["Cl"]}), "x_ref", xr[half - 1:], DT,
                     noise=NOISE, seed=1006, init=at)
    s1, s2 = first.to_samples(), second.to_samples()
    s2 = Samples(s2.t_ns[1:] + s1.t_ns[-1], {k: v[1:] for k, v in s2.signals.items()})
    base = {n: Baseline(TRUTH[n], TRUTH[n] * b.lo / b.value, TRUTH[n] * b.hi / b.value)
            for n, b in default_baseline(NAME).items()}
    tr = OnlineTracker(NAME, params=TRUTH)
    dm = DriftMonitor("rig", base, model=NAME)
    events = []
    for blk in (s1, s2):
        o = tr.process(blk)
        events += dm.update_block(tr.tracked, o.t_ns, o.t_ns * 1e-9, o.estimates, o.log_std, o.frozen, o.hold,
                                  o.guard)
    alarms = [e for e in events if e.level == "alarm"]
    assert {e.parameter for e in alarms} == {"Cl"}, [(e.parameter, e.kind, e.level, e.t_s) for e in events]
    assert min(e.t_s for e in alarms) > half * DT
