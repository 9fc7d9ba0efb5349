"""The published interval of a tracked parameter: the error variance of a parameter that holds still.

The filter's random walk (its drift rate) makes its own variance about twice
the real error variance of a constant parameter in a steady state;
:func:`twin.online.ukf.held_variance` propagates the error variance of the
same gain with no random walk.  Checked against a Monte Carlo of a scalar
Kalman filter (random-walk model, constant truth), where the real error
variance can be measured over many independent runs.
"""

from __future__ import annotations

import numpy as np

from twin.online import ukf


def _scalar_filter_runs(q, r, v0, dt, T, runs, rng, freeze=None):
    """A random-walk Kalman filter of a constant theta = 0 observed with white noise: (V [T], errors [T, runs])."""
    x = rng.normal(0.0, np.sqrt(v0), runs)  # the start is as far from the truth as the prior says
    v = v0
    V = np.empty(T)
    E = np.empty((T, runs))
    for k in range(T):
        if k:
            v = v + q * dt
        if freeze is None or not freeze[k]:
            K = v / (v + r)
            x = x + K * (rng.normal(0.0, np.sqrt(r), runs) - x)
            v = (1 - K) * v
        V[k] = v
        E[k] = x
    return V, E


def _held(V, dt, q, cap=np.inf):
    out = np.empty((len(V), 1))
    state = np.full((2, 1), np.nan)
    DT = np.full(len(V), dt)
    DT[0] = np.nan
    ukf.held_variance(np.ascontiguousarray(V[:, None]), DT, np.array([q]), float(cap), state, out)
    return out[:, 0]


def test_held_variance_matches_the_real_error_of_a_constant_parameter():
    rng = np.random.default_rng(11)
    q, r, v0, dt = 0.09, 0.5, 1.0, 1e-3
    V, E = _scalar_filter_runs(q, r, v0, dt, 3000, 4000, rng)
    held = _held(V, dt, q)
    real = np.mean(E ** 2, axis=1)
    for k in (10, 300, 2999):  # early (no random walk yet), on the way, steady state
        assert abs(held[k] / real[k] - 1) < 0.08, (k, held[k], real[k])
    # in the steady state the filter's own variance is about twice the real one: its interval over-covers
    assert 1.7 < V[-1] / real[-1] < 2.3
    z_held = E[-1] / np.sqrt(held[-1])
    assert 0.93 < np.mean(np.abs(z_held) <= 1.96) < 0.97
    assert np.mean(np.abs(E[-1] / np.sqrt(V[-1])) <= 1.96) > 0.99


def test_a_frozen_parameter_keeps_its_error_and_an_inflated_covariance_resets_it():
    rng = np.random.default_rng(12)
    q, r, v0, dt = 0.09, 0.5, 1.0, 1e-3
    freeze = np.zeros(3000, bool)
    freeze[1500:2500] = True  # no excitation: no update, the random walk goes on
    V, E = _scalar_filter_runs(q, r, v0, dt, 3000, 4000, rng, freeze)
    held = _held(V, dt, q)
    real = np.mean(E ** 2, axis=1)
    assert abs(held[2400] / real[2400] - 1) < 0.08
    assert V[2400] > 1.5 * V[1400]  # the filter's variance grew while frozen ...
    assert abs(held[2400] / held[1400] - 1) < 1e-9  # ... the error of a parameter that held still did not
    assert abs(held[-1] / real[-1] - 1) < 0.08
    # a re-inflated covariance (re-initialisation, recovery): the error is what the filter says again
    V2 = V.copy()
    V2[2000:] *= 50.0
    held2 = _held(V2, dt, q)
    assert held2[2000] == V2[2000] and np.all(held2 <= V2)


def test_with_no_random_walk_the_error_variance_is_the_filters():
    rng = np.random.default_rng(13)
    V, _ = _scalar_filter_runs(0.0, 0.5, 1.0, 1e-3, 500, 10, rng)
    np.testing.assert_allclose(_held(V, 1e-3, 0.0), V, rtol=1e-9)


def test_the_cap_stops_the_random_walk_as_the_kernel_does():
    V = np.full(200, 0.25)  # a frozen parameter sitting at the cap: no update, no growth
    held = _held(V, 1e-3, 50.0, cap=0.25)
    assert np.all(held == 0.25)
