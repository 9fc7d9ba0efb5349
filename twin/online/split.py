"""Whether the recent motion tells a second-order lag's damping ratio from its natural frequency.

A lag ``xs'' / wn^2 + (2 zeta / wn) xs' + xs = K u`` (the servo valve's spool) driven well below its band
answers with ``xs ~ K u - (2 zeta / wn) K u'``: the data then fix the ratio ``zeta / wn`` alone, and any small
error of the model elsewhere moves the estimate along the direction they do not fix (zeta and wn up or down
together) while the innovations stay consistent.  The two are told apart by the lag's inertia term
``xs'' / wn^2``, whose size against the damping term ``2 zeta xs' / wn`` is ``w / (2 zeta wn)`` for motion at
``w`` rad/s.  This module measures the recent motion's frequency from the filter's own lag states,
``w_eff = <|vs'|> / <|vs|>`` (exponential averages, the excitation's time constant), and says the pair is not
separately identifiable while ``w_eff < split_ratio * 2 zeta wn``: the tracker then marks both as frozen for
the drift test (:class:`twin.online.drift.DriftMonitor` holds their statistics), so a wander along the
unidentified direction never becomes an alarm.  The filter's estimates are not changed.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

#: the inertia term's smallest share of the damping term (``w_eff / (2 zeta wn)``) at which zeta and wn count
#: as separately identified (README, "Tuned constants")
SPLIT_RATIO = 0.25
#: envelope time constants ``1 / (zeta wn)`` after which the lag has settled onto its input (e^-20: exactly, in
#: double precision); a longer gap between samples restarts it there instead of stepping through the gap
SETTLED = 20.0


@nb.njit(cache=True)
def _unsplit(vs, dt, bar, alpha, carry, out):  # pragma: no cover - compiled
    """Per sample: True where ``w_eff < bar`` (``bar = ratio * 2 zeta wn``). ``carry``: [<|a|>, <|v|>, last vs]
    (NaN: none)."""
    a_m, v_m, last = carry[0], carry[1], carry[2]
    for k in range(vs.shape[0]):
        v = vs[k]
        h = dt[k]
        if not np.isfinite(v):
            out[k] = True
            continue
        if np.isfinite(last) and np.isfinite(h) and h > 0.0:
            acc = abs(v - last) / h
            a_m = acc if not np.isfinite(a_m) else a_m + alpha * (acc - a_m)
            v_m = abs(v) if not np.isfinite(v_m) else v_m + alpha * (abs(v) - v_m)
        last = v
        out[k] = not (np.isfinite(a_m) and np.isfinite(v_m) and v_m > 0.0 and a_m >= bar * v_m)
    carry[0], carry[1], carry[2] = a_m, v_m, last


@nb.njit(cache=True)
def _lag_rate(u, dt, zeta, wn, carry, out):  # pragma: no cover - compiled
    """The rate of a unit lag with the rig's zeta and wn driven by ``u`` (semi-implicit Euler per sample;
    ``carry``: [position, rate], NaN: start at rest on the first finite ``u``)."""
    y, v = carry[0], carry[1]
    for k in range(u.shape[0]):
        h = dt[k]
        if np.isfinite(u[k]):
            if not np.isfinite(y) or (np.isfinite(h) and h * zeta * wn > SETTLED):  # first, or after a gap: settled
                y, v = u[k], 0.0
            elif np.isfinite(h) and h > 0.0:
                n = max(1, int(math.ceil(h * wn / 0.25)))  # steps of at most a quarter of 1/wn: stable, smooth
                s = h / n
                for _ in range(n):
                    v += s * (wn * wn * (u[k] - y) - 2.0 * zeta * wn * v)
                    y += s * v
        out[k] = v if np.isfinite(y) else np.nan
    carry[0], carry[1] = y, v


def lag_rate(u: np.ndarray, dt: np.ndarray, zeta: float, wn: float, carry: np.ndarray) -> np.ndarray:
    """[T] the rate of a lag with the rig's ``zeta`` and ``wn`` driven by the logged command ``u`` (what the
    command asks of the valve, free of the filter's own estimates); ``carry``: 2 floats (NaN at the start)."""
    out = np.empty(u.shape[0])
    _lag_rate(np.ascontiguousarray(u, dtype=float), np.ascontiguousarray(dt, dtype=float), float(zeta), float(wn),
              carry, out)
    return out


def unsplit(vs: np.ndarray, dt: np.ndarray, zeta: float, wn: float, alpha: float, carry: np.ndarray,
            ratio: float = SPLIT_RATIO) -> np.ndarray:
    """[T] bool: the lag's damping ratio and natural frequency are not told apart at these samples.

    ``vs``: the lag's rate state (SI); ``dt``: seconds since the previous sample; ``zeta``, ``wn``: the rig's
    values (the configured or commissioned ones: an estimate wandering down would lower its own bar); ``alpha``: the averages' weight per sample; ``carry``: 3 floats carried from block to block
    (updated in place; NaN at the start)."""
    out = np.empty(vs.shape[0], dtype=np.bool_)
    _unsplit(np.ascontiguousarray(vs, dtype=float), np.ascontiguousarray(dt, dtype=float),
             float(ratio) * 2.0 * float(zeta) * float(wn), float(alpha), carry, out)
    return out
