"""The loop's timing as a candidate: a controller's rate, or an open loop's intersample rule."""

from __future__ import annotations


import numpy as np

from twin.models.base import INTERSAMPLE, Timing
from twin.params import ParameterSet
from twin.estimation.diagnose.constants import CONTROLLER_RATE, INPUT_INTERSAMPLE, RATE_MULTIPLES
from twin.estimation.diagnose.data import ModelState, _Data
from twin.estimation.diagnose.results import Trial
from twin.estimation.diagnose.naming import _judge
from twin.estimation.diagnose.extend import _fit_costs, _fit_state


def _try_timing(data: _Data, cur: ModelState, seed: int, min_share: float, configured: ParameterSet,
                say) -> Trial | None:
    """``controller_rate``: the best alternative loop timing, refitted and judged like an effect."""
    dt = data.records[0].dt
    if data.model.CLOSED_LOOP and data.model.drive_signal(data.records[0].signals, data.drive)[0] == "x_ref":
        name = CONTROLLER_RATE
        alts = [Timing("continuous", None, cur.timing.intersample)]
        alts += [Timing("digital", m / dt, cur.timing.intersample) for m in RATE_MULTIPLES]
        alts = [a for a in alts if a.ticks(dt) != cur.timing.ticks(dt)]
    else:  # an open loop: the logged input's behaviour between samples (zoh, foh, cubic) is its timing
        name = INPUT_INTERSAMPLE
        code = data.model.intersample_code(cur.timing, dt)
        alts = [Timing(cur.timing.controller, cur.timing.rate_hz, i) for i in INTERSAMPLE]
        alts = [a for a in alts if data.model.intersample_code(a, dt) != code]
    if not alts:
        return None
    ps = cur.params
    conf = ps.update({n: configured[n] for n in cur.free if n in configured})
    scores = []
    for a in alts:  # both parameter sets in one batch per timing
        costs = _fit_costs(data, [ps, conf], a)
        scores.append((min(costs), int(np.argmin(costs)), a))
    scores.sort(key=lambda s: s[0])
    say("  timings at the current estimates: " + ", ".join(f"{a.label} cost {c:.4g}" for c, _, a in scores))
    # the nominal estimates are bent to the assumed timing, so the timing closest to it scores best at them
    # even when the loop is analog: that one is refitted, then the other end of the scale (continuous) from
    # its estimates, then, from the better of the two, any alternative that scores lower at its estimates
    # than its refitted cost (a descent over the timings; at most len(alts) fits)
    _cost, which, first = scores[0]
    start = dict(cur.fit.estimate) if which == 0 else {n: configured[n] for n in cur.free if n in configured}
    best: Trial | None = None
    tried: set = set()
    queue = [first] + [a for a in alts if a.controller == "continuous" and a != first]
    while queue:
        a = queue.pop(0)
        if a in tried:
            continue
        tried.add(a)
        st = _fit_state(data, cur.params.update(start), cur.free, start, 1, seed, a)
        t = _judge(data, (name,), cur, st, min_share)
        say(f"  refitted under {a.label}: cost {st.fit.cost:.6g}")
        if best is None or t.state.fit.cost < best.state.fit.cost:
            best = t
        start = dict(best.state.fit.estimate)
        if queue:
            continue
        rest = [b for b in alts if b not in tried]
        if rest:
            costs = [0.5 * _fit_costs(data, [best.state.params], b)[0] for b in rest]
            k = int(np.argmin(costs))
            if costs[k] < best.state.fit.cost:
                queue.append(rest[k])
    return best
