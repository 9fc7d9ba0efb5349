"""One home per parameter and per model: what the online twin needs of a parameter is declared beside its spec,
and what a model can do is declared on the model; the tracker, the drift test, the configuration and the
commissioning read them from there."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fpdd.errors import ParameterError
from twin.models import MODELS, REGISTRY, get_model, trackable_models
from twin.online.baseline import default_baseline
from twin.online.drift import DriftMonitor
from twin.online.tracker import OnlineTracker
from twin.params import EXCITATION, Tracking


def test_the_registry_names_every_model_and_what_it_can_do():
    assert set(MODELS) == set(REGISTRY) == {"msp25", "oscillator", "axis"}
    assert trackable_models() == ("msp25", "oscillator", "axis")
    assert get_model("msp25").CLOSED_LOOP and not get_model("oscillator").CLOSED_LOOP
    with pytest.raises(ParameterError, match="unknown model 'msp26'; known: msp25, oscillator, axis"):
        get_model("msp26")


def test_every_phenomenological_parameter_of_the_rig_declares_its_tracking():
    m = get_model("msp25")
    assert m.trackable == m.PHENOMENOLOGICAL
    for name in m.trackable:
        t = m.tracking(name)
        assert t.band > 0 and t.drift_rate > 0 and t.bounds[0] < 1 < t.bounds[1]
        assert t.excited_by in EXCITATION
    with pytest.raises(ParameterError, match="KP is not a parameter the online twin tracks"):
        m.tracking("KP")


def test_a_tracking_entry_is_validated():
    with pytest.raises(ValueError, match="excited_by 'sound'"):
        Tracking(band=0.2, drift_rate=0.01, bounds=(0.5, 2.0), excited_by="sound")
    with pytest.raises(ValueError, match="bounds"):
        Tracking(band=0.2, drift_rate=0.01, bounds=(1.5, 2.0), excited_by="rod_motion")


def test_bands_drift_rates_bounds_and_channels_come_from_the_specs():
    m = get_model("msp25")
    ps = m.params()
    base = default_baseline("msp25")
    for name, b in base.items():
        r = m.tracking(name).band
        assert b.lo == pytest.approx(ps[name] / (1 + r)) and b.hi == pytest.approx(ps[name] * (1 + r))
    tr = OnlineTracker(tracked=("Ffric", "CdAleak", "wn"), dt=1e-3)
    assert tr.q_rate.tolist() == [m.tracking(n).drift_rate for n in ("Ffric", "CdAleak", "wn")]
    assert [EXCITATION[c] for c in tr.chan] == ["rod_motion", "pressure_difference", "valve_command"]
    lo, hi = m.tracking_bounds(ps, "Ffric")
    assert lo == pytest.approx(ps["Ffric"] * m.tracking("Ffric").bounds[0])
    assert hi == pytest.approx(min(ps["Ffric"] * m.tracking("Ffric").bounds[1], ps["pP"] * ps["A"]))
    dm = DriftMonitor("rig", base)
    assert dm.drift_rate == {n: m.tracking(n).drift_rate for n in base}


def test_changing_a_spec_changes_what_the_tracker_does(monkeypatch):
    """The tracker has no table of its own: a slower declared drift is the filter's process noise."""
    m = get_model("msp25")
    specs = list(m.BASE)
    i = [s.name for s in specs].index("wn")
    slower = dataclasses.replace(specs[i], tracking=dataclasses.replace(specs[i].tracking, drift_rate=0.001))
    specs[i] = slower
    monkeypatch.setattr(type(m), "BASE", tuple(specs))
    tr = OnlineTracker(tracked=("wn",), dt=1e-3)
    assert np.allclose(tr.q_rate, [0.001])


def test_the_online_twin_refuses_a_model_it_cannot_run(monkeypatch):
    m = get_model("oscillator")
    monkeypatch.setattr(type(m), "TRACKABLE", False)
    with pytest.raises(ParameterError, match="does not run the oscillator model; it runs: msp25, axis"):
        OnlineTracker("oscillator")


def test_every_model_declares_its_signals_with_their_roles():
    """What generic code asks of a model: its drive, demand, outputs and units, declared on the model."""
    for name in MODELS:
        m = get_model(name)
        sig = m.signals()
        assert m.drive_name in m.INPUTS and set(m.INPUTS) <= set(sig) and set(m.OUTPUTS) <= set(sig), name
        assert (m.demand_name is not None) == m.CLOSED_LOOP, name
        assert set(m.signals("output")) == set(m.OUTPUTS), name
        assert m.EXPERIMENT is not None and m.EXPERIMENT.drive in m.INPUTS, name
        if m.FILTER is not None:
            assert set(m.FILTER.measures) <= set(m.OUTPUTS) and set(m.FILTER.exogenous) <= set(
                m.signals("exogenous")), name
    assert get_model("oscillator").signal_unit("u") == "N" and get_model("msp25").signal_unit("u") == "V"
