"""``twin params``: list a model's parameters, units, bounds and effects."""

from __future__ import annotations

from twin.models import MODELS
from twin.commands.common import dump as _dump
from twin.commands.common import names as _names

HELP = "list a model's parameters, units, bounds and effects"


def add_arguments(p) -> None:
    p.add_argument("--model", default="msp25", choices=MODELS)
    p.add_argument("--effects", help="comma-separated effects to switch on")
    p.add_argument("--json", action="store_true")


def run(args) -> int:
    from twin.models import get_model

    model = get_model(args.model)
    ps = model.params(effects=_names(args.effects))
    if args.json:
        _dump({"model": model.name, "params": [dict(s.to_dict(), value=v) for s, v in zip(ps.specs, ps.values)],
               "effects": {n: {"description": e.description, "signature": e.signature,
                               "params": list(e.names), "mimicked_by": list(e.mimicked_by),
                               "mimicry": e.mimicry} for n, e in model.EFFECTS.items()}})
        return 0
    print(ps.table())
    print("\neffects (switch on with --effects NAME,...):")
    for n, e in model.EFFECTS.items():
        print(f"  {n:<22} {e.description}  [{', '.join(e.names)}]")
        if e.mimicked_by:
            print(f"  {'':<22} (mimicked by {', '.join(e.mimicked_by)} while it is free: diagnose tests it only "
                  "when it is held)")
    return 0
