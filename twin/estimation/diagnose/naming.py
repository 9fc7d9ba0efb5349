"""The naming rules: when a fitted extension is accepted, and when its size is implausible."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from twin.models import Model
from scipy import stats

from twin.estimation.diagnose.constants import HOLDOUT_LEVEL, PLAUSIBLE, SIGNATURE_SHIFTS, TIMING_EFFECTS
from twin.estimation.diagnose.data import ModelState, _Data, _blocks
from twin.estimation.diagnose.adequacy import _holdout_test, _innovations, _lr
from twin.estimation.diagnose.results import Trial


def _judge(data: _Data, effects: tuple[str, ...], cur: ModelState, st: ModelState, min_share: float) -> Trial:
    lr, p, df, d_aicc = _lr(cur, st, data)
    ht = _holdout_test(cur, st, data)
    share = record_share(data, cur, st)
    t = Trial(effects, st, lr, p, df, d_aicc, ht["gain"], (ht["lo"], ht["hi"]), share, p_adjusted=p,
              holdout_test=ht, holdout_p_adjusted=ht["p"])
    t.implausible = _implausible(data, effects, st)
    t.diverged = not (math.isfinite(st.fit.cost) and math.isfinite(st.wcost)
                      and all(np.all(np.isfinite(p[o])) for p in st.predicted for o in data.outputs))
    if not t.diverged:
        t.signature = _signature(data, cur, st)
    _verdict(t, data.alpha, min_share, judge_share=share_rule(data, cur))
    return t


def record_share(data: _Data, cur: ModelState, st: ModelState) -> float:
    """The share of ``cur``'s simulation misfit above the noise floor that ``st`` removes, over the whole records
    (fitting data and held-out tails: weighted squared simulation errors, the floor per output from the scatter
    of the errors' increments).  Over the fitting data alone a nominal fit bent to mimic an effect hides it (on
    EMPS a force offset removing 99 % of the held-out error was 21 % of the fitting data's excess); over the
    held-out tails alone an error outside the catalogue that grows during the record (a drifting transducer)
    hides the named effect's part."""
    b0, b1 = _blocks(data, cur.predicted, "all"), _blocks(data, st.predicted, "all")
    sse0 = sse1 = excess = 0.0
    n = 0
    for B0, B1 in zip(b0, b1):
        for e0, e1 in zip(B0, B1):
            if not (np.all(np.isfinite(e0)) and np.all(np.isfinite(e1))):
                return -math.inf
            s0 = float(e0 @ e0)
            nz = float(np.std(np.diff(e0)) / math.sqrt(2.0)) if e0.size > 2 else 0.0
            sse0 += s0
            sse1 += float(e1 @ e1)
            excess += max(s0 - e0.size * nz * nz, 0.0)
            n += e0.size
    # at least the chance fluctuation of a sum of n squared unit errors (a model at the noise floor)
    return (sse0 - sse1) / max(excess, math.sqrt(2.0 * max(n, 1)))


def _signature(data: _Data, cur: ModelState, st: ModelState) -> dict:
    """Is the extension's own signature in the residuals, or does it stand in for an error of other dynamics?

    ``c``: the extension's change of the one-step prediction errors on the fitting data (both under ``cur``'s
    noise model), ``r``: the errors it leaves.  An effect whose signature is in the residuals leaves errors
    unrelated to that signature moved in time; an effect that soaks up an error of other dynamics (a
    transducer's lag taken for a friction) leaves the difference between that error and its own signature,
    which the signature led and lagged by a few samples (``SIGNATURE_SHIFTS``) explains.  Per output, ``r`` is
    regressed on the shifted ``c``: ``Q`` (the explained sum of squares over the residual variance) is
    chi-square(df) when ``r`` is white and independent of them.  ``misplaced``: the explained part beyond
    chance as a share of what the extension removed (0 when the signature is where the residual has it)."""
    if cur.noise is None:
        return {}
    E0, _ = _innovations(data, cur.noise, cur.predicted)
    E1, _ = _innovations(data, cur.noise, st.predicted)
    if not (np.all(np.isfinite(E0)) and np.all(np.isfinite(E1))):
        return {}
    C = E0 - E1
    L = max(SIGNATURE_SHIFTS)
    n = E1.shape[1]
    if n <= 20 * L:
        return {}
    shifts = [k for k in SIGNATURE_SHIFTS] + [-k for k in SIGNATURE_SHIFTS]
    q, df, explained = 0.0, 0, 0.0
    for i in range(E1.shape[0]):
        c = C[i]
        if not np.any(c):
            continue
        r = E1[i, L:n - L] - np.mean(E1[i, L:n - L])
        X = np.stack([c[L - k:n - L - k] for k in shifts], axis=1)
        X = X - X.mean(axis=0)
        U, sv, _ = np.linalg.svd(X, full_matrices=False)
        U = U[:, sv > 1e-8 * sv[0]] if sv.size and sv[0] > 0 else U[:, :0]
        proj = U.T @ r
        ess = float(proj @ proj)
        s2 = (float(r @ r) - ess) / max(r.size - U.shape[1], 1)
        if s2 > 0:
            q += ess / s2
            explained += max(ess - U.shape[1] * s2, 0.0)
        df += U.shape[1]
    gain = float(np.sum(E0 * E0) - np.sum(E1 * E1))
    if df == 0:
        return {}
    return {"Q": q, "df": df, "p": float(stats.chi2.sf(q, df)), "explained": explained, "gain": gain,
            "misplaced": explained / gain if gain > 0 else float("inf")}


def _implausible(data: _Data | Model, effects: Sequence[str], st: ModelState) -> list[str]:
    """Parameters of ``effects`` fitted further from neutral than ``PLAUSIBLE`` times the effect's typical
    deviation (an out-of-catalogue error soaked up by bending an effect far beyond its physical range); the
    typical sizes of the records' diagnosis (``data``), or the catalogue's (a model)."""
    model = data.model if isinstance(data, _Data) else data
    out = []
    for e in effects:
        if e not in model.EFFECTS:
            continue
        E = data.effect(e) if isinstance(data, _Data) else model.EFFECTS[e]
        for s, n, typ in zip(E.params, E.neutral, E.typical):
            v = st.params[s.name]
            if typ != n and abs(v - n) > PLAUSIBLE * abs(typ - n):
                out.append(f"{s.name}={s.show(v)}")
    return out


def share_rule(data: _Data, cur: ModelState) -> str:
    """When an extension of ``cur`` must remove ``min_share`` (the majority) of its simulation misfit above the
    noise (:func:`record_share`): ``"no"`` for an adequate nominal model (the screen found something the adequacy tests did not),
    ``"unless_adequate"`` while ``cur`` is not adequate (an extension that leaves the model adequate is exempt:
    what it leaves is noise), ``"always"`` for an adequate model that already names something (a further name
    must account for most of what is left, not for a slight mismatch of a formulation: a linear droop beside a
    turbulent line loss)."""
    if not cur.adequate:
        return "unless_adequate"
    return "always" if (cur.effects or cur.timing != data.timing) else "no"


def _verdict(t: Trial, alpha: float, min_share: float, judge_share: str = "no") -> None:
    """One criterion for every kind of name (an effect, a pair, a timing): the whitened LR test significant
    after Holm over the catalogue, a lower AICc, the held-out gain significant against the noise (the
    Diebold-Mariano-type test of :func:`.adequacy._holdout_test`, one-sided at ``HOLDOUT_LEVEL``: a replication
    of the LR test's discovery on data the fit did not see), a plausible size and the effect's own signature where the residuals have it
    (a misplaced signature explaining over ``1 - min_share`` of its gain again: an error of other dynamics)."""
    reasons = ["diverged (its simulation of the record is not finite)"] if t.diverged else []
    if not t.p_adjusted < alpha:
        reasons.append(f"LR p_Holm={t.p_adjusted:.3g} >= {alpha:g}")
    if not t.delta_aicc < 0:
        reasons.append("AICc not lower")
    if not t.holdout_p_adjusted < HOLDOUT_LEVEL:
        z = float(t.holdout_test.get("z", 0.0))
        reasons.append(f"held-out gain {100 * t.holdout_gain:.2f} % not significant against the noise "
                       f"(Diebold-Mariano z={z:.3g}, p={t.holdout_p_adjusted:.3g} >= {HOLDOUT_LEVEL:g})")
    if t.implausible:
        reasons.append(f"implausible size ({', '.join(t.implausible)}: over {PLAUSIBLE:g} x the typical)")
    # the effect's own signature must be where the residuals have it: the part of its gain that its signature
    # moved by a few samples explains again in what it leaves is an error of other dynamics it stands in for
    sig = t.signature or {}
    timing = bool(set(t.effects) & set(TIMING_EFFECTS))  # a timing's signature is a shift in time by nature
    misplaced = 0.0
    if not timing and sig.get("p", 1.0) < alpha:
        misplaced = min(max(float(sig.get("misplaced", 0.0)), 0.0), 1.0)
    if misplaced > 1.0 - min_share:
        reasons.append(f"its own signature is misplaced: led or lagged a few samples it explains again "
                       f"{100 * misplaced:.0f} % of its gain in what it leaves (an error of other dynamics)")
    # the majority: a name accounts for the larger part of the error the model makes over the records, unless
    # what it leaves is adequate (the rest is noise)
    if judge_share == "always" or (judge_share == "unless_adequate" and not t.state.adequate):
        if not t.share >= min_share:
            reasons.append(f"removes only {100 * t.share:.0f} % of the simulation misfit above the noise"
                           + ("" if judge_share == "always" else " and leaves the model inadequate"))
    t.accepted = not reasons
    t.reason = "; ".join(reasons)
