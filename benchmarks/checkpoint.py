"""What a rig's checkpoint and an alarm's durability cost, against same-run baselines.

``python -m benchmarks.checkpoint [--saves 200] [--rounds 2] [--json]``

* a checkpoint as it is saved now (the twin's plain state, a versioned JSON
  file beside the journal, fsync, rename) against the way it was saved before
  (the tracker and detector pickled into an SQLite table, WAL,
  ``synchronous=FULL``), both on the same twin, in the same folder, in turns;
* an alarm journaled now (commit, then the WAL folded into the main file)
  against a commit alone (the WAL folded later).

Wall time per operation (mostly the disk's fsync) and CPU time per operation
(the encoding); the ratio now / before for each. Nothing is compared with
fixed milliseconds.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pickle
import sqlite3
import sys
import tempfile
import time
from pathlib import Path


def _twin(d: Path):
    from twin.models import msp25 as M
    from twin.models.scenario import simulate_wear
    from fpdd.units import NOMINAL_NOISE
    from twin.models.simulate import excite
    from twin.service.config import parse_config
    from twin.service.rig import make_twin

    rig = parse_config({"service": {"journal_dir": str(d)}, "rig": [{"name": "r", "source": str(d / "x.mcap")}]},
                       "<bench>").rigs[0]
    twin = make_twin(rig)
    _, xr = excite(M.MODEL, 2.0, 1e-3, seed=1003)
    rec, _ = simulate_wear(M.MODEL.params(), xr, 1e-3, [], noise={k: NOMINAL_NOISE[k] for k in ("x", "pA", "pB")},
                           seed=1003)
    twin.write(rec.to_samples())
    return twin


def _timed(fn, n: int) -> tuple[float, float]:
    w0, c0 = time.perf_counter(), time.process_time()
    for i in range(n):
        fn(i)
    return (time.perf_counter() - w0) / n, (time.process_time() - c0) / n


def run(saves: int, rounds: int) -> dict:
    from twin.online.events import AlarmEvent
    from twin.service.journal import AlarmJournal
    from twin.service.checkpoint_file import Checkpoint
    from twin.service.store import Store

    out: dict = {"saves": saves, "rounds": rounds, "rows": []}
    with tempfile.TemporaryDirectory(prefix="fpdd-checkpoint-") as tmp:
        d = Path(tmp)
        twin = _twin(d)
        old = sqlite3.connect(d / "old.db", isolation_level=None)
        old.execute("PRAGMA journal_mode = WAL")
        old.execute("PRAGMA synchronous = FULL")
        old.execute("CREATE TABLE checkpoints (rig TEXT PRIMARY KEY, state BLOB NOT NULL)")

        def before(_i: int) -> None:
            blob = pickle.dumps({"tracker": twin.tracker, "drift": twin.drift}, protocol=pickle.HIGHEST_PROTOCOL)
            old.execute("INSERT OR REPLACE INTO checkpoints VALUES ('r', ?)", (blob,))

        def alarm(i: int) -> AlarmEvent:
            return AlarmEvent(rig="r", parameter="Ffric", level="alarm", kind="raised", t_ns=i, t_s=i * 1e-9,
                              estimate=1.0, std=0.1, baseline=0.5, band_lo=0.4, band_hi=0.6, statistic=10.0,
                              message="bench")

        with AlarmJournal(d / "new.db") as journal:
            def now(_i: int) -> None:
                journal.save_checkpoint(Checkpoint("r", 1, 1, "fp", twin.state(), time.time()))

            store = Store(d / "commit.db")
            setattr(store, "_fold", lambda: None)  # noqa: B010 - the commit alone: what an alarm cost before

            ids = itertools.count(1)  # every alarm a new identity

            def commit_only(_i: int) -> None:
                store.insert_alarm(alarm(next(ids)))

            def commit_and_fold(_i: int) -> None:
                journal.store.insert_alarm(alarm(next(ids)))

            for r in range(rounds):
                for what, fn_now, fn_before in (("checkpoint", now, before), ("alarm", commit_and_fold, commit_only)):
                    wb, cb = _timed(fn_before, saves)
                    wn, cn = _timed(fn_now, saves)
                    out["rows"].append({"round": r + 1, "what": what, "before_wall_s": wb, "before_cpu_s": cb,
                                        "now_wall_s": wn, "now_cpu_s": cn, "wall_ratio": wn / wb,
                                        "cpu_ratio": cn / cb})
            store.close()
        old.close()
        out["checkpoint_bytes"] = (d / "new.checkpoint.json").stat().st_size
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.checkpoint", description=__doc__.split("\n")[0])
    ap.add_argument("--saves", type=int, default=200, help="operations per measurement")
    ap.add_argument("--rounds", type=int, default=2, help="measurements of each, in turns")
    ap.add_argument("--json", action="store_true", help="print the figures as JSON (seconds, SI)")
    a = ap.parse_args(argv)
    res = run(a.saves, a.rounds)
    if a.json:
        print(json.dumps(res, indent=2))
        return 0
    print(f"checkpoint file: {res['checkpoint_bytes']} bytes")
    for row in res["rows"]:
        print(f"round {row['round']} {row['what']:10s} before {row['before_wall_s'] * 1e3:6.2f} ms wall "
              f"{row['before_cpu_s'] * 1e3:6.3f} ms CPU | now {row['now_wall_s'] * 1e3:6.2f} ms wall "
              f"{row['now_cpu_s'] * 1e3:6.3f} ms CPU | ratio wall {row['wall_ratio']:.2f} CPU {row['cpu_ratio']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
