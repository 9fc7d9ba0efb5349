"""Validation shared by every reader: one gate that each block of samples passes through.

What the gate does to a block (all vectorised with numpy, in this order):

1. **NaN or infinite value** in any signal: the sample is dropped and counted under
   ``nan`` (or ``inf`` when it holds no NaN); the first few are named (file, signal,
   record).
2. **Time going backwards or repeating**: a single wild timestamp (a jump forward of
   more than 10 median steps after which time is back in line) is dropped alone and
   counted under ``time_jump``.  Then a sample is kept only if its ``t_ns`` is
   strictly greater than every kept time before it (across blocks).  Others are
   dropped and counted under ``time_backwards`` / ``time_repeated`` (duplicates are
   never passed on).
3. **Values outside the physical range** of the signal's SI unit
   (:data:`fpdd.units.SIGNALS`): an isolated glitch (at most ``range_tolerance`` of
   the samples checked so far, at least one sample per 1000) is dropped and counted
   under ``out_of_range``; anything more is systematic and raises
   :class:`~fpdd.errors.DataError` naming file, signal, observed range and expected
   unit, with a hint when the values look like another unit (a pressure in bar or MPa
   where Pa is expected, a displacement in mm where m is expected, a temperature in
   degC where K is expected).  A hydraulic pressure whose magnitude never exceeds
   1 kPa over a block of at least 100 samples (but is not all zero) is also taken as
   a wrong unit: a real transducer read in Pa has more offset and noise than that.
4. **Gaps** (time step longer than ``max_gap_s``, or, when not given, ``gap_factor``
   times the median step of the first samples): reported in ``ReadReport.gaps`` as
   ``(t_ns before, t_ns after)``; never interpolated across.  A file whose median step
   over the first samples gives a rate outside :data:`ACCEPTED_RATE_HZ` is refused
   (times in another unit: an MCAP ``log_time`` in us read as ns is 1 MHz times 1000).

A **missing required signal** is checked once, when a source knows its columns:
:func:`require_signals` raises :class:`~fpdd.errors.DataError` naming file, signal
and what the file has.

Skipped samples are counted in the report, never raised: nothing already accepted is
lost.  The unit table :data:`fpdd.units.UNITS` converts foreign units to SI at one boundary
(readers call :func:`fpdd.units.to_si`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np

from replay.base import Problem, ReadReport, Samples
from fpdd.errors import DataError
from fpdd.units import SIGNALS, UNITS, SignalSpec

#: Sample rates a record may have at all (Hz): below 10 Hz no rig dynamics (tens to hundreds of Hz) is
#: observable; above 10 MHz no rig data acquisition samples.  A file read at a rate outside is refused.
ACCEPTED_RATE_HZ = (10.0, 10.0e6)

# --- units ---------------------------------------------------------------------------------

#: Foreign units tried, in this order, when values look like a wrong unit.
_UNIT_SUSPECTS: dict[str, tuple[str, ...]] = {
    "Pa": ("bar", "MPa", "kPa", "psi"),
    "m": ("mm", "um"),
    "K": ("degC",),
    "N": ("kN",),
    "V": ("mV",),
}


def unit_hint(spec: SignalSpec, lo: float, hi: float) -> str:
    """A hint naming the units in which an observed range ``[lo, hi]`` would be plausible.

    Returns ``""`` when no unit of :data:`UNITS` brings the range into the spec's range.
    """
    fits = []
    for unit in _UNIT_SUSPECTS.get(spec.unit, ()):
        factor, offset, _ = UNITS[unit]
        a, b = lo * factor + offset, hi * factor + offset
        if spec.lo <= a and b <= spec.hi and (spec.unit != "Pa" or max(abs(a), abs(b)) > 1e4):
            fits.append(f"{unit} (would be [{a:.6g}, {b:.6g}] {spec.unit})")
    if not fits:
        return ""
    return "; the values look like " + " or ".join(fits) + ": give the unit in the column mapping"


def require_signals(file: str, have: Iterable[str], required: Iterable[str]) -> None:
    """Raise :class:`DataError` if a required signal is not among ``have``."""
    have = tuple(have)
    missing = [s for s in required if s not in have]
    if missing:
        raise DataError(
            f"{file}: required signal(s) {', '.join(repr(m) for m in missing)} missing; "
            f"the file has {', '.join(repr(h) for h in have) or 'no signals'}"
        )


def add_skips(report: ReadReport, reason: str, count: int, examples: Iterable[tuple[str, str]]) -> None:
    """Count ``count`` skipped records under ``reason`` and keep the first examples (where, what)."""
    if count <= 0:
        return
    report.skipped[reason] += int(count)
    for where, what in examples:
        if len(report.problems) >= report.max_problems:
            break
        report.problems.append(Problem(report.file, where, what))


def time_spikes(t: np.ndarray, min_jump: int) -> np.ndarray:
    """Mask of single wild timestamps: a jump forward of more than ``min_jump`` after which the
    next time is back in line (between the previous time and the wild one).

    Dropping such a sample alone keeps what follows it, which the strictly-increasing
    rule would otherwise drop until time caught up with the wild value.
    """
    out = np.zeros(t.size, dtype=bool)
    if t.size < 3:
        return out
    prev, mid, nxt = t[:-2], t[1:-1], t[2:]
    out[1:-1] = (mid - prev > min_jump) & (nxt < mid) & (nxt >= prev)
    return out


# --- the gate ------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class QualityOptions:
    """How strict the gate is.

    ``required``: signals that must be present.  ``max_gap_s`` (s): a time step longer
    than this is a gap; ``None`` means ``gap_factor`` times the median step of the first
    samples.  ``range_tolerance``: fraction of samples (at least 1 per 1000 checked)
    that may be out of range before the read is refused as a wrong unit.
    ``check_range``: turn the range and unit check off (e.g. for raw diagnostics).
    ``specs``: signal specifications that replace :data:`~fpdd.units.SIGNALS` for this
    read (e.g. the oscillator's ``u`` is a force in N, not a valve voltage).
    ``keep_nan``: pass NaN through as a missing value (live streams: ``null``); infinite
    values are still dropped.  ``systematic``: ``"raise"`` (files: a wrong unit refuses
    the read) or ``"drop"`` (live streams: the block is dropped and counted under
    ``wrong_unit`` with the same message; the gate never raises).  ``order_across_blocks``:
    ``False`` orders each block by itself (a live consumer that orders the blocks against what
    it processed and judges a block stamped in the future itself: one such block then does
    not make every later sample "backwards" here).
    """

    required: tuple[str, ...] = ()
    max_gap_s: float | None = None
    gap_factor: float = 5.0
    check_range: bool = True
    range_tolerance: float = 1e-3
    specs: Mapping[str, SignalSpec] | None = None
    keep_nan: bool = False
    systematic: str = "raise"
    order_across_blocks: bool = True

    def __post_init__(self) -> None:
        if self.max_gap_s is not None and not self.max_gap_s > 0:
            raise ValueError(f"max_gap_s (={self.max_gap_s}) must be > 0 s")
        if not self.gap_factor > 1:
            raise ValueError(f"gap_factor (={self.gap_factor}) must be > 1")
        if not 0 <= self.range_tolerance < 1:
            raise ValueError(f"range_tolerance (={self.range_tolerance}) must be in [0, 1)")
        if self.systematic not in ("raise", "drop"):
            raise ValueError(f"systematic (={self.systematic!r}) must be 'raise' or 'drop'")


_N_EXAMPLES = 5
_GAP_ESTIMATE_STEPS = 16  # steps needed before an automatic gap threshold is fixed
_PRESSURE_MIN_BLOCK = 100


class QualityGate:
    """Stateful validation of a stream of :class:`Samples` blocks from one file.

    Call :meth:`apply` on each block in time order; it returns the block with bad
    samples removed and updates ``report`` (``samples_out``, ``skipped``, ``gaps``).
    """

    def __init__(self, report: ReadReport, options: QualityOptions | None = None,
                 specs: Mapping[str, SignalSpec] = SIGNALS) -> None:
        self.report = report
        self.options = options or QualityOptions()
        self.specs = self.options.specs if self.options.specs is not None else specs
        self._last_t_ns: int | None = None
        self._max_gap_ns: int | None = (
            None if self.options.max_gap_s is None else int(round(self.options.max_gap_s * 1e9))
        )
        self._early_t: list[np.ndarray] = []  # kept times before an automatic threshold exists
        self._gap_prev: int | None = None  # last kept time seen by the gap check
        self._checked: dict[str, int] = {}
        self._out: dict[str, int] = {}
        self._recent: dict[str, np.ndarray] = {}  # live mode: the last pressures seen, per signal

    @property
    def max_gap_ns(self) -> int | None:
        """The gap threshold in ns (``None`` until enough samples were seen to estimate it)."""
        return self._max_gap_ns

    def apply(self, block: Samples, labels: Sequence[int] | np.ndarray | None = None,
              label: str = "sample") -> Samples:
        """Validate one block. ``labels[i]`` names sample i (e.g. a line number) as ``f"{label} {labels[i]}"``."""
        n = len(block)
        if labels is None:
            labels = np.arange(n)
        labels = np.asarray(labels)
        keep = np.ones(n, dtype=bool)
        self._non_finite(block, keep, labels, label)
        self._time_order(block, keep, labels, label)
        if self.options.check_range:
            self._range(block, keep, labels, label)
        if not keep.all():
            idx = np.flatnonzero(keep)
            block = Samples(block.t_ns[idx], {k: v[idx] for k, v in block.signals.items()})
        if len(block):  # the latest time of what is kept (a dropped block does not move it)
            self._last_t_ns = int(block.t_ns[-1])
        self._gaps(block.t_ns)
        self.report.samples_out += len(block)
        return block

    # -- checks, each marks samples to drop in ``keep`` ------------------------------------

    def _non_finite(self, block: Samples, keep: np.ndarray, labels: np.ndarray, label: str) -> None:
        nan_any = np.zeros(len(block), dtype=bool)
        inf_any = np.zeros(len(block), dtype=bool)
        examples: dict[str, list[tuple[str, str]]] = {"nan": [], "inf": []}
        keep_nan = self.options.keep_nan
        for name, v in block.signals.items():
            bad = np.isinf(v) if keep_nan else ~np.isfinite(v)
            if not bad.any():
                continue
            isnan = np.zeros_like(bad) if keep_nan else np.isnan(v)
            nan_any |= isnan
            inf_any |= bad & ~isnan
            for i in np.flatnonzero(bad)[:_N_EXAMPLES]:
                kind = "nan" if isnan[i] else "inf"
                examples[kind].append((f"{label} {labels[i]}", f"signal {name!r} is {v[i]}, expected a finite value"))
        if not (nan_any.any() or inf_any.any()):
            return
        inf_only = inf_any & ~nan_any
        add_skips(self.report, "nan", int(nan_any.sum()), examples["nan"])
        add_skips(self.report, "inf", int(inf_only.sum()), examples["inf"])
        keep &= ~(nan_any | inf_any)

    def _time_order(self, block: Samples, keep: np.ndarray, labels: np.ndarray, label: str) -> None:
        idx = np.flatnonzero(keep)
        if idx.size == 0:
            return
        t = block.t_ns[idx]
        if t.size >= 3:
            steps = np.diff(t[:4096])
            steps = steps[steps > 0]
            jump = max(int(10 * np.median(steps)) if steps.size else 0, 1000)
            spikes = time_spikes(t, jump)
            if spikes.any():
                pos = np.flatnonzero(spikes)
                add_skips(self.report, "time_jump", int(pos.size), (
                    (f"{label} {labels[idx[p]]}",
                     f"time {int(t[p])} ns jumps {int(t[p] - t[p - 1])} ns ahead of its neighbours "
                     f"({int(t[p - 1])} and {int(t[p + 1])} ns): a wild timestamp, this sample alone is dropped")
                    for p in pos[:_N_EXAMPLES]))
                keep[idx[pos]] = False
                idx = idx[~spikes]
                t = t[~spikes]
        carry = self._last_t_ns is not None and self.options.order_across_blocks
        first = int(self._last_t_ns) if carry and self._last_t_ns is not None else np.iinfo(np.int64).min
        prev_max = np.maximum.accumulate(np.concatenate(([first], t[:-1])))
        backwards = t < prev_max
        repeated = t == prev_max
        for reason, bad, word in (("time_backwards", backwards, "goes backwards"),
                                  ("time_repeated", repeated, "repeats")):
            if bad.any():
                pos = np.flatnonzero(bad)
                add_skips(self.report, reason, int(pos.size), (
                    (f"{label} {labels[idx[p]]}",
                     f"time {int(t[p])} ns {word} (latest time so far {int(prev_max[p])} ns), "
                     "expected strictly increasing time")
                    for p in pos[:_N_EXAMPLES]))
                keep[idx[pos]] = False

    def _range(self, block: Samples, keep: np.ndarray, labels: np.ndarray, label: str) -> None:
        idx = np.flatnonzero(keep)
        if idx.size == 0:
            return
        drop_mode = self.options.systematic == "drop"
        for name, v_all in block.signals.items():
            spec = self.specs.get(name)
            if spec is None:
                continue
            v = v_all[idx]
            fin = np.isfinite(v)
            if not fin.any():
                continue
            out = fin & ((v < spec.lo) | (v > spec.hi))
            n_out = int(out.sum())
            lo, hi = float(np.min(v[fin])), float(np.max(v[fin]))
            if drop_mode:
                if self._systematic_in_block(name, spec, v[fin], n_out, lo, hi, keep, idx, labels, label):
                    return
            else:
                self._checked[name] = self._checked.get(name, 0) + int(v.size)
                self._out[name] = self._out.get(name, 0) + n_out
                allowed = max(1, int(self.options.range_tolerance * self._checked[name]))
                if self._out[name] > allowed:
                    raise DataError(
                        f"{self.report.file}: signal {name!r}: observed range [{lo:.6g}, {hi:.6g}] "
                        f"({n_out} of {v.size} samples of this block outside [{spec.lo:.6g}, {spec.hi:.6g}] "
                        f"{spec.unit}), expected {spec.meaning} in {spec.unit}"
                        + unit_hint(spec, *_robust_range(v[fin]))
                    )
                if spec.unit == "Pa" and v.size >= _PRESSURE_MIN_BLOCK:
                    mag = float(np.max(np.abs(v[fin])))
                    if 1.0 < mag <= 1e3:
                        raise DataError(
                            f"{self.report.file}: signal {name!r}: observed range [{lo:.6g}, {hi:.6g}] Pa "
                            f"is implausibly small for {spec.meaning} (|p| <= 1 kPa over {v.size} samples), "
                            f"expected Pa" + unit_hint(spec, lo, hi)
                        )
            if n_out:
                pos = np.flatnonzero(out)
                add_skips(self.report, "out_of_range", n_out, (
                    (f"{label} {labels[idx[p]]}",
                     f"signal {name!r} = {v[p]:.6g} {spec.unit} outside [{spec.lo:.6g}, {spec.hi:.6g}] {spec.unit}")
                    for p in pos[:_N_EXAMPLES]))
                keep[idx[pos]] = False

    def _systematic_in_block(self, name: str, spec: SignalSpec, v: np.ndarray, n_out: int, lo: float, hi: float,
                             keep: np.ndarray, idx: np.ndarray, labels: np.ndarray, label: str) -> bool:
        """Live mode: drop the whole block if its values look like a wrong unit (True if dropped)."""
        why = ""
        if v.size >= 10 and n_out > max(1, self.options.range_tolerance * v.size):
            why = (f"{n_out} of {v.size} samples outside [{spec.lo:.6g}, {spec.hi:.6g}] {spec.unit}"
                   + unit_hint(spec, *_robust_range(v)))
        elif spec.unit == "Pa":
            recent = self._recent.get(name)
            recent = v[-_PRESSURE_MIN_BLOCK:] if recent is None else np.concatenate([recent, v])[-_PRESSURE_MIN_BLOCK:]
            self._recent[name] = recent
            mag = float(np.max(np.abs(recent)))
            if recent.size >= _PRESSURE_MIN_BLOCK and 1.0 < mag <= 1e3 and float(np.max(np.abs(v))) <= 1e3:
                why = (f"|p| <= 1 kPa over the last {recent.size} samples: implausibly small for {spec.meaning}"
                       + unit_hint(spec, lo, hi))
        if not why:
            return False
        add_skips(self.report, "wrong_unit", int(idx.size), [(
            f"{label} {labels[idx[0]]}..{labels[idx[-1]]}",
            f"signal {name!r}: observed range [{lo:.6g}, {hi:.6g}], expected {spec.meaning} in {spec.unit} "
            f"({why}); the block of {idx.size} samples is dropped")])
        keep[idx] = False
        return True

    def _gaps(self, t: np.ndarray) -> None:
        """Report steps longer than the threshold between kept samples (``t`` already ordered)."""
        if self._max_gap_ns is None:
            self._early_t.append(t)
            early = np.concatenate(self._early_t)
            if early.size <= _GAP_ESTIMATE_STEPS:
                return
            self._early_t = []
            median_dt = float(np.median(np.diff(early)))
            rate = 1e9 / median_dt if median_dt > 0 else math.inf
            lo, hi = ACCEPTED_RATE_HZ
            if self.options.systematic == "raise" and not lo <= rate <= hi:
                raise DataError(f"{self.report.file}: median time step {median_dt * 1e-9:.6g} s ({rate:.6g} Hz) "
                                f"over the first {early.size} samples is not a rig record's rate (expected {lo:g} Hz "
                                f"to {hi:g} Hz): the times are in another unit or not sample times")
            self._max_gap_ns = max(1, int(round(self.options.gap_factor * median_dt)))
            t = early
            start = None
        else:
            start = self._gap_prev
        if t.size == 0:
            return
        full = t if start is None else np.concatenate(([start], t))
        dt = np.diff(full)
        for i in np.flatnonzero(dt > self._max_gap_ns):
            self.report.gaps.append((int(full[i]), int(full[i + 1])))
        self._gap_prev = int(t[-1])


def _robust_range(v: np.ndarray) -> tuple[float, float]:
    """1st and 99th percentile: the bulk of the data, for a unit hint that ignores glitches."""
    lo, hi = np.percentile(v, [1.0, 99.0])
    return float(lo), float(hi)
