"""Is a fitted model adequate for its records?  The diagnosis's adequacy tests on a fit already made.

``twin fit`` asks this after every fit (``--no-adequacy`` skips it): a rig the model cannot represent (a
resonance of the load train, late sensors, an oil temperature the fit is not given) is still fitted, with
``success`` and parameters that absorbed what the model lacks.  The fit's residuals say so: their one-step
prediction errors (the residuals through a fitted autoregression, so loop noise and coloured sensors are not
counted as model errors) follow the exogenous drive, keep a material dependence on their own past, or grow
on the record's held-out tail (:func:`twin.estimation.diagnose.adequacy._adequacy`, the tests and the
family-wise level the diagnosis uses).  Here they are computed at the fit's parameters, which saw the whole
record: the held-out comparison is then a weaker test than the diagnosis's (which fits without the tail), the
whiteness and drive tests are the same.  No refit: one simulation per record and the noise model, a fraction
of the fit's own time.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from fpdd.jsonio import finite_or_none
from twin.estimation.diagnose.adequacy import _state
from twin.estimation.diagnose.constants import ALPHA
from twin.estimation.diagnose.data import _Data
from twin.estimation.fit import FitResult, noise_levels, resolve_outputs
from twin.estimation.threads import one_blas_thread
from twin.models import Model
from twin.models.base import DEFAULT_TIMING, Timing
from twin.record import Record


@one_blas_thread
def fit_adequacy(model: Model, records: Sequence[Record], res: FitResult, outputs: Sequence[str] | None = None,
                 noise: Mapping[str, float] | None = None, drive: str = "auto", timing: Timing | None = None,
                 holdout: float = 0.25, alpha: float = ALPHA) -> dict:
    """The adequacy tests of ``res`` on ``records``: ``{"adequate", "reasons" (one line each), "tests"}``.

    ``reasons`` name each failed test with its figure: an output whose prediction errors follow the drive
    (the share of their variance the drive's recent history explains beyond chance), stay predictable from
    their own past, or are larger on the held-out tail than on the rest."""
    outputs = resolve_outputs(model, records, outputs if outputs is not None else tuple(res.outputs))
    sigma = noise_levels(model, records, outputs, noise if noise is not None else res.noise)
    n_fit = [int(round(len(r) * (1.0 - holdout))) for r in records]
    data = _Data(model, list(records), n_fit, tuple(outputs), sigma, drive, timing or DEFAULT_TIMING, alpha)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        st = _state(data, res, tuple(res.free), data.timing)
    a = st.adequacy or {}
    reasons: list[str] = []
    if a.get("diverged"):
        reasons.append("the fitted model's simulation diverges on the record")
    n_tests = int(a.get("n_tests", 1))
    exo = a.get("exogenous")
    if exo and exo.get("dependent"):
        reasons.append(f"its prediction errors follow the drive: up to {100 * exo['r2_excess']:.1f} % of an "
                       f"output's variance explained by the drive's last {1e3 * exo['lags'] * records[0].dt:.0f} ms "
                       f"beyond chance (p {_p(exo['p'] * n_tests)})")
    for o, w in (a.get("whiteness") or {}).items():
        if w.get("dependent"):
            reasons.append(f"its {o} prediction errors stay predictable from their own past "
                           f"({100 * w['r2_excess']:.1f} % of their variance, p {_p(w['p'] * n_tests)})")
    hold = a.get("holdout") or {}
    if hold.get("worse"):
        reasons.append(f"its prediction errors are {hold['ratio']:.2f} times larger on the record's last "
                       f"{100 * holdout:.0f} % (p {_p(hold['p'] * n_tests)})")
    for o, v in (a.get("simulation_holdout") or {}).items():
        if v.get("worse"):
            reasons.append(f"its {o} simulation error is {v['ratio']:.2f} times larger on the record's last "
                           f"{100 * holdout:.0f} % (p {_p(v['p'] * n_tests)})")
    adequate = bool(a.get("adequate", False))
    if not adequate and not reasons:
        reasons.append("its prediction errors fail the adequacy tests")
    return {"adequate": adequate, "reasons": reasons if not adequate else [], "alpha": alpha,
            "holdout_fraction": holdout, "tests": finite_or_none(a)}


def judge(res: FitResult, model: Model, records: Sequence[Record], drive: str = "auto",
          timing: Timing | None = None) -> dict:
    """Judge ``res`` (:func:`fit_adequacy` with the fit's outputs and noise) and say so on it: ``res.adequacy``,
    and for an inadequate model a warning in ``res.warnings`` and ``res.message``.  Returns the check."""
    check = fit_adequacy(model, records, res, drive=drive, timing=timing)
    res.adequacy = check
    w = warning_of(check)
    if w is not None:
        res.warnings.append(w)
        res.message += f"; WARNING {w}"
    return check


def warning_of(check: Mapping) -> str | None:
    """The fit's warning line for an inadequate model (None when adequate)."""
    if check.get("adequate", True):
        return None
    return ("the model does not represent this record: " + "; ".join(check["reasons"])
            + ". The fitted values may have absorbed what the model lacks: `twin diagnose` names the cause "
            "(an effect of the catalogue, the loop's timing) or says it is unexplained")


def _p(p: float) -> str:
    return f"{min(max(p, 0.0), 1.0):.2g}"
