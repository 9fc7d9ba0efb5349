"""``twin simulate``: simulate an identification experiment and write CSV or MCAP."""

from __future__ import annotations

import sys

from twin.models import DEFAULT_MODEL, MODELS
from twin.commands.common import add_timing_arguments, timing_of
from twin.commands.common import dump as _dump
from twin.commands.common import kv as _kv
from twin.commands.common import names as _names

HELP = "simulate an identification experiment and write CSV or MCAP"


def add_arguments(p) -> None:
    p.add_argument("--model", default=DEFAULT_MODEL, choices=MODELS)
    p.add_argument("-o", "--out", "--output", dest="output", required=True, metavar="FILE",
                   help="output file (.csv or .mcap)")
    p.add_argument("--duration", type=float, default=10.0, help="seconds (default 10)")
    p.add_argument("--dt", type=float, default=1e-3, help="sample time in s (default 1e-3)")
    p.add_argument("--excitation", default=None, choices=("multisine", "chirp", "steps"))
    p.add_argument("--amplitude", default=None, metavar="PEAK",
                   help="peak of the drive of the model's default experiment, with a unit or SI: 5mm (a demand "
                        "x_ref in m) or 800N (a force u in N)")
    p.add_argument("--f-lo", type=float, default=None, help="lowest frequency in Hz")
    p.add_argument("--f-hi", type=float, default=None, help="highest frequency in Hz")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--set", help="parameter values NAME=VALUE,..., with a unit or SI (e.g. wn=43Hz,CdAleak=3.3mm^2)")
    p.add_argument("--effects", help="comma-separated effects to switch on")
    p.add_argument("--noise", choices=("default", "none"), default="default",
                   help="sensor noise: x 2 um, pressures 20 kPa (default) or none")
    p.add_argument("--noise-levels", help="override noise std per signal, NAME=STD,...")
    p.add_argument("--quantisation", help="LSB per signal, NAME=LSB,...")
    p.add_argument("--temperature", metavar="T[:T_END]",
                   help="oil temperature, logged as T_oil: a constant (40degC) or a linear ramp over the record "
                        "(40degC:60degC); with a unit (K, degC, C, degF) or SI (K). The bulk modulus and the "
                        "leakage follow it (kB_T, b_visc, T_ref; --set)")
    p.add_argument("--temperature-rate", metavar="HZ", default=None,
                   help="the rate T_oil is logged at, held between (e.g. 10Hz as the HPU status; default every "
                        "sample)")
    add_timing_arguments(p)
    p.add_argument("--json", action="store_true")


def temperature_of(args, model, n: int):
    """``({"T_oil": [n] K}, samples per logged refresh)`` of ``--temperature`` (``({}, 1)`` when not given)."""
    from fpdd.errors import ParameterError
    from twin.models.simulate import ramp
    from twin.units import to_si

    if args.temperature is None:
        if args.temperature_rate is not None:
            raise ParameterError("--temperature-rate: needs --temperature")
        return {}, 1
    if "T_oil" not in ((model.FILTER.exogenous if model.FILTER is not None else {}) or {}):
        raise ParameterError(f"--temperature: the {model.name} model has no oil temperature")
    parts = args.temperature.split(":")
    if len(parts) > 2 or not all(p.strip() for p in parts):
        raise ParameterError(f"--temperature: expected T or T_START:T_END (e.g. 40degC:60degC), got "
                             f"{args.temperature!r}")
    t0 = to_si("--temperature", parts[0], "K")
    t1 = to_si("--temperature", parts[-1], "K")
    every = 1
    if args.temperature_rate is not None:
        hz = to_si("--temperature-rate", args.temperature_rate, "Hz")
        if not 0 < hz <= 1.0 / args.dt * (1 + 1e-9):
            raise ParameterError(f"--temperature-rate: {args.temperature_rate!r} must be above 0 and at most the "
                                 f"log rate {1.0 / args.dt:g} Hz")
        every = max(1, round(1.0 / (hz * args.dt)))
    return {"T_oil": ramp(t0, t1, n)}, every


def run(args) -> int:
    from replay.factory import open_sink
    from twin.models import get_model
    from twin.models.simulate import default_noise, excite, measure

    model = get_model(args.model)
    ps = model.params(effects=_names(args.effects), **_kv(args.set))
    amplitude = None
    if args.amplitude is not None:
        from twin.models.simulate import default_experiment
        from twin.units import to_si

        drive_name = default_experiment(model)["drive"]
        amplitude = to_si(f"--amplitude ({drive_name})", args.amplitude, model.signal_unit(drive_name) or None)
    name, drive = excite(model, args.duration, args.dt, args.excitation, amplitude, args.seed,
                         args.f_lo, args.f_hi)
    noise = {} if args.noise == "none" else default_noise(model)
    noise.update(_kv(args.noise_levels))
    timing = timing_of(args)
    exo, every = temperature_of(args, model, drive.size)
    rec = measure(model, ps, name, drive, args.dt, noise=noise, quantisation=_kv(args.quantisation),
                  seed=args.seed, name=args.output, timing=timing, exogenous=exo, exogenous_every=every)
    from replay import formats
    from twin.models.records import signal_specs

    # a CSV names each column's SI unit (t[s], x[m], pA[Pa]; a force u[N]: the model's own), as every reader
    # understands
    csv = formats.lookup(args.output, what="output").suffix == ".csv"
    specs = signal_specs(model.name)
    units = {k: specs[k].unit for k in rec.signals if k in specs}
    with open_sink(args.output, **({"units": units} if csv else {})) as sink:
        sink.write(rec.to_samples())
    info = {"output": args.output, "model": model.name, "samples": len(rec), "dt": {"value": args.dt, "unit": "s"},
            "signals": list(rec.signals),
            "params": {s.name: {"value": float(v), "unit": s.unit} for s, v in zip(ps.specs, ps.values)},
            "effects": list(ps.effects),
            "noise": {k: {"value": float(v), "unit": model.signal_unit(k)} for k, v in noise.items()},
            "timing": timing.to_dict()}
    if exo:
        t = exo["T_oil"]
        info["temperature"] = {"start": {"value": float(t[0]), "unit": "K"}, "end": {"value": float(t[-1]), "unit": "K"},
                               "logged_every": {"value": every * args.dt, "unit": "s"}}
    if args.json:
        _dump(info)
    else:
        print(f"wrote {len(rec)} samples of {', '.join(rec.signals)} to {args.output}", file=sys.stderr)
    return 0
