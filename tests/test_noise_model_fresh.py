"""The diagnosis's noise model on a signal logged at its own rate: its autoregression runs over the measurements
(the fresh samples), not over the held copies on the grid, as the fit weighs only the measurements."""

from __future__ import annotations

import numpy as np
import pytest

from twin.estimation.noise_model import fit_noise_model


def _records(seed: int, T: int = 4000):
    rng = np.random.default_rng(seed)
    x = np.zeros(T)
    e = rng.normal(size=T)
    for t in range(1, T):
        x[t] = 0.6 * x[t - 1] + e[t]  # a coloured output measured on every sample
    p = np.repeat(rng.normal(size=T // 2), 2)  # a white pressure at 500 Hz held onto the 1 kHz grid
    fresh = np.array([np.ones(T, bool), np.tile([True, False], T // 2)])
    return np.array([x, p]), fresh


def test_a_held_white_signal_is_white_on_its_measurements_and_its_held_copies_are_not_innovations():
    B, fresh = _records(7)
    grid = fit_noise_model([B], ("x", "pA"))
    own = fit_noise_model([B], ("x", "pA"), fresh=[fresh])
    assert grid.orders["pA"] >= 20  # on the grid the hold looks like a long colour
    assert own.orders["pA"] == 0 and own.orders["x"] <= 3  # white on its measurements; x keeps its AR(1)
    E = own.whiten(B, fresh)
    kept = own.kept(fresh, B.shape[1])
    assert E.shape == (2, int(kept.sum())) and int(kept.sum()) <= fresh[1].sum()  # measurements only
    assert np.allclose(E.var(axis=1), 1.0, atol=0.1)  # normalised innovations
    assert abs(np.corrcoef(E[1, 1:], E[1, :-1])[0, 1]) < 0.1
    # every sample a measurement: the same noise model and innovations as without masks, exactly
    none = fit_noise_model([B], ("x", "pA"), fresh=[np.ones_like(fresh)])
    assert np.array_equal(none.whiten(B, np.ones_like(fresh)), grid.whiten(B))


@pytest.mark.slow
def test_healthy_can_rate_record_is_diagnosed_on_its_measurements_naming_nothing(reference_records):
    """The PID rig's pressures at 500 Hz held onto the 1 kHz grid, time stamps 0-150 us late (verification seed
    1001, 12 s, truth drawn): the healthy diagnosis names nothing and is not "unexplained", and its noise model
    kept the innovations of the measurements only."""
    from conftest import msp25_spec
    from user_rig_accuracy import CASES, product_record

    from twin.estimation.diagnose import diagnose
    from twin.models import get_model

    spec_kw, known = CASES["can_rate"]
    (ref,) = reference_records([msp25_spec(1001, duration=12.0, truth="draw", **spec_kw)])
    rig = get_model("msp25")
    d = diagnose(rig, product_record(ref, "can_rate1001"), base=rig.params(**known))
    assert list(d.causes) == [] and not d.unexplained, (d.causes, d.final.adequacy)
    assert d.final.n_w < 0.6 * 3 * 12000  # about half the grid: the samples where the pressures are measured
