"""Simulate an identification record of the MSP25 rig and fit its dry friction and valve damping.

    python examples/fit_a_record.py [--seed N]

The record comes from the product's own simulator (a multisine demand, sensor noise through the loop); a rig's
log goes in its place with ``twin.load_records("rig.mcap")``. Prints each estimate with its standard error beside
the value it was simulated with.
"""

from __future__ import annotations

import argparse

import twin


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=1, help="seed of the excitation and the sensor noise")
    args = ap.parse_args()

    model = twin.get_model("msp25")
    drive, x_ref = twin.excite(model, duration_s=10.0, seed=args.seed)
    truth = model.params(Ffric="65N", zeta=0.42)  # values with units, as --set takes them; a bare number is SI
    record = twin.measure(model, truth, drive, x_ref, dt=1e-3, noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
                          seed=args.seed)

    # start away from the truth: the fit has to find it
    result = twin.fit(model, record, ["Ffric", "zeta"], start={"Ffric": 40.0, "zeta": 0.3})
    print(repr(result))
    for name in ("Ffric", "zeta"):
        est, std, true = result.estimate[name], result.std[name], truth[name]
        print(f"{name}: {est:.6g} +- {std:.3g} (simulated with {true:.6g}; {abs(est - true) / std:.2f} std off)")


if __name__ == "__main__":
    main()
