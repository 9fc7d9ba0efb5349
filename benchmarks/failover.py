"""Failover between ``twin serve`` processes: takeover time and alarms lost or repeated over many kills.

``python -m benchmarks.failover [--kills 10] [--seed 1000] [--json]``

A loopback lab of separate processes: a Zenoh router, three ``twin serve`` sharing one rig (``[failover]``,
priorities 0, 1, 2), a ``twin alarms`` subscriber. The rig replays a wearing rig's log in real time; at seeded
random moments the service that runs it is killed with SIGKILL, a standby takes over from the replicated
checkpoint, and the killed one comes back (it stands by). Per kill: the takeover time, from the kill to the
rig's next estimate on the bus (the rig watched again). At the end the alarms the subscriber received and the
journals of the three services together are compared with one uninterrupted run of the same log: alarms lost
(in the reference, nowhere else) and duplicated (one number given to two different alarms, or one alarm under
two numbers, or a number received twice by the subscriber) - both must be 0.

The process harness (:class:`Proc`, :func:`router`, :func:`service_config`, ...) is the one
``tests/test_failover.py`` uses.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
WAIT_S = 60.0
RIG = "rig-f"
#: The services' Zenoh lease (the liveliness timeout) and claim wait [s].
LEASE_S = 1.0
CLAIM_S = 0.3
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
RUNNING = re.compile(r"^twin serve: 1 rig\(s\)")
CLAIMING = re.compile(rf"^twin serve: rig {RIG}: no owner; claiming it")
TOOK_OVER = re.compile(rf"^twin serve: rig {RIG}: took over from (\S+) ")
ALARM_LINE = re.compile(rf"^twin serve: {RIG} #(\d+) ")


def free_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Proc:
    """A process of the lab (its stderr, or its stdout, as lines on a queue); :meth:`cleanup` kills what is left."""

    started: list[Proc] = []

    def __init__(self, args: list[str], *, stdout: bool = False) -> None:
        self.args = args
        self.proc = subprocess.Popen([sys.executable, *args], env=ENV, text=True,
                                     stdout=subprocess.PIPE if stdout else subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL if stdout else subprocess.PIPE)
        Proc.started.append(self)
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.seen: list[str] = []
        stream = self.proc.stdout if stdout else self.proc.stderr
        threading.Thread(target=self._read, args=(stream,), daemon=True).start()

    def _read(self, stream) -> None:
        with stream:
            for line in stream:
                self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    def wait_for(self, pattern: re.Pattern, timeout: float = WAIT_S) -> re.Match:
        deadline = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:  # say what the process printed instead of a bare queue.Empty
                raise AssertionError(f"no line matching {pattern.pattern!r} within {timeout:g} s; the last lines: "
                                     + "\n".join(self.seen[-15:])) from None
            assert line is not None, "process ended before: " + "\n".join(self.seen[-15:])
            self.seen.append(line)
            m = pattern.match(line)
            if m:
                return m

    def drain(self) -> list[str]:
        while True:
            try:
                line = self.lines.get_nowait()
            except queue.Empty:
                return self.seen
            if line is None:
                return self.seen
            self.seen.append(line)

    def kill(self, sig: int = signal.SIGKILL) -> None:
        self.proc.send_signal(sig)
        self.proc.wait(timeout=WAIT_S)

    def finish(self, timeout: float = WAIT_S) -> int:
        deadline = time.monotonic() + timeout
        while (line := self.lines.get(timeout=max(0.01, deadline - time.monotonic()))) is not None:
            self.seen.append(line)
        return self.proc.wait(timeout=WAIT_S)

    @classmethod
    def cleanup(cls) -> None:
        while cls.started:
            p = cls.started.pop()
            if p.proc.poll() is None:
                p.proc.kill()
            p.proc.wait(timeout=WAIT_S)


def router(tmp: Path) -> str:
    """A Zenoh router process on a free loopback port (scouting off); its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = tmp / "router.json5"
    conf.write_text('{ mode: "router", scouting: { multicast: { enabled: false }, gossip: { enabled: false } } }')
    r = Proc(["-m", "twin.service.router", str(conf), "--listen", endpoint], stdout=True)
    r.wait_for(re.compile(r"^router: listening"))
    return endpoint


def service_config(tmp: Path, name: str, endpoint: str, source: str, *, priority: int, speed: float,
                   prefer: bool = False) -> Path:
    """A service's ``rigs.toml``: client of the router, its own journal, ``[failover]``."""
    path = tmp / f"{name}.toml"
    path.write_text(f"""
[zenoh]
mode = "client"
connect = ["{endpoint}"]
[service]
journal_dir = "{tmp / name}"
checkpoint_s = 0.3
[failover]
service_id = "{name}"
priority = {priority}
prefer = {str(prefer).lower()}
lease_s = {LEASE_S}
claim_s = {CLAIM_S}
[[rig]]
name = "{RIG}"
source = "{source}"
speed = {speed}
""")
    return path


def serve_proc(config: Path) -> Proc:
    return Proc(["-m", "twin.cli", "serve", "--config", str(config)])


def subscriber(endpoint: str) -> Proc:
    """``twin alarms`` for the rig, JSON lines."""
    return Proc(["-m", "twin.cli", "alarms", "--connect", endpoint, "--mode", "client", "--rig", RIG, "--json",
                 "--wait", "0", "-q"], stdout=True)


def received(sub: Proc) -> list[dict]:
    return [json.loads(line) for line in sub.drain() if line.startswith("{")]


def journal(tmp: Path, name: str) -> list:
    from twin.service.store import Store

    path = tmp / name / f"{RIG}.db"
    if not path.exists():
        return []
    with Store(path, writer=False) as store:
        return store.alarms(RIG)


def key(a) -> tuple:
    """What identifies an alarm and its number (not when it was raised)."""
    if isinstance(a, dict):
        return (a["seq"], a["parameter"], a["level"], a["kind"], a["t_ns"])
    return (a.seq, a.parameter, a.level, a.kind, a.t_ns)


def wear_log(tmp: Path, seconds: float, drifts: list, seed: int) -> tuple[Path, list]:
    """A log of a wearing rig and the alarms of one uninterrupted run of it (as fast as it goes)."""
    from replay.mcapio import McapSink
    from twin.models import msp25 as M
    from twin.models.scenario import simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite
    from twin.service.config import load_config
    from twin.service.serve import serve

    _, xr = excite(M.MODEL, seconds, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, drifts, noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=seed)
    log = tmp / "rig.mcap"
    with McapSink(str(log)) as sink:
        sink.write(rec.to_samples())
    ref = tmp / "ref.toml"
    ref.write_text(f'[zenoh]\nlisten = ["tcp/127.0.0.1:{free_port()}"]\n[service]\njournal_dir = "{tmp / "ref"}"\n'
                   f'[[rig]]\nname = "{RIG}"\nsource = "{log}"\nspeed = 0\n')
    serve(load_config(str(ref)))
    return log, journal(tmp, "ref")


class Estimates:
    """Arrival time and record time of each estimate of the rig (a subscription of ``session``)."""

    def __init__(self, session) -> None:
        self.seen: list[tuple[float, int]] = []
        self._sub = session.declare_subscriber(f"fpdd/{RIG}/estimate", self._on)

    def _on(self, sample) -> None:
        self.seen.append((time.monotonic(), int(json.loads(sample.payload.to_string())["t_ns"])))

    def first_after(self, t: float, timeout: float = WAIT_S) -> tuple[float, int]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            later = [e for e in list(self.seen) if e[0] > t]
            if later:
                return min(later)
            time.sleep(0.01)
        raise TimeoutError(f"no estimate of {RIG} within {timeout:g} s")

    def last_before(self, t: float) -> tuple[float, int]:
        return max(e for e in list(self.seen) if e[0] <= t)

    def close(self) -> None:
        self._sub.undeclare()


def tally(reference: list, sub_lines: list[dict], journals: list[list]) -> dict:
    """Lost and duplicated alarms of the lab against the reference (see the module docstring)."""
    by_seq: dict[int, set] = {}
    by_alarm: dict[tuple, set] = {}
    for a in [*sub_lines, *(x for j in journals for x in j)]:
        k = key(a)
        by_seq.setdefault(k[0], set()).add(k[1:])
        by_alarm.setdefault(k[1:], set()).add(k[0])
    seqs = [d["seq"] for d in sub_lines]
    union = {(s, *a) for s, alarms in by_seq.items() for a in alarms}
    ref = {key(a) for a in reference}
    return {"alarms": len(reference), "lost": len(ref - union),
            "duplicated": (sum(len(v) - 1 for v in by_seq.values()) + sum(len(v) - 1 for v in by_alarm.values())
                           + len(seqs) - len(set(seqs))),
            "unexpected": len(union - ref)}


def _took_overs(p: Proc) -> int:
    return sum(1 for line in p.drain() if TOOK_OVER.match(line))


def _new_owner(procs: dict[str, Proc], before: dict[str, int], killed: str) -> str:
    """The service that took the rig over since ``before`` (its count of takeover lines grew)."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        for n, p in procs.items():
            if n != killed and _took_overs(p) > before[n]:
                return n
        time.sleep(0.02)
    raise TimeoutError("no service said it took the rig over")


def run(kills: int = 10, seed: int = 1000, quick: bool = False, freeze: bool = False) -> dict:
    """``kills`` kills of the rig's owner during one replayed log (3 when ``quick``); ``freeze``: the owner is
    frozen (SIGSTOP, a host that hangs or loses its network: its tokens go when its lease expires), and killed
    once the rig runs elsewhere."""
    import numpy as np

    from fpdd.zenohconf import zenoh_config
    from twin.models.scenario import Drift

    import zenoh

    kills = min(kills, 3) if quick else kills
    rng = np.random.default_rng(seed)
    took: list[float] = []
    gaps: list[float] = []
    how = "SIGSTOP (frozen: gone when its lease expires), then SIGKILL" if freeze else "SIGKILL"
    with tempfile.TemporaryDirectory(prefix="fpdd-failover-") as d:
        tmp = Path(d)
        seconds = 12.0 + 5.0 * kills
        drifts = [Drift("Ffric", 3.0, 3.0, shape="step"), Drift("wn", 0.6, 0.3 * seconds, 0.5 * seconds, "ramp"),
                  Drift("CdAleak", 4.0, 0.6 * seconds, 0.9 * seconds, "ramp")]
        print(f"failover: simulating a {seconds:g} s log and its uninterrupted run ...", file=sys.stderr)
        log, reference = wear_log(tmp, seconds, drifts, seed)
        try:
            ep = router(tmp)
            sub = subscriber(ep)
            names = ["svc-0", "svc-1", "svc-2"]
            procs = {"svc-0": serve_proc(service_config(tmp, "svc-0", ep, str(log), priority=0, speed=1.0))}
            procs["svc-0"].wait_for(CLAIMING)  # first, so that it owns the rig
            for i, n in enumerate(names[1:], 1):
                procs[n] = serve_proc(service_config(tmp, n, ep, str(log), priority=i, speed=1.0))
            for n in names[1:]:
                procs[n].wait_for(RUNNING)
            owner = "svc-0"
            with zenoh.open(zenoh_config("client", connect=[ep])) as session:
                est = Estimates(session)
                try:
                    est.first_after(time.monotonic())  # the rig runs
                    for k in range(kills):
                        time.sleep(float(rng.uniform(0.5, 2.0)))
                        before = {n: _took_overs(p) for n, p in procs.items()}
                        killed = time.monotonic()
                        if freeze:
                            procs[owner].proc.send_signal(signal.SIGSTOP)
                        else:
                            procs[owner].kill()
                        first = est.first_after(killed)
                        last = est.last_before(killed)
                        took.append(first[0] - killed)
                        gaps.append(first[0] - last[0])
                        new = _new_owner(procs, before, owner)
                        if freeze:
                            procs[owner].kill()
                        print(f"failover: kill {k + 1}/{kills}: {owner} killed, {new} ran the rig again after "
                              f"{took[-1]:.2f} s", file=sys.stderr)
                        procs[owner] = serve_proc(service_config(tmp, owner, ep, str(log), priority=names.index(owner),
                                                                 speed=1.0))
                        procs[owner].wait_for(RUNNING)
                        owner = new
                        est.first_after(time.monotonic())
                finally:
                    est.close()
            exits = {n: p.finish(timeout=seconds + WAIT_S) for n, p in procs.items()}
            time.sleep(0.5)
            sub.kill(signal.SIGTERM)
            counts = tally(reference, received(sub), [journal(tmp, n) for n in names])
            # every service, the ones that took the rig over included, ends its run with exit code 0
            counts["unclean_exits"] = sum(1 for rc in exits.values() if rc != 0)
            if counts["unclean_exits"]:
                print(f"failover: exit codes {exits}:\n  " + "\n  ".join(
                    f"{n}: " + " | ".join(procs[n].seen[-4:]) for n, rc in exits.items() if rc != 0), file=sys.stderr)
        except BaseException:
            for p in Proc.started:  # what each process said, for the failure's cause
                print(f"failover: {' '.join(p.args[:3])} ...:\n  " + "\n  ".join(p.drain()[-8:]), file=sys.stderr)
            raise
        finally:
            Proc.cleanup()
    return {"kills": kills, "how": how, "seed": seed, "lease_s": LEASE_S, "claim_s": CLAIM_S,
            "takeover_median_s": float(np.median(took)), "takeover_worst_s": float(max(took)),
            "estimate_gap_median_s": float(np.median(gaps)), "estimate_gap_worst_s": float(max(gaps)), **counts}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.failover", description=__doc__.split("\n")[0])
    ap.add_argument("--kills", type=int, default=10, help="kills of the rig's owner (default 10)")
    ap.add_argument("--seed", type=int, default=1000, help="seed of the log and of the kill moments (default 1000)")
    ap.add_argument("--freeze", action="store_true", help="freeze the owner (SIGSTOP: a host that hangs or loses "
                    "its network, gone when its lease expires) instead of killing it; killed after the takeover")
    ap.add_argument("--json", action="store_true", help="the result as JSON (SI: seconds)")
    args = ap.parse_args(argv)
    if args.kills < 1:
        ap.error("--kills: at least 1")
    out = run(args.kills, args.seed, freeze=args.freeze)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"{out['kills']} kills by {out['how']} (lease {out['lease_s']:g} s, claim {out['claim_s']:g} s): "
              f"takeover median {out['takeover_median_s']:.2f} s, worst {out['takeover_worst_s']:.2f} s (kill to the "
              f"rig's next estimate); no estimate for median {out['estimate_gap_median_s']:.2f} s, worst "
              f"{out['estimate_gap_worst_s']:.2f} s; {out['alarms']} alarms: {out['lost']} lost, "
              f"{out['duplicated']} duplicated; {out['unclean_exits']} service(s) exited with a code other than 0")
    return 0 if out["lost"] == 0 and out["duplicated"] == 0 and out["unexpected"] == 0 and \
        out["unclean_exits"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
