"""Memory per rig in one worker of ``twin serve``: the service in its own process, real Zenoh on loopback, logs replayed.

``python -m benchmarks.memory [--rigs 1,5,10] [--seconds 40] [--speed 1] [--json]``
    for each rig count, ``twin serve`` with ``workers = 1`` (every rig in one
    spawned worker process) replays MCAP logs; once every rig has reported a
    status and the run has settled, the worker's resident memory is read from
    ``/proc/<pid>/smaps_rollup`` (RSS and USS: its private pages), sampled
    every second to the end of the log. Reported: the worker's memory per rig
    count, the marginal memory per rig (slope of a least-squares line through
    the counts), and, as the baseline measured in the same run, the worker
    with 1 rig: the ratios of every count to it, and the slope against the
    target (20 MB per rig). ``--soak`` samples from the first status to the
    end of every rig's log instead and reports the growth after the first
    fifth of the readings (flat: a bounded service).

Nothing is timed; memory figures are in MB (10^6 bytes).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.service import _config, _Statuses, _free_port, _log, _start, _stop, _tree

TARGET_MB_PER_RIG = 20.0


def memory_kib(pid: int) -> dict[str, int]:
    """Resident memory of ``pid`` from ``/proc/<pid>/smaps_rollup`` [KiB]: ``rss`` and ``uss`` (private pages)."""
    out = {"rss": 0, "uss": 0}
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            for line in f:
                key, _, rest = line.partition(":")
                if key == "Rss":
                    out["rss"] = int(rest.split()[0])
                elif key in ("Private_Clean", "Private_Dirty"):
                    out["uss"] += int(rest.split()[0])
    except OSError:
        pass
    return out


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def worker_pids(service_pid: int) -> list[int]:
    """The service's worker processes (spawned children running the multiprocessing entry, not its resource
    tracker nor a commissioning fit's process)."""
    return [p for p in _tree(service_pid) if p != service_pid and "multiprocessing.spawn" in _cmdline(p)
            and "resource_tracker" not in _cmdline(p)]


def run_count(d: Path, logs: list[Path], rigs: int, seconds: float, speed: float, soak: bool, say=print) -> dict:
    """One ``twin serve`` with ``rigs`` rigs in one worker: its worker's memory over the run."""
    run = d / f"n{rigs}"
    run.mkdir()
    port = _free_port()
    proc = _start(_config(run, logs, rigs, port, workers="1", speed=speed))
    watch = _Statuses(f"tcp/127.0.0.1:{port}")
    reporting: set[str] = set()
    ended: set[str] = set()
    series: list[tuple[float, int, int]] = []
    t0 = time.monotonic()
    deadline = t0 + (seconds / speed if speed > 0 else seconds) + 180.0
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(1.0)
            sts = watch.drain()
            reporting |= {st["rig"] for _, st in sts}
            ended |= {st["rig"] for _, st in sts if st.get("state") in ("finished", "failed")}
            if (len(ended) == rigs if soak else ended) and len(series) > 3:
                break  # a soak: to the end of every rig's log; else while every rig runs
            workers = worker_pids(proc.pid)
            if len(reporting) < (1 if soak else rigs) or not workers:
                continue
            m = memory_kib(workers[0])
            series.append((time.monotonic() - t0, m["rss"], m["uss"]))
    finally:
        err = _stop(proc)
        watch.close()
    if not series:
        raise RuntimeError(f"{rigs} rig(s): no worker memory read (rigs reporting {len(reporting)}); "
                           f"service said: {err.strip()[-400:]}")
    t = np.array([s[0] for s in series])
    rss = np.array([s[1] for s in series], float) * 1024 / 1e6
    uss = np.array([s[2] for s in series], float) * 1024 / 1e6
    if soak:
        k = max(1, len(series) // 5)
        r = {"rigs": rigs, "samples": len(series), "rss_mb_after_warm": float(rss[k]), "rss_mb_end": float(rss[-1]),
             "uss_mb_end": float(uss[-1]), "growth_after_warm_pct": float(100 * (rss[-1] - rss[k]) / rss[k]),
             "rss_mb_max": float(rss.max())}
    else:
        half = len(series) // 2  # the settled second half of the run: its median
        r = {"rigs": rigs, "samples": len(series), "rss_mb": float(np.median(rss[half:])),
             "uss_mb": float(np.median(uss[half:])), "rss_mb_max": float(rss.max())}
    say(f"  {rigs:3d} rig(s): worker RSS {r.get('rss_mb', r.get('rss_mb_end')):7.1f} MB  "
        f"USS {r.get('uss_mb', r.get('uss_mb_end')):7.1f} MB  ({len(series)} readings over {t[-1] - t[0]:.0f} s)")
    return r


def measure(counts: list[int], seconds: float, speed: float = 1.0, soak: bool = False, say=print) -> dict:
    with tempfile.TemporaryDirectory(prefix="fpdd-memory-") as tmp:
        d = Path(tmp)
        say(f"simulating {seconds:.0f} s logs...")
        logs = [d / f"rig{i}.mcap" for i in range(2)]
        for i, p in enumerate(logs):
            _log(p, seconds, seed=1000 + i)
        rows = [run_count(d, logs, n, seconds, speed, soak, say) for n in counts]
    out: dict = {"counts": counts, "seconds": seconds, "speed": speed, "rows": rows,
                 "target_mb_per_rig": TARGET_MB_PER_RIG, "cores": os.cpu_count()}
    if not soak and len(counts) >= 2:
        x = np.array(counts, float)
        for key in ("rss", "uss"):
            y = np.array([r[f"{key}_mb"] for r in rows])
            out[f"{key}_mb_per_rig"] = float(np.polyfit(x, y, 1)[0])
        base = rows[0]
        out["baseline_rigs"] = counts[0]
        out["baseline_rss_mb"] = base["rss_mb"]
        out["ratios_to_baseline"] = {str(r["rigs"]): r["rss_mb"] / base["rss_mb"] for r in rows}
        out["per_rig_vs_target"] = out["rss_mb_per_rig"] / TARGET_MB_PER_RIG
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.memory", description=__doc__.split("\n")[0])
    ap.add_argument("--rigs", default="1,5,10", help="rig counts, comma-separated; the first is the baseline")
    ap.add_argument("--seconds", type=float, default=40.0, help="length of each replayed log [s]")
    ap.add_argument("--speed", type=float, default=1.0, help="replay speed (0 = as fast as possible)")
    ap.add_argument("--soak", action="store_true", help="report growth over the run instead of the slope")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    say = (lambda m: print(m, file=sys.stderr, flush=True)) if args.json else print
    r = measure([int(x) for x in args.rigs.split(",")], args.seconds, args.speed, args.soak, say)
    if args.json:
        print(json.dumps(r, indent=2))
    elif args.soak:
        for row in r["rows"]:
            print(f"soak: {row['rigs']} rigs in one worker: RSS after warm-up {row['rss_mb_after_warm']:.1f} MB, at "
                  f"the end {row['rss_mb_end']:.1f} MB ({row['growth_after_warm_pct']:+.2f} %), max "
                  f"{row['rss_mb_max']:.1f} MB")
    else:
        ratios = ", ".join(f"{k} rigs x{v:.2f}" for k, v in r["ratios_to_baseline"].items())
        print(f"memory: {r['rss_mb_per_rig']:.1f} MB RSS per rig (USS {r['uss_mb_per_rig']:.1f}) in one worker, "
              f"{r['per_rig_vs_target']:.2f} of the {TARGET_MB_PER_RIG:g} MB target; baseline (the worker with "
              f"{r['baseline_rigs']} rig) {r['baseline_rss_mb']:.1f} MB; against it: {ratios}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
