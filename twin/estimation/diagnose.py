"""Diagnose what a simulation gets wrong: name the physical cause, extend the model, measure the gain.

The method (``twin diagnose DATA --model msp25|oscillator``):

1. **Split** every record: the first ``1 - holdout`` (75 %) is fitting data, the
   rest is held out; held-out figures come from simulating the whole record
   with the fitted parameters and scoring only its tail.
2. **Fit the nominal model** (its phenomenological parameters free) by output
   error, under the loop's timing (``--controller``/``--intersample``).
3. **Noise model and one-step-ahead prediction errors** (:mod:`twin.estimation.noise_model`):
   output-error residuals of a closed loop whose controller reads the noisy
   measured displacement are coloured even when the model is exact (the
   sensor noise goes round the loop), and a sensor may itself be coloured.  An
   autoregression per output (order by AIC, raised along the grid while its
   errors stay materially predictable; innovations correlated across outputs)
   is fitted to the residuals on the fitting data; the residuals filtered by
   it are normalised innovations, one-step-ahead prediction errors.  Every
   statistic below is computed on them (Box-Jenkins style: output-error model,
   fitted noise model).
4. **Adequacy** of a model: its innovations are white (Ljung-Box per output,
   degrees of freedom reduced by the autoregression's order; a significant
   dependence counts only when the errors' own past predicts over 1 % of
   their variance beyond chance, ``WHITE_R2``) and the held-out
   innovations are no larger than those on the fitting data (a drift, or an
   error the fit bent the parameters around, shows there), and they do not
   follow the exogenous drive (``x_ref``; regressed on its increments at lags
   0-50 ms: significant, and explaining over 1 % of an output's innovation
   variance beyond chance) - an autoregression can soak up a deterministic
   error such as a resonance, an exogenous drive it cannot explain away;
   Bonferroni over the tests.  Loop noise and coloured sensor noise are not
   model errors.
5. **Screen the catalogue** with a score (Lagrange-multiplier) test in one
   batched simulation per record: the model at the estimate, at a step of
   every free parameter (Jacobian ``J``) and at probes of every candidate
   effect (a small step of each of its parameters away from neutral, plus
   secants to a few plausible magnitudes where the derivative at neutral
   vanishes; a limit such as the spool's stroke is probed at levels the
   record reaches: quantiles of the limited state's magnitude).  Residuals, ``J`` and the probe sensitivities ``s`` are
   whitened by the current noise model; with ``s_perp`` = ``s`` with the span
   of ``J`` projected out and ``g_t`` the per-sample score ``s_perp r``,

       LM = (sum g_t)^2 / (N * long-run variance of g)      (Newey-West),

   chi-square(1) when the effect is absent, even if whitening left some
   colour.  An effect's p-value is its best probe's times its number of
   probes; the effects' p-values are Holm-corrected over the catalogue.  One-
   sided effects (a friction, a stroke limit) score 0 when the residual
   points the wrong way.  Nothing passes: nothing is fitted.  An effect that
   a free nominal parameter mimics (``Effect.mimicked_by``: a position sensor
   gain is a Cd change while Cd is free) is not screened; the diagnosis says
   so (``not_testable``) and how to test it (hold that parameter at a
   commissioned value).
6. **The loop's timing** (``controller_rate``): the alternative timings (a
   continuous controller, a digital one 2, 5, 10 times faster than the log)
   are simulated at the current estimates; the best is refitted, then the
   continuous one from its estimates (the nominal estimates are bent to the
   assumed timing, so the closest alternative scores best at them even when
   the loop is analog), then any other that scores lower at the best refit's
   estimates; the best refit is judged by the same tests as an effect,
   counted as one parameter.
7. **Fit the promising extensions** (nominal free parameters plus the
   effect's own) and **decide**: accepted when its likelihood-ratio test on
   the whitened residuals (``LR = C0 - C1``, the innovations' sums of squares
   under the current noise model, chi-square(df)) is significant after a
   Holm correction over the catalogue, its (whitened) AICc is lower, and its
   held-out gain - the relative reduction of the held-out innovations' sum of
   squares - exceeds its moving-block bootstrap spread (the lower end of its
   95 % interval above zero).  While the current model is not adequate the
   extension must also remove at least ``min_share`` of the current model's
   excess misfit (an effect soaking up a little of an out-of-catalogue error
   is not named) or leave a model that is adequate, and its parameters must
   lie within 10 times the effect's
   typical deviation from neutral.  Candidates whose screen LM is below a
   tenth of an accepted extension's LR are not fitted.  The lowest AICc
   among accepted ones wins; the screen is
   run again on the extended model (greedy).  When no single effect passes
   but two are significant, the pair is fitted together and judged the same
   way, each significant within the pair.
8. **Verdict**: ``causes`` are the accepted effects; ``unexplained`` is true
   when the final model is not adequate (step 4): the residual signature is
   shown instead of a forced name.

:func:`diagnose` returns a :class:`Diagnosis`; the command line is
:mod:`twin.commands.diagnose`, the plots :func:`twin.reports.plots.diagnosis_plots`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats

from replay.jsonio import finite_or_none
from twin.errors import DataError, ParameterError
from twin.estimation.fit import FitResult, fit, noise_levels, resolve_outputs
from twin.models import Model, get_model
from twin.models.base import DEFAULT_TIMING, INTERSAMPLE, Timing
from twin.estimation.noise_model import ORDERS as NOISE_ORDERS
from twin.estimation.noise_model import (NoiseModel, bartlett_lag, block_bootstrap, fit_noise_model,
                                         long_run_variance)
from twin.params import Effect, ParameterSet, check_names
from twin.record import Record, as_logged
from twin.estimation.residuals import ResidualAnalysis, analyse, ljung_box
from twin.models.simulate import DEFAULT_NOISE  # noqa: F401  (the plots' residual scale)

#: significance level of the screen, the LR test and the adequacy tests (family-wise, after Holm/Bonferroni)
ALPHA = 1e-3
#: share of the current model's excess misfit an extension must remove to be named (while not adequate)
MIN_SHARE = 0.5
#: multiples of an effect's typical magnitude used as secant probes in the screen
SECANTS = (0.3, 1.0, 3.0)
#: multiples of a secondary parameter's typical value tried in the screen (e.g. Stribeck velocity)
SECONDARY = (1.0 / 3.0, 1.0, 3.0)
#: limit parameters (a clipping effect) and the model state they clip: probed at levels the record reaches
LIMITS = {"xs_max": "xs"}
#: quantiles of the limited state's magnitude used as a limit's probe levels
LIMIT_QUANTILES = (0.75, 0.9, 0.97, 0.995)
#: relative tolerance of the diagnosis's fits (cost, step, gradient): the LR tests need the cost to a small
#: fraction of one whitened unit, not to machine precision
FIT_TOL = 1e-8
#: a candidate whose screen LM is below this fraction of an accepted trial's LR is not fitted in that round
#: (its linearised gain cannot reach the accepted one's AICc; the margin covers nonlinear effects)
PRUNE = 0.1
#: a named effect's parameters lie within this multiple of the effect's typical deviation from neutral
PLAUSIBLE = 10.0
#: lags of the drive in the exogeneity test of the one-step prediction errors
EXO_LAGS = 50
#: share of an output's innovation variance the drive's history must explain (beyond chance) for a
#: significant dependence to make a model inadequate: an error outside the catalogue that the noise model
#: soaked up (a resonance) is over it, a slight mismatch of formulation is not
EXO_R2 = 0.01
#: the share of a one-step prediction error's variance its own past may predict beyond chance (``(Q - df) / n``
#: of the Ljung-Box test, about the sum of the squared autocorrelations less what white errors give) before
#: the remaining dependence makes a model inadequate: a loop noise that a finite autoregression leaves
#: slightly coloured is significant yet immaterial (healthy reference records: 0.2-0.6 %; a catalogue error
#: leaves far more, and a resonance or a drift is caught by the drive or the held-out test)
WHITE_R2 = 0.01
#: held-out / fitting mean squared simulation error above which a significant increase makes a model
#: inadequate (healthy reference records: 0.85-1.13; a pressure sensor drifting 0.2 MPa over 8 s: 3.9)
SIM_HOLDOUT = 1.1
#: times a noise model's order may be raised (one step along ``ORDERS`` each) while its innovations keep a
#: material dependence
NOISE_RAISE = 2
#: lags of the Ljung-Box test beyond the noise model's order
LB_LAGS = 25
#: two-sided coverage of the held-out gain's bootstrap interval; its lower end must be above zero
GAIN_COVERAGE = 0.95
#: bootstrap replicates of the held-out gain
N_BOOT = 1000
#: the pseudo-effect naming a wrong loop timing, and the controller rates tried (multiples of the log rate)
CONTROLLER_RATE = "controller_rate"
RATE_MULTIPLES = (2, 5, 10)
#: the pseudo-effect naming a wrong intersample rule of an open loop's logged input (no controller to time)
INPUT_INTERSAMPLE = "input_intersample"
TIMING_EFFECTS = (CONTROLLER_RATE, INPUT_INTERSAMPLE)
#: regime variable against which each effect's signature is plotted
SIGNATURE_AXIS = {
    "viscous_friction": "velocity", "stribeck_friction": "velocity", "laminar_leakage": "dp",
    "spool_deadband": "spool_opening", "valve_null_bias": "spool_opening", "supply_pressure_droop": "velocity",
    "specimen_stiffness": "position", "sensor_delay": "velocity", "entrained_air": "dp",
    "spool_saturation": "spool_opening", "coulomb_friction": "velocity", "cubic_stiffness": "position",
    "input_delay": "velocity", "position_sensor_gain": "position", "pressure_sensor_offset": "dp",
    "supply_line_loss": "velocity", "pressure_sensor_lag": "dp", "input_offset": "position",
    "output_offset": "position",
    CONTROLLER_RATE: "velocity", INPUT_INTERSAMPLE: "velocity",
}


#: SI units of the outputs, for plot labels
UNITS = {"x": "m", "pA": "Pa", "pB": "Pa", "y": "m"}
#: effects whose signature is best seen as a residual force (A times the pressure-difference residual)
FORCE_EFFECTS = ("viscous_friction", "stribeck_friction", "specimen_stiffness")


# --- data --------------------------------------------------------------------------------
@dataclasses.dataclass
class _Data:
    model: Model
    records: list[Record]
    n_fit: list[int]
    outputs: tuple[str, ...]
    sigma: dict[str, float]
    drive: str
    timing: Timing = DEFAULT_TIMING
    alpha: float = ALPHA
    seed: int = 0
    exo_cache: dict = dataclasses.field(default_factory=dict, repr=False)
    #: each effect's typical size on these records (from the fitted nominal model; the catalogue's until then)
    typical: dict[str, tuple[float, ...]] = dataclasses.field(default_factory=dict)

    def effect(self, name: str) -> Effect:
        """The catalogue's effect ``name`` with its typical size on these records."""
        E = self.model.EFFECTS[name]
        t = self.typical.get(name)
        return dataclasses.replace(E, typical=tuple(t)) if t is not None else E

    def scales(self) -> dict[str, float]:
        """The order of magnitude of every effect parameter on these records (a fit's coordinate scale)."""
        out = {}
        for name in self.model.EFFECTS:
            E = self.effect(name)
            for n, neutral, t in zip(E.names, E.neutral, E.typical):
                out[n] = abs(t - neutral) or abs(t)
        return out

    @property
    def parts(self) -> list[Record]:
        return [r.slice(0, n) for r, n in zip(self.records, self.n_fit)]

    def drives(self, records: Sequence[Record] | None = None) -> list[tuple[str, np.ndarray]]:
        return [self.model.drive_signal(r.signals, self.drive) for r in (records or self.records)]

    def init(self, ps: ParameterSet) -> list[dict]:
        from twin.estimation.fit import initial_from_data

        return [initial_from_data(self.model, r, ps) for r in self.records]


def _timing_label(t: Timing) -> str:
    return t.label


@dataclasses.dataclass
class ModelState:
    """One model of the greedy path: parameters, timing, fit, noise model, held-out figures, adequacy."""

    params: ParameterSet
    free: tuple[str, ...]
    fit: FitResult
    predicted: list[dict[str, np.ndarray]] = dataclasses.field(repr=False)  # whole records
    timing: Timing = DEFAULT_TIMING
    holdout: dict = dataclasses.field(default_factory=dict)
    analysis: ResidualAnalysis | None = None          # output-error residuals on the fitting data (first record)
    noise: NoiseModel | None = None                    # fitted to this model's residuals on the fitting data
    adequacy: dict = dataclasses.field(default_factory=dict)
    excess: float = 0.0                               # weighted residual power above the noise floor
    wcost: float = 0.0                                # innovations' sum of squares on the fitting data
    n_w: int = 0                                      # number of innovations (samples x outputs)

    @property
    def effects(self) -> tuple[str, ...]:
        return self.params.effects

    @property
    def adequate(self) -> bool:
        return bool(self.adequacy.get("adequate", False))

    @property
    def converged(self) -> bool:
        return bool(self.fit.success)

    def param_table(self, names: Sequence[str] | None = None) -> dict:
        out = {}
        for n in (names or self.free):
            spec = self.params.spec(n)
            v = self.fit.estimate.get(n, self.params[n])
            out[n] = {"value": v, "std": self.fit.std.get(n, 0.0), "std_white": self.fit.std_white.get(n),
                      "unit": spec.unit, "shown": spec.show(v)}
        return out

    def summary(self) -> dict:
        return {"effects": list(self.effects), "timing": self.timing.to_dict(), "params": self.param_table(),
                "aicc": self.fit.aicc, "aic": self.fit.aic, "loglik": self.fit.loglik, "n_par": self.fit.n_par,
                "fit_pct": self.fit.fit_pct, "nrmse": self.fit.nrmse, "converged": self.fit.success,
                "fit_message": self.fit.message,
                "holdout": self.holdout, "innovations_ss": self.wcost, "n_innovations": self.n_w,
                "noise_model": self.noise.summary() if self.noise is not None else None,
                "adequacy": self.adequacy,
                "residuals": self.analysis.summary() if self.analysis is not None else None}


@dataclasses.dataclass
class ScreenRow:
    """Score-test result of one candidate effect."""

    effect: str
    lm: float
    p: float                   # chi-square(1) p-value of the best probe column (HAC, whitened)
    p_effect: float            # times the effect's number of probes (Bonferroni within the effect)
    p_adjusted: float          # Holm over the catalogue
    probe: str                 # "derivative[:param]" or "secant@<value>"
    estimate: dict[str, float]  # one-step estimate of the effect's parameters (a fit start)
    share: float               # share of the excess misfit the linearised effect would remove

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class Trial:
    """A fitted extension of the current model by one or more effects (or another timing), and how it compares."""

    effects: tuple[str, ...]
    state: ModelState
    lr: float
    p: float
    df: int
    delta_aicc: float
    holdout_gain: float        # relative reduction of the held-out innovations' sum of squares
    gain_interval: tuple[float, float]   # block-bootstrap interval (GAIN_COVERAGE)
    share: float               # share of the current model's excess misfit removed
    p_adjusted: float = 1.0    # Holm over the catalogue
    implausible: list[str] = dataclasses.field(default_factory=list)  # parameters beyond PLAUSIBLE
    accepted: bool = False
    reason: str = ""
    diverged: bool = False     # its fit or its simulation of the record went non-finite

    @property
    def effect(self) -> str:
        return "+".join(self.effects)

    def params(self) -> dict:
        out = {}
        for e in self.effects:
            out.update(_effect_params(self.state, e))
        return out

    def to_dict(self) -> dict:
        return {"effect": self.effect, "effects": list(self.effects), "lr": self.lr, "p": self.p,
                "p_adjusted": self.p_adjusted, "df": self.df, "delta_aicc": self.delta_aicc,
                "holdout_gain": self.holdout_gain, "holdout_gain_interval": list(self.gain_interval),
                "share": self.share, "converged": self.state.converged, "accepted": self.accepted,
                "reason": self.reason, "implausible": list(self.implausible), "diverged": self.diverged,
                "params": self.params()}


def _effect_params(state: ModelState, effect: str) -> dict:
    """The parameters of ``effect`` in ``state`` (for ``controller_rate``: the timing)."""
    if effect in TIMING_EFFECTS:
        t = state.timing
        return {"controller": {"value": t.controller, "rate_hz": t.rate_hz, "intersample": t.intersample,
                               "shown": t.label, "unit": "Hz", "std": None}}
    E = get_model(state.params.model).EFFECTS[effect]
    return state.param_table(E.names)


@dataclasses.dataclass
class Diagnosis:
    """What :func:`diagnose` found: causes, whether something is left unexplained, the models and gains."""

    model: str
    causes: list[str]
    unexplained: bool
    nominal: ModelState
    final: ModelState
    path: list[ModelState]                 # nominal, then one state per accepted step
    screens: list[list[ScreenRow]]
    trials: list[list[Trial]]
    gains: dict[str, dict]                 # per cause: gain of the step that added it
    outputs: tuple[str, ...]
    holdout: float
    time_s: float
    records: list[Record] = dataclasses.field(repr=False, default_factory=list)
    n_fit: list[int] = dataclasses.field(repr=False, default_factory=list)
    plots: list[str] = dataclasses.field(default_factory=list)
    timing: Timing = DEFAULT_TIMING        # the timing assumed (given)
    alpha: float = ALPHA
    #: effects not tested because free parameters mimic them: effect -> {"mimicked_by": [...], "why": text}
    not_testable: dict[str, dict] = dataclasses.field(default_factory=dict)

    def __repr__(self) -> str:
        """One line: verdict, causes, the records' count and time (``text()`` has the whole story)."""
        return (f"Diagnosis(model={self.model!r}, verdict={self.verdict()!r}, causes={list(self.causes)}, "
                f"records={len(self.records)}, time_s={self.time_s:.1f})")

    def save(self, path: str) -> str:
        """Write the extended parameter set (as ``twin diagnose --save``: JSON for twin fit / the tracker)."""
        from replay import jsonio

        return jsonio.write(path, self.extended_params())

    def report(self, out_dir: str = "diagnosis_report") -> str:
        """Write the HTML diagnosis report with its plots (as ``twin diagnose --report``); returns its path."""
        import os

        from replay import jsonio
        from twin.reports import diagnose_report
        from twin.reports.plots import diagnosis_plots

        self.plots = diagnosis_plots(self, out_dir)
        jsonio.write(os.path.join(out_dir, "extended_params.json"), self.extended_params())
        jsonio.write(os.path.join(out_dir, "diagnosis.json"), self.to_dict())
        return diagnose_report(self, out_dir)

    def effect_params(self, effect: str) -> dict:
        return _effect_params(self.final, effect)

    def extended_params(self) -> dict:
        """The extended model as JSON usable by ``twin fit`` and the tracker (effects by name + values)."""
        ps = self.final.params
        return {"model": self.model, "effects": list(ps.effects), "params": ps.as_dict(),
                "std": dict(self.final.fit.std), "timing": self.final.timing.to_dict(),
                "set": ",".join(f"{k}={v:.10g}" for k, v in ps.as_dict().items()
                                if k in self.final.free),
                "free": list(self.final.free)}

    def verdict(self) -> str:
        if self.causes and self.unexplained:
            return "partly explained"
        if self.causes:
            return "explained"
        return "unexplained" if self.unexplained else "adequate"

    def to_dict(self) -> dict:
        """Strict-JSON-ready dictionary (non-finite numbers become None)."""
        return finite_or_none({
            "model": self.model,
            "verdict": self.verdict(),
            "causes": list(self.causes),
            "unexplained": bool(self.unexplained),
            "timing_assumed": self.timing.to_dict(),
            "timing_final": self.final.timing.to_dict(),
            "effects": {c: {"params": self.effect_params(c), "gain": self.gains[c]} for c in self.causes},
            "nominal": self.nominal.summary(),
            "extended": self.final.summary() if self.causes else None,
            "overall_gain": _gain(self.nominal, self.final) if self.causes else None,
            "extended_params": self.extended_params(),
            "screens": [[row.to_dict() for row in s] for s in self.screens],
            "trials": [[t.to_dict() for t in ts] for ts in self.trials],
            "signature": (self.final.analysis.summary() | {"adequacy": self.final.adequacy}
                          if self.unexplained and self.final.analysis else None),
            "not_testable": self.not_testable,
            "diverged": [t.effect for ts in self.trials for t in ts if t.diverged],
            "holdout_fraction": self.holdout,
            "alpha": self.alpha,
            "outputs": list(self.outputs),
            "time_s": self.time_s,
            "plots": list(self.plots),
        })

    def text(self) -> str:
        lines = [f"model {self.model} ({self.timing.label}): nominal fit of {', '.join(self.nominal.free)} "
                 f"on the first {100 * (1 - self.holdout):.0f} % of {len(self.records)} record(s)"]
        lines.append(self.nominal.fit.table())
        lines.append("nominal residuals (fitting data, output error):")
        lines.append(self.nominal.analysis.text() if self.nominal.analysis else "  -")
        lines.append(_adequacy_text(self.nominal))
        for i, (scr, trials) in enumerate(zip(self.screens, self.trials)):
            against = ", ".join(self.path[min(i, len(self.path) - 1)].effects) or "the nominal model"
            lines.append(f"screen {i + 1} (score test on one-step prediction errors, against {against}):")
            for row in scr[:6]:
                lines.append(f"  {row.effect:<22} LM={row.lm:11.4g} p_Holm={row.p_adjusted:9.3g} "
                             f"share~{row.share:6.3f} ({row.probe})")
            if not any(r.p_adjusted < self.alpha for r in scr):
                lines.append(f"  nothing passes the screen at {self.alpha:g} (Holm): no extension fitted")
            for t in trials:
                lo, hi = t.gain_interval
                lines.append(f"  fitted {t.effect:<18} LR={t.lr:10.4g} p_Holm={t.p_adjusted:9.3g} "
                             f"dAICc={t.delta_aicc:10.4g} held-out gain={100 * t.holdout_gain:7.2f}% "
                             f"[{100 * lo:.2f}, {100 * hi:.2f}] share={t.share:6.3f} "
                             f"{'' if t.state.converged else '(fit NOT converged) '}"
                             f"-> {'ACCEPTED' if t.accepted else 'rejected'} {t.reason}")
        if self.causes:
            lines.append(f"causes: {', '.join(self.causes)}")
            for c in self.causes:
                g = self.gains[c]
                lo, hi = g["holdout_gain_interval"]
                lines.append(f"  {c}: LR={g['lr']:.4g} (df {g['df']}) p_Holm={g['p_adjusted']:.3g} "
                             f"dAICc={g['delta_aicc']:.4g} held-out gain {100 * g['holdout_gain']:.2f}% "
                             f"[{100 * lo:.2f}, {100 * hi:.2f}]")
                for p, v in self.effect_params(c).items():
                    if c in TIMING_EFFECTS:
                        lines.append(f"    timing     {v['shown']} (assumed: {self.timing.label})")
                        continue
                    spec = self.final.params.spec(p)
                    std = v["std"]
                    lines.append(f"    {p:<10} {v['shown']:>18} +/- "
                                 f"{spec.show(std) if std is not None and math.isfinite(std) else 'n/a'}")
                for o in self.outputs:
                    b, a = g["holdout"]["before"][o], g["holdout"]["after"][o]
                    lines.append(f"    held-out {o:<3} Fit {b['fit_pct']:8.3f}% -> {a['fit_pct']:8.3f}%   "
                                 f"NRMSE {b['nrmse']:.4g} -> {a['nrmse']:.4g}")
        else:
            lines.append("causes: none")
        if self.unexplained:
            left = "after the extension " if self.causes else ""
            lines.append(f"UNEXPLAINED: the one-step prediction errors are not adequate {left}and no catalogue "
                         "effect explains what is left; residual signature:")
            lines.append(_adequacy_text(self.final))
            lines.append(self.final.analysis.text() if self.final.analysis else "  -")
        elif not self.causes:
            lines.append("the nominal model is adequate (one-step prediction errors white and consistent on "
                         "held-out data; output-error colour is the noise model's)")
        for e, v in self.not_testable.items():
            lines.append(f"not tested: {e} (free {', '.join(v['mimicked_by'])} mimics it): {v['why']}")
        for p in self.plots:
            lines.append(f"plot: {p}")
        return "\n".join(lines)


def _adequacy_text(st: ModelState) -> str:
    a = st.adequacy
    if not a:
        return "  adequacy: -"
    parts = [f"{o}: LB p={v['p']:.3g}, past predicts {100 * v.get('r2', 0.0):.2g} % "
             f"({100 * v.get('r2_excess', 0.0):.2g} % beyond chance, AR {v['ar_order']})"
             for o, v in a["whiteness"].items()]
    h = a["holdout"]
    parts.append(f"held-out/fitting innovation power {h['ratio']:.3g} (p={h['p']:.3g})")
    sim = a.get("simulation_holdout") or {}
    if sim:
        parts.append("held-out/fitting simulation error power " + ", ".join(
            f"{o} {v['ratio']:.3g} (p={v['p']:.3g}){' WORSE' if v.get('worse') else ''}" for o, v in sim.items()))
    x = a.get("exogenous")
    if x:
        parts.append(f"drive explains up to {100 * x['r2']:.1f} % of an output's innovations "
                     f"({100 * x['r2_excess']:.1f} % beyond chance, p={x['p']:.3g})")
    return (f"  one-step prediction errors ({'adequate' if a['adequate'] else 'NOT adequate'}): "
            + "; ".join(parts))


# --- helpers -------------------------------------------------------------------------------
def _simulate(data: _Data, ps: ParameterSet, timing: Timing) -> list[dict[str, np.ndarray]]:
    """Whole-record predictions of ``ps`` (outputs and inputs), started where the data start."""
    model = data.model
    P = model.vector(ps)[None, :]
    out = []
    for rec, (name, drive), init in zip(data.records, data.drives(), data.init(ps)):
        S0 = model.initial_state(P, init)
        sim = model.simulate_batch(P, name, drive, rec.dt, S0, None, timing)
        d = {o: as_logged(rec, o, sim.outputs[o][0]) if o in rec else sim.outputs[o][0] for o in model.OUTPUTS}
        for k, v in sim.inputs.items():
            d[k] = np.asarray(v)[0] if np.ndim(v) == 2 else np.asarray(v)
        for j, k in enumerate(getattr(model, "STATES", ())):  # the states a limit probe needs (LIMITS)
            if k in LIMITS.values():
                d[f"state:{k}"] = sim.states[0, :, j]
        out.append(d)
    return out


def _blocks(data: _Data, pred: list[dict[str, np.ndarray]], part: str = "fit") -> list[np.ndarray]:
    """Weighted residuals ``[m, T]`` per record: on the fitting part, or on the whole record."""
    out = []
    for r, p, n in zip(data.records, pred, data.n_fit):
        stop = n if part == "fit" else len(r)
        out.append(np.array([(r[o][:stop] - p[o][:stop]) / data.sigma[o] for o in data.outputs]))
    return out


def _innovations(data: _Data, nm: NoiseModel, pred: list[dict[str, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Normalised innovations ``[m, n]`` on the fitting data and on the held-out tails (whole records
    filtered, so the tail's predictor sees the samples before it)."""
    fit_parts, hold_parts = [], []
    for B, n in zip(_blocks(data, pred, "all"), data.n_fit):
        E = nm.whiten(B)
        cut = max(n - nm.order, 0)
        fit_parts.append(E[:, :cut])
        hold_parts.append(E[:, cut:])
    return np.concatenate(fit_parts, axis=1), np.concatenate(hold_parts, axis=1)


def _holdout(data: _Data, pred: list[dict[str, np.ndarray]]) -> dict:
    """Held-out Fit %, NRMSE per output and the weighted squared error, on the records' tails."""
    out: dict = {}
    cost = 0.0
    for o in data.outputs:
        y = np.concatenate([r[o][n:] for r, n in zip(data.records, data.n_fit)])
        yh = np.concatenate([p[o][n:] for p, n in zip(pred, data.n_fit)])
        e = y - yh
        den = float(np.linalg.norm(y - y.mean()))
        out[o] = {"fit_pct": 100.0 * (1.0 - float(np.linalg.norm(e)) / den) if den > 0 else float("nan"),
                  "nrmse": float(np.sqrt(np.mean(e * e)) / np.std(y)) if np.std(y) > 0 else float("nan"),
                  "rms": float(np.sqrt(np.mean(e * e)))}
        cost += float(np.sum((e / data.sigma[o]) ** 2))
    out["weighted_sse"] = cost
    return out


def _excess(data: _Data, pred: list[dict[str, np.ndarray]]) -> float:
    """Weighted residual power above the noise floor on the fitting data (sum over outputs)."""
    total = 0.0
    for B in _blocks(data, pred, "fit"):
        for e in B:
            nz = float(np.std(np.diff(e)) / math.sqrt(2.0))
            total += float(np.sum(e * e)) - e.size * nz * nz
    return max(total, 0.0)


def _whiteness(e: np.ndarray, order: int) -> dict:
    """Ljung-Box test of one output's prediction errors ``e`` at the ``LB_LAGS`` lags beyond its noise model's
    ``order``, and the share of their variance their past predicts, in all (``r2``) and beyond chance
    (``r2_excess``, ``(Q - df) / n``: white errors give ``E Q = df``); ``material`` above ``WHITE_R2``."""
    lb = ljung_box(e, LB_LAGS + order, df=LB_LAGS)
    n_e = max(e.size, 1)
    r2_excess = max(float(lb["Q"]) - float(lb["df"]), 0.0) / n_e
    return {"Q": lb["Q"], "df": lb["df"], "lags": lb["lags"], "p": lb["p"], "ar_order": order,
            "r2": float(lb["Q"]) / n_e, "r2_excess": r2_excess, "material": bool(r2_excess > WHITE_R2)}


def _simulation_holdout(data: _Data, pred: list[dict[str, np.ndarray]]) -> dict:
    """Per output: is the simulation's (output) error larger on the held-out tails than on the fitting data?
    One-sided test of the mean squared weighted error, Newey-West variances with a lag of at least 0.1 s (the
    errors are coloured by the loop noise).  A slow error the noise model follows step by step (a sensor
    drifting during the record) leaves the one-step prediction errors white; the simulation shows it."""
    out = {}
    lag_min = int(round(0.1 / data.records[0].dt))
    blocks = _blocks(data, pred, "all")
    for i, o in enumerate(data.outputs):
        qf = np.concatenate([B[i, :n] ** 2 for B, n in zip(blocks, data.n_fit)])
        qh = np.concatenate([B[i, n:] ** 2 for B, n in zip(blocks, data.n_fit)])
        if qh.size <= 10 or not (np.all(np.isfinite(qf)) and np.all(np.isfinite(qh))):
            out[o] = {"ratio": float("nan"), "z": 0.0, "p": 1.0, "material": False}
            continue
        var = sum(long_run_variance(q - q.mean(), max(bartlett_lag(q), lag_min)) / q.size for q in (qf, qh))
        mf, mh = float(qf.mean()), float(qh.mean())
        z = (mh - mf) / math.sqrt(var) if var > 0 else 0.0
        ratio = mh / mf if mf > 0 else float("inf")
        out[o] = {"ratio": ratio, "z": z, "p": float(stats.norm.sf(z)), "material": bool(ratio > SIM_HOLDOUT)}
    return out


def _adequacy(data: _Data, nm: NoiseModel, E_fit: np.ndarray, E_hold: np.ndarray, exo: dict | None = None,
              sim: dict | None = None) -> dict:
    """Are the one-step prediction errors white, and no larger on held-out data than on fitting data?"""
    white = {o: _whiteness(E_fit[i], int(nm.orders.get(o, nm.order))) for i, o in enumerate(data.outputs)}
    q_fit = np.sum(E_fit * E_fit, axis=0)
    q_hold = np.sum(E_hold * E_hold, axis=0)
    if q_hold.size > 10:
        mf, mh = float(np.mean(q_fit)), float(np.mean(q_hold))
        var = long_run_variance(q_fit - mf) / q_fit.size + long_run_variance(q_hold - mh) / q_hold.size
        z = (mh - mf) / math.sqrt(var) if var > 0 else 0.0
        hold = {"ratio": mh / mf if mf > 0 else float("inf"), "z": z, "p": float(stats.norm.sf(z))}
    else:
        hold = {"ratio": 1.0, "z": 0.0, "p": 1.0}
    sim = sim or {}
    n_tests = len(white) + 1 + (exo is not None) + len(sim)
    ps = [v["p"] for v in white.values()] + [hold["p"]] + [v["p"] for v in sim.values()]
    # white: no output's remaining dependence both significant and material; held-out: not worse, neither the
    # one-step prediction errors nor (significantly and materially) the simulation's errors
    for v in sim.values():
        v["worse"] = bool(v["p"] * n_tests < data.alpha and v["material"])
    adequate = (all(v["p"] * n_tests >= data.alpha or not v["material"] for v in white.values())
                and hold["p"] * n_tests >= data.alpha and not any(v["worse"] for v in sim.values()))
    out = {"whiteness": white, "holdout": hold, "simulation_holdout": sim, "n_tests": n_tests}
    if exo is not None:
        # a deterministic error the noise model soaked up: the innovations follow the exogenous drive, by a
        # share of their variance that matters (a slight formulation mismatch is significant on long records)
        exo["dependent"] = bool(exo["p"] * n_tests < data.alpha and exo["r2_excess"] > EXO_R2)
        adequate = adequate and not exo["dependent"]
        out["exogenous"] = exo
        ps.append(exo["p"])
    out.update({"p_min_bonferroni": min(1.0, min(ps) * n_tests), "adequate": bool(adequate)})
    return out


def _exogenous(data: _Data, nm: NoiseModel, pred: list[dict[str, np.ndarray]]) -> dict | None:
    """Are the one-step prediction errors on the fitting data independent of the exogenous drive (the
    reference ``x_ref`` of a closed loop, the logged input of an open one)?  Each output's innovations are
    regressed on the drive's increments at lags ``0 ... EXO_LAGS``; with white innovations and an exogenous
    drive, ``Q = T sum_outputs R^2`` is chi-square(m x rank) under independence.  ``r2`` is the largest share
    of an output's innovation variance the drive's history explains."""
    L = EXO_LAGS
    Es, Xs = [], []
    for rec, n, (_name, drive), p in zip(data.records, data.n_fit, data.drives(), pred):
        start = nm.order + L
        if n - start < 10 * L:
            continue
        key = (id(rec), n, start)
        if key not in data.exo_cache:
            d = np.diff(np.asarray(drive[:n], float), prepend=float(drive[0]))
            sd = float(np.std(d))
            if not sd > 0:
                return None
            d = d / sd
            data.exo_cache[key] = np.stack([d[start - lag: n - lag] for lag in range(L + 1)], axis=1)
        B = np.array([(rec[o][:n] - p[o][:n]) / data.sigma[o] for o in data.outputs])
        E = nm.whiten(B)[:, start - nm.order:]               # samples start ... n - 1
        if not np.all(np.isfinite(E)):
            return None
        Es.append(E)
        Xs.append(data.exo_cache[key])
    if not Es:
        return None
    E = np.concatenate(Es, axis=1)
    E = E - E.mean(axis=1, keepdims=True)
    X = np.concatenate(Xs, axis=0)
    U, sv, _ = np.linalg.svd(X - X.mean(axis=0), full_matrices=False)
    U = U[:, sv > 1e-8 * sv[0]]
    proj = E @ U                                             # [m, rank]
    r2 = np.sum(proj * proj, axis=1) / np.sum(E * E, axis=1)
    T = E.shape[1]
    q = float(T * np.sum(r2))
    df = int(U.shape[1] * E.shape[0])
    # the share explained beyond what chance explains under independence (rank / T per output)
    return {"Q": q, "df": df, "lags": L, "p": float(stats.chi2.sf(q, df)), "r2": float(np.max(r2)),
            "r2_excess": float(np.max(r2) - U.shape[1] / T), "dependent": False}


def _noise_model(data: _Data, blocks: list[np.ndarray], pred) -> tuple[NoiseModel, np.ndarray, np.ndarray]:
    """The noise model of a model's residuals and its innovations on the fitting and held-out data.  Each
    output's autoregression has the order AIC picks, raised (along ``ORDERS``) while its innovations keep a
    significant and material dependence at lags beyond it (Box-Jenkins: a noise model is not done while its
    errors are predictable; AIC alone stops short when many small correlations remain)."""
    nm = fit_noise_model(blocks, data.outputs)
    E_fit, E_hold = _innovations(data, nm, pred)
    for _ in range(NOISE_RAISE):
        low = {}
        for i, o in enumerate(data.outputs):
            order = int(nm.orders.get(o, nm.order))
            w = _whiteness(E_fit[i], order)
            higher = [p for p in NOISE_ORDERS if p > order]
            if w["p"] * len(data.outputs) < data.alpha and w["material"] and higher:
                low[o] = higher[0]
        if not low:
            break
        nm = fit_noise_model(blocks, data.outputs, min_orders={**nm.orders, **low})
        E_fit, E_hold = _innovations(data, nm, pred)
    return nm, E_fit, E_hold


def _state(data: _Data, res: FitResult, free: tuple[str, ...], timing: Timing) -> ModelState:
    pred = _simulate(data, res.params, timing)
    st = ModelState(res.params, free, res, pred, timing)
    st.holdout = _holdout(data, pred)
    st.analysis = analyse(data.model.name, data.records[0], pred[0], data.outputs, 0, data.n_fit[0])
    st.excess = _excess(data, pred)
    blocks = _blocks(data, pred, "fit")
    if all(np.all(np.isfinite(b)) for b in blocks):
        st.noise, E_fit, E_hold = _noise_model(data, blocks, pred)
        st.wcost = float(np.sum(E_fit * E_fit))
        st.n_w = int(E_fit.size)
        st.adequacy = _adequacy(data, st.noise, E_fit, E_hold, _exogenous(data, st.noise, pred),
                                _simulation_holdout(data, pred))
    else:  # a diverged simulation: nothing to judge, never adequate
        st.wcost, st.n_w = float("inf"), 0
        st.adequacy = {"adequate": False, "whiteness": {}, "holdout": {"ratio": float("nan"), "z": float("nan"),
                                                                      "p": 0.0}, "diverged": True}
    return st


def _gain(before: ModelState, after: ModelState, data: _Data | None = None) -> dict:
    """The gain of ``after`` over ``before``: held-out figures, whitened LR, AICc, bootstrap interval."""
    def figures(st: ModelState) -> dict:
        return {o: {k: st.holdout[o][k] for k in ("fit_pct", "nrmse")} for o in st.fit.outputs}

    out: dict[str, Any] = {"holdout": {"before": figures(before), "after": figures(after)},
           "holdout_fit_pct_gain": {o: after.holdout[o]["fit_pct"] - before.holdout[o]["fit_pct"]
                                    for o in after.fit.outputs}}
    if data is not None:
        lr, p, df, d_aicc = _lr(before, after, data)
        g, lo, hi = _holdout_gain(before, after, data)
        out.update({"lr": lr, "p": p, "df": df, "delta_aicc": d_aicc, "holdout_gain": g,
                    "holdout_gain_interval": [lo, hi]})
    return out


def _wcost_under(data: _Data, nm: NoiseModel, pred) -> tuple[float, np.ndarray, np.ndarray]:
    E_fit, E_hold = _innovations(data, nm, pred)
    return float(np.sum(E_fit * E_fit)), E_fit, E_hold


def _n_par(st: ModelState, base_timing: Timing) -> int:
    return st.fit.n_par + (0 if st.timing == base_timing else 1)


def _lr(cur: ModelState, st: ModelState, data: _Data) -> tuple[float, float, int, float]:
    """Whitened LR statistic of ``st`` against ``cur`` (both filtered by ``cur``'s noise model), its
    chi-square p-value, degrees of freedom and the whitened AICc difference."""
    df = max(_n_par(st, data.timing) - _n_par(cur, data.timing), 1)
    if cur.noise is None or not math.isfinite(st.wcost):
        return 0.0, 1.0, df, float("inf")
    c0 = cur.wcost
    c1, _, _ = _wcost_under(data, cur.noise, st.predicted)
    if not math.isfinite(c1):
        return 0.0, 1.0, df, float("inf")
    s2 = c0 / max(cur.n_w, 1)  # ~1: normalised innovations
    lr = max(0.0, (c0 - c1) / s2)
    n = cur.n_w
    k0 = _n_par(cur, data.timing)
    k1 = k0 + df
    aicc = lambda c, k: c / s2 + 2 * k + 2 * k * (k + 1) / max(n - k - 1, 1)  # noqa: E731
    return lr, float(stats.chi2.sf(lr, df)), df, aicc(c1, k1) - aicc(c0, k0)


def _holdout_gain(cur: ModelState, st: ModelState, data: _Data) -> tuple[float, float, float]:
    """Relative reduction of the held-out innovations' sum of squares (``cur``'s noise model) and its
    moving-block bootstrap interval."""
    if cur.noise is None:
        return float("nan"), float("nan"), float("nan")
    _, _, H0 = _wcost_under(data, cur.noise, cur.predicted)
    _, _, H1 = _wcost_under(data, cur.noise, st.predicted)
    q0 = np.sum(H0 * H0, axis=0)
    q1 = np.sum(H1 * H1, axis=0)
    if not (np.all(np.isfinite(q1)) and q0.sum() > 0):
        return float("-inf"), float("-inf"), float("-inf")
    d = q0 - q1
    total0 = float(q0.sum())
    g = float(d.sum()) / total0
    block = max(50, 4 * cur.noise.order, int(round(0.1 / data.records[0].dt)))
    # the ratio resampled as a ratio (numerator and denominator from the same blocks): an error that comes in
    # bursts (a stroke limit reached now and then) makes the denominator as variable as the numerator, and a
    # fixed denominator would put resamples far above 100 % and, mirrored, the interval's lower end below zero
    sums = block_bootstrap(np.stack([d, q0]), block, N_BOOT, data.seed)
    ratio = sums[:, 0] / np.maximum(sums[:, 1], 1e-300)
    a = (1.0 - GAIN_COVERAGE) / 2.0
    lo, hi = np.quantile(ratio, [a, 1.0 - a])  # percentile interval of the resampled ratio
    return g, float(lo), float(hi)


def _fd_step(spec, value: float, typical: float | None) -> float:
    """A relative step: of the value for a parameter that cannot reach zero (a mass of 5e-6 in a circuit's
    units is stepped by its own size, not the catalogue's), else of the larger of value and typical size."""
    ref = abs(value) if spec.lo > 0 else max(abs(value), abs(typical or 0.0))
    h = 1e-6 * max(ref, 1e-300)
    if value + h > spec.hi:
        h = -h
    return h


def holm(pvals: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (same order as given)."""
    m = len(pvals)
    order = sorted(range(m), key=lambda i: pvals[i])
    out = [1.0] * m
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * pvals[i]))
        out[i] = running
    return out


# --- the score-test screen --------------------------------------------------------------
def _probe_params(E) -> list[int]:
    """Indices of an effect's parameters probed by a derivative: those whose typical value differs from the
    neutral one, and those that can move either way from a neutral inside their bounds (an offset of the
    other transducer)."""
    out = [j for j, (n, t) in enumerate(zip(E.neutral, E.typical)) if n != t] or [0]
    for j, s in enumerate(E.params):
        two_sided = s.lo < E.neutral[j] < s.hi
        if j not in out and two_sided and E.typical[j] == E.neutral[j] and s.unit == E.params[out[0]].unit:
            out.append(j)
    return out


def _limit_levels(model: Model, name: str, state: ModelState, data: _Data) -> list[float] | None:
    """Probe levels of a limit parameter (``LIMITS``): quantiles of the limited state's magnitude in the
    current model's simulation of the fitting data, so that a probe clips a plausible share of the record;
    ``None`` for a parameter that is not a limit."""
    key = LIMITS.get(name)
    if key is None or f"state:{key}" not in state.predicted[0]:
        return None
    mag = np.concatenate([np.abs(p[f"state:{key}"][:n]) for p, n in zip(state.predicted, data.n_fit)])
    mag = mag[np.isfinite(mag)]
    if not mag.size or not np.max(mag) > 0:
        return []
    return sorted({float(v) for v in np.quantile(mag, LIMIT_QUANTILES)}, reverse=True)


def screen(data: _Data, state: ModelState, candidates: Sequence[str]) -> list[ScreenRow]:
    """Score-test every candidate effect against ``state`` in one batched simulation per record, on the
    one-step prediction errors of ``state``'s noise model (module docstring)."""
    model = data.model
    ps = state.params
    base = model.vector(ps)
    rows = [base]
    jac_cols = []
    for name in state.free:
        i = model.kernel_index(name)
        spec = ps.spec(name)
        h = _fd_step(spec, base[i], spec.typical)
        v = base.copy()
        v[i] += h
        rows.append(v)
        jac_cols.append(h)
    probes = []  # (effect, label, denominator, values dict, spec of the moved parameter, neutral)
    for eff in candidates:
        E = data.effect(eff)
        movers = _probe_params(E)
        prim = movers[0]
        pspec = E.params[prim]
        neutral, typical = E.neutral[prim], E.typical[prim]
        direction = 1.0 if typical > neutral else -1.0
        sec_idx = [j for j in range(len(E.params)) if j not in movers]
        sec_grid: list[dict[str, float]] = [{}]
        for j in sec_idx:
            s = E.params[j]
            vals = sorted({float(np.clip(E.typical[j] * f, s.lo, s.hi)) for f in SECONDARY})
            sec_grid = [dict(g, **{s.name: v}) for g in sec_grid for v in vals]
        pvals = []
        levels = _limit_levels(model, pspec.name, state, data)
        if levels is None:  # a limit's derivative at neutral (no clipping) vanishes: probed by levels only
            pvals.append(("derivative", pspec, neutral, neutral + direction * 1e-4 * abs(typical - neutral)))
            # secants to a few plausible magnitudes: multiples of the typical deviation from neutral
            levels = [neutral + f * (typical - neutral) for f in SECANTS]
        for lv in levels:
            pv = float(np.clip(lv, pspec.lo, pspec.hi))
            if pv != neutral:
                pvals.append((f"secant@{pspec.show(pv)}", pspec, neutral, pv))
        for j in movers[1:]:  # a parameter that moves either way from neutral (e.g. the other offset)
            s = E.params[j]
            step = 1e-4 * abs(typical - neutral)
            pvals.append((f"derivative:{s.name}", s, E.neutral[j], E.neutral[j] + step))
        for g in sec_grid:
            for label, sp, neut, pv in pvals:
                v = base.copy()
                for j, s in enumerate(E.params):
                    v[model.kernel_index(s.name)] = g.get(s.name, E.neutral[j])
                v[model.kernel_index(sp.name)] = pv
                rows.append(v)
                extra = "" if not g else " " + ",".join(f"{k}={_show(E, k, x)}" for k, x in g.items())
                probes.append((eff, label + extra, pv - neut, dict(g, **{sp.name: pv}), sp, neut))
    P = np.ascontiguousarray(np.array(rows))
    raw = []
    for rec, n, (dname, drive), init in zip(data.records, data.n_fit, data.drives(), data.init(ps)):
        S0 = model.initial_state(P, init)  # each row from its own sensor errors
        sim = model.simulate_batch(P, dname, drive[:n], rec.dt, S0, None, state.timing)
        Y = np.stack([as_logged(rec, o, sim.outputs[o]) / data.sigma[o] for o in data.outputs], axis=1)  # [K, m, n]
        y = np.array([rec[o][:n] / data.sigma[o] for o in data.outputs])
        raw.append(np.concatenate([(y - Y[0])[None], Y[1:] - Y[0]], axis=0))
    nm = _clean_noise_model(data, raw) or state.noise
    assert nm is not None  # the state's model was fitted with its noise model
    _set_noise(data, state, nm)
    R, C = [], []
    for W in raw:
        W = nm.whiten(W)  # [K, m, n - p]
        R.append(W[0])
        C.append(W[1:])
    r2 = np.concatenate(R, axis=1)             # [m, n]
    C2 = np.concatenate(C, axis=2)             # [K-1, m, n]
    m_out, n_t = r2.shape
    r = r2.reshape(-1)
    Cf = C2.reshape(C2.shape[0], -1)
    nj = len(jac_cols)
    J = (Cf[:nj] / np.array(jac_cols)[:, None]).T
    S = Cf[nj:]
    N = r.size
    ok = np.isfinite(r).all() and np.isfinite(J).all()
    Q, _ = np.linalg.qr(J) if nj and ok else (np.zeros((N, 0)), None)
    r_perp = r - Q @ (Q.T @ r)
    sigma2 = float(r_perp @ r_perp) / max(N - nj, 1)
    excess = max(state.excess, math.sqrt(2.0 * N))
    best: dict[str, ScreenRow] = {}
    n_probes: dict[str, int] = {}
    for k, (eff, label, denom, values, pspec, neutral) in enumerate(probes):
        n_probes[eff] = n_probes.get(eff, 0) + 1
        s = S[k] / denom
        lm, delta = 0.0, 0.0
        if np.isfinite(s).all():
            s_perp = s - Q @ (Q.T @ s)
            ss = float(s_perp @ s_perp)
            if ss > 0 and math.isfinite(ss):
                sr = float(s_perp @ r_perp)
                delta = sr / ss
                g = (s_perp * r_perp).reshape(m_out, n_t).sum(axis=0)  # per-sample score, outputs summed
                lrv = long_run_variance(g - delta * (s_perp * s_perp).reshape(m_out, n_t).sum(axis=0))
                lm = sr * sr / (n_t * lrv) if lrv > 0 else 0.0
        one_sided_up = neutral <= pspec.lo
        one_sided_down = neutral >= pspec.hi
        if (one_sided_up and delta <= 0) or (one_sided_down and delta >= 0):
            lm = 0.0
        pval = float(stats.chi2.sf(lm, 1))
        est = dict(values)
        if label.startswith("derivative") and lm > 0:  # one Gauss-Newton step from neutral
            est[pspec.name] = float(np.clip(neutral + delta, pspec.lo, pspec.hi))
        share = min(lm * sigma2 / excess, 10.0)
        row = ScreenRow(eff, lm, pval, 1.0, 1.0, label, est, share)
        if eff not in best or lm > best[eff].lm:
            if eff in best and label.startswith("derivative:"):  # keep both offsets' one-step estimates
                row.estimate = {**best[eff].estimate, **est}
            best[eff] = row
        elif label.startswith("derivative:") and lm > 0:
            best[eff].estimate[pspec.name] = est[pspec.name]
    out = sorted(best.values(), key=lambda row: -row.lm)
    for row in out:
        row.p_effect = min(1.0, row.p * n_probes[row.effect])
    for row, pa in zip(out, holm([row.p_effect for row in out])):
        row.p_adjusted = pa
    return out


def _clean_noise_model(data: _Data, raw: Sequence[np.ndarray]) -> NoiseModel | None:
    """The noise model fitted to the residuals with every screened direction (free parameters and candidate
    effects, linearised) regressed out: an effect in the catalogue is not taken for coloured noise."""
    cleaned = []
    for W in raw:
        r = W[0].reshape(-1)
        X = W[1:].reshape(W.shape[0] - 1, -1).T
        good = np.all(np.isfinite(X), axis=0)
        if not np.all(np.isfinite(r)):
            return None
        X = X[:, good]
        if X.shape[1]:
            nrm = np.linalg.norm(X, axis=0)
            X = X[:, nrm > 0] / nrm[nrm > 0]
            G = X.T @ X
            beta = np.linalg.solve(G + 1e-10 * np.eye(G.shape[0]), X.T @ r)
            r = r - X @ beta
        cleaned.append(r.reshape(W.shape[1], W.shape[2]))
    return fit_noise_model(cleaned, data.outputs)


def _set_noise(data: _Data, state: ModelState, nm: NoiseModel) -> None:
    """Use ``nm`` as ``state``'s noise model from now on (the tests of its extensions are judged under it)."""
    state.noise = nm
    E_fit, _ = _innovations(data, nm, state.predicted)
    state.wcost = float(np.sum(E_fit * E_fit))
    state.n_w = int(E_fit.size)


def _show(E, name: str, value: float) -> str:
    for s in E.params:
        if s.name == name:
            return s.show(value)
    return f"{value:g}"


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
        sim = model.simulate_batch(P, dname, drive[:n], rec.dt, S0, None, timing)
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
    free = cur.free + E.names
    ps = model.params(effects=cur.effects + (row.effect,)).update(cur.params.as_dict())
    # starts: the effect at the screen's estimate, its typical magnitude and close to neutral; the other
    # free parameters at the current estimates (which may have bent to mimic the effect) or as configured.
    # All screened in one batch; the best is refined, the second best too when the first does not pass.
    base_starts = [dict(cur.fit.estimate), {n: configured[n] for n in cur.free if n in configured}]
    ranked = _rank_starts(data, ps, [{**b, **e} for b in base_starts
                                     for e in _effect_starts(data, row.effect, row.estimate)], cur.timing)
    near = dict(cur.fit.estimate)
    for s, n, v in zip(E.params, E.neutral, E.typical):
        near[s.name] = n + 1e-3 * (v - n) if n < v else (n if n == v else min(s.hi, 10.0 * v))
    t: Trial | None = None
    for attempt, start in enumerate(ranked[:n_ranked] + [near]):
        if attempt == n_ranked and t is not None and t.state.fit.cost < cur.fit.cost:
            break
        st = _fit_state(data, ps.update(start), free, start, 1, seed, cur.timing)
        cand = _judge(data, (row.effect,), cur, st, min_share)
        if t is None or cand.state.fit.cost < t.state.fit.cost:
            t = cand
        if t.accepted:
            break
    assert t is not None  # the loop ran at least once (the start near neutral)
    return t


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


def _judge(data: _Data, effects: tuple[str, ...], cur: ModelState, st: ModelState, min_share: float) -> Trial:
    lr, p, df, d_aicc = _lr(cur, st, data)
    hg, lo, hi = _holdout_gain(cur, st, data)
    floor = math.sqrt(2.0 * cur.fit.n_obs)
    share = (cur.fit.cost - st.fit.cost) * 2.0 / max(cur.excess, floor)
    t = Trial(effects, st, lr, p, df, d_aicc, hg, (lo, hi), share, p_adjusted=p)
    t.implausible = _implausible(data, effects, st)
    t.diverged = not (math.isfinite(st.fit.cost) and math.isfinite(st.wcost)
                      and all(np.all(np.isfinite(p[o])) for p in st.predicted for o in data.outputs))
    _verdict(t, data.alpha, min_share, judge_share=not cur.adequate)
    return t


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


def _verdict(t: Trial, alpha: float, min_share: float, judge_share: bool) -> None:
    reasons = ["diverged (its simulation of the record is not finite)"] if t.diverged else []
    if not t.p_adjusted < alpha:
        reasons.append(f"LR p_Holm={t.p_adjusted:.3g} >= {alpha:g}")
    if not t.delta_aicc < 0:
        reasons.append("AICc not lower")
    if not (t.gain_interval[0] > 0):
        reasons.append(f"held-out gain {100 * t.holdout_gain:.2f} % not above its bootstrap spread "
                       f"(interval from {100 * t.gain_interval[0]:.2f} %)")
    if t.implausible:
        reasons.append(f"implausible size ({', '.join(t.implausible)}: over {PLAUSIBLE:g} x the typical)")
    if judge_share and not t.share >= min_share and not t.state.adequate:
        reasons.append(f"explains only {100 * t.share:.0f} % of the excess misfit and leaves the model "
                       "inadequate")
    if not t.state.converged and not reasons:
        pass  # a fit stopped by its evaluation budget can still be better; its figures are what they are
    t.accepted = not reasons
    t.reason = "; ".join(reasons)


# --- the diagnosis ----------------------------------------------------------------------------
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
        cands = [e for e in catalogue if e not in cur.effects]
        if cur.noise is None or (not cands and not timing_candidate):
            break
        scr = screen(data, cur, cands) if cands else []
        screens.append(scr)
        say("screen: " + ", ".join(f"{r.effect} LM={r.lm:.3g} p_Holm={r.p_adjusted:.2g}" for r in scr[:4]))
        promising = [r for r in scr if r.p_adjusted < alpha][:max_fits]
        trials: list[Trial] = []
        if timing_candidate and cur is nominal:
            tt = _try_timing(data, cur, seed, min_share, base, say)
            if tt is not None:
                trials.append(tt)
        for row in promising:
            best_lr = max((t.lr for t in trials if t.accepted), default=0.0)
            if row.lm < PRUNE * best_lr:
                say(f"  {row.effect}: not fitted (screen LM {row.lm:.3g} < {PRUNE:g} x LR {best_lr:.4g} of an "
                    "accepted extension)")
                continue
            # the second-best start (the nominal parameters as configured) is for the first round, where
            # they may have bent to mimic the effect; later rounds extend a model already fitted with them
            trials.append(_try(data, cur, row, seed, min_share, base, n_ranked=2 if cur is nominal else 1))
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
            _verdict(t, alpha, min_share, judge_share=not cur.adequate)
            say(f"  {t.effect}: LR={t.lr:.4g} p_Holm={t.p_adjusted:.3g} dAICc={t.delta_aicc:.4g} held-out gain "
                f"{100 * t.holdout_gain:.2f}% [{100 * t.gain_interval[0]:.2f}, {100 * t.gain_interval[1]:.2f}] "
                f"share {t.share:.3f} {'accepted' if t.accepted else 'rejected: ' + t.reason}")
        trials_all.append(trials)
        if not trials:
            break
        ok = [t for t in trials if t.accepted]
        if not ok:
            sig = sorted((t for t in trials if t.p_adjusted < alpha and t.delta_aicc < 0 and t.holdout_gain > 0
                          and t.effects[0] not in TIMING_EFFECTS), key=lambda t: -t.lr)
            if len(sig) == 1:  # its partner may be mimicked by bent nominal parameters when fitted alone
                rest = [t for t in trials if t is not sig[0] and t.effects[0] not in TIMING_EFFECTS
                        and math.isfinite(t.state.wcost)]
                rank = {r.effect: i for i, r in enumerate(scr)}
                rest.sort(key=lambda t: rank.get(t.effects[0], len(rank)))
                sig += rest[:1]
            if len(sig) < 2 or len(causes) + 2 > max_effects:
                break
            a, b = sig[0], sig[1]
            pair, each = _try_pair(data, cur, a, b, seed, min_share, base)
            pair.p_adjusted = min(1.0, pair.p * len(pool))
            _verdict(pair, alpha, min_share, judge_share=not cur.adequate)
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
        win = min(ok, key=lambda t: t.delta_aicc)
        for t in ok:
            if t is not win:
                t.accepted = False
                t.reason = f"higher AICc than {win.effect}"
        gains[win.effect] = _gain(cur, win.state, data) | {"share": win.share, "p_adjusted": win.p_adjusted}
        causes.append(win.effect)
        cur = win.state
        path.append(cur)
    unexplained = not cur.adequate
    return Diagnosis(model.name, causes, unexplained, nominal, cur, path, screens, trials_all, gains, outputs,
                     holdout, time.perf_counter() - t0, records, n_fit, timing=timing, alpha=alpha,
                     not_testable={e: {"mimicked_by": [n for n in model.EFFECTS[e].mimicked_by if n in free],
                                       "why": why} for e, why in mimicked.items()})
