"""``twin params``: list a model's parameters, units, bounds and effects."""

from __future__ import annotations

from twin.models import DEFAULT_MODEL, MODELS
from twin.commands.common import dump as _dump
from twin.commands.common import names as _names

HELP = "list a model's parameters, units, bounds and effects"


def add_arguments(p) -> None:
    p.add_argument("--model", default=DEFAULT_MODEL, choices=MODELS)
    p.add_argument("--effects", help="comma-separated effects to switch on")
    p.add_argument("--json", action="store_true")


def table(ps) -> str:
    """The parameters in their display units: value, bounds, unit, category, meaning."""
    from twin.reports.units import fmt

    rows = [f"{'parameter':<12} {'value':>11} {'min':>11} {'max':>11}  {'unit':<10} {'category':<16} meaning"]
    for s, v in zip(ps.specs, ps.values):
        unit = s.display_unit or s.unit
        k = s.display_scale
        rows.append(f"{s.name:<12} {fmt(v * k, 6):>11} {fmt(s.lo * k, 4):>11} {fmt(s.hi * k, 4):>11}  "
                    f"{'' if unit == '1' else unit:<10} {s.category:<16} {s.meaning}")
    return "\n".join(rows)


def _param_json(spec, value: float) -> dict:
    """One parameter as JSON: SI value, bounds and unit; its tracking settings name their units (``band`` and
    ``bounds`` are relative: ``"1"``; ``drift_rate`` is a random-walk intensity in log units per √s)."""
    d = dict(spec.to_dict(), value=value)
    if isinstance(d.get("tracking"), dict):
        d["tracking"] = dict(d["tracking"], band_unit="1", bounds_unit="1", drift_rate_unit="1/s^0.5")
    return d


def run(args) -> int:
    from twin.models import get_model

    model = get_model(args.model)
    ps = model.params(effects=_names(args.effects))
    if args.json:
        _dump({"model": model.name, "params": [_param_json(s, v) for s, v in zip(ps.specs, ps.values)],
               "effects": {n: {"description": e.description, "signature": e.signature,
                               "params": list(e.names), "mimicked_by": list(e.mimicked_by),
                               "mimicry": e.mimicry} for n, e in model.EFFECTS.items()}})
        return 0
    print(table(ps))
    print("\neffects (switch on with --effects NAME,...):")
    for n, e in model.EFFECTS.items():
        print(f"  {n:<22} {e.description}  [{', '.join(e.names)}]")
        if e.mimicked_by:
            print(f"  {'':<22} (mimicked by {', '.join(e.mimicked_by)} while it is free: diagnose tests it only "
                  "when it is held)")
    return 0
