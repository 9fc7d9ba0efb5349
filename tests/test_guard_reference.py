"""The consistency guard, proven on the independent reference simulator: a rig with effects the tracker's model
does not have, strong enough that the innovations are far from their covariance, raises no parameter alarm while
the filter's status says it is not consistent with the data (verification seed 1021, truth drawn off the defaults,
noise through the loop, bands centred on the truth as a commissioning fit gives them).

The filter keeps its commissioned sensor noise here (``adapt``: 0): learning the noise online absorbs a late
position sensor into a coloured, louder noise (2.2 x, AR(1) 0.72 on this record) and the filter then reads the
rest of the mismatch as parameter changes, consistently (zeta x1.6, wn x0.78: alarms; docs/explanation/tracking-and-alarms.md, "The strong-chirp
divergence").  What the guard can see, it holds."""

from __future__ import annotations

import numpy as np

from test_tracker_reference import _commissioned, _run
from track_reference import to_samples
import pytest
from twin.online.tracker import OnlineTracker, consistency_note

#: out of the model: the position sensor 3 ms late, first-order pressure transducers of 2 ms
LATE_SENSORS = {"sensor_delay": {"delay": 3e-3}, "pressure_sensor_lag": {"tau": 2e-3}}


@pytest.mark.slow
def test_a_rig_the_model_cannot_represent_raises_no_alarm_and_says_inconsistent(reference_records):
    from conftest import msp25_spec

    (ref,) = reference_records([msp25_spec(1021, duration=20.0, truth="draw", effects=LATE_SENSORS)])
    tr = OnlineTracker(guard={"adapt": 0.0})
    dm, events, outs = _run(to_samples(ref), tr, _commissioned(ref))
    guard = np.concatenate([o.guard for o in outs])
    late = np.arange(guard.size) * ref.dt > 2.0  # after the guard's averages have filled
    assert (guard[late] != "consistent").mean() > 0.9, np.unique(guard[late], return_counts=True)
    est = outs[-1].estimates[-1]
    biased = [n for j, n in enumerate(tr.tracked) if not 0.85 < est[j] / ref.truth[n] < 1.15]
    assert biased  # the filter's estimates are off the truth: evidence that must not count
    assert events == [], [(e.t_s, e.parameter, e.level) for e in events]
    # what a user reads: the drift test holds, each parameter says why
    assert dm.guard.startswith("inconsistent")
    assert "drift test holds: inconsistent" in consistency_note(tr, dm)
    assert set(dm.statuses().values()) <= {"inconsistent", "frozen"}, dm.statuses()
