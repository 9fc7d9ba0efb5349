"""Track a log of a rig whose cross-piston seal leaks, and read the alarms the twin raises.

    python examples/track_and_alarms.py [--seed N] [--out DIR]

A 6 s record of the MSP25 rig with ten times the nominal leakage (the product's own simulator) is tracked
against the default healthy bands, as ``twin track`` does; each alarm is printed as ``twin alarms`` prints it,
then the final estimates (SI, with their units). With ``--out`` the estimates and alarms also go to ``DIR/rig.twin.mcap`` (Foxglove
opens it).
"""

from __future__ import annotations

import argparse

import twin
from twin.online.events import format_alarm


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=2, help="seed of the excitation and the sensor noise")
    ap.add_argument("--out", help="write the twin's MCAP here")
    args = ap.parse_args()

    model = twin.get_model("msp25")
    drive, x_ref = twin.excite(model, duration_s=6.0, seed=args.seed)
    worn = model.params(CdAleak="0.03mm^2")  # the nominal leakage is 0.0033 mm^2
    record = twin.measure(model, worn, drive, x_ref, dt=1e-3, noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
                          seed=args.seed)

    rig = twin.track(record, out_dir=args.out)  # a log's path works the same: twin.track("worn.mcap")
    for alarm in rig.alarms:
        print(format_alarm(alarm))
    raised = sorted({a.parameter for a in rig.alarms if a.level in ("warning", "alarm")})
    print(f"alarmed parameters: {', '.join(raised) or 'none'}")
    for name, est in rig.final_estimates().items():  # SI, the unit beside
        print(f"final {name}: {est['value']:.6g} +- {est['std']:.3g} {est['unit']}")


if __name__ == "__main__":
    main()
