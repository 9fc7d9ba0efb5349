"""A position column in mm whose values stay inside the stroke (below 0.25) is not read as metres: the rig's loop
tells (x_ref and x share a scale; the drive u is KP times their difference), and fit and track refuse it in one
line naming the column and the --map fix."""

from __future__ import annotations

import numpy as np
import pytest

from twin import cli
from twin.models import get_model
from twin.models.scenario import simulate_wear
from twin.models.simulate import excite
from fpdd.units import NOMINAL_NOISE


@pytest.fixture(scope="module")
def record():
    m = get_model("msp25")
    _, xr = excite(m, 3.0, 1e-3, seed=21)
    rec, _ = simulate_wear(m.params(), xr, 1e-3, [], noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=21)
    # a small-amplitude test (+-0.2 mm): position, demand and drive scaled alike, so u = KP (x_ref - x) still holds
    k = 0.02
    return type(rec)(rec.dt, {**rec.signals, **{n: rec.signals[n] * k for n in ("x_ref", "u", "x")}}, rec.name)


def _csv(path, rec, mm=()):
    cols = {k: rec.signals[k] * (1e3 if k in mm else 1.0) for k in ("x_ref", "u", "x", "pA", "pB")}
    np.savetxt(path, np.column_stack([rec.t_s, *cols.values()]), delimiter=",", comments="",
               header="t," + ",".join(cols), fmt="%.17g")
    return str(path)


@pytest.mark.parametrize("mm, named", [(("x",), "x is"), (("x_ref",), "x_ref is"), (("x", "x_ref"), "x and x_ref")])
def test_a_position_in_mm_inside_the_stroke_is_refused(tmp_path, capsys, record, mm, named):
    path = _csv(tmp_path / "run.csv", record, mm)
    assert np.abs(record.signals["x"]).max() * 1e3 < 0.25  # inside the stroke read as metres: no range tells
    rc = cli.main(["fit", path, "--free", "Ffric"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "Traceback" not in err[0]
    assert named in err[0] and "read as metres" in err[0] and f"--map {mm[0]}={mm[0]}:mm" in err[0]
    if len(mm) == 2:
        assert "--map x_ref=x_ref:mm" in err[0]


def test_the_same_record_with_its_units_given_is_read(tmp_path, capsys, record):
    from twin.units import check_loop_scale

    path = _csv(tmp_path / "run.csv", record, ("x", "x_ref"))
    from twin.models.records import load_records

    rec = load_records(path, map=["x=x:mm", "x_ref=x_ref:mm"])[0]
    check_loop_scale(get_model("msp25").params(), rec.signals, path)  # no refusal: SI again
    assert np.allclose(rec.signals["x"], record.signals["x"], rtol=1e-12, atol=1e-15)


@pytest.mark.slow
@pytest.mark.parametrize("controller, known, pid, seed", [
    ("analog", None, None, 1), ("digital", {"KI": 200.0}, None, 2), ("digital", {"KD": 2.0}, None, 3),
    ("digital", None, {"Kff": 0.5}, 4), ("digital", {"KP": 250.0}, None, 5)])
def test_reference_loops_pass_and_their_mm_copies_are_refused(controller, known, pid, seed):
    """On the independent simulator (truth drawn, its noise; P, PI, PD, feed-forward, another KP) a record in SI
    passes and the same record with x, x_ref or both in mm is refused, naming them."""
    from fpdd.errors import DataError
    from reference import msp25_spec
    from conftest import get_records

    from twin.units import check_loop_scale

    spec = msp25_spec(seed, duration=4.0, controller=controller, truth="draw", known=known, pid=pid)
    sig = dict(get_records([spec], workers=1)[0].signals)
    ps = get_model("msp25").params().replace(KP=(known or {}).get("KP", 400.0))
    check_loop_scale(ps, sig, "ref")  # SI: no refusal
    for mm, named in ((("x",), "ref: x is"), (("x_ref",), "ref: x_ref is"), (("x", "x_ref"), "ref: x and x_ref")):
        with pytest.raises(DataError, match=f"^{named}"):
            check_loop_scale(ps, {**sig, **{n: sig[n] * 1e3 for n in mm}}, "ref")


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_demand_starting_from_rest_leaves_the_scale_undetermined_not_refused(seed):
    """The tracker checks the first block it is handed: half a second in which the demand ramps up from rest (a
    sweep whose onset is drawn) while x is mostly its sensor's coloured noise.  The projection of one on the other
    is no scale there; the scale's interval at the 0.1 % level is wide, and nothing is refused (a healthy campaign
    draw was refused as 'x 2620 times its demand').  The whole record in mm is still refused."""
    from fpdd.errors import DataError
    from reference import msp25_spec
    from conftest import get_records

    from twin.units import check_loop_scale

    rng = np.random.default_rng(seed)
    onset = float(rng.uniform(0.4, 0.49))
    demand = {"kind": "sequence", "onset_s": onset, "parts": [
        {"kind": "sweep", "seconds": 2.5, "amplitude": float(rng.uniform(2e-3, 4e-3)), "v_max": 0.15,
         "ramp_s": float(rng.uniform(0.05, 0.1))}]}
    spec = msp25_spec(seed, duration=3.0, controller="analog", truth="draw", demand=demand,
                      noise={"x": 2e-6 * float(rng.uniform(0.6, 1.0)), "tau": 0.005})
    sig = dict(get_records([spec], workers=1)[0].signals)
    ps = get_model("msp25").params()
    first = {k: np.asarray(v)[:500] for k, v in sig.items()}
    check_loop_scale(ps, first, "ref")  # the first half-second: undetermined, not refused
    check_loop_scale(ps, sig, "ref")
    with pytest.raises(DataError, match="^ref: x is"):
        check_loop_scale(ps, {**sig, "x": sig["x"] * 1e3}, "ref")


def test_the_tracker_refuses_a_position_in_mm_once_the_demand_moves():
    """A small-amplitude test (0.1 mm) whose demand starts from rest, fed in the service's 0.1-s blocks: the first
    block cannot tell the loop's scale, so the tracker checks again as the blocks gather (each time they double)
    and refuses x in mm once the demand has moved; the same record in SI runs through."""
    from fpdd.errors import DataError
    from reference import msp25_spec
    from conftest import get_records
    from replay.base import Samples

    from twin.models.base import Timing
    from twin.online.tracker import OnlineTracker

    demand = {"kind": "sequence", "onset_s": 0.45, "parts": [
        {"kind": "sweep", "seconds": 2.5, "amplitude": 1e-4, "v_max": 0.05, "ramp_s": 0.08}]}
    spec = msp25_spec(4, duration=3.0, controller="analog", truth="draw", demand=demand,
                      noise={"x": 1e-6, "tau": 0.005})
    rec = get_records([spec], workers=1)[0]
    sig = {k: np.asarray(v, dtype=float) for k, v in rec.signals.items()}
    t_ns = 1_700_000_000_000_000_000 + np.round(np.asarray(rec.t) * 1e9).astype(np.int64)

    def feed(signals):
        tr = OnlineTracker(timing=Timing.parse("continuous", "cubic"))
        for i in range(0, t_ns.size, 100):
            tr.process(Samples(t_ns[i:i + 100], {k: v[i:i + 100] for k, v in signals.items()}))
        return tr

    assert feed(sig).samples == t_ns.size
    with pytest.raises(DataError, match="^the tracked signals: x is .* times larger than the demand"):
        feed({**sig, "x": sig["x"] * 1e3})
