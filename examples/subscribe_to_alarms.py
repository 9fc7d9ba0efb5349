"""Serve a rig on a loopback Zenoh session and subscribe to its alarms, as ``twin serve`` and ``twin alarms`` do.

    python examples/subscribe_to_alarms.py [--seed N] [--wait S]

A 5 s log of a rig whose seal leaks ten times more than nominal is replayed in real time by ``twin.serve`` (the
service, in a thread here); an ``AlarmSubscriber`` on another Zenoh session receives its alarms (journaled,
numbered, history first). The two sessions meet on an explicit loopback endpoint, multicast scouting off.
"""

from __future__ import annotations

import argparse
import os
import socket
import tempfile
import threading

import zenoh

import replay
import twin
from fpdd.zenohconf import zenoh_config
from twin.online.events import format_alarm


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=2, help="seed of the log's excitation and sensor noise")
    ap.add_argument("--wait", type=float, default=30.0, help="wait at most this long for the alarms [s]")
    args = ap.parse_args()
    here = tempfile.mkdtemp(prefix="fpdd-alarms-")

    # the rig's log: the product's simulator, written to MCAP as a rig's logger would
    model = twin.get_model("msp25")
    drive, x_ref = twin.excite(model, duration_s=5.0, seed=args.seed)
    worn = model.params(CdAleak="0.03mm^2")
    record = twin.measure(model, worn, drive, x_ref, dt=1e-3, noise={"x": 2e-6, "pA": 2e4, "pB": 2e4},
                          seed=args.seed)
    with replay.open_sink(os.path.join(here, "worn.mcap")) as sink:
        sink.write(record.to_samples())

    # the subscriber's session listens; the service connects to it
    endpoint = free_endpoint()
    with open(os.path.join(here, "rigs.toml"), "w", encoding="utf-8") as f:
        f.write(f'[zenoh]\nmode = "peer"\nconnect = ["{endpoint}"]\n\n'
                f'[service]\njournal_dir = "{os.path.join(here, "journal")}"\nworkers = 0\n\n'
                f'[[rig]]\nname = "rig-a"\nsource = "{os.path.join(here, "worn.mcap")}"\nspeed = 1.0\n')
    config = twin.load_config(os.path.join(here, "rigs.toml"))

    with zenoh.open(zenoh_config("peer", listen=[endpoint])) as session, \
            twin.AlarmSubscriber(session, "rig-a") as alarms:
        stop = threading.Event()
        failed: list[BaseException] = []

        def run_service() -> None:
            try:
                twin.serve(config, stop)
            except BaseException as exc:  # shown by the main thread
                failed.append(exc)

        service = threading.Thread(target=run_service)
        service.start()
        got = []
        try:
            while not any(a.level == "alarm" for a in got):
                try:
                    got.append(alarms.recv(timeout=args.wait))
                except TimeoutError:
                    if failed:
                        raise failed[0] from None
                    raise
                print(format_alarm(got[-1]))
        finally:
            stop.set()  # the service stops its rig, closes its session and returns
            service.join()
    print(f"received {len(got)} alarm(s), numbered {[a.seq for a in got]}, "
          f"on {sorted({a.parameter for a in got})}")


if __name__ == "__main__":
    main()
