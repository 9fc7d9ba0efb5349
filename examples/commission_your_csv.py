"""Commission a rig from a CSV in your own column names and units, then track another run against it.

    python examples/commission_your_csv.py [--seed N] [--dir DIR]

Two 10 s runs of a healthy rig are written as a test engineer's logger would (time in ms, positions in mm,
pressures in bar, its own column names); here they come from the product's simulator with values away from the
nominal ones, so the fit has something to find. The column map reads them (as ``--map`` does), the fit
commissions the rig (``commissioning.json``, as ``twin fit --save``), and the second run is tracked against the
bands centred on that fit (as ``twin track --params``): a healthy rig raises no alarm.
"""

from __future__ import annotations

import argparse
import csv
import os
import tempfile

import twin

#: your logger's columns -> the rig's signals, with their units (as --map x=pos_mm:mm ...)
COLUMNS = {"t": "time_ms:ms", "x_ref": "dem_mm:mm", "u": "valve_V:V", "x": "pos_mm:mm", "pA": "pa_bar:bar",
           "pB": "pb_bar:bar"}


def write_run(path: str, record) -> None:
    """The record as the logger writes it: ms, mm, V, bar, its own names."""
    scale = {"x_ref": 1e3, "u": 1.0, "x": 1e3, "pA": 1e-5, "pB": 1e-5}  # SI -> mm, V, bar
    names = [COLUMNS[s].split(":")[0] for s in COLUMNS]
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(names)
        for i in range(len(record.signals["x"])):
            w.writerow([f"{i * record.dt * 1e3:.3f}"] + [f"{record.signals[s][i] * k:.9g}" for s, k in scale.items()])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=4, help="seed of the runs' excitation and sensor noise")
    ap.add_argument("--dir", help="where to write the CSVs and commissioning.json (default: a temporary folder)")
    args = ap.parse_args()
    out = args.dir or tempfile.mkdtemp(prefix="fpdd-commission-")
    os.makedirs(out, exist_ok=True)

    model = twin.get_model("msp25")
    rig = model.params(Ffric="62N", CdAleak="0.004mm^2", Cd=0.23, zeta=0.34, wn="46Hz")  # the rig, unknown to the fit
    noise = {"x": 2e-6, "pA": 2e4, "pB": 2e4}
    for k, name in enumerate(("run1.csv", "run2.csv")):
        drive, x_ref = twin.excite(model, duration_s=10.0, seed=args.seed + k)
        write_run(os.path.join(out, name), twin.measure(model, rig, drive, x_ref, dt=1e-3, noise=noise,
                                                        seed=args.seed + k))

    # 1. read your CSV through the column map, 2. fit, 3. save the commissioning
    records = twin.load_records(os.path.join(out, "run1.csv"), map=COLUMNS)
    free = ["Ffric", "CdAleak", "Cd", "zeta", "wn"]
    result = twin.fit(model, records, free)
    print(repr(result))
    for name in free:
        est, std = result.estimate[name], result.std[name]
        print(f"{name}: {abs(est - rig[name]) / std:.2f} std from the rig's value")
    path = result.save(os.path.join(out, "commissioning.json"))
    print(f"commissioning: {path}")

    # 4. track the second run against it (the same map reads it)
    second = twin.load_records(os.path.join(out, "run2.csv"), map=COLUMNS)[0]
    tracked = twin.track(second, commission=path)
    print(f"alarms on the second run: {len(tracked.alarms)}")


if __name__ == "__main__":
    main()
