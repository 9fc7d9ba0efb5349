"""``twin.fit``: the fit (:func:`twin.estimation.fit.fit`) and the adequacy test of the fitted model.

What ``twin fit`` and a commissioning run: a free parameter that an un-modelled effect of the catalogue can mimic
(:func:`mimicry_warnings`: a transducer gain and Cd) is said in ``caveats`` (the text, the JSON, the saved file and
the report show them: the data cannot tell the two apart, so it is said beside every such fit, apart from the
``warnings`` that say a fit or a model failed its record); a model that does not represent its record (its one-step prediction
errors follow the drive, stay predictable or grow on the record's tail; :mod:`twin.estimation.diagnose.check`) is
fitted all the same and said so, in ``warnings``, ``message`` and ``adequacy``; never a silently biased fit.  The
diagnosis's own fits, which judge adequacy their own way, call the fit alone.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from twin.estimation.fit import fit as fit_alone
from twin.estimation.fit_result import FitResult
from twin.models import Model, get_model
from twin.models.base import DEFAULT_TIMING
from twin.record import Record


def fit(model: Model | str, records: Sequence[Record] | Record, free: Sequence[str], *,
        adequacy: bool = True, params: Any = None, **options: Any) -> FitResult:
    """:func:`twin.estimation.fit.fit` with the same arguments (``options``), then, unless ``adequacy`` is
    false, the adequacy test of the fitted model (a tenth of a second on a 20 s record).

    ``params``: the known parameter values the fit starts from and holds (the command line's ``--params`` and
    ``--set``): a :class:`~twin.params.ParameterSet`, a mapping of values (SI floats, or text with units as
    ``--set``: ``{"A": "2000mm^2"}``) or the path of a ``twin fit --save`` file; ``base=`` is the same keyword
    under its older name."""
    if params is not None:
        if options.get("base") is not None:
            from fpdd.errors import ParameterError

            raise ParameterError("fit: give params= or its older name base=, not both")
        options["base"] = _params_of(model, params)
    t0 = time.perf_counter()
    res = fit_alone(model, records, free, **options)
    if adequacy:
        from twin.estimation.diagnose.check import judge  # imported only by a fit that runs the test

        m = get_model(model) if isinstance(model, str) else model
        recs = [records] if isinstance(records, Record) else list(records)
        judge(res, m, recs, drive=options.get("drive", "auto"), timing=options.get("timing") or DEFAULT_TIMING)
        res.time_s = time.perf_counter() - t0
    m = get_model(model) if isinstance(model, str) else model
    for w in mimicry_warnings(m, free, effects=getattr(options.get("base"), "effects", ())):
        if w not in res.caveats:
            res.caveats.append(w)
    return res


def _params_of(model: Model | str, params: Any):
    """A parameter set from what ``fit(params=...)`` takes (a set, a mapping of values, a saved fit's path)."""
    import os
    from collections.abc import Mapping

    from twin.params import ParameterSet

    if isinstance(params, ParameterSet):
        return params
    m = get_model(model) if isinstance(model, str) else model
    if isinstance(params, (str, os.PathLike)):
        saved = FitResult.load(os.fspath(params))
        if saved.model != m.name:
            from fpdd.errors import ConfigError

            raise ConfigError(f"{os.fspath(params)}: parameters of model {saved.model!r}, expected {m.name!r}")
        return saved.params
    if isinstance(params, Mapping):
        return m.params(**dict(params))
    from fpdd.errors import ParameterError

    raise ParameterError(f"fit: params= takes a ParameterSet, a mapping of values or a saved fit's path, got "
                         f"{type(params).__name__}")


def mimicry_warnings(model: Model, free: Sequence[str], effects: Sequence[str] = ()) -> list[str]:
    """What ``twin diagnose`` knows and the fit would hide: a free parameter that an effect of the catalogue
    (not switched on) can mimic (``Effect.mimicked_by``: a displacement transducer's gain is a Cd change while Cd
    is free).  One line per effect: the fitted value carries the effect's error, and how to tell them apart."""
    out = []
    for name, E in model.EFFECTS.items():
        hit = [n for n in E.mimicked_by if n in free]
        if hit and name not in effects:
            out.append(f"{', '.join(hit)} can mimic {name} ({E.description}): if the rig has it, the fitted "
                       f"{', '.join(hit)} carries its error ({E.mimicry})")
    return out
