"""Rig samples to CAN frames: each DBC message at its own period (``GenMsgCycleTime``), as a controller
sends them; used by the CAN log writers, the live bus sink and the Zenoh frame sink."""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator

import can
import numpy as np

from replay.base import Samples
from replay.can.codec import EFF_FLAG, Frames, VectorCodec
from fpdd.errors import DataError


#: Nominal values of a status message's rig signals, for a record that carries some of the message's signals but
#: not these (a CAN frame carries all its fields): the MSP25's supply pressure (28 MPa) and its oil at the
#: temperature its parameters hold at (``T_ref``, 40 degC), the model's own defaults, so that a log read back gives
#: the model what it assumes without them. A record with none of a message's signals gets no such message.
NOMINAL_STATUS: dict[str, float] = {"pP": 28e6, "T_oil": 313.15}


class FrameScheduler:
    """Turns sample blocks into CAN frames following the DBC (shared by log and bus sinks).

    Messages are sent at their DBC period (``decimate=True``: a message of period P is
    sent on the first sample of every P-long slot counted from the first sample) or on
    every sample (``decimate=False``).  All frames of one sample carry its timestamp,
    in id order.  Rolling counters count up per frame sent.  A message is sent only if
    the samples carry all its rig signals, or some of them and a nominal value
    (:data:`NOMINAL_STATUS`) for each of the others (the MSP25's ``HPU_Status``: ``T_oil`` and ``pP``); a
    frame with a non-finite value is not sent (counted in ``skipped``).
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
            missing = [r for r in rig if r not in names]
            if missing and all(r in NOMINAL_STATUS for r in missing):
                fill = {r: np.full(n, NOMINAL_STATUS[r]) for r in missing}
                samples = Samples(samples.t_ns, {**samples.signals, **fill})
                names |= set(missing)
                have = list(rig)
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
