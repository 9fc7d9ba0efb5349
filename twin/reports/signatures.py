"""Each named cause's own signature in a diagnosis: the residual before the cause was added and the cause's
contribution, binned against the cause's regime variable, as the report's table and its plot read them."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from twin.reports import views
from twin.reports.units import signal_unit

__all__ = ["signature_data"]


#: the regime variable of a signature -> the signal whose display unit it is shown in
_AXIS_SIGNAL = {"position": "x", "velocity": "v", "dp": "pA", "spool_opening": "u", "demand": "x_ref",
                "force": "force"}


def signature_data(diagnosis: Any) -> list[dict]:
    """Per accepted cause (from a :class:`twin.estimation.diagnose.Diagnosis`; ``[]`` from its dict): the regime
    variable its signature is read against (``x``, SI, with ``axis_unit``/``axis_scale``), the residual of the
    model before the cause was added and the cause's contribution (extended − before) on the signal where it
    is largest against the noise (``signal``, SI arrays with ``unit``/``scale``), and whether it is flat in
    that view (:func:`twin.reports.views.signature_flatness`)."""
    try:
        from fpdd.units import NOMINAL_NOISE
        from twin.estimation.diagnose import CONTROLLER_RATE, FORCE_EFFECTS, SIGNATURE_AXIS, TIMING_EFFECTS
        from twin.estimation.residuals import regime_signals

        rec = diagnosis.records[0]
        path = diagnosis.path
        outs = list(diagnosis.outputs)
        reg = regime_signals(diagnosis.model, rec, diagnosis.nominal.predicted[0])
    except (AttributeError, IndexError, KeyError, TypeError):
        return []
    steps: list[tuple[int, str]] = []
    for i in range(1, len(path)):
        new = [c for c in diagnosis.causes if c not in path[i - 1].effects and c in path[i].effects]
        if path[i].timing != path[i - 1].timing:
            new.append(next((c for c in diagnosis.causes if c in TIMING_EFFECTS), CONTROLLER_RATE))
        steps.extend((i, c) for c in new)
    out = []
    for i, c in steps:
        before = path[i - 1].predicted[0]
        after = path[i].predicted[0]
        axis = SIGNATURE_AXIS.get(c, "velocity")
        if axis not in reg:
            axis = "velocity"
        # (residual before, the cause's contribution, noise level, name, display unit and scale) per signal
        shown = {}
        for o in outs:
            unit, sc = signal_unit(o, diagnosis.model)
            shown[o] = (rec[o] - before[o], after[o] - before[o], NOMINAL_NOISE.get(o, 1.0), unit, sc)
        if {"pA", "pB"} <= set(outs):
            area = diagnosis.final.params["A"]
            dp = {k: p["pA"] - p["pB"] for k, p in (("rec", rec.signals), ("before", before), ("after", after))}
            shown["force"] = (area * (dp["rec"] - dp["before"]), area * (dp["after"] - dp["before"]),
                              area * math.sqrt(2.0) * NOMINAL_NOISE["pA"], "N", 1.0)
        if c in FORCE_EFFECTS and "force" in shown:
            o = "force"
        else:
            o = max(shown, key=lambda k: float(np.std(shown[k][1])) / shown[k][2])
        res, contrib, _, unit, sc = shown[o]
        a_unit, a_sc = signal_unit(_AXIS_SIGNAL.get(axis, axis), diagnosis.model)
        flat, span, scatter = views.signature_flatness(reg[axis], contrib, res)
        out.append({"cause": c, "axis": axis, "axis_unit": a_unit, "axis_scale": a_sc, "x": reg[axis],
                    "signal": o, "unit": unit, "scale": sc, "residual": res, "contribution": contrib,
                    "flat": flat, "span": span, "scatter": scatter})
    return out
