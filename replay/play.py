"""Real-time replay of a recorded stream: ``replay play LOG --to can|zenoh [--speed 1.0]``.

``--to can`` needs ``--channel can://INTERFACE/CHANNEL`` (no default: python-can's
``virtual`` bus lives inside one process, no other program would hear it).  A bus
that cannot be opened (e.g. SocketCAN on a host without it) is a one-line error.

Pacing follows python-can's :class:`can.MessageSync`: every sample is due at
``wall_start + (t_ns - t_first) / speed`` on the monotonic clock, fixed when the
replay starts, so a late write never shifts the samples after it (no drift
accumulates).  At each wake-up every sample already due is written as one block,
then the player sleeps until the next one is due.  Lateness (write start minus due
time) is measured for every sample and returned in :class:`PlayStats`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable

import numpy as np

from fpdd.argtypes import non_negative_seconds
from replay.base import Sink, Source

#: Seconds between two progress reports.
PROGRESS_EVERY_S = 0.5


@dataclasses.dataclass
class PlayStats:
    """What a replay did and how well it kept time (all times in s)."""

    samples: int = 0
    writes: int = 0
    log_span_s: float = 0.0
    wall_s: float = 0.0
    speed: float = 1.0
    late_max_s: float = 0.0
    late_mean_s: float = 0.0
    late_p99_s: float = 0.0
    early_max_s: float = 0.0  # a write before its due time would be a bug: kept to prove it is 0

    def to_dict(self) -> dict:
        """As a JSON-ready dict (``speed`` null: as fast as possible)."""
        d = dataclasses.asdict(self)
        if not np.isfinite(d["speed"]):
            d["speed"] = None
        return d


class _Lateness:
    """Lateness statistics in bounded memory, however long the replay: exact max, min and mean; the 99th
    percentile from a histogram of 20 bins per decade from 1 us to 1000 s (within 12 % of the exact value;
    lateness below 1 us counts as 0)."""

    EDGES = np.concatenate(([-np.inf, 1e-6], np.logspace(-6, 3, 9 * 20 + 1)[1:], [np.inf]))

    def __init__(self) -> None:
        self.n = 0
        self.total = 0.0
        self.max = -np.inf
        self.min = np.inf
        self.counts = np.zeros(self.EDGES.size - 1, dtype=np.int64)

    def add(self, late: np.ndarray) -> None:
        if late.size == 0:
            return
        self.n += late.size
        self.total += float(late.sum())
        self.max = max(self.max, float(late.max()))
        self.min = min(self.min, float(late.min()))
        self.counts += np.histogram(late, self.EDGES)[0]

    def p99(self) -> float:
        k = int(np.searchsorted(np.cumsum(self.counts), 0.99 * self.n))
        if k == 0:
            return 0.0
        return float(min(self.EDGES[k + 1], self.max))


def play(source: Source, sink: Sink, speed: float = 1.0, *, chunk: int = 4096,
         progress: Callable[[PlayStats, float], None] | None = None,
         clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
         should_stop: Callable[[], bool] | None = None) -> PlayStats:
    """Write ``source``'s samples to ``sink`` paced by their timestamps.

    :param speed: replay speed factor (2.0 = twice as fast); ``inf`` = as fast as possible.
    :param progress: called about every 0.5 s with the running stats and the log time
        played so far (s).
    :param should_stop: polled between writes; True ends the replay early.
    :returns: :class:`PlayStats` with lateness statistics.
    """
    if not speed > 0:
        raise ValueError(f"speed (={speed}) must be > 0")
    stats = PlayStats(speed=speed)
    lat = _Lateness()
    t_first: int | None = None
    wall0 = 0.0
    last_progress = clock()
    played_s = 0.0
    for block in source.chunks(chunk):
        n = len(block)
        if n == 0:
            continue
        if t_first is None:
            t_first = int(block.t_ns[0])
            wall0 = clock()
        rel = (block.t_ns - t_first).astype(np.float64) * 1e-9
        due = wall0 + rel / speed if np.isfinite(speed) else np.full(n, -np.inf)
        i = 0
        while i < n:
            if should_stop is not None and should_stop():
                return _finish(stats, lat, clock() - wall0)
            now = clock()
            j = int(np.searchsorted(due, now, side="right"))
            if j <= i:
                sleep(max(due[i] - now, 0.0))
                continue
            start = clock()
            sink.write(block.slice(i, j))
            lat.add(start - due[i:j] if np.isfinite(speed) else np.zeros(j - i))
            stats.writes += 1
            stats.samples += j - i
            played_s = float(rel[j - 1])
            i = j
            if progress is not None and start - last_progress >= PROGRESS_EVERY_S:
                last_progress = start
                progress(_finish(dataclasses.replace(stats), lat, start - wall0), played_s)
        stats.log_span_s = played_s
    return _finish(stats, lat, clock() - wall0 if t_first is not None else 0.0)


def _finish(stats: PlayStats, lat: _Lateness, wall_s: float) -> PlayStats:
    stats.wall_s = float(wall_s)
    if lat.n:
        stats.late_max_s = max(lat.max, 0.0)
        stats.late_mean_s = lat.total / lat.n
        stats.late_p99_s = lat.p99()
        stats.early_max_s = max(-lat.min, 0.0)
    return stats


# --- command line --------------------------------------------------------------------------

def _open_sink(args: argparse.Namespace) -> Sink:
    if args.to == "can":
        from replay.can.bus import CanBusSink

        return CanBusSink(args.channel, dbc=args.dbc)
    from replay.live import ZenohCanSink, ZenohSampleSink
    from fpdd.zenohconf import zenoh_config

    conf = zenoh_config(listen=args.zenoh_listen or (), connect=args.zenoh_connect or (),
                        multicast_scouting=None if args.zenoh_config else not (args.zenoh_listen or args.zenoh_connect),
                        config_file=args.zenoh_config)
    if args.payload == "can":
        return ZenohCanSink(args.key, dbc=args.dbc, config=conf)
    return ZenohSampleSink(args.key, config=conf)


def _print_progress(total_s: float) -> Callable[[PlayStats, float], None]:
    def show(st: PlayStats, played_s: float) -> None:
        pct = f" ({100 * played_s / total_s:5.1f} %)" if total_s > 0 else ""
        sys.stderr.write(f"\rplayed {played_s:9.3f} s{pct}, {st.samples} samples, x{st.speed:g}, "
                         f"late max {st.late_max_s * 1e3:.2f} ms   ")
        sys.stderr.flush()
    return show


def cmd_play(args: argparse.Namespace) -> int:
    """``replay play``: open LOG and the target, replay, print the pacing statistics."""
    from replay.options import loss_warning, source_options
    from replay.factory import open_source

    if args.to == "can" and not args.channel:
        args.parser.error("--to can needs --channel can://INTERFACE/CHANNEL, e.g. can://socketcan/can0 "
                          "(python-can's virtual bus is in-process: no other program would hear it)")
    if args.to == "can" and args.payload != "samples":
        args.parser.error("--payload applies to --to zenoh")
    from replay import formats

    ns = argparse.Namespace(**vars(args))
    if not formats.is_can_log(args.log):
        ns.dbc = None  # --dbc then encodes the output frames only
    try:
        options = source_options(ns, args.log)
    except argparse.ArgumentTypeError as exc:
        args.parser.error(str(exc))
    with open_source(args.log, **options) as src, _open_sink(args) as sink:
        if args.to == "zenoh" and args.wait_s > 0:
            from replay.live.sinks import ZenohPublisher

            assert isinstance(sink, ZenohPublisher)  # what _open_sink makes for --to zenoh
            sink.wait_for_subscriber(args.wait_s)
        stats = play(src, sink, args.speed, progress=None if args.quiet else _print_progress(0.0))
        if not args.quiet:
            sys.stderr.write("\n")
    if args.json:
        print(json.dumps({"stats": stats.to_dict(), "report": src.report.to_dict()}))
    else:
        print(f"played {stats.samples} samples ({stats.log_span_s:.3f} s of log) in {stats.wall_s:.3f} s "
              f"at x{stats.speed:g}; lateness max {stats.late_max_s * 1e3:.3f} ms, "
              f"p99 {stats.late_p99_s * 1e3:.3f} ms, mean {stats.late_mean_s * 1e3:.3f} ms")
        print(src.report.summary())
    return loss_warning(src.report.to_dict())


def _speed(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if v == 0:  # as in twin demo --speed 0
        return float("inf")
    if not v > 0:
        raise argparse.ArgumentTypeError(f"{text}: expected a factor > 0, or 0 (or inf) for as fast as possible")
    return v


def register(subparsers) -> argparse.ArgumentParser:
    """Add ``play`` to the ``replay`` command's subparsers."""
    from replay import formats
    from replay.options import add_input_options, plain_text

    p = subparsers.add_parser("play", help="replay a log in real time to a CAN bus or Zenoh",
                              description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("log", help=f"log to replay ({', '.join(formats.FILE_SUFFIXES)})")
    p.add_argument("--to", choices=("can", "zenoh"), required=True, help="where to send the samples")
    p.add_argument("--speed", type=_speed, default=1.0, help="speed factor (default 1.0 = real time; 0 or inf: "
                   "as fast as possible, as in twin demo)")
    p.add_argument("--channel", metavar="can://INTERFACE/CHANNEL",
                   help="CAN bus, required with --to can, e.g. can://socketcan/can0, can://pcan/PCAN_USBBUS1")
    p.add_argument("--key", default="fpdd/msp25/samples", help="Zenoh key expression (default fpdd/msp25/samples)")
    p.add_argument("--payload", choices=("samples", "can"), default="samples",
                   help="Zenoh payload: JSON sample blocks or raw CAN frames (see replay.live)")
    p.add_argument("--zenoh-listen", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-config", help="Zenoh json5 config file")
    p.add_argument("--wait", "--wait-s", dest="wait_s", type=non_negative_seconds, default=2.0, metavar="S",
                   help="Zenoh: wait up to S seconds for a subscriber before starting (default 2; as twin alarms "
                   "--wait)")
    add_input_options(p)
    p.set_defaults(dbc=None)
    p.add_argument("--json", action="store_true", help="print the statistics and read report as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display on stderr")
    p.set_defaults(func=cmd_play, parser=p)
    return p
