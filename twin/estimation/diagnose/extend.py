"""Fitting an extension of the current model: its starts, the fits, a pair of effects."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np

from twin.estimation.fit import fit
from twin.models.base import Timing
from twin.params import ParameterSet
from twin.record import as_logged
from twin.estimation.diagnose.constants import FIT_TOL, GROW_FRACTION
from twin.estimation.diagnose.data import ModelState, _Data
from twin.estimation.diagnose.adequacy import _lr, _state
from twin.estimation.diagnose.results import ScreenRow, Trial
from twin.estimation.diagnose.naming import _judge


# --- fitting an extension -----------------------------------------------------------------
def _plausible_start(data: _Data, effect: str, est: Mapping[str, float]) -> dict[str, float]:
    """The screen's one-step estimate, pulled into [typical/100, 100 typical] of the effect."""
    E = data.effect(effect)
    out = {}
    for s, n, t in zip(E.params, E.neutral, E.typical):
        v = float(est.get(s.name, t))
        if n != t and t != 0:
            mag = abs(v - n)
            ref = abs(t - n)
            if not (ref / 100 <= mag <= 100 * ref):
                v = n + math.copysign(min(max(mag, ref / 100), 100 * ref), v - n if v != n else t - n)
        lo_in = s.lo + 1e-9 * (abs(s.lo) + 1e-300)
        hi_in = s.hi - 1e-9 * (abs(s.hi) + 1e-300)
        out[s.name] = float(np.clip(v, lo_in, hi_in))
    return out


def _fit_state(data: _Data, ps: ParameterSet, free: tuple[str, ...], start: Mapping[str, float],
               n_starts: int, seed: int, timing: Timing, max_nfev: int = 80) -> ModelState:
    res = fit(data.model, data.parts, free, base=ps, start=start, outputs=data.outputs, noise=data.sigma,
              drive=data.drive, n_starts=n_starts, n_refine=1 if n_starts <= 2 else 2, spread=1.5, seed=seed,
              max_nfev=max_nfev, timing=timing, tol=FIT_TOL, scales=data.scales())
    return _state(data, res, free, timing)


def _fit_grown(data: _Data, ps: ParameterSet, free: tuple[str, ...], start: Mapping[str, float], seed: int,
               timing: Timing, hold: Sequence[str] = ()) -> ModelState:
    """A fit over a growing horizon: first on the first ``GROW_FRACTION`` of each record's fitting data with
    ``hold`` (an effect's shape parameters: a friction's smoothing velocity) held at the start, then, from there,
    on all of it with everything free.  An open-loop simulation of a plant that a loop held (a free axis driven by its
    logged force) drifts with every force error, so the whole record's cost has many local minima far from the
    start; over a short stretch the drift is small and the start's basin wide (multiple shooting's reason)."""
    short = [max(int(GROW_FRACTION * n), min(n, 200)) for n in data.n_fit]
    part = dataclasses.replace(data, records=[r.slice(0, k) for r, k in zip(data.records, short)],
                               n_fit=short, exo_cache={})
    res = fit(data.model, part.parts, tuple(n for n in free if n not in hold), base=ps, start=start, outputs=data.outputs, noise=data.sigma,
              drive=data.drive, n_starts=1, n_refine=1, spread=1.5, seed=seed, max_nfev=80, timing=timing,
              tol=FIT_TOL, scales=data.scales())
    mid = {**start, **res.estimate}
    if not all(math.isfinite(v) for v in mid.values()):
        mid = dict(start)
    return _fit_state(data, ps.update(mid), free, mid, 1, seed, timing)


def _open_loop(data: _Data) -> bool:
    """Is the model driven by a logged input (its simulation runs open loop), not by a loop's reference?"""
    return data.drives()[0][0] != "x_ref"


def _rank_starts(data: _Data, ps: ParameterSet, starts: Sequence[Mapping[str, float]],
                 timing: Timing) -> list[dict[str, float]]:
    """Starts sorted by weighted cost on the fitting data, all evaluated in one batch per record."""
    cost = _fit_costs(data, [ps.update(s) for s in starts], timing)
    return [dict(starts[i]) for i in np.argsort(cost, kind="stable")]


def _fit_costs(data: _Data, sets: Sequence[ParameterSet], timing: Timing) -> list[float]:
    """Weighted sums of squares on the fitting data of several parameter sets, one batch per record."""
    model = data.model
    P = np.ascontiguousarray(np.array([model.vector(ps) for ps in sets]))
    cost = np.zeros(len(sets))
    for rec, n, (dname, drive), init in zip(data.records, data.n_fit, data.drives(), data.init(sets[0])):
        S0 = model.initial_state(P, init)  # each row from its own sensor errors
        exo = {k: v[:n] for k, v in model.exogenous_of(rec.signals).items()}
        sim = model.simulate_batch(P, dname, drive[:n], rec.dt, S0, None, timing, exo)
        for o in data.outputs:
            e = (as_logged(rec, o, sim.outputs[o]) - rec[o][None, :n]) / data.sigma[o]
            cost += np.sum(e * e, axis=1)
    return [float(c) if math.isfinite(c) else float("inf") for c in cost]


def _effect_starts(data: _Data, effect: str, est: Mapping[str, float]) -> list[dict[str, float]]:
    """The screen's estimate, the typical magnitude and a tenth of it (close to neutral) of ``effect``."""
    E = data.effect(effect)
    out = [_plausible_start(data, effect, est), dict(zip(E.names, E.typical))]
    small = {}
    for s, n, t in zip(E.params, E.neutral, E.typical):
        small[s.name] = t if n == t else (n + 0.1 * (t - n) if n < t else min(s.hi, 10.0 * t))
    out.append(_plausible_start(data, effect, small))
    return out


def _try(data: _Data, cur: ModelState, row: ScreenRow, seed: int, min_share: float,
         configured: ParameterSet, n_ranked: int = 2) -> Trial:
    model = data.model
    E = data.effect(row.effect)
    # a named special case of this effect (the static droop of the supply line) is replaced, nested: its
    # parameters become this effect's (Effect.generalises), the LR test counts only the parameters added
    special = {e: dict(m) for e, m in model.EFFECTS[row.effect].generalises if e in cur.effects}
    drop = {n for e in special for n in model.EFFECTS[e].names}
    carried = {g: cur.params[n] for m in special.values() for n, g in m.items()}
    free = tuple(n for n in cur.free if n not in drop) + E.names
    effects = tuple(e for e in cur.effects if e not in special) + (row.effect,)
    ps = model.params(effects=effects).update({k: v for k, v in cur.params.as_dict().items() if k not in drop})
    # starts: the effect at the screen's estimate, its typical magnitude and close to neutral; the other
    # free parameters at the current estimates (which may have bent to mimic the effect) and as configured (the
    # baseline: nominal or commissioned values).  All screened in one batch; the best start of each baseline is
    # refined and the better by held-out error kept; a start close to neutral when neither passes.
    named = {n for e in cur.effects for n in model.EFFECTS[e].names}  # earlier causes stay at their estimates
    kept = {n: v for n, v in cur.fit.estimate.items() if n not in drop}
    bases = [dict(kept),
             {**kept, **{n: configured[n] for n in cur.free if n in configured and n not in named}}]
    if n_ranked < 2 or all(bases[1].get(n) == v for n, v in bases[0].items() if n in cur.free):
        bases = bases[:1]
    eff_starts = _effect_starts(data, row.effect, row.estimate)
    if carried:  # the special case's estimates carried over (the rest of the effect at its starts)
        eff_starts = eff_starts + [{**e, **carried} for e in eff_starts]
    tops = [_rank_starts(data, ps, [{**b, **e} for e in eff_starts], cur.timing)[0] for b in bases]
    near = {**kept, **carried}
    for s, n, v in zip(E.params, E.neutral, E.typical):
        if s.name not in carried:
            near[s.name] = n + 1e-3 * (v - n) if n < v else (n if n == v else min(s.hi, 10.0 * v))
    t: Trial | None = None
    for attempt, start in enumerate(tops + [near]):
        if attempt == len(tops) and t is not None and (t.accepted or t.state.fit.cost < cur.fit.cost):
            break
        if attempt == 0 and _open_loop(data):  # from the current estimates, over a growing horizon
            st = _fit_grown(data, ps.update(start), free, start, seed, cur.timing, hold=E.names[1:])
        else:
            st = _fit_state(data, ps.update(start), free, start, 1, seed, cur.timing)
        cand = _judge(data, (row.effect,), cur, st, min_share)
        if t is None or (not cand.accepted, _held_out(cand)) < (not t.accepted, _held_out(t)):
            t = cand
    assert t is not None  # the loop ran at least once (the start near neutral)
    if t.accepted and not t.state.converged and math.isfinite(t.state.fit.cost):
        # accepted, stopped by its evaluation budget: continued once from where it stopped, so that the verdict
        # on the model it leaves reads an estimate, not the round-off of the path that was cut short (a Stribeck
        # curve's refit on seed 1001 stopped at LR 4175 or 4177 with one or two BLAS threads, one side of
        # WHITE_R2 or the other)
        start = dict(t.state.fit.estimate)
        st = _fit_state(data, ps.update(start), free, start, 1, seed, cur.timing)
        if st.fit.cost < t.state.fit.cost:
            t = _judge(data, (row.effect,), cur, st, min_share)
    return t


def _held_out(t: Trial) -> float:
    """A trial's held-out weighted squared error (infinite when its simulation diverged)."""
    v = float(t.state.holdout.get("weighted_sse", math.inf))
    return v if math.isfinite(v) and not t.diverged else math.inf


def _try_pair(data: _Data, cur: ModelState, a: Trial, b: Trial, seed: int, min_share: float,
              configured: ParameterSet) -> tuple[Trial, bool]:
    """Fit ``cur`` extended by both effects of trials ``a`` and ``b`` (effects recognisable only together:
    each alone is mimicked by bending the nominal parameters).  Returns the pair's trial (judged against
    ``cur``) and whether each effect is also significant within the pair."""
    model = data.model
    effects = (a.effects[0], b.effects[0])
    names = cur.free + tuple(n for e in effects for n in model.EFFECTS[e].names)
    ps = model.params(effects=cur.effects + effects).update(cur.params.as_dict())
    eff_vals = {n: a.state.fit.estimate[n] for n in model.EFFECTS[effects[0]].names}
    eff_vals.update({n: b.state.fit.estimate[n] for n in model.EFFECTS[effects[1]].names})
    typical = {n: v for e in effects for n, v in zip(data.effect(e).names, data.effect(e).typical)}
    base_starts = [dict(cur.fit.estimate), {n: configured[n] for n in cur.free if n in configured},
                   {n: a.state.fit.estimate[n] for n in cur.free}, {n: b.state.fit.estimate[n] for n in cur.free}]
    ranked = _rank_starts(data, ps, [{**bs, **ev} for bs in base_starts for ev in (eff_vals, typical)], cur.timing)
    best: Trial | None = None
    for start in ranked[:2]:
        st = _fit_state(data, ps.update(start), names, start, 1, seed, cur.timing)
        t = _judge(data, effects, cur, st, min_share)
        if best is None or t.state.fit.cost < best.state.fit.cost:
            best = t
        if best.accepted:
            break
    assert best is not None, "no start to refine"
    each = all(_lr(single.state, best.state, data)[1] < data.alpha for single in (a, b))
    return best, each
