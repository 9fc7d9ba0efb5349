"""Models: parameter validation, the compiled integrator against solve_ivp, batch consistency."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, signal

from fpdd.errors import DataError, ParameterError
from twin.models import get_model
from twin.models import msp25 as M
from twin.models import oscillator as O
from twin.models.base import Timing
from twin.models.simulate import excite, measure


# --- parameter validation: one test per kind of error -------------------------------------
def test_out_of_bounds_names_parameter_value_unit_and_range():
    with pytest.raises(ParameterError, match=r"Ffric \(=-3 N\) must be in \[0 \.\.\. 100000\] N"):
        M.MODEL.params(Ffric=-3.0)


def test_non_finite_value_rejected():
    with pytest.raises(ParameterError, match=r"Cd \(=nan\) must be finite"):
        M.MODEL.params(Cd=float("nan"))


def test_non_numeric_value_rejected():
    with pytest.raises(ParameterError, match=r"zeta \(='high'\) must be a number"):
        M.MODEL.params(zeta="high")


def test_unknown_parameter_rejected():
    with pytest.raises(ParameterError, match=r"no parameter 'friction'"):
        M.MODEL.params(friction=1.0)


def test_unknown_effect_rejected():
    with pytest.raises(ParameterError, match=r"unknown effect of model msp25 'gremlins'"):
        M.MODEL.params(effects=["gremlins"])


def test_unknown_model_rejected():
    with pytest.raises(ParameterError, match="unknown model"):
        get_model("msp26")


def test_effect_parameter_only_when_effect_is_on():
    with pytest.raises(ParameterError):
        M.MODEL.params(c_visc=10.0)
    ps = M.MODEL.params(effects=["viscous_friction"], c_visc=10.0)
    assert ps["c_visc"] == 10.0
    assert M.MODEL.vector(ps)[M.I_CVISC] == 10.0
    assert M.MODEL.vector(M.MODEL.params())[M.I_CVISC] == 0.0


def test_metadata_complete_and_display_units():
    ps = M.MODEL.params()
    for s in M.MODEL.kernel_specs:
        assert s.unit and s.meaning and s.category
    assert ps.spec("wn").show(ps["wn"]) == "43 Hz"
    assert ps.by_category("phenomenological") == ("Ffric", "CdAleak", "Cd", "zeta", "wn")


# --- the integrator against solve_ivp ------------------------------------------------------
def _reference_msp25(ps, u_samples, dt):
    """solve_ivp (Radau, tight tolerances) of the same right-hand side, input held per sample."""
    p = M.MODEL.vector(ps)

    def f(t, s):
        k = min(int(t / dt + 1e-9), len(u_samples) - 1)
        return np.array(M.deriv(*s, u_samples[k], p))

    s = M.MODEL.initial_state(p[None])[0]
    out = [s]
    for k in range(len(u_samples) - 1):
        sol = integrate.solve_ivp(f, (k * dt, (k + 1) * dt), s, method="Radau", rtol=1e-10,
                                  atol=[1e-12, 1e-10, 1e-2, 1e-2, 1e-12, 1e-10])
        s = sol.y[:, -1]
        out.append(s)
    return np.array(out)


@pytest.mark.slow
def test_rk4_matches_solve_ivp_on_the_rig():
    ps = M.MODEL.params()
    dt = 1e-3
    name, xr = excite(M.MODEL, 0.3, dt, amplitude=0.005, f_lo=2.0, f_hi=10.0)
    closed = M.MODEL.simulate(ps, name, xr, dt)
    u = closed.inputs["u"]
    ref = _reference_msp25(ps, u, dt)
    ours = M.MODEL.simulate(ps, "u", u, dt, substeps=3).states
    np.testing.assert_allclose(ours[:, 4], ref[:, 4], atol=2e-7 * 0.005 / 1e-3 + 1e-9)
    rel_x = np.max(np.abs(ours[:, 4] - ref[:, 4])) / np.max(np.abs(ref[:, 4]))
    assert rel_x < 1e-4
    dp_err = np.max(np.abs((ours[:, 2] - ours[:, 3]) - (ref[:, 2] - ref[:, 3])))
    assert dp_err < 0.02 * np.max(np.abs(ref[:, 2] - ref[:, 3]))


def test_rk4_matches_solve_ivp_on_the_oscillator():
    ps = O.MODEL.params()
    dt = 1e-3
    u = np.random.default_rng(3).normal(0, 50, 400)
    ours = O.MODEL.simulate(ps, "u", u, dt, timing=Timing(intersample="zoh")).outputs["y"]  # held, as zoh
    p = O.MODEL.vector(ps)
    A, B, C, D = O.MODEL.state_space(ps)
    sysd = signal.cont2discrete((A, B, C, D), dt, method="zoh")
    ref = signal.dlsim(sysd[:4] + (dt,), u)[1][:, 0]
    assert np.max(np.abs(ours - ref)) < 1e-6 * np.max(np.abs(ref))
    assert p.shape == (O.NP,)


def test_oscillator_transfer_function_matches_state_space():
    ps = O.MODEL.params()
    A, B, C, D = O.MODEL.state_space(ps)
    num, den = O.MODEL.transfer_function(ps)
    w = np.logspace(0, 3, 50)
    _, h_tf = signal.freqs(num, den, worN=w)
    h_ss = np.array([(C @ np.linalg.solve(1j * wi * np.eye(2) - A, B) + D)[0, 0] for wi in w])
    np.testing.assert_allclose(h_tf, h_ss, rtol=1e-12)
    # resonance at 10 Hz, as the paper says
    assert abs(np.sqrt(ps["k"] / ps["m"]) / (2 * np.pi) - 10.0) < 1e-3


def test_batch_rows_equal_single_simulations():
    ps = M.MODEL.params()
    name, xr = excite(M.MODEL, 1.0, 1e-3, seed=4)
    P = np.stack([M.MODEL.vector(ps.replace(Ffric=f)) for f in (20.0, 50.0, 120.0)])
    batch = M.MODEL.simulate_batch(P, name, xr, 1e-3)
    for k, f in enumerate((20.0, 50.0, 120.0)):
        single = M.MODEL.simulate(ps.replace(Ffric=f), name, xr, 1e-3)
        np.testing.assert_array_equal(batch.outputs["x"][k], single.outputs["x"])
    assert not np.allclose(batch.outputs["x"][0], batch.outputs["x"][2])


def test_closed_loop_log_replays_open_loop_exactly():
    ps = M.MODEL.params()
    name, xr = excite(M.MODEL, 2.0, 1e-3)
    closed = M.MODEL.simulate(ps, name, xr, 1e-3)
    opened = M.MODEL.simulate(ps, "u", closed.inputs["u"], 1e-3)
    np.testing.assert_array_equal(closed.states, opened.states)


def test_rest_is_an_equilibrium_and_tracking_works():
    ps = M.MODEL.params()
    rest = M.MODEL.simulate(ps, "x_ref", np.zeros(500), 1e-3)
    assert np.max(np.abs(rest.states[:, 4])) < 1e-12
    name, xr = excite(M.MODEL, 5.0, 1e-3)
    run = M.MODEL.simulate(ps, name, xr, 1e-3)
    err = run.outputs["x"] - xr
    assert np.sqrt(np.mean(err**2)) < 0.2 * np.sqrt(np.mean(xr**2))


def test_every_effect_changes_the_response_and_neutral_is_nominal():
    name, xr = excite(M.MODEL, 2.0, 1e-3, seed=2)
    nominal = M.MODEL.simulate(M.MODEL.params(), name, xr, 1e-3)
    for effect in M.EFFECTS:
        neutral = dict(zip(M.EFFECTS[effect].names, M.EFFECTS[effect].neutral))
        off = M.MODEL.simulate(M.MODEL.params(effects=[effect], **neutral), name, xr, 1e-3)
        np.testing.assert_array_equal(off.outputs["x"], nominal.outputs["x"], err_msg=effect)
        on = M.MODEL.simulate(M.MODEL.params(effects=[effect]), name, xr, 1e-3)
        dx = np.max(np.abs(on.outputs["x"] - nominal.outputs["x"]))
        dp = np.max(np.abs(on.outputs["pA"] - nominal.outputs["pA"]))
        assert dx > 5e-6 or dp > 5e4, f"{effect} at its typical size is below the sensor noise (dx={dx}, dp={dp})"


def test_measured_initial_state_is_read_through_the_sensor_errors():
    """x0, pA0, pB0 are what the transducers read: a row with a pressure offset or a position gain starts at
    the true state those errors imply, and the first sample it predicts is the measured one again."""
    rig = M.MODEL
    init = {"x0": 0.012, "pA0": 15.2e6, "pB0": 12.1e6}
    ps = [rig.params(), rig.params(effects=["pressure_sensor_offset", "position_sensor_gain"],
                                  pA_off=4e5, pB_off=-2e5, k_xm=1.03)]
    P = np.array([rig.vector(p) for p in ps])
    S0 = rig.initial_state(P, init)
    assert S0[0, 2] == 15.2e6 and S0[0, 3] == 12.1e6 and S0[0, 4] == 0.012
    assert S0[1, 2] == pytest.approx(15.2e6 - 4e5) and S0[1, 3] == pytest.approx(12.1e6 + 2e5)
    assert S0[1, 4] == pytest.approx(0.012 / 1.03)
    sim = rig.simulate_batch(P, "x_ref", np.full(50, 0.012), 1e-3, S0)
    for k in range(2):
        assert sim.outputs["x"][k, 0] == pytest.approx(0.012, rel=1e-9)
        assert sim.outputs["pA"][k, 0] == pytest.approx(15.2e6, rel=1e-9)
        assert sim.outputs["pB"][k, 0] == pytest.approx(12.1e6, rel=1e-9)


def test_bad_drive_is_rejected_with_a_clear_message():
    ps = M.MODEL.params()
    bad = np.zeros(100)
    bad[40] = np.nan
    with pytest.raises(DataError, match="non-finite value at sample 40"):
        M.MODEL.simulate(ps, "x_ref", bad, 1e-3)
    with pytest.raises(DataError, match="positive number of seconds"):
        M.MODEL.simulate(ps, "x_ref", np.zeros(10), 0.0)


def test_measure_adds_seeded_noise():
    name, xr = excite(M.MODEL, 1.0, 1e-3)
    a = measure(M.MODEL, M.MODEL.params(), name, xr, 1e-3, noise={"x": 2e-6}, seed=5)
    b = measure(M.MODEL, M.MODEL.params(), name, xr, 1e-3, noise={"x": 2e-6}, seed=5)
    c = measure(M.MODEL, M.MODEL.params(), name, xr, 1e-3)
    np.testing.assert_array_equal(a["x"], b["x"])
    assert 1.5e-6 < np.std(a["x"] - c["x"]) < 2.5e-6
    q = measure(M.MODEL, M.MODEL.params(), name, xr, 1e-3, quantisation={"pA": 1e3})
    assert np.allclose(q["pA"] / 1e3, np.round(q["pA"] / 1e3))


def test_a_kernel_cache_is_dropped_when_a_module_it_inlines_changed(tmp_path):
    """numba checks a cached kernel against its own file only: keep_fresh drops it when a dependency changed."""
    from twin.models.jitcache import keep_fresh

    mod, dep = tmp_path / "kernel.py", tmp_path / "layout.py"
    mod.write_text("x = 1\n")
    dep.write_text("I_A = 5\n")
    cache = tmp_path / "__pycache__"
    cache.mkdir()

    def cached() -> list[str]:
        for name in ("kernel.step-10.py311.nbi", "kernel.step-10.py311.1.nbc"):
            (cache / name).write_bytes(b"code")
        (cache / "other.step-3.py311.nbi").write_bytes(b"not ours")
        return sorted(p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc"))

    cached()
    assert keep_fresh(str(mod), str(dep)) is True  # no stamp yet: whatever was cached is of unknown provenance
    assert sorted(p.name for p in cache.iterdir()) == ["kernel.deps", "other.step-3.py311.nbi"]
    before = cached()
    assert keep_fresh(str(mod), str(dep)) is False  # nothing changed: the cache stays
    assert sorted(p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc")) == before
    dep.write_text("I_A = 6\n")  # the layout the kernel inlined moved
    assert keep_fresh(str(mod), str(dep)) is True
    assert [p.name for p in cache.iterdir() if p.suffix in (".nbi", ".nbc")] == ["other.step-3.py311.nbi"]


@pytest.mark.parametrize("mode,t_oil", [(0, None), (1, None), (2, None), (0, 333.15), (2, 298.15)])
def test_the_filters_lanes_are_the_models_one_definition_bit_for_bit(mode, t_oil):
    """The rig's physics is written once (``deriv``); the batched form calls it, and the filter's side-by-side
    lanes (every effect neutral) compute the same operations in the same order: each lane, with its own valve and
    leak parameters, is the model's ``advance`` of its point, bit for bit."""
    from twin.models import msp25_lanes as F

    rng = np.random.default_rng(1100 + mode)
    ps = M.MODEL.params() if t_oil is None else M.MODEL.params(T_oil=t_oil)  # the oil's temperature off T_ref
    idx = np.array([M.MODEL.kernel_index(n) for n in F.LANE_PARAMS], dtype=np.int64)
    p = M.MODEL.vector(ps)
    assert F.lanes_applicable(p) and not F.lanes_applicable(M.MODEL.vector(M.MODEL.params(("viscous_friction",))))
    S = np.column_stack([rng.normal(0, 3e-4, F.LANES), rng.normal(0, 0.05, F.LANES), rng.uniform(2e6, 26e6, F.LANES),
                         rng.uniform(2e6, 26e6, F.LANES), rng.normal(0, 0.02, F.LANES), rng.normal(0, 0.05, F.LANES)])
    TH = p[idx] * np.exp(rng.normal(0, 0.3, size=(F.LANES, idx.size)))
    wnd = rng.normal(0, 1, size=4)
    got = S.copy()
    F.lanes(got, TH, F.LANES, p.copy(), idx, wnd, mode, 1e-3, 3, np.empty(F.LANE_WORK))
    for ln in range(F.LANES):
        q = p.copy()
        q[idx] = TH[ln]
        one = np.empty(M.NS)
        M.advance(S[ln].copy(), 1, wnd, False, 1, mode, q, 1e-3, 3, 0.0, np.zeros(M.N_CTRL), one)
        np.testing.assert_array_equal(got[ln], one)
        np.testing.assert_array_equal(M.rhs_batch(S[ln:ln + 1], wnd[1:2], q[None])[0],
                                      np.array(M.deriv(*S[ln], wnd[1], q)))


@pytest.mark.parametrize("mode,effects", [(0, ()), (1, ()), (2, ()), (2, ("coulomb_friction", "cubic_stiffness")),
                                          (1, ("coulomb_friction", "input_offset"))])
def test_the_oscillators_lanes_are_its_advance_bit_for_bit(mode, effects):
    """The oscillator's lanes run every sigma point's interval in one call; each lane, with its own damping, stiffness
    and friction, is the model's ``advance`` of its point, bit for bit, with or without its effects."""
    rng = np.random.default_rng(1200 + mode)
    ps = O.MODEL.params(effects)
    if "coulomb_friction" in effects:
        ps = O.MODEL.params(effects, Fc=0.7, vc=2e-3)
    idx = np.array([O.MODEL.kernel_index(n) for n in ("d", "k", "Fc")], dtype=np.int64)
    p = O.MODEL.vector(ps)
    assert O.lanes_applicable(p) and 2 * (len(O.STATES) + idx.size) + 1 <= O.LANES
    S = np.column_stack([rng.normal(0, 1e-3, O.LANES), rng.normal(0, 0.05, O.LANES)])
    TH = p[idx] * np.exp(rng.normal(0, 0.3, size=(O.LANES, idx.size)))
    wnd = rng.normal(0, 1, size=4)
    got = S.copy()
    m = O.LANES - 3  # the lanes beyond m are not touched
    O.lanes(got, TH, m, p.copy(), idx, wnd, mode, 1e-3, 3, np.empty(O.LANE_WORK))
    np.testing.assert_array_equal(got[m:], S[m:])
    for ln in range(m):
        q = p.copy()
        q[idx] = TH[ln]
        one = np.empty(len(O.STATES))
        O.advance(S[ln].copy(), 1, wnd, False, 1, mode, q, 1e-3, 3, 0.0, np.zeros(O.N_CTRL), one)
        np.testing.assert_array_equal(got[ln], one)
        assert not np.array_equal(one, S[ln])


def test_records_without_an_oil_temperature_are_unchanged_bit_for_bit():
    """At T_oil = T_ref (the default) the temperature factors are exactly one: the same numbers as without the
    temperature law; a warmer oil softens the oil column and leaks more."""
    _, xr = excite(M.MODEL, 1.0, 1e-3, seed=1101)
    base = M.MODEL.simulate(M.MODEL.params(), "x_ref", xr, 1e-3)
    off = M.MODEL.simulate(M.MODEL.params(kB_T=0.0, b_visc=0.0), "x_ref", xr, 1e-3)
    for o in ("x", "pA", "pB"):
        np.testing.assert_array_equal(base.outputs[o], off.outputs[o])
    warm = M.MODEL.simulate(M.MODEL.params(T_oil=333.15), "x_ref", xr, 1e-3)
    assert not np.array_equal(warm.outputs["pA"], base.outputs["pA"])


@pytest.mark.parametrize("mode", [0, 1, 2])
def test_the_oscillators_filter_step_is_its_simulation_bit_for_bit(mode):
    """The filter's one-interval ``advance`` of the oscillator reads its parameters and the drive around the
    interval once, as numbers (no array handed to the inner calls): the same operations in the same order as the
    simulation's RK4 through ``deriv`` and ``input_at``, bit for bit, with a dry friction and a cubic spring on
    (a cubic drive is taken linear online: the next sample is not known yet)."""
    import numpy as np

    from twin.models import oscillator as O
    from twin.models.intersample import input_at, input_between

    rng = np.random.default_rng(7 + mode)
    a = rng.normal(size=6)
    for k in range(6):
        for f in (0.0, 0.25, 0.5, 1.0):
            n = a.shape[0]
            w = (a[max(k - 1, 0)], a[k], a[min(k + 1, n - 1)], a[min(k + 2, n - 1)])
            assert input_between(*w, f, mode) == input_at(a, k, f, mode)
    p = np.zeros(O.NP)
    p[[O.I_M, O.I_D, O.I_K, O.I_FC, O.I_VC, O.I_K3, O.I_U0]] = [1.3, 0.4, 3900.0, 0.6, 2e-3, 4e5, 0.05]
    u = rng.normal(size=5) * 20.0
    for k in range(4):
        s0 = np.array([rng.normal() * 1e-3, rng.normal() * 0.05])
        out = np.empty(2)
        O.advance(s0, k, u, False, 1, mode, p, 1e-3, 2, 0.0, np.zeros(1), out)
        S = np.empty((u.size - k, 2))
        O._simulate_one(s0, p, u[k:], min(mode, 1), 1e-3, 2, S)  # from sample k: the interval k -> k + 1
        np.testing.assert_array_equal(out, S[1])
