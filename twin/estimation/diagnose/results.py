"""What a diagnosis found: screen rows, fitted trials and the :class:`Diagnosis` with its text and JSON."""

from __future__ import annotations

import dataclasses
import math


from fpdd.jsonio import finite_or_none
from twin.models import get_model
from twin.models.base import DEFAULT_TIMING, Timing
from twin.record import Record
from twin.estimation.diagnose.constants import ALPHA, TIMING_EFFECTS
from twin.estimation.diagnose.data import ModelState
from twin.estimation.diagnose.adequacy import _gain


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
        """As JSON; the estimate in SI with each parameter's unit in ``estimate_unit``."""
        from twin.models import MODELS
        from twin.units import param_spec

        d = dataclasses.asdict(self)
        d["estimate_unit"] = {}
        for n in self.estimate:  # an effect's parameter: the same name has the same unit in every model
            spec = next((sp for sp in (param_spec(m, n) for m in MODELS) if sp is not None), None)
            d["estimate_unit"][n] = spec.unit if spec is not None else ""
        return d


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
    gain_interval: tuple[float, float]   # GAIN_COVERAGE interval (HAC, delta method)
    share: float               # share of the current model's excess misfit removed
    p_adjusted: float = 1.0    # Holm over the catalogue
    implausible: list[str] = dataclasses.field(default_factory=list)  # parameters beyond PLAUSIBLE
    accepted: bool = False
    reason: str = ""
    diverged: bool = False     # its fit or its simulation of the record went non-finite
    signature: dict = dataclasses.field(default_factory=dict)  # is the effect's own signature in the residuals
    holdout_test: dict = dataclasses.field(default_factory=dict)  # Diebold-Mariano test of the held-out gain
    holdout_p_adjusted: float = 1.0  # its one-sided p-value (judged at HOLDOUT_LEVEL)
    replaces: tuple[str, ...] = ()  # named causes it contains as special cases (Effect.generalises), replaced

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
                "signature": self.signature, "holdout_test": self.holdout_test,
                "holdout_p_adjusted": self.holdout_p_adjusted, "replaces": list(self.replaces),
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
        from fpdd import jsonio

        return jsonio.write(path, self.extended_params())

    def effect_params(self, effect: str) -> dict:
        return _effect_params(self.final, effect)

    def extended_params(self) -> dict:
        """The extended model as JSON usable by ``twin fit`` and the tracker (effects by name + values)."""
        ps = self.final.params
        std = self.final.fit.std
        params: dict[str, dict] = {}
        for s, v in zip(ps.specs, ps.values):  # as twin fit --save: {"value", "unit"[, "std"]} in SI
            params[s.name] = {"value": float(v), "unit": s.unit}
            if s.name in std:
                params[s.name]["std"] = float(std[s.name])
        return {"model": self.model, "effects": list(ps.effects), "params": params,
                "timing": self.final.timing.to_dict(),
                "set": ",".join(f"{s.name}={_typed(s, v)}" for s, v in zip(ps.specs, ps.values)
                                if s.name in self.final.free),
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


def _typed(spec, value: float) -> str:
    """``value`` as typed after ``--set``: in the display unit, e.g. ``wn=43.13512051Hz`` (read back by pint)."""
    unit = spec.display_unit or spec.unit
    text = f"{float(value) * spec.display_scale:.10g}"
    return text if unit in ("1", "") else text + unit.replace(" ", "*")
