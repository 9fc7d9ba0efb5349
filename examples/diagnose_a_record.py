"""Diagnose a record of a rig with a viscous friction the nominal model lacks: the diagnosis names it.

    python examples/diagnose_a_record.py [--seed N] [--report DIR]

An 8 s record of the MSP25 rig with the catalogue's ``viscous_friction`` switched on (the product's own
simulator). ``twin.diagnose`` fits the nominal model on the first 75 %, tests its prediction errors, screens the
catalogue of effects and names what removes the error on the held-out 25 %. Prints the verdict, the named
causes and their fitted sizes; with ``--report`` also the HTML report of ``twin diagnose --report``.
"""

from __future__ import annotations

import argparse

import twin


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=3, help="seed of the excitation and the sensor noise")
    ap.add_argument("--report", metavar="DIR", help="write diagnose_report.html there")
    args = ap.parse_args()

    model = twin.get_model("msp25")
    drive, x_ref = twin.excite(model, duration_s=8.0, seed=args.seed)
    rig = model.params(effects=["viscous_friction"], c_visc="2000N*s/m")  # what the nominal model lacks
    record = twin.measure(model, rig, drive, x_ref, dt=1e-3, noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
                          seed=args.seed)

    diagnosis = twin.diagnose(model, record)
    print(repr(diagnosis))
    print(f"verdict: {diagnosis.verdict()}")
    print(f"named: {', '.join(diagnosis.causes) or 'nothing'}")
    for cause in diagnosis.causes:
        for name, p in diagnosis.effect_params(cause).items():  # SI, the unit beside
            print(f"  {cause}: {name} = {p['value']:.6g} +- {p['std']:.3g} {p['unit']} (simulated with {rig[name]:.6g})")
    if args.report:
        from twin.reports import write_diagnosis

        print(f"report: {write_diagnosis(diagnosis, args.report)}")


if __name__ == "__main__":
    main()
