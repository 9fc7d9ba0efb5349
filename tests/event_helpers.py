"""Alarm events for the bus and journal tests (one builder, one epoch)."""

from __future__ import annotations

from twin.online.events import AlarmEvent

T0_NS = 1_740_000_000_000_000_000


def alarm(rig: str = "msp25", i: int = 1, seq: int = 0, level: str = "alarm") -> AlarmEvent:
    """The ``i``-th alarm of ``rig`` (one second apart), numbered ``seq`` (0: not journaled yet)."""
    return AlarmEvent(
        rig=rig,
        parameter="Kleak",
        level=level,
        kind="raised",
        t_ns=T0_NS + i * 1_000_000_000,
        t_s=float(i),
        estimate=3e-12,
        std=2e-13,
        baseline=1e-12,
        band_lo=5e-13,
        band_hi=2e-12,
        statistic=10.0 + i,
        message=f"alarm {i}",
        seq=seq,
    )
