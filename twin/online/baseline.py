"""Healthy baselines of the drift test: each tracked parameter's value and band.

From the rig's values (:func:`default_baseline`: the model's nominal values, each band as wide as the
parameter's tracking band declared beside its spec, :class:`twin.params.Tracking`), or from a commissioning
fit (:func:`baseline_from_fit`).  Light to import: the rig configuration reads it."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

from fpdd.errors import ParameterError
from twin.models import get_model


#: relative band of a parameter whose spec declares none (not tracked online)
FALLBACK_BAND = 0.3


@dataclasses.dataclass(frozen=True)
class Baseline:
    """Healthy value of one parameter and its band [lo, hi] (SI units)."""

    value: float
    lo: float
    hi: float


def default_band(model_name: str, name: str) -> float:
    """The healthy band (relative half-width) of ``name``: its spec's tracking band, else
    :data:`FALLBACK_BAND`."""
    model = get_model(model_name)
    return model.tracking(name).band if name in model.trackable else FALLBACK_BAND


def default_baseline(model_name: str, params: Mapping[str, float] | None = None,
                     names: Sequence[str] | None = None) -> dict[str, Baseline]:
    """Bands around the rig's values (the model's nominal ones), each as wide as its spec's
    tracking band."""
    model = get_model(model_name)
    ps = model.params((), **dict(params or {}))
    out = {}
    for n in names or model.PHENOMENOLOGICAL:
        v = ps[n]
        r = default_band(model_name, n)
        out[n] = Baseline(v, v / (1 + r), v * (1 + r))
    return out


def baseline_from_fit(fit, names: Sequence[str] | None = None, rel_band: Mapping[str, float] | None = None,
                      k_sigma: float = 3.0) -> dict[str, Baseline]:
    """Healthy bands centred on a commissioning fit (:class:`twin.estimation.fit.FitResult`).

    Each band is ``[v / (1 + r), v (1 + r)]`` around the fitted value ``v`` with
    ``r`` the configured relative band (``rel_band``, default each parameter's
    tracking band in the model), widened to ``k_sigma`` standard errors of
    the fit when the fit itself is less certain than that.  ``names``: the
    parameters to take (default: all free parameters of the fit).
    """
    names = tuple(names or fit.free)
    missing = [n for n in names if n not in fit.estimate]
    if missing:
        raise ParameterError(f"the commissioning fit did not estimate {', '.join(missing)}; "
                             f"it estimated {', '.join(fit.free)}")
    model_name = fit.params.model
    bands = {**{n: default_band(model_name, n) for n in names}, **dict(rel_band or {})}
    out = {}
    for n in names:
        v = float(fit.estimate[n])
        if not (v > 0 and math.isfinite(v)):
            raise ParameterError(f"the commissioning fit's {n} (={v}) is not a positive number; no band around it")
        sd = float(fit.std.get(n, math.nan))
        r = float(bands.get(n, FALLBACK_BAND))
        if math.isfinite(sd):
            r = max(r, k_sigma * sd / v)
        out[n] = Baseline(v, v / (1.0 + r), v * (1.0 + r))
    return out
