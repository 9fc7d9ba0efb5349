"""Alarms confirmed by window re-fits (twin.online.confirm): the decision rule, the window, the status field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from replay.base import Samples
from twin.online.baseline import Baseline
from twin.online.confirm import (ALPHA, OFFSET_TOLERANCE_PA, REPLICATE_ALPHA, RESOLVE, ConfirmedDrift, Window,
                                 critical_z, decide, decide_offset, noise_ratios,
                                 quiet_sensors)
from twin.online.events import StatusEvent

BAND = Baseline(100.0, 100.0 / 1.5, 150.0)  # log half-width log(2.25)/2 = 0.405


def test_critical_z_is_the_two_sided_normal_quantile():
    from scipy.stats import norm

    assert critical_z(1e-3) == pytest.approx(norm.isf(5e-4), rel=1e-9)
    assert critical_z(ALPHA) > 3.0


def test_outside_the_band_and_significant_is_confirmed_on_its_side():
    hi = decide("p", 200.0, 0.05, BAND, True)
    lo = decide("p", 50.0, 0.05, BAND, True)
    assert (hi.state, lo.state) == ("high", "low")
    assert hi.z == pytest.approx(math.log(2.0) / 0.05)
    assert lo.z == pytest.approx(math.log(0.5) / 0.05)


def test_outside_the_band_but_not_away_from_the_baseline_is_not_confirmed():
    # 160 is outside [66.7, 150] but log(1.6) / 0.19 = 2.5 < 3.29: the two-sample test does not reject the baseline
    # nor does it show the parameter inside its band: unresolved, neither a confirmation nor a return
    v = decide("p", 160.0, 0.19, BAND, True)
    assert v.state == "unresolved" and 2.0 < v.z < critical_z(ALPHA) and "not away from the baseline" in v.why
    # the commissioning's own uncertainty counts as the second sample
    assert decide("p", 200.0, 0.1, BAND, True).state == "high"
    assert decide("p", 200.0, 0.1, BAND, True, base_rel_std=0.2).state == "unresolved"
    assert decide("p", 140.0, 0.01, BAND, True).state == "inside"


def test_a_window_that_does_not_inform_the_parameter_is_not_testable():
    half = 0.5 * math.log(BAND.hi / BAND.lo)
    wide = decide("p", 400.0, 1.01 * RESOLVE * half, BAND, True)
    assert wide.state == "not_testable" and "informs it" in wide.why
    assert decide("p", 400.0, 0.99 * RESOLVE * half, BAND, True).state == "high"
    assert decide("p", 400.0, math.nan, BAND, True).state == "not_testable"
    assert decide("p", 0.0, 0.01, BAND, True).state == "not_testable"


def test_an_inadequate_window_tests_nothing():
    v = decide("p", 400.0, 0.01, BAND, False)
    assert v.state == "not_testable" and v.why == "the model does not represent the rig now"
    assert decide_offset("pA_off", 1e6, 1e3, False).state == "not_testable"


def test_an_offset_counts_beyond_the_tolerance_and_when_significant():
    assert decide_offset("pA_off", 2 * OFFSET_TOLERANCE_PA, 1e3, True).state == "high"
    assert decide_offset("pA_off", -2 * OFFSET_TOLERANCE_PA, 1e3, True).state == "low"
    assert decide_offset("pA_off", 0.5 * OFFSET_TOLERANCE_PA, 1e3, True).state == "inside"  # within calibration
    assert decide_offset("pA_off", 2 * OFFSET_TOLERANCE_PA, 1e5, True).state == "unresolved"  # z = 2.5: not shown
    assert decide_offset("pA_off", 2 * OFFSET_TOLERANCE_PA, math.nan, True).state == "not_testable"


def _block(t0: float, n: int, dt: float = 1e-3) -> Samples:
    t = t0 + dt * np.arange(n)
    return Samples(np.round(t * 1e9).astype(np.int64), {"x": np.sin(t)})


def test_the_window_keeps_the_last_seconds_whatever_the_blocks():
    w = Window(2.0)
    for k in range(10):
        w.add(_block(0.7 * k, 700))
    s = w.samples()
    assert s.t_ns[-1] == pytest.approx(6.999e9, abs=1)
    assert (int(s.t_ns[-1]) - int(s.t_ns[0])) * 1e-9 == pytest.approx(2.0, abs=1.5e-3)
    assert w.span_s() >= 2.0


def test_statuses_before_any_window_say_untested_and_the_status_event_carries_test_times():
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    assert cd.statuses() == {"p": "untested"} and cd.tested == {"p": None}
    ev = StatusEvent(rig="r", t_ns=1, state="running", parameters={"p": "not_testable"}, tested={"p": 12.5})
    back = StatusEvent.from_dict(ev.to_dict())
    assert back.tested == {"p": 12.5} and back.parameters == {"p": "not_testable"}
    assert "tested" not in StatusEvent(rig="r", t_ns=1, state="running").to_dict()  # as before without them
    from fpdd.errors import DataError

    with pytest.raises(DataError, match=r"StatusEvent\.tested\.p: -1\.0 must be >= 0"):
        StatusEvent.from_dict({**ev.to_dict(), "tested": {"p": -1.0}})


def test_sensor_verdicts_of_the_filter_follow_the_windows():
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    filt = {"x": "noisy", "pA": "offset", "pB": "stuck"}
    # no window yet: a verdict resting on the model is not confirmed (a signal's own fault stands), and a pressure
    # transducer's offset is the windows' to say
    assert cd.sensor_status(filt) == {"x": "ok", "pA": "ok", "pB": "stuck"}
    assert cd.sensor_status({"x": "offset"}) == {"x": "ok"}
    cd.fits.append(None)  # a window has run (its verdicts are read from quiet and adequate)
    cd.adequate = False  # the model does not represent the rig: its model-based verdicts are not the sensors'
    assert cd.sensor_status(filt) == {"x": "ok", "pA": "ok", "pB": "stuck"}
    cd.adequate = True
    # a window that predicted x and pA to within their noise: the filter's model-based verdicts on them are not
    # the sensors'; one that found x's residuals beyond the factor leaves the filter's word
    cd.quiet = {"x": True, "pA": True, "pB": True}
    assert cd.sensor_status(filt) == {"x": "ok", "pA": "ok", "pB": "stuck"}  # a signal's own fault stays
    assert cd.sensor_status({"x": "offset", "pA": "noisy"}) == {"x": "ok", "pA": "ok"}
    cd.quiet = {"x": False, "pA": True}  # a window that found x's residuals beyond the factor confirms the filter
    assert cd.sensor_status({"x": "noisy", "pA": "noisy"}) == {"x": "noisy", "pA": "ok"}
    assert cd.sensor_status({"x": "offset"}) == {"x": "offset"}
    cd.sensor_level["pB"] = "warning"
    assert cd.sensor_status({"x": "ok", "pA": "ok", "pB": "ok"})["pB"] == "offset"


def test_a_windows_noise_ratio_is_its_residual_rms_over_the_nominal_noise():
    import types

    res = types.SimpleNamespace(outputs=("x", "pA", "pB"), mse={"x": (3e-6) ** 2, "pA": (2e4) ** 2, "pB": math.nan},
                                noise={"x": 2e-6, "pA": 2e4, "pB": 2e4})
    assert noise_ratios(res) == pytest.approx({"x": 1.5, "pA": 1.0})


def test_two_confirmations_warn_three_alarm_not_testable_keeps_count_inside_returns():
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    high = decide("p", 200.0, 0.05, BAND, True)
    idle = decide("p", 200.0, 0.05, BAND, False)
    inside = decide("p", 110.0, 0.05, BAND, True)
    low = decide("p", 50.0, 0.05, BAND, True)

    def apply(v, t):
        return [(e.level, e.kind) for e in cd._apply("p", v, int(t * 1e9), t, "scheduled")]

    assert apply(high, 4.0) == []  # one window: not yet
    assert cd.statuses() == {"p": "ok"} and cd.tested["p"] == 4.0
    assert apply(idle, 8.0) == [] and cd.statuses() == {"p": "not_testable"} and cd.tested["p"] == 4.0
    assert apply(high, 12.0) == [("warning", "raised")]  # the untestable window between did not reset the count
    assert apply(low, 16.0) == []  # the other side starts again
    assert apply(low, 20.0) == [] and cd.level["p"] == "warning"
    assert apply(low, 24.0) == [("alarm", "escalated")]
    assert apply(inside, 28.0) == [("ok", "returned")] and cd.count["p"] == 0
    assert apply(high, 32.0) == [] and apply(inside, 36.0) == [] and apply(high, 40.0) == []  # inside resets


def test_an_alarm_returns_only_on_a_window_that_puts_the_parameter_inside_at_the_level():
    """A wear just past its band's edge: a window's point estimate falls inside by chance about half the time.
    The return needs the edge rejected at the level (``back_inside``), as the raise needs the baseline rejected."""
    from twin.online.confirm import back_inside, critical_z

    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    high = decide("p", 200.0, 0.05, BAND, True)
    for t in (4.0, 8.0, 12.0):
        events = cd._apply("p", high, 1, t, "scheduled")
    assert [e.level for e in events] == ["alarm"] and cd.raised_side["p"] == "high"
    barely = decide("p", 145.0, 0.05, BAND, True)  # inside by 3 %, the window's error 5 %
    assert barely.state == "inside"
    assert back_inside(145.0, 0.05, BAND, "high") == (False, pytest.approx(math.log(145 / 150) / 0.05))
    assert cd._apply("p", barely, 1, 16.0, "scheduled") == [] and cd.level["p"] == "alarm"
    assert cd.count["p"] == 0  # the next confirmation starts again, the alarm stays
    clearly = decide("p", 120.0, 0.05, BAND, True)
    ok, z = back_inside(120.0, 0.05, BAND, "high")
    assert ok and z < -critical_z()
    (ev,) = cd._apply("p", clearly, 1, 20.0, "scheduled")
    assert (ev.level, ev.kind) == ("ok", "returned") and "against its upper edge" in ev.message
    assert ev.statistic == pytest.approx(z)
    # the commissioning's own uncertainty widens the test as it widens the raise's
    assert back_inside(120.0, 0.05, BAND, "high", base_rel_std=0.03)[0] is True
    assert back_inside(120.0, 0.05, BAND, "high", base_rel_std=0.08)[0] is False
    assert back_inside(80.0, 0.05, BAND, "low") == (True, pytest.approx(math.log(80 / (100 / 1.5)) / 0.05))


def test_an_unresolved_window_neither_confirms_nor_returns():
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    high = decide("p", 200.0, 0.05, BAND, True)
    unresolved = decide("p", 160.0, 0.19, BAND, True, base_rel_std=0.3)  # z 1.3: below the replication level
    assert unresolved.state == "unresolved" and 0 < unresolved.z < critical_z(2 * REPLICATE_ALPHA)
    assert cd._apply("p", high, 1, 4.0, "scheduled") == []
    assert cd._apply("p", unresolved, 1, 8.0, "scheduled") == [] and cd.count["p"] == 1  # the count stays
    assert cd.tested["p"] == 8.0 and cd.statuses() == {"p": "ok"}  # it was tested: the status says when
    assert [e.level for e in cd._apply("p", high, 1, 12.0, "scheduled")] == ["warning"]
    assert cd._apply("p", unresolved, 1, 16.0, "scheduled") == [] and cd.level["p"] == "warning"  # not returned
    off = decide_offset("pA_off", 2 * OFFSET_TOLERANCE_PA, 1e3, True)
    unsure = decide_offset("pA_off", 2 * OFFSET_TOLERANCE_PA, 1e5, True)
    cd._apply_sensor("pA_off", off, 1, 4.0)
    assert cd._apply_sensor("pA_off", unsure, 1, 8.0) == [] and cd.sensor_count["pA"] == 1
    assert [e.level for e in cd._apply_sensor("pA_off", off, 1, 12.0)] == ["warning"]


def test_a_systematic_error_of_one_window_is_not_an_event():
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    high = decide("p", 200.0, 0.05, BAND, True)
    idle = decide("p", 200.0, 0.05, BAND, False)
    events = cd._apply("p", high, 1, 5.0, "scheduled")
    for k in range(6):
        events += cd._apply("p", idle, 1, 9.0 + 4 * k, "scheduled")
    assert events == [] and cd.count["p"] == 1 and cd.statuses() == {"p": "not_testable"}


def test_a_window_the_filter_does_not_back_decides_nothing():
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    high = decide("p", 200.0, 0.05, BAND, True)
    assert cd._apply("p", high, 1, 4.0, "scheduled", filtered=120.0) == []  # the filter is inside its band
    assert cd._apply("p", high, 1, 8.0, "scheduled", filtered=60.0) == []  # ... or beyond it on the other side
    assert cd.count["p"] == 0 and cd.tested["p"] == 8.0
    cd._apply("p", high, 1, 12.0, "scheduled", filtered=180.0)
    assert [e.level for e in cd._apply("p", high, 1, 16.0, "scheduled", filtered=190.0)] == ["warning"]


def test_an_offset_becomes_a_sensor_event_in_two_windows_and_returns():
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    off = decide_offset("pA_off", 2 * OFFSET_TOLERANCE_PA, 1e3, True)
    within = decide_offset("pA_off", 0.1 * OFFSET_TOLERANCE_PA, 1e3, True)
    assert cd._apply_sensor("pA_off", off, 1, 4.0) == []
    ev = cd._apply_sensor("pA_off", off, 1, 8.0)
    assert [(e.parameter, e.level, e.kind) for e in ev] == [("pA_off", "warning", "raised")]
    assert ev[0].estimate == pytest.approx(2 * OFFSET_TOLERANCE_PA) and "sensor pA" in ev[0].message
    assert cd.sensor_status({"pA": "ok"}) == {"pA": "offset"}
    assert cd._apply_sensor("pA_off", within, 1, 12.0) == []  # one window within: not yet
    assert cd._apply_sensor("pA_off", off, 1, 16.0) == [] and cd.sensor_status({"pA": "ok"}) == {"pA": "offset"}
    assert cd._apply_sensor("pA_off", within, 1, 20.0) == []
    assert [e.kind for e in cd._apply_sensor("pA_off", within, 1, 24.0)] == ["returned"]
    assert cd.sensor_status({"pA": "ok"}) == {"pA": "ok"}


def test_a_confirmation_is_replicated_at_the_replication_level_on_the_same_side_beyond_the_band():
    """The first confirmation needs the level ALPHA; a later window on the same side, beyond the band, replicates
    it at REPLICATE_ALPHA (one-sided): an honest test of a weakly informed parameter (a leakage on a PI loop)
    rarely shows the first window's evidence twice over."""
    zr = critical_z(2 * REPLICATE_ALPHA)
    assert zr == pytest.approx(1.6449, abs=1e-4)
    weak = decide("p", 160.0, 0.19, BAND, True)  # beyond the band, z 2.5: unresolved alone
    assert weak.state == "unresolved" and zr < weak.z < critical_z(ALPHA)
    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    assert cd._apply("p", weak, 1, 4.0, "scheduled") == [] and cd.count["p"] == 0  # alone it confirms nothing
    high = decide("p", 200.0, 0.05, BAND, True)
    assert cd._apply("p", high, 1, 8.0, "scheduled") == [] and cd.count["p"] == 1
    (ev,) = cd._apply("p", weak, 1, 12.0, "scheduled")
    assert (ev.level, ev.kind) == ("warning", "raised") and cd.count["p"] == 2
    # on the other side, or inside the band, or below the level, it replicates nothing
    cd2 = ConfirmedDrift("r", {"p": BAND}, "msp25")
    cd2._apply("p", high, 1, 4.0, "scheduled")
    low_weak = decide("p", 60.0, 0.19, BAND, True)  # z -2.7
    assert low_weak.state == "unresolved" and low_weak.z < -zr
    assert cd2._apply("p", low_weak, 1, 8.0, "scheduled") == [] and cd2.count["p"] == 1
    faint = decide("p", 160.0, 0.19, BAND, True, base_rel_std=0.3)  # z 1.3
    assert faint.state == "unresolved" and faint.z < zr
    assert cd2._apply("p", faint, 1, 12.0, "scheduled") == [] and cd2.count["p"] == 1
    # and the filter must stand beyond the band on that side, as for any confirmation
    assert cd2._apply("p", weak, 1, 16.0, "scheduled", filtered=120.0) == [] and cd2.count["p"] == 1


def test_a_window_beyond_a_standing_confirmation_is_not_gated_by_its_width():
    """A window whose standard error is too wide to test the band (``not_testable`` alone) may still replicate a
    confirmation when its value lies beyond the band on the confirmed side: its likelihood ratio decides, as for
    any replication.  Inside the band, on the other side, or with nothing confirmed, the width gate stands."""
    import types

    half = 0.5 * math.log(BAND.hi / BAND.lo)
    rel = 1.2 * RESOLVE * half  # too wide for the band: the gate alone would call it not testable

    def res(value: float):
        return types.SimpleNamespace(estimate={"p": value}, std={"p": rel * value}, free=["p"], corr=np.eye(1))

    cd = ConfirmedDrift("r", {"p": BAND}, "msp25")
    bounds = {"p": (1.0, 1e4)}
    (alone,) = cd._verdicts(res(400.0), ["p"], bounds, True)[0].values()
    assert alone.state == "not_testable" and "informs it" in alone.why  # nothing confirmed: the gate stands
    cd._apply("p", decide("p", 200.0, 0.05, BAND, True), 1, 4.0, "scheduled")
    assert cd.count["p"] == 1 and cd.side["p"] == "high"
    (beyond,) = cd._verdicts(res(180.0), ["p"], bounds, True)[0].values()  # z 2.4: a replication's candidate
    assert beyond.state == "unresolved" and beyond.z == pytest.approx(math.log(1.8) / rel)
    assert cd._may_replicate("p", beyond)
    (strong,) = cd._verdicts(res(400.0), ["p"], bounds, True)[0].values()  # z 5.7: a confirmation's candidate
    assert strong.state == "high"
    for value in (120.0, 40.0):  # inside the band, beyond it on the other side: the gate stands
        (v,) = cd._verdicts(res(value), ["p"], bounds, True)[0].values()
        assert v.state == "not_testable" and "informs it" in v.why, value
    (idle,) = cd._verdicts(res(400.0), ["p"], bounds, False)[0].values()
    assert idle.state == "not_testable" and idle.why == "the model does not represent the rig now"


def test_one_sensor_beyond_its_noise_is_that_sensor_several_are_the_model():
    assert quiet_sensors({"x": 1.1, "pA": 7.0, "pB": 0.9}, 5.0, True) == {"x": True, "pA": False, "pB": True}
    # both pressures beyond at once: a load the model lacks, not two faulty transducers
    assert quiet_sensors({"x": 1.1, "pA": 7.0, "pB": 6.0}, 5.0, True) == {"x": True, "pA": True, "pB": True}
    assert quiet_sensors({"x": 1.1, "pA": 7.0}, 5.0, False) == {"x": True, "pA": True}  # an inadequate window
    assert quiet_sensors({"x": math.nan}, 5.0, True) == {"x": False}
