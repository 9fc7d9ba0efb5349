"""The diagnosis: nominal fit, screen, extensions judged and accepted greedily, verdict."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from fpdd.errors import DataError, ParameterError
from twin.estimation.fit import noise_levels, resolve_outputs
from twin.estimation.threads import one_blas_thread
from twin.models import Model, get_model
from twin.models.base import DEFAULT_TIMING, Timing
from twin.params import ParameterSet, check_names
from twin.record import Record
from twin.estimation.diagnose.constants import AICC_TIE, ALPHA, MIN_SHARE, PRUNE, TIMING_EFFECTS
from twin.estimation.diagnose.data import _Data, holm
from twin.estimation.diagnose.adequacy import _gain, _lr
from twin.estimation.diagnose.results import Diagnosis, ScreenRow, Trial
from twin.estimation.diagnose.screen import screen
from twin.estimation.diagnose.naming import _verdict, share_rule
from twin.estimation.diagnose.extend import _fit_state, _try, _try_pair
from twin.estimation.diagnose.timing import _try_timing


# --- the diagnosis ----------------------------------------------------------------------------
@one_blas_thread
def diagnose(model: Model | str, records: Sequence[Record] | Record, outputs: Sequence[str] | None = None,
             free: Sequence[str] | None = None, base: ParameterSet | None = None,
             candidates: Sequence[str] | None = None, holdout: float = 0.25, alpha: float = ALPHA,
             min_share: float = MIN_SHARE, max_effects: int = 3, max_fits: int = 3,
             noise: Mapping[str, float] | None = None, drive: str = "auto", seed: int = 0,
             progress: Callable[[str], None] | None = None, timing: Timing | None = None,
             test_timing: bool = True) -> Diagnosis:
    """Fit the nominal model, judge its one-step prediction errors, screen the catalogue (and the loop's
    timing), extend greedily, measure the gain (module docstring).

    Candidate models may be unstable on the data (a trial start or fitted extension whose simulation
    diverges); their costs come out infinite and they are rejected, so floating-point overflow inside the
    diagnosis is expected and not reported as a warning.
    """
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        return _diagnose(model, records, outputs, free, base, candidates, holdout, alpha, min_share,
                         max_effects, max_fits, noise, drive, seed, progress, timing or DEFAULT_TIMING,
                         test_timing)


def _diagnose(model, records, outputs, free, base, candidates, holdout, alpha, min_share, max_effects,
              max_fits, noise, drive, seed, progress, timing, test_timing) -> Diagnosis:
    t0 = time.perf_counter()
    model = get_model(model) if isinstance(model, str) else model
    if isinstance(records, Record):
        records = [records]
    records = list(records)
    if not records:
        raise DataError("diagnose needs at least one record")
    if not 0.0 < holdout < 0.9:
        raise ParameterError(f"holdout (={holdout}) must be a fraction in (0 ... 0.9) of each record")
    if not 0.0 < alpha < 0.5:
        raise ParameterError(f"alpha (={alpha}) must be a significance level in (0 ... 0.5)")
    base = base or model.params()
    outputs = resolve_outputs(model, records, outputs)
    for r in records:
        r.require(outputs, "diagnose")
        if len(r) < 200:
            raise DataError(f"{r.name}: {len(r)} samples; diagnose needs at least 200 per record")
        timing.ticks(r.dt)  # a controller rate must be a whole multiple of every record's rate
    free = tuple(free or getattr(model, "PHENOMENOLOGICAL", ()))
    sigma = noise_levels(model, records, outputs, noise)
    n_fit = [int(round(len(r) * (1.0 - holdout))) for r in records]
    data = _Data(model, records, n_fit, outputs, sigma, drive, timing, alpha, seed)
    catalogue = [e for e in (candidates or model.EFFECTS) if e not in base.effects]
    check_names(model.EFFECTS, catalogue, f"effect of {model.name}")
    # an effect that free parameters mimic cannot be told from them: not screened, said in the verdict
    mimicked = {e: model.EFFECTS[e].mimicry for e in catalogue
                if set(model.EFFECTS[e].mimicked_by) & set(free)}
    catalogue = [e for e in catalogue if e not in mimicked]
    # the loop's timing is a candidate: a controller's rate, or for an open loop the input's intersample rule
    closed = model.drive_signal(records[0].signals, drive)[0] == "x_ref"
    timing_candidate = test_timing and (candidates is None) and (closed or not model.CLOSED_LOOP)
    say = progress or (lambda _m: None)

    say(f"fitting the nominal model ({', '.join(free)}) on {sum(n_fit)} samples, {timing.label}")
    nominal = _fit_state(data, base, free, {}, 8, seed, timing)
    # every effect's size from the record and the fitted nominal model (units and scale are the record's)
    data.typical = model.effect_typicals(nominal.params, records[0].signals, nominal.predicted[0], records[0].dt)
    say(f"nominal: noise model AR orders {nominal.noise.orders if nominal.noise else '-'}; one-step prediction "
        f"errors {'adequate' if nominal.adequate else 'NOT adequate'}")
    cur = nominal
    path = [nominal]
    screens: list[list[ScreenRow]] = []
    trials_all: list[list[Trial]] = []
    causes: list[str] = []
    gains: dict[str, dict] = {}
    for _ in range(max_effects):
        # a special case of a named effect is inside it already (Effect.generalises)
        inside = {g for e in cur.effects for g, _m in model.EFFECTS[e].generalises}
        cands = [e for e in catalogue if e not in cur.effects and e not in inside]
        if cur.noise is None or (not cands and not timing_candidate):
            break
        scr = screen(data, cur, cands) if cands else []
        screens.append(scr)
        say("screen: " + ", ".join(f"{r.effect} LM={r.lm:.3g} p_Holm={r.p_adjusted:.2g}" for r in scr[:4]))
        promising = [r for r in scr if r.p_adjusted < alpha][:max_fits]
        # an effect containing a promising one as its special case is fitted beside it: the two are nested, and
        # the data choose between them at alpha (below), whatever the screen's order
        companions = {r.effect for r in scr if r not in promising
                      and any(g in {q.effect for q in promising} for g, _m in model.EFFECTS[r.effect].generalises)}
        promising += [r for r in scr if r.effect in companions]
        trials: list[Trial] = []
        if timing_candidate and cur is nominal:
            tt = _try_timing(data, cur, seed, min_share, base, say)
            if tt is not None:
                trials.append(tt)
        for row in promising:
            best_lr = max((t.lr for t in trials if t.accepted), default=0.0)
            if row.lm < PRUNE * best_lr and row.effect not in companions:
                say(f"  {row.effect}: not fitted (screen LM {row.lm:.3g} < {PRUNE:g} x LR {best_lr:.4g} of an "
                    "accepted extension)")
                continue
            # from the current estimates (which may have bent to mimic the effect) and from the baseline
            trials.append(_try(data, cur, row, seed, min_share, base))
        # Holm over the catalogue (the timing counts as one more candidate): the trials' LR p-values take the
        # places of their effects' screen p-values; effects not fitted keep theirs
        fitted = {t.effects[0]: t for t in trials}
        pool = [(r.effect, fitted[r.effect].p if r.effect in fitted else r.p_effect) for r in scr]
        for te in TIMING_EFFECTS:
            if te in fitted:
                pool.append((te, fitted[te].p))
        adj = dict(zip([e for e, _ in pool], holm([p for _, p in pool])))
        for t in trials:
            t.p_adjusted = adj.get(t.effects[0], t.p)
            _verdict(t, alpha, min_share, judge_share=share_rule(data, cur))
            say(f"  {t.effect}: LR={t.lr:.4g} p_Holm={t.p_adjusted:.3g} dAICc={t.delta_aicc:.4g} held-out gain "
                f"{100 * t.holdout_gain:.2f}% [{100 * t.gain_interval[0]:.2f}, {100 * t.gain_interval[1]:.2f}] "
                f"share {t.share:.3f} {'accepted' if t.accepted else 'rejected: ' + t.reason}")
        trials_all.append(trials)
        if not trials:
            break
        ok = [t for t in trials if t.accepted]
        if not ok:
            # a pair extends the current model by two effects (not a trial that replaced a special case)
            extends = [t for t in trials if t.effects[0] not in TIMING_EFFECTS
                       and set(cur.effects) <= set(t.state.effects)]
            sig = sorted((t for t in extends if t.p_adjusted < alpha and t.delta_aicc < 0 and t.holdout_gain > 0),
                         key=lambda t: -t.lr)
            if len(sig) == 1:  # its partner may be mimicked by bent nominal parameters when fitted alone
                rest = [t for t in extends if t is not sig[0] and math.isfinite(t.state.wcost)]
                rank = {r.effect: i for i, r in enumerate(scr)}
                rest.sort(key=lambda t: rank.get(t.effects[0], len(rank)))
                sig += rest[:1]
            if len(sig) < 2 or len(causes) + 2 > max_effects:
                break
            a, b = sig[0], sig[1]
            pair, each = _try_pair(data, cur, a, b, seed, min_share, base)
            pair.p_adjusted = min(1.0, pair.p * len(pool))
            _verdict(pair, alpha, min_share, judge_share=share_rule(data, cur))
            say(f"  pair {pair.effect}: LR={pair.lr:.4g} p={pair.p:.3g} dAICc={pair.delta_aicc:.4g} "
                f"held-out gain {100 * pair.holdout_gain:.2f}% share {pair.share:.3f} "
                f"each significant: {each} -> {'accepted' if pair.accepted and each else 'rejected'}")
            if not each and pair.accepted:
                pair.accepted = False
                pair.reason = "one of the two is not significant within the pair"
            trials.append(pair)
            if not pair.accepted:
                break
            for e in pair.effects:
                gains[e] = _gain(cur, pair.state, data) | {"share": pair.share, "pair": pair.effect,
                                                           "p_adjusted": pair.p_adjusted}
                causes.append(e)
            cur = pair.state
            path.append(cur)
            continue
        # nested: an effect and its special case both accepted; the larger one only if the parameters it adds
        # are significant at alpha (its LR against the special case), else the special case
        for t in ok:
            for g, _m in model.EFFECTS[t.effects[0]].generalises if t.effects[0] in model.EFFECTS else ():
                sp = next((u for u in ok if u.effects[0] == g and u.accepted), None)
                if sp is None or not t.accepted:
                    continue
                lr_n, p_n, df_n, _ = _lr(sp.state, t.state, data)
                if p_n < alpha:
                    sp.accepted = False
                    sp.reason = f"contained in {t.effect}, whose {df_n} more parameters are significant (LR {lr_n:.4g})"
                else:
                    t.accepted = False
                    t.reason = (f"its {df_n} parameters beyond {g} are not significant (LR {lr_n:.4g}, p {p_n:.3g} "
                                f">= {alpha:g})")
                say(f"  nested: {t.effect} against {g}: LR {lr_n:.4g} p {p_n:.3g} -> "
                    f"{t.effect if p_n < alpha else g}")
        ok = [t for t in ok if t.accepted]
        # the lowest AICc wins; extensions within AICC_TIE of it are not told apart by the data (an input and an
        # output offset of a linear spring are the same error): the first in the catalogue's order is taken, so
        # the choice does not hang on round-off (the same record in other units names them in the same order)
        low = min(t.delta_aicc for t in ok)
        order = {e: i for i, e in enumerate(list(model.EFFECTS) + list(TIMING_EFFECTS))}
        win = min((t for t in ok if t.delta_aicc <= low + AICC_TIE),
                  key=lambda t: (order.get(t.effects[0], len(order)), t.delta_aicc))
        for t in ok:
            if t is not win:
                t.accepted = False
                t.reason = (f"higher AICc than {win.effect}" if t.delta_aicc > win.delta_aicc + AICC_TIE else
                            f"not told apart from {win.effect} (AICc within {AICC_TIE:g}), which comes first")
        gains[win.effect] = _gain(cur, win.state, data) | {"share": win.share, "p_adjusted": win.p_adjusted}
        replaced = [c for c in causes if c in model.EFFECTS and c not in win.state.effects]
        if replaced:  # a special case the winner contains (Effect.generalises): named by the winner alone
            say(f"  {win.effect} replaces {', '.join(replaced)}, which it contains")
            win.replaces = tuple(replaced)
            causes = [c for c in causes if c not in replaced]
            for c in replaced:
                gains.pop(c, None)
        causes.append(win.effect)
        cur = win.state
        path.append(cur)
    unexplained = not cur.adequate
    return Diagnosis(model.name, causes, unexplained, nominal, cur, path, screens, trials_all, gains, outputs,
                     holdout, time.perf_counter() - t0, records, n_fit, timing=timing, alpha=alpha,
                     not_testable={e: {"mimicked_by": [n for n in model.EFFECTS[e].mimicked_by if n in free],
                                       "why": why} for e, why in mimicked.items()})
