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


def wear_forecasts(rig: str, seconds: float = 400.0, seed: int = 1201) -> list[dict]:
    """The forecast messages of a rig whose leakage wears out of its band (1 to 3.5 times its baseline over 700 s,
    band up to 3 times), its estimates with AR(1) errors (``seed`` >= 1000), as the twin makes them: one per second
    once the trend shows."""
    import numpy as np

    from twin.online.baseline import Baseline
    from twin.online.forecast import ForecastMonitor
    from twin.online.events.forecast import forecast_message

    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 0.05)
    a = np.exp(-0.05 / 0.5)
    err = np.empty(t.size)
    x, noise = 0.0, rng.normal(0.0, 0.05 * np.sqrt(1 - a * a), t.size)
    for i in range(t.size):
        x = a * x + noise[i]
        err[i] = x
    est = ((1.0 + 2.5 * t / 700.0) * np.exp(err))[:, None]
    fm = ForecastMonitor(rig, {"CdAleak": Baseline(1.0, 1.0 / 3.0, 3.0)}, horizon_s=600.0)
    _, fcs = fm.update_block(("CdAleak",), T0_NS + np.round(t * 1e9).astype(np.int64), t, est,
                             np.full_like(est, 0.05), np.zeros(est.shape, bool))
    return forecast_message(rig, fcs, fm.horizon_s)
