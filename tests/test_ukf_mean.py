"""The filter's two settings against the strong-chirp divergence (``guard={"central_mean": 1, "noise_share": 1}``,
the default; docs/explanation/tracking-and-alarms.md, "The central mean"): what each fixes on the product's own simulator, where the
tracker's model is the simulator's, against the weighted mean and the plain noise learning (both ``0``), and
filterpy's algebra for the central mean."""

from __future__ import annotations

import numpy as np

from replay.base import Samples
from tests.test_ukf import _compare, _samples
from twin.models import get_model
from twin.models.base import Timing
from twin.models.simulate import default_noise, excite, measure
from twin.online.tracker import OnlineTracker

#: the rig of the product's chirp (tests/chirp_divergence.py), away from Table 9
RIG = {"wn": 250.0, "zeta": 0.4, "Ffric": 55.0, "CdAleak": 4e-6, "Cd": 0.2}


def _chirp_start(noise: dict[str, float], seed: int = 1004) -> Samples:
    """The first 3 s of the product's 120 s chirp (0.1-8 Hz, 5 mm), digital controller at the log's rate."""
    rig = get_model("msp25")
    name, xr = excite(rig, 120.0, 1e-3, "chirp", 5e-3, 0, 0.1, 8.0)
    rec = measure(rig, rig.params(**RIG), name, xr[:3000], 1e-3, noise=noise, seed=seed,
                  timing=Timing.parse("digital", None))
    return rec.to_samples()


def _track(s: Samples, **guard) -> tuple[OnlineTracker, object]:
    rig = get_model("msp25")
    tr = OnlineTracker(params=RIG, timing=Timing.parse("digital", None), substeps=rig.substeps,
                       noise=default_noise(rig), guard=guard)
    return tr, tr.process(s)


def test_the_weighted_mean_biases_a_noise_free_record_and_the_central_mean_does_not():
    """A noise-free record of the tracker's own model (the simulator's substeps), the tracker started at the
    rig's values: with the sigma points' weighted mean the predicted pressures go tens of kPa off and friction
    follows; with the central point's prediction nothing moves."""
    s = _chirp_start({"x": 1e-12, "pA": 1e-6, "pB": 1e-6})
    tr, weighted = _track(s, central_mean=0.0)
    j = tr.tracked.index("Ffric")
    assert np.sqrt(np.mean(weighted.innovation[500:, 1] ** 2)) > 10e3  # Pa: the one-step prediction is off
    assert np.min(weighted.estimates[500:, j]) < 0.7 * RIG["Ffric"]
    tr, central = _track(s)
    assert tr.guard_settings["central_mean"] == 1.0  # the default
    assert np.sqrt(np.mean(central.innovation[500:, 1] ** 2)) < 1e3
    for k, n in enumerate(tr.tracked):
        np.testing.assert_allclose(central.estimates[500:, k], RIG[n], rtol=0.02, err_msg=n)


def test_noise_share_keeps_the_learnt_noise_at_the_sensors_own_under_a_wide_prior():
    """Nominal noise on the product's own record: the noise learning takes each sensor's noise to about half
    its nominal in the first half second (every innovation is small against a wide prior) and the guard calls
    the filter inconsistent; weighted by the sensor noise's share, the noise stays within 10 % of its own."""
    rig = get_model("msp25")
    s = _chirp_start(default_noise(rig))
    nominal = np.array([default_noise(rig)[o] for o in ("x", "pA", "pB")])
    _, plain = _track(s, noise_share=0.0)
    assert np.min(plain.noise[:1000] / nominal) < 0.6
    # the guard calls it inconsistent for a while (12 % of the samples after the first second with the pressure
    # states' process noise at 3e-7 MPa^2 per sample, over 30 % at 1e-6)
    assert np.mean(plain.guard[1000:] == "inconsistent_nis") > 0.1
    tr, shared = _track(s)
    assert tr.guard_settings["noise_share"] == 1.0  # the default
    assert tr.outputs == ("x", "pA", "pB")
    np.testing.assert_allclose(shared.noise / nominal, 1.0, atol=0.1)
    assert np.mean(shared.guard[1000:] == "consistent") > 0.9


def test_the_central_mean_is_filterpys_with_the_central_point_as_x_mean_fn():
    """The compiled predict with ``central_mean`` against filterpy's UnscentedKalmanFilter given
    ``x_mean_fn = sigmas[0]`` (its covariance about that mean), on the paths of the production settings."""
    s = _samples(0.5, 27)
    tr, out, _ = _compare(s, rtol=1e-6, atol=1e-7, guard={"central_mean": 1.0})
    assert tr.guard_settings["central_mean"] == 1.0 and np.all(np.isfinite(out.estimates))
