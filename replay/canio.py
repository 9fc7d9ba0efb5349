"""CAN logs (ASC, BLF, candump ``.log``, TRC) as a sample stream, and samples as CAN logs.

Reading goes through python-can's own log readers (:class:`can.ASCReader`,
:class:`can.BLFReader`, :class:`can.CanutilsLogReader`, :class:`can.TRCReader`);
frames are collected into numpy blocks (:class:`replay.dbc.Frames`), checked, decoded
with the DBC-driven :class:`replay.dbc.VectorCodec` and aligned onto one grid.

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

Damage costs only itself: python-can's text readers are restarted after a bad line
(the header is replayed to them), so the lines after it are read; a BLF file is walked
object by object here (python-can's structs and its container parser) and
resynchronised at the next ``LOBJ`` signature; a container that fails to inflate keeps
what inflated before the damage.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import re
from collections import Counter
from pathlib import Path
from typing import IO
from collections.abc import Iterable, Iterator, Sequence

import can
import numpy as np

from replay import formats
from replay.base import SIGNALS, Problem, ReadReport, Samples, Sink, Source
from replay.dbc import COUNTER, EFF_FLAG, FrameCollector, Frames, MessageLayout, VectorCodec, key_str
from replay.quality import require_signals, time_spikes
from replay.errors import DataError, LogFormatError, SourceError

#: CAN log formats by suffix -> (python-can reader, python-can writer, text format?), from the
#: one registry :data:`replay.formats.FORMATS`.
FORMATS: dict[str, tuple[type, type, bool]] = {
    suf: (*formats.python_can_classes(suf), formats.FORMATS[suf].text) for suf in formats.CAN_LOG_SUFFIXES
}

#: A forward jump of a frame's time beyond this (ns) followed by a time back in line is a wild timestamp.
_WILD_JUMP_NS = 1_000_000

#: Frames per block read from a log.
BLOCK_FRAMES = 65536

#: Default max age of a held value, in periods of its message.
MAX_AGE_PERIODS = 2.5


def _fmt_t(t_ns: int) -> str:
    return f"t={t_ns / 1e9:.6f} s"


def _codec(dbc) -> VectorCodec:
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
            raise DataError(f"{source}: no frame of a DBC message carrying rig signals "
                            f"({', '.join(codec.rig_signals)}) at the start of the stream")
    else:
        signals = tuple(signals)
        for s in signals:
            if codec.message_of(s) is None:
                raise DataError(f"{source}: signal {s!r} is in no message of the DBC {codec.source}; "
                                f"available: {', '.join(codec.rig_signals)}")
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


# --- reading logs ----------------------------------------------------------------------------

def _suffix(path: Path) -> str:
    return formats.lookup(path, kind="can", what="CAN log").suffix


#: Bytes of a BLF object beyond which its size field is taken as damaged (CAN objects are < 100 bytes).
_BLF_MAX_OBJECT = 1 << 20
_BLF_CAN_OBJECT = 48  # bytes of a CAN_MESSAGE object with a v1 header: frames lost per byte of a lost container


@dataclasses.dataclass
class _ReadState:
    n: int = 0                      # frames read
    last_t: float | None = None     # timestamp of the last frame read, s
    blf_declared: tuple[int, int] | None = None  # (file size, object count) from a BLF header
    damaged: int = 0                # damaged lines / objects skipped (resynchronised after)


_ASC_FRAME_START = re.compile(r"^\S+\s+(\d+|canfd)\s+\S+", re.IGNORECASE)  # time, channel, id
_ASC_EVENT = re.compile(r"statistic|status|j1939|chip|error ?frame|swstat|log trigger")


def _classify_line(suf: str, text: str) -> str | None:
    """What a text-log line that gave no frame is: None (structure), ``bad_line`` or ``ignored_line``."""
    t = text.strip()
    if not t:
        return None
    if suf == ".trc":
        return None if t.startswith(";") else "bad_line"
    if suf == ".asc":
        low = t.lower()
        if low.startswith(("date ", "base ", "//", "begin triggerblock", "end triggerblock", "internal events",
                           "no internal events")) or "start of measurement" in low:
            return None
        if "\ufffd" in t or (_ASC_FRAME_START.match(t) and not _ASC_EVENT.search(low)):
            return "bad_line"
        return "ignored_line"
    return "bad_line"  # candump: every line is a frame


class _Lines:
    """The lines a python-can text reader iterates, with resynchronisation after a bad line.

    Hands out the header again after a restart (``head``), then the file from where the
    last reader stopped, decoding each line on its own (a byte that is not UTF-8 spoils
    that line only); remembers which file line it handed out last and reports a line
    that gave no frame (python-can skips some silently) under ``bad_line`` / ``ignored_line``.
    """

    def __init__(self, raw: IO[bytes], suf: str, path: Path, report: ReadReport) -> None:
        self.raw = raw
        self.suf = suf
        self.path = path
        self.report = report
        self.head: list[str] = []     # file lines before the first frame (the header)
        self.replay: list[str] = []
        self.line_no = 0
        self.current: str | None = None
        self.produced = 0             # file line of the last frame
        self.any_frame = False

    def __iter__(self) -> _Lines:
        return self

    def __next__(self) -> str:
        self.settle()
        if self.replay:
            return self.replay.pop(0)
        raw = self.raw.readline()
        if not raw:
            raise StopIteration
        self.line_no += 1
        self.current = raw.decode("utf-8", "replace")
        if not self.any_frame:
            self.head.append(self.current)
        return self.current

    def settle(self) -> None:
        """Account for the line handed out last: a frame, structure, or a line lost."""
        text, self.current = self.current, None
        if text is None or self.produced == self.line_no:
            return
        kind = _classify_line(self.suf, text)
        if kind == "bad_line":
            self.lost(text, "not a CAN frame the python-can reader understands")
        elif kind == "ignored_line":
            self.report.skip("ignored_line", f"line {self.line_no}", f"not a CAN frame, ignored: {text.strip()[:60]!r}")

    def lost(self, text: str, why: str) -> None:
        if not self.any_frame and self.head and self.head[-1] is text:
            self.head.pop()
        self.report.skip("bad_line", f"line {self.line_no}",
                         f"{why}: {text.strip()[:60]!r}; expected a {self.suf[1:].upper()} frame line; "
                         "that frame is lost, reading goes on with the next line")

    def frame(self) -> None:
        if not self.any_frame:
            self.any_frame = True
            if self.head and self.head[-1] is self.current:
                self.head.pop()  # the first frame's line is no header
        self.produced = self.line_no

    def fail(self, exc: Exception) -> bool:
        """The reader raised on the current line: count it and arrange a restart; False if not a file line."""
        text, self.current = self.current, None
        if text is None:
            return False
        self.lost(text, f"{type(exc).__name__}: {exc}")
        self.replay = list(self.head)
        return True

    def readable(self) -> bool:
        return True

    def close(self) -> None:
        """python-can readers close their file on stop(); the underlying file stays open here."""


def _text_messages(path: Path, suf: str, report: ReadReport, state: _ReadState) -> Iterator[can.Message]:
    """Frames of a text log; a line that fails costs only itself (the reader restarts after it)."""
    reader_cls = formats.python_can_classes(suf)[0]
    relative = False
    try:
        raw = open(path, "rb")
    except OSError as e:
        raise SourceError(f"{path}: cannot open CAN log: {e.strerror or e}") from e
    with raw:
        lines = _Lines(raw, suf, path, report)
        while True:
            try:
                reader = reader_cls(lines, **({"relative_timestamp": relative} if suf == ".asc" else {}))
            except Exception as e:
                raise LogFormatError(f"{path}: not a {suf[1:].upper()} file: {type(e).__name__}: {e}") from e
            try:
                for msg in reader:
                    lines.frame()
                    state.n += 1
                    state.last_t = msg.timestamp
                    yield msg
                lines.settle()
                return
            except Exception as e:  # a line python-can cannot parse: skip it, restart after it
                if suf == ".asc" and state.n == 0 and not relative and "datetime" in str(e):
                    relative = True
                    report.skip("asc_date", "header", f"date not understood ({e}); timestamps are relative "
                                                      "to the start of measurement")
                    raw.seek(0)
                    lines = _Lines(raw, suf, path, report)
                    continue
                if not lines.fail(e):  # the header itself does not parse
                    if state.n == 0:
                        raise LogFormatError(f"{path}: not a readable {suf[1:].upper()} file: its header does not "
                                             f"parse ({type(e).__name__}: {e})") from e
                    _truncated(report, path, state.n, state.last_t, e)
                    return
                state.damaged += 1


def _blf_messages(path: Path, report: ReadReport, state: _ReadState) -> Iterator[can.Message]:
    """Frames of a BLF file, object by object: a damaged object or container costs only itself.

    The file header and the container framing are walked here (python-can's structs);
    the objects inside a container are parsed by python-can's ``BLFReader``.  After a
    damaged object the walk resynchronises at the next ``LOBJ`` signature.
    """
    import io
    import mmap

    from can.io import blf as B

    try:
        f = open(path, "rb")
    except OSError as e:
        raise SourceError(f"{path}: cannot open CAN log: {e.strerror or e}") from e
    with f:
        size = os.fstat(f.fileno()).st_size
        hs = B.FILE_HEADER_STRUCT.size
        if size < hs:
            raise LogFormatError(f"{path}: not a BLF file: {size} bytes, shorter than its {hs}-byte header")
        mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            head = bytearray(mm[:hs])
            h = B.FILE_HEADER_STRUCT.unpack_from(head)
            if h[0] != b"LOGG":
                if not (hs <= h[1] <= 4096 and mm.find(b"LOBJ", h[1], h[1] + 4) == h[1]):
                    raise LogFormatError(f"{path}: not a BLF file: starts with {bytes(head[:4])!r}, "
                                         "expected the BLF signature b'LOGG'")
                report.skip("damaged_header", "file header", f"signature {bytes(head[:4])!r} damaged, expected "
                            "b'LOGG'; the rest of the header is used as is")
                head[:4] = b"LOGG"
            try:
                parser = B.BLFReader(io.BytesIO(bytes(head) + b"\0" * max(0, h[1] - hs)))
            except Exception as e:  # a start time that is no date
                raise LogFormatError(f"{path}: not a readable BLF file: header: {type(e).__name__}: {e}") from e
            state.blf_declared = (h[10], h[12])
            pos = max(h[1], hs)
            obj = 0
            while pos + 16 <= size:
                sig, _hsize, _hver, osize, otype = B.OBJ_HEADER_BASE_STRUCT.unpack_from(mm, pos)
                if sig == b"LOBJ" and 16 <= osize <= size - pos:
                    body_end = pos + osize
                    nxt = body_end + osize % 4
                    if otype == B.LOG_CONTAINER:
                        yield from _blf_container(mm, pos, body_end, parser, report, state, path)
                    pos, obj = nxt, obj + 1
                    continue
                if sig == b"LOBJ" and osize > size - pos and mm.find(b"LOBJ", pos + 1) < 0:
                    report.truncated = True
                    n0 = state.n
                    if otype == B.LOG_CONTAINER:
                        quiet = ReadReport(report.file)
                        yield from _blf_container(mm, pos, size, parser, quiet, state, path)
                    report.problems.append(Problem(str(path), f"object {obj} at byte {pos}",
                                                   f"declares {osize} bytes, the file ends after {size - pos}: "
                                                   f"truncated; the {state.n} frame(s) read are kept "
                                                   f"({state.n - n0} from the cut object)"))
                    break
                found = mm.find(b"LOBJ", pos + 1)
                report.skip("damaged_object", f"object {obj} at byte {pos}",
                            f"object header damaged (signature {bytes(sig)!r}, size {osize}); "
                            + (f"skipped {found - pos} bytes to the next object" if found >= 0 else
                               "no further object in the file"))
                state.damaged += 1
                parser._tail = b""
                if found < 0:
                    break
                pos, obj = found, obj + 1
        finally:
            mm.close()


def _inflate(cdata: bytes) -> tuple[bytes, str | None]:
    """zlib-inflate ``cdata``; on damage, what inflated before it and the error."""
    import zlib

    z = zlib.decompressobj()
    out = []
    step = 1024
    for i in range(0, len(cdata), step):
        try:
            out.append(z.decompress(cdata[i:i + step]))
        except zlib.error as e:
            return b"".join(out), f"zlib: {e} (compressed byte {i}..{i + step} of {len(cdata)})"
    if not z.eof:
        return b"".join(out), f"zlib: compressed data ends early ({len(cdata)} bytes)"
    return b"".join(out), None


def _blf_container(mm, pos: int, end: int, parser, report: ReadReport, state: _ReadState,
                   path: Path) -> Iterator[can.Message]:
    import struct

    from can.io import blf as B

    body = mm[pos + 16:end]
    where = f"container at byte {pos}"
    err: str | None = None
    usize = 0
    try:
        method, usize = B.LOG_CONTAINER_STRUCT.unpack_from(body)
        cdata = body[B.LOG_CONTAINER_STRUCT.size:]
        if method == B.ZLIB_DEFLATE:
            data, err = _inflate(cdata)
        elif method == B.NO_COMPRESSION:
            data = bytes(cdata)
        else:
            raise ValueError(f"unknown compression method {method}")
    except (ValueError, struct.error) as e:
        data, err = b"", f"{type(e).__name__}: {e}"
    if err is not None:
        lost = max(0, int(usize) - len(data)) // _BLF_CAN_OBJECT
        report.skip("damaged_object", where, f"{err}; " + (
            f"the frames of its first {len(data)} bytes are kept, " if data else "") +
            f"about {lost} frame(s) after the damage in this container are lost")
        state.damaged += 1
        if not data:
            parser._tail = b""
            return
    data = parser._tail + data
    parser._tail = b""
    off = 0
    while True:
        chunk = data[off:] if off else data
        bad_at = None
        try:
            for msg in parser._parse_data(chunk):
                state.n += 1
                state.last_t = msg.timestamp
                yield msg
        except struct.error:
            pass  # not enough data left for the next object: it continues in the next container
        except B.BLFParseError:
            bad_at = parser._pos
        tail = chunk[parser._pos:] if bad_at is None else b""
        if bad_at is None and len(tail) >= 16 and tail[:4] == b"LOBJ":
            osize = B.OBJ_HEADER_BASE_STRUCT.unpack_from(tail)[3]
            if osize > _BLF_MAX_OBJECT or osize < 16:
                bad_at = parser._pos
        if bad_at is None:
            parser._tail = tail
            return
        found = chunk.find(b"LOBJ", bad_at + 1)
        report.skip("damaged_object", f"{where}, byte {bad_at} of its data",
                    "object damaged (no valid object header where one should be); "
                    + ("resynchronised at the next object" if found >= 0 else "the rest of the container is lost"))
        state.damaged += 1
        if found < 0:
            return
        off += found


class _ReaderWarnings(logging.Filter):
    """Takes python-can's reader warnings (``Unknown object header version``, ``Failed to parse
    message``) off stderr while a log is read: the report already counts what they are about."""

    def __init__(self, report: ReadReport) -> None:
        super().__init__()
        self.report = report

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if "object header version" in msg:  # a BLF object whose header is garbage (damaged container)
            self.report.skip("damaged_object", "BLF object", f"python-can: {msg}; the object is skipped")
        return False


def iter_frames(path: str | Path, report: ReadReport, block_frames: int = BLOCK_FRAMES) -> Iterator[Frames]:
    """Frames of a CAN log in blocks, through python-can's reader for the suffix.

    A damaged line (text logs) or object (BLF) costs only itself: it is counted under
    ``bad_line`` / ``damaged_object`` with its line number or byte offset, and reading
    goes on after it.  A file cut short keeps every frame before the cut and sets
    ``report.truncated``.
    """
    path = Path(path)
    suf = _suffix(path)
    if not path.is_file():
        raise SourceError(f"{path}: CAN log not found")
    coll = FrameCollector()
    state = _ReadState()
    messages = _blf_messages(path, report, state) if suf == ".blf" else _text_messages(path, suf, report, state)
    quiet = _ReaderWarnings(report)
    loggers = [logging.getLogger(n) for n in ("can.io.blf", "can.io.trc", "can.io.asc", "can.io.canutils")]
    for lg in loggers:
        lg.addFilter(quiet)
    try:
        for msg in messages:
            coll.add(msg)
            if len(coll) >= block_frames:
                yield coll.take()
    finally:
        for lg in loggers:
            lg.removeFilter(quiet)
    if len(coll):
        yield coll.take()
    _check_complete(path, suf, report, state)
    if state.n == 0 and not report.truncated:
        raise LogFormatError(f"{path}: no CAN frames found; expected a {suf[1:].upper()} log"
                             + (f" ({state.damaged} damaged line(s)/object(s) skipped)" if state.damaged else ""))


def _truncated(report: ReadReport, path: Path, n: int, last_t: float | None, e: Exception) -> None:
    report.truncated = True
    size = path.stat().st_size
    where = f"after frame {n - 1} (t={last_t:.6f} s)" if n else "before the first frame"
    report.problems.append(Problem(
        str(path), where, f"reading stopped: {type(e).__name__}: {e}; the {n} frame(s) read before are kept "
                          f"(file size {size} bytes)"))


def _check_complete(path: Path, suf: str, report: ReadReport, state: _ReadState) -> None:
    """Detect a file cut short that the reader accepted silently."""
    if report.truncated:
        return
    n = state.n
    size = path.stat().st_size
    if formats.FORMATS[suf].text:
        with open(path, "rb") as f:
            if size:
                f.seek(max(size - 64, 0))
                tail = f.read()
            else:
                tail = b""
        cut = bool(tail) and not tail.endswith(b"\n")
        if suf == ".asc" and b"end triggerblock" not in tail.lower():
            cut = True
        if cut:
            report.truncated = True
            report.problems.append(Problem(
                str(path), f"end of file after {n} frame(s)",
                "file ends without its closing line (" + ("'End TriggerBlock'" if suf == ".asc" else "newline")
                + "): truncated; the frames read are kept, a cut last frame is reported on its own"))
    elif suf == ".blf" and state.blf_declared is not None:
        declared, count = state.blf_declared
        if (declared and declared != size) or (count and n < count and not state.damaged):
            report.truncated = True
            report.problems.append(Problem(
                str(path), f"end of file after {n} frame(s)",
                f"BLF header declares {declared} bytes and {count} objects, the file has {size} bytes "
                f"and {n} CAN frame(s) could be read: truncated; the frames read are kept"))


def _split(block: Samples, size: int) -> Iterator[Samples]:
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


class CanLogSource(Source):
    """Rig samples from a CAN log (ASC, BLF, candump ``.log``, TRC), decoded with a DBC.

    :param path: the log; the format is taken from the suffix.
    :param dbc: DBC path, loaded database or :class:`VectorCodec` (default: MSP25).
    :param grid_hz: uniform output grid in Hz (default: the master frames' own times).
    :param signals: rig signals to deliver (default: those present at the start of the log).
    :param window_s: same-cycle window in s (default: half the master period or grid step).
    :param max_age_s: max age of a held value in s (default: 2.5 periods of its message).
    :param probe_s: span of log time looked at to find which messages are present
        (default: 2.5 times the slowest DBC period, at least 50 ms).
    :param required: signals that must be delivered (DataError naming them if not).
    """

    def __init__(self, path: str | Path, dbc=None, grid_hz: float | None = None, *,
                 signals: Sequence[str] | None = None, window_s: float | None = None,
                 max_age_s: float | None = None, probe_s: float | None = None,
                 required: Sequence[str] = (), block_frames: int = BLOCK_FRAMES) -> None:
        self.path = str(path)
        _suffix(Path(path))
        if not Path(path).is_file():
            raise SourceError(f"{path}: CAN log not found")
        self.codec = _codec(dbc)
        self.block_frames = block_frames
        self.report = ReadReport(self.path)
        periods = [m.period_s for m in self.codec.messages.values() if m.period_s and m.rig_signals]
        self.probe_s = probe_s if probe_s is not None else max(0.05, MAX_AGE_PERIODS * max(periods, default=0.02))
        head = self._head()
        if len(head) == 0:
            raise LogFormatError(f"{self.path}: no CAN frames found; expected a {Path(path).suffix[1:].upper()} log")
        self.plan = probe_plan(self.codec, head, self.path, signals, grid_hz, window_s, max_age_s)
        require_signals(self.path, self.plan.signals, required)

    def _head(self) -> Frames:
        span_ns = int(self.probe_s * 1e9)
        blocks = []
        t0 = None
        for fr in iter_frames(self.path, ReadReport(self.path), block_frames=4096):
            blocks.append(fr)
            if t0 is None and len(fr):
                t0 = int(fr.t_ns[0])
            if t0 is not None and int(fr.t_ns.max()) - t0 >= span_ns:
                break
        head = Frames.concat(blocks)
        if t0 is not None:
            head = head.take(np.flatnonzero(head.t_ns - t0 <= span_ns))
        return head

    @property
    def signals(self) -> tuple[str, ...]:
        return self.plan.signals

    def chunks(self, size: int = 65536) -> Iterator[Samples]:
        """Aligned sample blocks of at most ``size``; each call reads the log from the start."""
        self.report = ReadReport(self.path)
        stream = CanStream(self.codec, self.plan, self.report)
        for frames in iter_frames(self.path, self.report, self.block_frames):
            yield from _split(stream.feed(frames), size)
        yield from _split(stream.flush(), size)


# --- writing logs ----------------------------------------------------------------------------

class FrameScheduler:
    """Turns sample blocks into CAN frames following the DBC (shared by log and bus sinks).

    Messages are sent at their DBC period (``decimate=True``: a message of period P is
    sent on the first sample of every P-long slot counted from the first sample) or on
    every sample (``decimate=False``).  All frames of one sample carry its timestamp,
    in id order.  Rolling counters count up per frame sent.  A message is sent only if
    the samples carry all its rig signals; a frame with a non-finite value is not sent
    (counted in ``skipped``).
    """

    def __init__(self, codec: VectorCodec, decimate: bool = True, source: str = "") -> None:
        self.codec = codec
        self.decimate = decimate
        self.source = source
        self.t0: int | None = None
        self.last_slot: dict[int, int] = {}
        self.counter: dict[int, int] = {}
        self.skipped: Counter[str] = Counter()
        self.frames_out = 0
        self.step = 0  # ns, median sample step seen so far

    def frames(self, samples: Samples) -> Frames:
        n = len(samples)
        if n == 0:
            return Frames.empty()
        if self.t0 is None:
            self.t0 = int(samples.t_ns[0])
        names = set(samples.names)
        if n > 1:
            self.step = int(np.median(np.diff(samples.t_ns)))
        step = self.step
        parts = []
        any_msg = False
        for key, lay in sorted(self.codec.messages.items()):
            rig = lay.rig_signals
            if not rig:
                continue
            have = [r for r in rig if r in names]
            if not have:
                continue
            if len(have) != len(rig):
                raise DataError(f"{self.source}: message {lay.label} needs {', '.join(rig)}; the samples carry "
                                f"{', '.join(have)} but not {', '.join(r for r in rig if r not in names)}")
            any_msg = True
            rows = np.arange(n)
            if self.decimate and lay.period_s:
                p = int(round(lay.period_s * 1e9))
                # a sample up to half a sample step early still counts for its slot (timestamp jitter)
                tol = min(p // 10, step // 2) if step else p // 10
                slot = (samples.t_ns - self.t0 + tol) // p
                prev = np.concatenate([[self.last_slot.get(key, -1)], slot[:-1]])
                rows = np.flatnonzero(slot != prev)
                self.last_slot[key] = int(slot[-1])
            vals = {r: samples.signals[r][rows] for r in rig}
            finite = np.ones(rows.size, bool)
            for v in vals.values():
                finite &= np.isfinite(v)
            if not finite.all():
                self.skipped[f"not finite {lay.name}"] += int((~finite).sum())
                rows = rows[finite]
                vals = {r: v[finite] for r, v in vals.items()}
            if rows.size == 0:
                continue
            extra = {}
            cnt = lay.counter
            if cnt is not None:
                c0 = self.counter.get(key, -1) + 1
                c = (c0 + np.arange(rows.size)) % (1 << cnt.length)
                self.counter[key] = int(c[-1])
                extra[cnt.name] = c.astype(np.float64)
            data = self.codec.encode_rig(key, vals, rows.size, extra)
            parts.append(Frames(samples.t_ns[rows], np.full(rows.size, key, np.uint32),
                                np.full(rows.size, lay.length, np.uint8), data, np.zeros(rows.size, np.uint8)))
        if not any_msg:
            raise DataError(f"{self.source}: the samples carry none of the DBC's signals "
                            f"({', '.join(self.codec.rig_signals)}); they have {', '.join(samples.names)}")
        fr = Frames.concat(parts)
        order = np.lexsort((fr.key, fr.t_ns))
        fr = fr.take(order)
        self.frames_out += len(fr)
        return fr


def frames_to_messages(fr: Frames, channel=None) -> Iterator[can.Message]:
    """python-can messages of a :class:`Frames` block (timestamps in s)."""
    t = (fr.t_ns // 1000).tolist()  # whole microseconds, exact in float division below
    keys = fr.key.tolist()
    dlcs = fr.dlc.tolist()
    data = fr.data.tobytes()
    for i in range(len(fr)):
        k = keys[i]
        yield can.Message(timestamp=t[i] / 1e6, arbitration_id=k & 0x1FFF_FFFF, is_extended_id=bool(k & EFF_FLAG),
                          dlc=dlcs[i], data=data[8 * i: 8 * i + dlcs[i]], channel=channel, check=False)


class CanLogSink(Sink):
    """Samples written as the rig's CAN frames to a log (ASC, BLF, candump ``.log``, TRC).

    :param path: the log to write; the format is taken from the suffix.
    :param dbc: DBC path, database or :class:`VectorCodec` (default: MSP25).
    :param decimate: send each message at its DBC period (True) or on every sample.
    :param channel: channel written into the log (python-can numbering from 0; ``can0`` for candump).
    """

    def __init__(self, path: str | Path, dbc=None, *, decimate: bool = True, channel: int | str = 0) -> None:
        self.path = Path(path)
        suf = _suffix(self.path)
        self.codec = _codec(dbc)
        self.scheduler = FrameScheduler(self.codec, decimate, str(self.path))
        writer_cls = FORMATS[suf][1]
        try:
            if writer_cls is can.CanutilsLogWriter:
                self.channel: str | int = channel if isinstance(channel, str) else f"can{channel}"
                self.writer = writer_cls(str(self.path), channel=self.channel)
            else:
                number = channel if isinstance(channel, int) else 0
                self.channel = number
                self.writer = writer_cls(str(self.path), channel=number + 1)
        except OSError as e:
            raise SourceError(f"{self.path}: cannot write CAN log: {e}") from e
        self._closed = False

    @property
    def frames_out(self) -> int:
        return self.scheduler.frames_out

    @property
    def skipped(self) -> Counter:
        return self.scheduler.skipped

    def write(self, samples: Samples) -> None:
        fr = self.scheduler.frames(samples)
        write = self.writer.on_message_received
        for msg in frames_to_messages(fr, channel=self.channel if not isinstance(self.channel, str) else None):
            write(msg)

    def write_frames(self, frames: Iterable[can.Message]) -> None:
        """Write raw python-can messages (e.g. bad frames for a test, or a bus capture)."""
        for m in frames:
            self.writer.on_message_received(m)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.writer.stop()
