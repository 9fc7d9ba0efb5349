"""Oil temperature beyond a constant: the fit reads a logged ``T_oil`` sample by sample (as the tracker does), and
``twin simulate`` runs the rig on a temperature trajectory and logs it.  Accuracy on the independent reference
simulator (verification seed 1003: truth drawn off the defaults, noise through the loop, starts off the truth)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fpdd.errors import DataError, ParameterError
from twin import cli
from twin.estimation.fit import fit
from twin.models import get_model
from twin.models.simulate import measure, ramp
from twin import load_records
from twin.record import Record

RIG = get_model("msp25")
FREE = RIG.PHENOMENOLOGICAL
DURATION = 8.0


@pytest.fixture(scope="module")
def warming(reference_records):
    """8 s of a drawn rig whose oil warms 40 -> 60 degC (bulk modulus -12 %, leakage x1.82 at the reference's
    b_visc 0.03/K), ``T_oil`` logged at 10 Hz and held onto the 1 kHz grid as the HPU status is."""
    from conftest import msp25_spec

    ramp_spec = {"kind": "ramp", "t0": 0.0, "t1": DURATION, "start": 313.15, "end": 333.15}
    return reference_records([msp25_spec(1003, duration=DURATION, truth="draw", temperature={"T": ramp_spec},
                                         signal_rates={"T_oil": 10.0})])[0]


def _start(ref, seed=1003):
    rng = np.random.default_rng(seed)
    return {k: ref.truth[k] * (1 + rng.choice([-1, 1]) * rng.uniform(0.1, 0.4)) for k in FREE}


def _z(res, ref):
    return {k: (res.estimate[k] - ref.truth[k]) / res.std[k] for k in FREE}


@pytest.mark.slow
def test_warming_oil_fits_within_three_standard_errors_with_the_logged_temperature_and_is_biased_without(warming):
    sig = {k: np.asarray(v, float) for k, v in warming.signals.items()}
    assert np.ptp(sig["T_oil"]) > 19.0  # the oil warmed
    start = _start(warming)
    res = fit(RIG, Record(warming.dt, sig, "warming"), FREE, start=start)
    assert res.success, res.message
    z = _z(res, warming)
    assert max(abs(v) for v in z.values()) < 3.0, z
    for k in FREE:
        if k != "CdAleak":  # resolved to its standard error only
            assert abs(res.estimate[k] / warming.truth[k] - 1) < 0.05, k
    cold = {k: v for k, v in sig.items() if k != "T_oil"}
    blind = fit(RIG, Record(warming.dt, cold, "warming without T_oil"), FREE, start=start)
    zb = _z(blind, warming)
    assert max(abs(v) for v in zb.values()) > 3.0 or blind.warnings, zb  # biased (or warned), never silently fine


def test_a_constant_logged_temperature_is_the_stated_one_bit_for_bit():
    name, drive = "x_ref", np.sin(np.linspace(0, 20, 2000)) * 2e-3
    stated = RIG.simulate(RIG.params(T_oil=330.0), name, drive, 1e-3)
    logged = RIG.simulate(RIG.params(), name, drive, 1e-3, exogenous={"T_oil": np.full(drive.size, 330.0)})
    for o in RIG.OUTPUTS:
        assert np.array_equal(stated.outputs[o], logged.outputs[o]), o
    ramped = RIG.simulate(RIG.params(), name, drive, 1e-3, exogenous={"T_oil": ramp(313.15, 343.15, drive.size)})
    assert not np.array_equal(stated.outputs["pA"], ramped.outputs["pA"])


def test_a_logged_temperature_is_not_free_and_a_wrong_unit_is_refused():
    name, drive = "x_ref", np.sin(np.linspace(0, 20, 2000)) * 2e-3
    with pytest.raises(DataError, match=r"T_oil.*40 K at sample 0.*\[233.15, 423.15\] K"):
        RIG.simulate(RIG.params(), name, drive, 1e-3, exogenous={"T_oil": np.full(drive.size, 40.0)})
    rec = measure(RIG, RIG.params(), name, drive, 1e-3, seed=1, exogenous={"T_oil": np.full(drive.size, 320.0)})
    with pytest.raises(ParameterError, match="T_oil is set sample by sample"):
        fit(RIG, rec, ("Ffric", "T_oil"))
    with pytest.raises(DataError, match="reads no exogenous signal"):
        get_model("oscillator").simulate(get_model("oscillator").params(), "u", drive, 1e-3,
                                         exogenous={"T_oil": np.full(drive.size, 320.0)})


def test_simulate_takes_a_temperature_trajectory_with_units_and_logs_it_held_at_its_rate(tmp_path, capsys):
    out = tmp_path / "warm.csv"
    assert cli.main(["simulate", "-o", str(out), "--duration", "2", "--temperature", "30C:50degC",
                     "--temperature-rate", "10Hz", "--json", "-q"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["temperature"]["start"] == {"value": pytest.approx(303.15), "unit": "K"}
    assert info["temperature"]["end"] == {"value": pytest.approx(323.15), "unit": "K"}
    (rec,) = load_records(str(out), model="msp25")
    t = rec["T_oil"]
    assert t[0] == pytest.approx(303.15) and t[-1] == pytest.approx(303.15 + 20.0 * 1900 / 1999, abs=1e-6)
    changes = np.flatnonzero(np.diff(t) != 0) + 1
    assert np.all(changes % 100 == 0) and changes.size == 19  # refreshed at 10 Hz, held between
    for bad, what in ((["--temperature", "40"], "40 K at sample 0"), (["--temperature", "40m"], "not in a unit of K"),
                      (["--temperature", "1:2:3"], "T_START:T_END"), (["--temperature-rate", "10Hz"], "needs")):
        assert cli.main(["simulate", "-o", str(tmp_path / "bad.csv"), "--duration", "1", "-q", *bad]) == 2
        err = capsys.readouterr().err.strip()
        assert what in err and "\n" not in err, err
