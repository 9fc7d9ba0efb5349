"""The service under load, as an operator runs it: ``twin serve`` in its own process, logs replayed in real time.

``python -m benchmarks.service soak [--rigs 10] [--minutes 10]``
    memory of the service's process tree (the service and its workers) over a
    long real-time run; baseline: the resident size at the end of the warm-up
    (the first fifth of the run, at most 2 minutes), measured in the same run;
    prints the growth after it (target < 5 %) and the rigs' lag.

``python -m benchmarks.service fleet [--rigs 60,100,120] [--seconds 30]``
    how many 1 kHz rigs one ``twin serve`` keeps in real time on this machine:
    for each count, the rigs' lag as they report it in their status
    (``lag_ms``), and whether every rig stayed under its warning level; baseline
    in the same run: how many rigs the compiled filter alone could follow
    (its samples per second on every core, divided by 1000).

Every figure is measured here and now; nothing is compared with fixed
milliseconds. Statuses are read over Zenoh, as a dashboard would.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import subprocess
import sys
import tempfile
import time
from typing import Any
from pathlib import Path

import numpy as np


def _log(path: Path, seconds: float, seed: int) -> None:
    from replay.mcapio import McapSink
    from twin.models import msp25 as M
    from twin.models.scenario import Drift, simulate_wear
    from twin.models.simulate import DEFAULT_NOISE, excite

    _, xr = excite(M.MODEL, seconds, 1e-3, seed=seed)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [Drift("Ffric", 2.0, seconds / 2, shape="step")],
                           noise={k: DEFAULT_NOISE[k] for k in ("x", "pA", "pB")}, seed=seed)
    with McapSink(str(path)) as sink:
        sink.write(rec.to_samples())


def _free_port() -> int:
    from twin.commands.demo import free_port

    return free_port()


def _config(directory: Path, logs: list[Path], rigs: int, port: int, workers: str = '"auto"') -> Path:
    lines = [f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n',
             f'[service]\njournal_dir = "{directory / "journal"}"\nworkers = {workers}\n']
    for i in range(rigs):
        lines.append(f'[[rig]]\nname = "rig-{i:03d}"\nsource = "{logs[i % len(logs)]}"\nspeed = 1.0\n')
    path = directory / "rigs.toml"
    path.write_text("\n".join(lines))
    return path


def _rss_kib(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def _tree(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    todo += [int(c) for c in f.read().split()]
        except OSError:
            pass
    return out


def _cpu_s(pids: list[int]) -> float:
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for p in pids:
        try:
            with open(f"/proc/{p}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
        except OSError:
            pass
    return total


class _Statuses:
    """Every rig's statuses over Zenoh (a peer connected to the service)."""

    def __init__(self, endpoint: str) -> None:
        import zenoh

        from replay.zenohconf import zenoh_config

        self.q: queue.Queue = queue.Queue()
        self.session = zenoh.open(zenoh_config("peer", connect=[endpoint]))
        self.sub = self.session.declare_subscriber("fpdd/*/status", lambda s: self.q.put(
            (time.monotonic(), json.loads(s.payload.to_string()))))

    def drain(self) -> list:
        out = []
        while True:
            try:
                out.append(self.q.get_nowait())
            except queue.Empty:
                return out

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def _start(config: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "twin.cli", "serve", "--config", str(config),
                             "--log-level", "warning"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _stop(proc: subprocess.Popen) -> str:
    import signal

    proc.send_signal(signal.SIGTERM)
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return err


def soak(rigs: int, minutes: float, say=print) -> dict:
    seconds = minutes * 60.0
    with tempfile.TemporaryDirectory(prefix="fpdd-soak-") as tmp:
        d = Path(tmp)
        say(f"simulating {seconds + 30:.0f} s of data for {rigs} rigs (2 logs)...")
        logs = [d / f"rig{i}.mcap" for i in range(2)]
        for i, p in enumerate(logs):
            _log(p, seconds + 30.0, seed=20 + i)
        port = _free_port()
        proc = _start(_config(d, logs, rigs, port))
        watch = _Statuses(f"tcp/127.0.0.1:{port}")
        samples: list[tuple[float, int]] = []
        lags: dict[str, list[float]] = {}
        t0 = time.monotonic()
        warm = min(120.0, seconds / 5)
        try:
            while time.monotonic() - t0 < seconds:
                time.sleep(5.0)
                if proc.poll() is not None:
                    assert proc.stderr is not None  # started with stderr=PIPE
                    raise RuntimeError(f"twin serve ended early: {proc.stderr.read()}")
                now_rss = sum(_rss_kib(p) for p in _tree(proc.pid))
                samples.append((time.monotonic() - t0, now_rss))
                for _, st in watch.drain():
                    lags.setdefault(st["rig"], []).append(st["counters"].get("lag_ms", 0) / 1000)
                say(f"  t={samples[-1][0]:6.0f} s  RSS {now_rss / 1024:7.1f} MiB  rigs reporting {len(lags)}")
        finally:
            err = _stop(proc)
            watch.close()
    t = np.array([s[0] for s in samples])
    rss = np.array([s[1] for s in samples], dtype=float)
    base = rss[np.searchsorted(t, warm)] if np.any(t >= warm) else rss[0]
    after = rss[t >= warm]
    slope = float(np.polyfit(t[t >= warm], after, 1)[0]) if after.size > 2 else 0.0
    all_lags = [x for v in lags.values() for x in v]
    return {"rigs": rigs, "minutes": minutes, "warm_up_s": warm,
            "rss_warm_mib": base / 1024, "rss_final_mib": rss[-1] / 1024, "rss_max_after_warm_mib": after.max() / 1024,
            "growth_after_warm_pct": 100.0 * (rss[-1] - base) / base,
            "slope_kib_per_min": slope * 60.0,
            "lag_max_s": max(all_lags, default=float("nan")), "lag_p95_s": float(np.percentile(all_lags, 95))
            if all_lags else float("nan"), "service_stderr_tail": err.strip().splitlines()[-rigs:]}


def _filter_rigs() -> float:
    """Rigs the compiled filter alone follows at 1 kHz on every core (the tracker benchmark's fleet figure)."""
    import multiprocessing as mp

    from benchmarks.tracker import _worker

    cores = os.cpu_count() or 1
    with mp.get_context("spawn").Pool(cores) as pool:
        res = pool.map(_worker, [(10.0, 3, 30 + i) for i in range(cores)])
    return sum(r[0] for r in res) / max(r[1] for r in res) / 1000.0


def fleet(counts: list[int], seconds: float, say=print) -> dict:
    rows = []
    with tempfile.TemporaryDirectory(prefix="fpdd-fleet-") as tmp:
        d = Path(tmp)
        logs = [d / f"rig{i}.mcap" for i in range(3)]
        for i, p in enumerate(logs):
            _log(p, seconds, seed=40 + i)
        for n in counts:
            run = d / f"n{n}"
            run.mkdir()
            port = _free_port()
            proc = _start(_config(run, logs, n, port))
            watch = _Statuses(f"tcp/127.0.0.1:{port}")
            t0 = time.monotonic()
            finished: set[str] = set()
            lags: dict[str, list[float]] = {}
            cpu0: float | None = None
            cpu1: float | None = None
            tc0 = tc1 = 0.0
            deadline = t0 + seconds + 120.0
            while len(finished) < n and time.monotonic() < deadline and proc.poll() is None:
                time.sleep(1.0)
                for _, st in watch.drain():
                    rig = st["rig"]
                    if st["state"] == "finished":
                        finished.add(rig)
                    elif st["state"] in ("running", "degraded"):
                        lags.setdefault(rig, []).append(st["counters"].get("lag_ms", 0) / 1000)
                if not finished:  # CPU of the tree while every rig runs (a finished worker leaves the tree)
                    now_cpu, now_t = _cpu_s(_tree(proc.pid)), time.monotonic()
                    if cpu0 is None and len(lags) == n:
                        cpu0, tc0 = now_cpu, now_t
                    elif cpu0 is not None:
                        cpu1, tc1 = now_cpu, now_t
            # tc1 > tc0 only once cpu1 is measured too
            cpu = (cpu1 - cpu0) / (tc1 - tc0) if cpu0 is not None and cpu1 is not None and tc1 > tc0 else float("nan")
            err = _stop(proc)
            watch.close()
            # the steady part: each rig's statuses after its first 5 s
            steady = [x for v in lags.values() for x in v[5:]]
            row: dict[str, Any] = {"rigs": n, "finished": len(finished), "lag_max_s": max(steady, default=float("nan")),
                   "lag_p95_s": float(np.percentile(steady, 95)) if steady else float("nan"),
                   "cpu_cores_busy": cpu, "errors": [line for line in err.splitlines() if "error" in line][:3]}
            row["real_time"] = row["finished"] == n and row["lag_max_s"] < 1.0
            rows.append(row)
            say(f"  {n:4d} rigs: finished {row['finished']}/{n}, lag max {row['lag_max_s']:.3f} s, "
                f"p95 {row['lag_p95_s']:.3f} s, {cpu:.2f} cores busy -> "
                f"{'real time' if row['real_time'] else 'NOT real time'}")
    say("baseline: the compiled filter alone on every core...")
    alone = _filter_rigs()
    best = max((r["rigs"] for r in rows if r["real_time"]), default=0)
    return {"rows": rows, "filter_alone_rigs": alone, "best_real_time_rigs": best,
            "service_vs_filter_alone": best / alone if alone else float("nan"), "cores": os.cpu_count()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.service", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("soak", help="memory and lag of N rigs in real time over minutes")
    s.add_argument("--rigs", type=int, default=10)
    s.add_argument("--minutes", type=float, default=10.0)
    f = sub.add_parser("fleet", help="how many 1 kHz rigs one twin serve keeps in real time")
    f.add_argument("--rigs", default="60,100,120", help="rig counts to try, comma-separated")
    f.add_argument("--seconds", type=float, default=30.0, help="length of each replayed log")
    for p in (s, f):
        p.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    say = (lambda m: print(m, file=sys.stderr, flush=True)) if args.json else print
    if args.what == "soak":
        r = soak(args.rigs, args.minutes, say)
        if args.json:
            print(json.dumps(r, indent=2))
        else:
            print(f"soak: {r['rigs']} rigs x {r['minutes']:g} min in real time: RSS after warm-up ({r['warm_up_s']:.0f} s) "
                  f"{r['rss_warm_mib']:.1f} MiB, at the end {r['rss_final_mib']:.1f} MiB: growth "
                  f"{r['growth_after_warm_pct']:+.2f} % (target < 5 %), slope {r['slope_kib_per_min']:+.0f} KiB/min; "
                  f"lag max {r['lag_max_s']:.3f} s, p95 {r['lag_p95_s']:.3f} s")
    else:
        r = fleet([int(x) for x in args.rigs.split(",")], args.seconds, say)
        if args.json:
            print(json.dumps(r, indent=2))
        else:
            print(f"fleet: {r['best_real_time_rigs']} rigs at 1 kHz in real time in one twin serve on {r['cores']} "
                  f"cores; the filter alone would follow {r['filter_alone_rigs']:.0f} "
                  f"(service/filter {r['service_vs_filter_alone']:.2f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
