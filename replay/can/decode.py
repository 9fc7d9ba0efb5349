"""CAN frames to rig samples: frame checks, DBC decoding and alignment onto one grid.

Frames come in numpy blocks (:class:`replay.can.codec.Frames`), are checked, decoded with the DBC-driven
:class:`replay.can.codec.VectorCodec` and aligned onto one grid; the same path serves CAN logs
(:mod:`replay.can.logs`), a live bus (:mod:`replay.can.bus`) and frames over Zenoh (:mod:`replay.live`).

Alignment rule
==============

* **Grid.**  By default the grid is the timestamps of the *master* message: the
  message carrying ``x`` (``MSP25_Position``, 1 kHz), or, if the log has none, the
  fastest message seen.  With ``grid_hz`` the grid is uniform instead,
  ``t0 + k / grid_hz`` from the first master frame.
* **Same-cycle window.**  A controller sends several frames per control cycle
  (``MSP25_Valve`` follows ``MSP25_Position`` by some 100 us).  Grid instant ``t_k``
  takes, for every signal, the value of the *latest frame with timestamp
  < t_k + window*, ``window`` = half the master period (half the grid step with
  ``grid_hz``).  So ``u`` of the same cycle lands on the same sample as ``x``.
* **Zero-order hold with a max age.**  Slower signals (pressures at 500 Hz, supply
  pressure and oil temperature at 10 Hz) keep their last value.  When that value is
  older than ``max_age`` (default 2.5 periods of its message from the DBC's
  ``GenMsgCycleTime``) the sample is set to NaN and counted in the report as
  ``stale <signal>``, with a message naming the time span.  Nothing is interpolated.
* **Start.**  Grid instants before every delivered signal has had a first value are
  dropped and counted as ``warmup``.
* **Which signals.**  Those of ``signals=`` if given; otherwise the rig signals of
  the DBC messages seen in the first ``probe_s`` of the log (default 2.5 times the
  slowest DBC period).  Gaps in the master message longer than 2.5 master periods
  are reported in ``report.gaps``.

Timestamps are python-can's float seconds, rounded to whole microseconds (no format
here stores more) and returned as int64 ns.  ASC files are read with absolute times
(start of the trigger block, millisecond resolution, plus the relative offsets).

Bad input (each counted in ``report.skipped`` under the name given, with a message
naming file, frame index, timestamp and id): ``unknown_id 0x...`` (id not in the DBC;
the first 20 ids by name, further ones as ``unknown_id other``),
``wrong_dlc``, ``decode_error`` (a value outside the DBC's [min, max], a remote or
error frame), ``time_backwards`` (earlier than a frame before it), ``time_repeated``
(same id, same or earlier time), ``counter_gap`` (frames lost by the rolling counter,
nothing skipped), ``time_jump`` (a single wild timestamp: only that frame is skipped),
``bad_line`` (a text-log line python-can cannot parse, or skips silently although it
looks like a frame; ``ignored_line`` for ASC event lines), ``damaged_object`` (a BLF
object or container that does not parse or inflate), and a truncated file
(``report.truncated``; what was read is kept).
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Iterator, Sequence

import numpy as np

from fpdd.units import SIGNALS
from replay.base import Problem, ReadReport, Samples
from replay.can.codec import COUNTER, Frames, MessageLayout, VectorCodec, key_str
from replay.quality import time_spikes
from fpdd.errors import DataError


#: A forward jump of a frame's time beyond this (ns) followed by a time back in line is a wild timestamp.
_WILD_JUMP_NS = 1_000_000

#: Frames per block read from a log.
BLOCK_FRAMES = 65536

#: Default max age of a held value, in periods of its message.
MAX_AGE_PERIODS = 2.5


def _fmt_t(t_ns: int) -> str:
    return f"t={t_ns / 1e9:.6f} s"


def as_codec(dbc) -> VectorCodec:
    return dbc if isinstance(dbc, VectorCodec) else VectorCodec(dbc)


# --- frame checks and decoding ----------------------------------------------------------

@dataclasses.dataclass
class Decoded:
    """Decoded frames of one message: times (ns, increasing) and rig signal values (SI)."""

    t_ns: np.ndarray
    values: dict[str, np.ndarray]


class FrameDecoder:
    """Checks and decodes :class:`Frames` blocks (stateful across blocks of one stream).

    ``decode(frames)`` returns ``{key: Decoded}`` for the frames that passed every check
    and records every skipped frame in ``report``.  Frame indices in messages count
    from 0 at the start of the stream.
    """

    def __init__(self, codec: VectorCodec, report: ReadReport, max_named_ids: int = 20) -> None:
        self.codec = codec
        self.report = report
        self.index0 = 0
        self.t_max: int | None = None
        self.last_t: dict[int, int] = {}
        self.last_counter: dict[int, int] = {}
        self.unknown: Counter = Counter()  # frames of each unknown id
        self._named: set[int] = set()  # unknown ids counted under their own name in the report
        self.max_named_ids = max_named_ids
        self.frames_ok = 0

    def _where(self, frames: Frames, i: int) -> str:
        return f"frame {self.index0 + i} ({_fmt_t(int(frames.t_ns[i]))}, id {key_str(int(frames.key[i]))})"

    def _skip_rows(self, frames: Frames, bad: np.ndarray, reason: str, what) -> None:
        """Count rows ``bad`` (bool) under ``reason``; message for the first few via ``what(i)``."""
        idx = np.flatnonzero(bad)
        for j, i in enumerate(idx):
            if j < 3:
                self.report.skip(reason, self._where(frames, int(i)), what(int(i)))
            else:
                self.report.skipped[reason] += len(idx) - j
                break

    def decode(self, frames: Frames) -> dict[int, Decoded]:
        n = len(frames)
        rep = self.report
        rep.records_read += n
        keep = np.ones(n, bool)

        # error frames carry no data; remote frames of a DBC id carry none either
        err = frames.kind == Frames.ERROR
        if err.any():
            self._skip_rows(frames, err, "decode_error", lambda i: "error frame on the bus; no data to decode")
            keep &= ~err

        # a single wild timestamp (a damaged log line or object) is dropped alone
        t = frames.t_ns
        spike = keep & time_spikes(t, _WILD_JUMP_NS)
        if spike.any():
            self._skip_rows(frames, spike, "time_jump",
                            lambda i: f"timestamp jumps to {t[i] / 1e9:.6f} s between {t[i - 1] / 1e9:.6f} s and "
                                      f"{t[i + 1] / 1e9:.6f} s: a wild timestamp, this frame alone is skipped")
            keep &= ~spike
            t = np.where(spike, np.concatenate([[t[0]], t[:-1]]), t)  # out of the running maximum

        # time going backwards (vs. any frame before it, across blocks)
        prev_max = np.maximum.accumulate(t)
        prev_max = np.concatenate([[self.t_max if self.t_max is not None else np.iinfo(np.int64).min], prev_max[:-1]])
        back = keep & (t < prev_max)
        if back.any():
            self._skip_rows(frames, back, "time_backwards",
                            lambda i: f"timestamp goes back to {t[i] / 1e9:.6f} s after {prev_max[i] / 1e9:.6f} s; "
                                      "expected non-decreasing time")
            keep &= ~back
        if n:
            self.t_max = int(max(prev_max[-1], t[-1]))

        # unknown ids
        known = np.isin(frames.key, self.codec.keys)
        unk = keep & ~known
        if unk.any():
            rows_u = np.flatnonzero(unk)
            ids, first_rows, counts = np.unique(frames.key[rows_u], return_index=True, return_counts=True)
            for k, j, c in zip(ids.tolist(), first_rows.tolist(), counts.tolist()):
                self.unknown[k] += c
                if k not in self._named and len(self._named) < self.max_named_ids:
                    self._named.add(k)
                    rep.skip(f"unknown_id {key_str(k)}", self._where(frames, int(rows_u[j])),
                             f"id {key_str(k)} is not in the DBC {self.codec.source}; frames with this id are skipped")
                    c -= 1
                rep.skipped[f"unknown_id {key_str(k)}" if k in self._named else "unknown_id other"] += c
            keep &= ~unk

        out: dict[int, Decoded] = {}
        for key in np.unique(frames.key[keep]):
            key = int(key)
            lay = self.codec.messages[key]
            rows = np.flatnonzero(keep & (frames.key == key))
            rows = self._check_rows(frames, rows, lay)
            if rows.size == 0:
                continue
            phys = self.codec.decode_raw(key, frames.data[rows])
            bad_by_sig = self.codec.out_of_range(key, phys)
            if bad_by_sig:
                bad = np.zeros(rows.size, bool)
                for name, b in bad_by_sig.items():
                    s = next(s for s in lay.signals if s.name == name)
                    for j in np.flatnonzero(b & ~bad)[:3]:
                        rep.skip("decode_error", self._where(frames, int(rows[j])),
                                 f"{lay.name}: signal {name} = {phys[name][j]:g} {s.unit} outside the DBC range "
                                 f"[{s.minimum:g}, {s.maximum:g}]; frame skipped")
                    extra = int((b & ~bad).sum()) - min(3, int((b & ~bad).sum()))
                    rep.skipped["decode_error"] += extra
                    bad |= b
                good = ~bad
                rows = rows[good]
                phys = {k: v[good] for k, v in phys.items()}
                if rows.size == 0:
                    continue
            # rolling counter: count lost frames (nothing is skipped)
            cnt = lay.counter
            if cnt is not None:
                c = phys[cnt.name].astype(np.int64)
                prev = self.last_counter.get(key)
                seq = np.concatenate([[prev], c]) if prev is not None else c
                step = np.diff(seq) % (1 << cnt.length)
                lost = np.flatnonzero(step != 1)
                for j in lost[:3]:
                    r = int(rows[j + (0 if prev is not None else 1)])
                    where = f"frame {self.index0 + r} ({_fmt_t(int(frames.t_ns[r]))}, id {key_str(key)})"
                    rep.skip("counter_gap", where,
                             f"{lay.name}: rolling counter {cnt.name} jumps {int(seq[j])} -> {int(seq[j + 1])}, "
                             f"expected {(int(seq[j]) + 1) % (1 << cnt.length)}: "
                             f"{(int(step[j]) - 1) % (1 << cnt.length)} frame(s) lost")
                if lost.size > 3:
                    rep.skipped["counter_gap"] += int(lost.size - 3)
                self.last_counter[key] = int(c[-1])
            values = {}
            for s in lay.signals:
                if s.rig is not None and s.rig != COUNTER:
                    values[s.rig] = phys[s.name] * s.si_factor + s.si_offset
            out[key] = Decoded(frames.t_ns[rows], values)
            self.frames_ok += rows.size
        self.index0 += n
        return out

    def _check_rows(self, frames: Frames, rows: np.ndarray, lay: MessageLayout) -> np.ndarray:
        kind = frames.kind[rows]
        remote = kind == Frames.REMOTE
        if remote.any():
            self._skip_rows(frames, np.isin(np.arange(len(frames)), rows[remote]), "decode_error",
                            lambda i: f"{lay.name}: remote frame carries no data; "
                                      f"expected a data frame of {lay.length} bytes")
            rows = rows[~remote]
        dlc = frames.dlc[rows]
        wrong = (dlc != lay.length) | (frames.kind[rows] == Frames.LONG_FD)
        if wrong.any():
            mask = np.zeros(len(frames), bool)
            mask[rows[wrong]] = True
            self._skip_rows(frames, mask, "wrong_dlc",
                            lambda i: f"{lay.name}: DLC {int(frames.dlc[i])}, expected {lay.length} bytes")
            rows = rows[~wrong]
        if rows.size == 0:
            return rows
        # time must increase per id
        tt = frames.t_ns[rows]
        prev = self.last_t.get(lay.key)
        first = np.iinfo(np.int64).min if prev is None else prev
        prev_t = np.concatenate([[first], np.maximum.accumulate(tt)[:-1]])
        rep_mask = tt <= prev_t
        if rep_mask.any():
            mask = np.zeros(len(frames), bool)
            mask[rows[rep_mask]] = True
            self._skip_rows(frames, mask, "time_repeated",
                            lambda i: f"{lay.name}: timestamp repeats or goes back for this id; expected a later one")
            rows = rows[~rep_mask]
        if rows.size:
            self.last_t[lay.key] = int(frames.t_ns[rows[-1]])
        return rows


# --- alignment -------------------------------------------------------------------------------

@dataclasses.dataclass
class AlignPlan:
    """What the aligner needs: signals, the message of each, master, grid, window, max ages (ns)."""

    signals: tuple[str, ...]
    message_of: dict[str, int]
    master: int
    grid_ns: int | None
    window_ns: int
    max_age_ns: dict[int, int]
    master_period_ns: int


def make_plan(codec: VectorCodec, seen: dict[int, Decoded] | None, signals: Sequence[str] | None = None,
              grid_hz: float | None = None, window_s: float | None = None, max_age_s: float | None = None,
              source: str = "") -> AlignPlan:
    """Choose signals, master message, window and max ages (see the module docstring).

    ``seen`` are frames decoded in the probe window (None: use every DBC signal).
    """
    if signals is None:
        if seen is None:
            signals = codec.rig_signals
        else:
            have = {r for k in seen for r in codec.messages[k].rig_signals}
            signals = tuple(s for s in SIGNALS if s in have)
        if not signals:
            if not codec.rig_signals:
                raise DataError(f"{source}: no rig signal in the DBC: {codec.describe_lookup()}")
            raise DataError(f"{source}: no frame of a DBC message carrying rig signals "
                            f"({', '.join(codec.rig_signals)}) at the start of the stream")
    else:
        signals = tuple(signals)
        for s in signals:
            if codec.message_of(s) is None:
                raise DataError(f"{source}: signal {s!r} is in no message of the DBC {codec.source}"
                                + (f" (it carries {', '.join(codec.rig_signals)})" if codec.rig_signals else "")
                                + f": {codec.describe_lookup()}")
    message_of = {}
    for s in signals:
        lay = codec.message_of(s)
        assert lay is not None  # a signal of the DBC's rig messages, or checked above
        message_of[s] = lay.key
    keys = sorted(set(message_of.values()))

    def period_ns(k: int) -> int | None:
        p = codec.messages[k].period_s
        if p:
            return int(round(p * 1e9))
        if seen is not None and k in seen and len(seen[k].t_ns) > 2:
            return int(np.median(np.diff(seen[k].t_ns)))
        return None

    if "x" in message_of:
        master = message_of["x"]
    else:
        master = min(keys, key=lambda k: period_ns(k) or 1 << 62)
    mp = period_ns(master)
    if mp is None:
        raise DataError(f"{source}: no period for master message {codec.messages[master].label}: "
                        "no GenMsgCycleTime in the DBC and too few frames to estimate it")
    grid_ns = int(round(1e9 / grid_hz)) if grid_hz else None
    if window_s is not None:
        window_ns = int(round(window_s * 1e9))
    else:
        window_ns = (grid_ns if grid_ns else mp) // 2
    ages = {}
    for k in keys:
        p = period_ns(k) or mp
        ages[k] = int(round(max_age_s * 1e9)) if max_age_s is not None else int(MAX_AGE_PERIODS * p)
    return AlignPlan(signals, message_of, master, grid_ns, window_ns, ages, mp)


class Aligner:
    """Streaming alignment of decoded frames onto one sample grid (rule in the module docstring).

    ``feed(decoded)`` takes one block of :class:`Decoded` per message (time ordered,
    later than anything fed before) and returns the grid samples that can be final;
    ``flush()`` returns the rest at the end of the stream.
    """

    def __init__(self, plan: AlignPlan, codec: VectorCodec, report: ReadReport) -> None:
        self.plan = plan
        self.codec = codec
        self.report = report
        self.keys = sorted(set(plan.message_of.values()))
        self.buf_t = {k: np.zeros(0, np.int64) for k in self.keys}
        self.buf_v = {k: {s: np.zeros(0) for s in plan.signals if plan.message_of[s] == k} for k in self.keys}
        self.t_latest: int | None = None
        self.last_grid: int | None = None
        self.next_grid: int | None = None
        self.started = False
        self.warmup = 0
        self.warmup_t: tuple[int, int] | None = None
        self.last_master_t: int | None = None

    def feed(self, decoded: dict[int, Decoded]) -> Samples:
        for k, d in decoded.items():
            if k not in self.buf_t or len(d.t_ns) == 0:
                continue
            self.buf_t[k] = np.concatenate([self.buf_t[k], d.t_ns])
            for s in self.buf_v[k]:
                self.buf_v[k][s] = np.concatenate([self.buf_v[k][s], d.values[s]])
            tl = int(d.t_ns[-1])
            self.t_latest = tl if self.t_latest is None else max(self.t_latest, tl)
            if k == self.plan.master:
                self._check_gaps(d.t_ns)
        return self._emit(final=False)

    def release(self) -> Samples:
        """Live streams, after a quiet spell longer than the window: emit every pending grid
        instant now (no frame of its cycle can still come); alignment goes on after."""
        return self._emit(final=True)

    def flush(self) -> Samples:
        out = self._emit(final=True)
        if not self.started and self.warmup:
            self._report_warmup(final=True)
        return out

    def _check_gaps(self, t: np.ndarray) -> None:
        seq = np.concatenate([[self.last_master_t], t]) if self.last_master_t is not None else t
        self.last_master_t = int(t[-1])
        if len(seq) < 2:
            return
        dt = np.diff(seq)
        limit = MAX_AGE_PERIODS * self.plan.master_period_ns
        for j in np.flatnonzero(dt > limit):
            a, b = int(seq[j]), int(seq[j + 1])
            self.report.gaps.append((a, b))
            if len(self.report.problems) < self.report.max_problems:
                self.report.problems.append(Problem(
                    self.report.file, f"{_fmt_t(a)} .. {_fmt_t(b)}",
                    f"gap of {(b - a) / 1e6:.3f} ms in {self.codec.messages[self.plan.master].name} "
                    f"(period {self.plan.master_period_ns / 1e6:g} ms); not interpolated"))

    def _grid(self, final: bool) -> np.ndarray:
        p = self.plan
        if self.t_latest is None:
            return np.zeros(0, np.int64)
        horizon = self.t_latest if not final else np.iinfo(np.int64).max - p.window_ns
        mt = self.buf_t[p.master]
        if p.grid_ns is None:
            lo = 0 if self.last_grid is None else np.searchsorted(mt, self.last_grid, side="right")
            g = mt[lo:]
            return g[g + p.window_ns <= horizon] if not final else g
        if self.next_grid is None:
            if mt.size == 0:
                return np.zeros(0, np.int64)
            self.next_grid = int(mt[0])
        end = self.t_latest - (p.window_ns if not final else 0)
        if end < self.next_grid:
            return np.zeros(0, np.int64)
        n = (end - self.next_grid) // p.grid_ns + 1
        return self.next_grid + p.grid_ns * np.arange(n, dtype=np.int64)

    def _emit(self, final: bool) -> Samples:
        p = self.plan
        g = self._grid(final)
        if g.size == 0:
            return Samples(np.zeros(0, np.int64), {s: np.zeros(0) for s in p.signals})
        g_last = int(g[-1])
        cols: dict[str, np.ndarray] = {}
        valid = np.ones(g.size, bool)
        for k in self.keys:
            t = self.buf_t[k]
            if k == p.master and p.grid_ns is None:
                idx = np.searchsorted(t, g, side="left")  # the grid instants are these frames
            else:
                idx = np.searchsorted(t, g + p.window_ns, side="left") - 1
            ok = idx >= 0
            valid &= ok
            idxc = np.clip(idx, 0, None)
            t_used = t[idxc] if t.size else np.zeros(g.size, np.int64)
            stale = ok & (g - t_used > p.max_age_ns[k])
            for s, v in self.buf_v[k].items():
                col = v[idxc] if v.size else np.full(g.size, np.nan)
                cols[s] = np.where(ok & ~stale, col, np.nan)
            if stale.any():
                self._report_stale(k, g, stale, t_used)
        # warm-up: drop grid instants before every signal has had a value
        if not self.started:
            first = np.flatnonzero(valid)
            n_drop = int(first[0]) if first.size else g.size
            if n_drop:
                self.warmup += n_drop
                a = int(g[0]) if self.warmup_t is None else self.warmup_t[0]
                self.warmup_t = (a, int(g[n_drop - 1]))
            if first.size:
                self.started = True
                if self.warmup:
                    self._report_warmup(final=False)
            g = g[n_drop:]
            cols = {s: c[n_drop:] for s, c in cols.items()}
        # advance and trim the buffers
        self.last_grid = g_last
        if p.grid_ns is not None:
            self.next_grid = g_last + p.grid_ns
        self._trim()
        self.report.samples_out += int(g.size)
        return Samples(g, cols)

    def _trim(self) -> None:
        p = self.plan
        if self.last_grid is None:
            return
        for k in self.keys:
            t = self.buf_t[k]
            if k == p.master and p.grid_ns is None:
                i = int(np.searchsorted(t, self.last_grid, side="right"))
                # keep the last emitted master frame as carry (for nothing but symmetry)
                i = max(i - 1, 0)
            else:
                i = int(np.searchsorted(t, self.last_grid + p.window_ns, side="left")) - 1
                i = max(i, 0)
            if i:
                self.buf_t[k] = t[i:]
                for s in self.buf_v[k]:
                    self.buf_v[k][s] = self.buf_v[k][s][i:]

    def _report_warmup(self, final: bool) -> None:
        assert self.warmup_t is not None  # set with the first grid instant dropped
        a, b = self.warmup_t
        missing = [s for s in self.plan.signals if self.buf_t[self.plan.message_of[s]].size == 0]
        what = (f"{self.warmup} grid sample(s) dropped before every signal had a first value"
                + (f"; never seen: {', '.join(missing)}" if missing and final else ""))
        self.report.skip("warmup", f"{_fmt_t(a)} .. {_fmt_t(b)}", what)
        self.report.skipped["warmup"] += self.warmup - 1

    def _report_stale(self, k: int, g: np.ndarray, stale: np.ndarray, t_last: np.ndarray) -> None:
        lay = self.codec.messages[k]
        names = [s for s in self.buf_v[k]]
        idx = np.flatnonzero(stale)
        # contiguous stretches
        breaks = np.flatnonzero(np.diff(idx) > 1)
        starts = np.concatenate([[idx[0]], idx[breaks + 1]])
        ends = np.concatenate([idx[breaks], [idx[-1]]])
        for s in names:
            self.report.skipped[f"stale {s}"] += int(idx.size)
        for a, b in list(zip(starts, ends))[:3]:
            if len(self.report.problems) >= self.report.max_problems:
                break
            self.report.problems.append(Problem(
                self.report.file, f"{_fmt_t(int(g[a]))} .. {_fmt_t(int(g[b]))}",
                f"{', '.join(names)} stale: last {lay.label} frame at {_fmt_t(int(t_last[a]))}, older than the "
                f"max age {self.plan.max_age_ns[k] / 1e6:g} ms; {b - a + 1} sample(s) set to NaN"))


def split_block(block: Samples, size: int) -> Iterator[Samples]:
    if len(block) == 0:
        return
    if len(block) <= size:
        yield block
        return
    for a in range(0, len(block), size):
        yield block.slice(a, a + size)


class CanStream:
    """Decode + align a stream of :class:`Frames` blocks (shared by log and live sources)."""

    def __init__(self, codec: VectorCodec, plan: AlignPlan, report: ReadReport) -> None:
        self.decoder = FrameDecoder(codec, report)
        self.aligner = Aligner(plan, codec, report)

    def feed(self, frames: Frames) -> Samples:
        return self.aligner.feed(self.decoder.decode(frames))

    def release(self) -> Samples:
        """What the aligner holds back for a window that has passed (live: after a quiet spell)."""
        return self.aligner.release()

    def flush(self) -> Samples:
        return self.aligner.flush()


def probe_plan(codec: VectorCodec, frames: Frames, source: str, signals=None, grid_hz=None,
               window_s=None, max_age_s=None) -> AlignPlan:
    """Alignment plan from the first frames of a stream (which messages are present)."""
    seen = FrameDecoder(codec, ReadReport(source)).decode(frames)
    return make_plan(codec, seen, signals, grid_hz, window_s, max_age_s, source)
