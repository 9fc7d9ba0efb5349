"""Record a live input to a log file: ``replay record INPUT --out FILE`` (like python-can's ``can.logger``).

::

    replay record can://socketcan/can0 --out rig.blf --duration 60
    replay record can://virtual/rig1 --out rig.mcap --limit 10000
    replay record zenoh://fpdd/msp25/samples --out rig.mcap --zenoh-connect tcp/10.0.0.5:7447
    replay record zenoh://fpdd/msp25/can --out rig.asc

What is written depends on the output's suffix (:mod:`replay.formats`):

* a CAN log (``.asc .blf .log .trc``): the raw frames as they come, written by
  python-can's writer for the suffix -- from a CAN bus (every frame, any id, nothing
  decoded), or from Zenoh ``fpdd.can/1`` payloads (:mod:`replay.live`);
* ``.mcap`` or ``.csv``: decoded rig samples in SI -- from a CAN bus through the DBC
  (:class:`~replay.can.bus.CanBusSource`) or from Zenoh (either payload,
  :class:`~replay.live.ZenohSource`).

The recording ends after ``--duration`` seconds (wall time, at most a week), after
``--limit`` frames (CAN log) or samples, at the sender's end marker (Zenoh), or on
Ctrl-C; the file is closed properly in every case.  Progress goes to stderr twice a
second (``--quiet``: none); the summary to stdout (``--json``: one JSON object).
Exit status: 0 something was recorded; 1 nothing was (or the input or output could
not be opened: one line naming it); 2 bad command line; 3 recorded, but input was
dropped on the way (the warning line says what).

No real CAN interface may exist where this runs (CI, containers): python-can's
``virtual`` interface works in-process only, so ``can://virtual/...`` is for tests.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import queue
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable

from fpdd.argtypes import positive_int
from replay import formats
from replay.base import ReadReport
from fpdd.errors import DataError, SourceError

#: Longest recording one command takes (s): a week.
MAX_DURATION_S = 7 * 24 * 3600.0
#: Seconds between two progress lines.
PROGRESS_EVERY_S = 0.5


@dataclasses.dataclass
class RecordStats:
    """What a recording did."""

    input: str
    output: str
    kind: str              # "frames" (a CAN log) or "samples"
    count: int = 0         # frames or samples written
    wall_s: float = 0.0
    ended_by: str = ""     # "duration", "limit", "end marker", "interrupt", "closed"
    report: dict = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _check(duration_s: float | None, limit: int | None) -> None:
    if duration_s is not None and not (0 < duration_s <= MAX_DURATION_S):
        raise DataError(f"--duration {duration_s:g}: expected seconds in (0, {MAX_DURATION_S:g}] "
                        f"(at most a week per recording)")
    if limit is not None and limit < 1:
        raise DataError(f"--limit {limit}: expected a positive number of frames or samples")


class _Until:
    """The end condition of a recording: duration, limit, stop event; and progress."""

    def __init__(self, duration_s: float | None, limit: int | None, stop: threading.Event,
                 progress: Callable[[int, float], None] | None) -> None:
        self.t0 = time.monotonic()
        self.deadline = None if duration_s is None else self.t0 + duration_s
        self.limit = limit
        self.stop = stop
        self.progress = progress
        self.last = self.t0
        self.ended_by = ""

    def left_s(self) -> float:
        return float("inf") if self.deadline is None else self.deadline - time.monotonic()

    def done(self, count: int) -> bool:
        now = time.monotonic()
        if self.progress is not None and now - self.last >= PROGRESS_EVERY_S:
            self.last = now
            self.progress(count, now - self.t0)
        if self.limit is not None and count >= self.limit:
            self.ended_by = "limit"
        elif self.deadline is not None and now >= self.deadline:
            self.ended_by = "duration"
        elif self.stop.is_set():
            self.ended_by = "interrupt"
        return bool(self.ended_by)


def _can_log_writer(path: str):
    fmt = formats.lookup(path, kind="can", what="CAN log")
    writer_cls = formats.python_can_classes(fmt.suffix)[1]
    try:
        return writer_cls(path)
    except OSError as e:
        raise SourceError(f"{path}: cannot create CAN log: {e.strerror or e}") from e


def record(input_uri: str, out: str, *, duration_s: float | None = None, limit: int | None = None,
           dbc: str | None = None, zenoh_conf=None, stop: threading.Event | None = None,
           progress: Callable[[int, float], None] | None = None, poll_s: float = 0.1,
           session=None) -> RecordStats:
    """Record ``input_uri`` (``can://...`` or ``zenoh://...``) to ``out`` until an end condition.

    ``stop``: set it (from another thread, or the SIGINT handler of the command) to end
    the recording.  Returns :class:`RecordStats`; the output is closed in every case.
    """
    from replay.factory import _scheme

    _check(duration_s, limit)
    scheme = _scheme(input_uri)
    if scheme not in formats.URI_SCHEMES:
        raise DataError(f"{input_uri}: expected a live input can://INTERFACE/CHANNEL or zenoh://KEYEXPR "
                        "(to copy a log file use replay convert)")
    fmt = formats.lookup(out, what="output")
    if os.path.isdir(out):
        raise SourceError(f"{out}: cannot create output file: is a directory")
    stop = stop or threading.Event()
    until = _Until(duration_s, limit, stop, progress)
    if fmt.kind == "can":
        if scheme == "can":
            stats = _bus_to_can_log(input_uri, out, until, poll_s)
        else:
            stats = _zenoh_to_can_log(input_uri, out, until, poll_s, zenoh_conf, session)
    else:
        stats = _to_samples(input_uri, out, until, dbc, poll_s, zenoh_conf, session)
    stats.wall_s = time.monotonic() - until.t0
    stats.ended_by = stats.ended_by or until.ended_by
    return stats


def _bus_to_can_log(uri: str, out: str, until: _Until, poll_s: float) -> RecordStats:
    from replay.can.bus import open_bus

    writer = _can_log_writer(out)  # before the bus: an unwritable output is said first
    stats = RecordStats(uri, out, "frames")
    try:
        bus, owned = open_bus(uri)
    except Exception:
        writer.stop()
        os.unlink(out)
        raise
    try:
        while not until.done(stats.count):
            msg = bus.recv(timeout=max(0.0, min(poll_s, until.left_s())))
            if msg is not None:
                writer.on_message_received(msg)
                stats.count += 1
    finally:
        writer.stop()
        if owned:
            bus.shutdown()
    return stats


def _zenoh_to_can_log(uri: str, out: str, until: _Until, poll_s: float, conf, session) -> RecordStats:
    import zenoh

    from replay.can.encode import frames_to_messages
    from replay.live.payloads import PayloadError, payload_to_frames
    from replay.live.sinks import open_live_session, parse_zenoh_uri

    key = parse_zenoh_uri(uri)
    writer = _can_log_writer(out)
    stats = RecordStats(uri, out, "frames")
    report = ReadReport(uri)
    q: queue.Queue[bytes] = queue.Queue(maxsize=1024)
    drops: Counter[str] = Counter()

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            q.put_nowait(sample.payload.to_bytes())
        except queue.Full:
            drops["flood"] += 1

    owned = session is None
    try:
        sess = session if session is not None else open_live_session(conf, uri)
    except Exception:
        writer.stop()
        os.unlink(out)
        raise
    sub = sess.declare_subscriber(key, on_sample)
    n = 0
    try:
        while not until.done(stats.count):
            try:
                payload = q.get(timeout=max(0.0, min(poll_s, until.left_s())))
            except queue.Empty:
                continue
            n += 1
            try:
                frames = payload_to_frames(payload, f"payload {n}")
            except PayloadError as e:
                report.skip(e.cause, f"payload {n}", str(e).split(": ", 1)[-1])
                continue
            if not len(frames):
                stats.ended_by = "end marker"
                break
            for msg in frames_to_messages(frames):
                writer.on_message_received(msg)
                stats.count += 1
                if until.limit is not None and stats.count >= until.limit:
                    break
    finally:
        writer.stop()
        sub.undeclare()
        if owned:
            sess.close()
    report.skipped.update(drops)
    report.samples_out = stats.count
    stats.report = report.to_dict()
    return stats


def _to_samples(uri: str, out: str, until: _Until, dbc, poll_s: float, conf, session) -> RecordStats:
    from replay.factory import open_sink, open_source

    options: dict = {"poll_s": poll_s}
    if dbc:
        options["dbc"] = dbc
    if uri.startswith("zenoh://"):
        if session is not None:
            options["session"] = session
        elif conf is not None:
            options["config"] = conf
    stats = RecordStats(uri, out, "samples")
    sink = open_sink(out)  # before the input: an unwritable output is said first
    try:
        src = open_source(uri, **options)
    except Exception:
        sink.close()
        os.unlink(out)
        raise
    try:
        with src:
            for block in src.chunks(1000):
                if len(block):
                    if until.limit is not None and stats.count + len(block) > until.limit:
                        block = block.slice(0, until.limit - stats.count)
                    sink.write(block)
                    stats.count += len(block)
                if until.done(stats.count):
                    break
            else:
                stats.ended_by = "end marker"
            stats.report = src.report.to_dict()
    finally:
        sink.close()
    return stats


# --- command line --------------------------------------------------------------------------

def _duration(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (0 < v <= MAX_DURATION_S):
        raise argparse.ArgumentTypeError(f"{text} s: expected seconds in (0, {MAX_DURATION_S:g}] (at most a week)")
    return v


def cmd_record(args: argparse.Namespace) -> int:
    from replay.options import loss_warning
    from fpdd.zenohconf import zenoh_config

    conf = None
    if args.input.startswith("zenoh://"):
        conf = zenoh_config(listen=args.zenoh_listen or (), connect=args.zenoh_connect or (),
                            multicast_scouting=None if args.zenoh_config else not (args.zenoh_listen or args.zenoh_connect),
                            config_file=args.zenoh_config)
    stop = threading.Event()

    def on_sigint(signum, frame):  # noqa: ARG001 - end the recording, close the file properly
        stop.set()

    shown = []

    def show(count: int, wall_s: float) -> None:
        shown.append(1)
        sys.stderr.write(f"\rrecording {args.input} -> {args.out}: {count} "
                         f"{'frames' if formats.is_can_log(args.out) else 'samples'} in {wall_s:.1f} s   ")
        sys.stderr.flush()

    previous = signal.signal(signal.SIGINT, on_sigint) if threading.current_thread() is threading.main_thread() \
        else None
    try:
        stats = record(args.input, args.out, duration_s=args.duration, limit=args.limit, dbc=args.dbc,
                       zenoh_conf=conf, stop=stop, progress=None if args.quiet else show)
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
        if shown:
            sys.stderr.write("\n")
    if args.json:
        print(json.dumps(stats.to_dict()))
    else:
        print(f"recorded {stats.count} {stats.kind} from {stats.input} to {stats.output} in {stats.wall_s:.3f} s "
              f"(ended by {stats.ended_by or 'closed'})")
    if stats.count == 0:
        print(f"replay: error: {args.input}: nothing received"
              + (f" within {args.duration:g} s" if args.duration else "") + f"; {args.out} holds no data",
              file=sys.stderr)
        return 1
    return loss_warning(stats.report)


def register(subparsers) -> argparse.ArgumentParser:
    """Add ``record`` to the ``replay`` command's subparsers."""
    from replay.options import plain_text

    p = subparsers.add_parser("record", help="record a live CAN bus or Zenoh input to a log file",
                              description=plain_text(__doc__), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", metavar="INPUT", help="can://INTERFACE/CHANNEL or zenoh://KEYEXPR")
    p.add_argument("--out", "-o", required=True, metavar="FILE",
                   help=f"log to write ({', '.join(formats.FILE_SUFFIXES)}): CAN logs get the raw frames, "
                        ".mcap/.csv the decoded samples")
    p.add_argument("--duration", type=_duration, metavar="S", help="stop after S seconds (wall time)")
    p.add_argument("--limit", type=positive_int, metavar="N", help="stop after N frames (CAN log) or samples")
    p.add_argument("--dbc", metavar="FILE", help="DBC to decode CAN frames to samples (default: the MSP25 DBC)")
    p.add_argument("--zenoh-listen", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh json5 config file")
    p.add_argument("--json", action="store_true", help="print the recording's statistics as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_record)
    return p
