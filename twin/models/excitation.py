"""Excitation signals for identification experiments (all return ``[T]`` float arrays).

* :func:`multisine` - Schroeder-phased sum of sines on a band, low crest factor;
* :func:`chirp` - linear frequency sweep;
* :func:`random_steps` - band-limited random steps (random levels held for
  random durations, smoothed by a second-order low-pass so a servo can follow).
"""

from __future__ import annotations

import numpy as np

from fpdd.errors import DataError


def _grid(duration_s: float, dt: float) -> np.ndarray:
    if not (duration_s > 0 and dt > 0):
        raise DataError(f"excitation needs duration_s > 0 and dt > 0, got {duration_s} and {dt}")
    return np.arange(int(round(duration_s / dt))) * dt


def multisine(duration_s: float, dt: float, f_lo: float, f_hi: float, amplitude: float,
              n_lines: int = 24, seed: int | None = None, ramp_s: float = 0.5) -> np.ndarray:
    """Sum of ``n_lines`` sines log-spaced on [f_lo, f_hi] Hz, peak ``amplitude``.

    Phases are Schroeder's (``seed=None``) or random from ``np.random.default_rng(seed)``;
    the start is ramped in over ``ramp_s`` so the rig starts at rest.
    """
    t = _grid(duration_s, dt)
    if not (0 < f_lo < f_hi < 0.5 / dt):
        raise DataError(f"multisine band [{f_lo}, {f_hi}] Hz must lie in (0, {0.5 / dt:g}) Hz")
    f = np.geomspace(f_lo, f_hi, n_lines)
    k = np.arange(1, n_lines + 1)
    if seed is None:
        phi = -np.pi * k * (k - 1) / n_lines
    else:
        phi = np.random.default_rng(seed).uniform(0, 2 * np.pi, n_lines)
    # equal power per line, falling with frequency like a displacement demand (velocity-limited)
    a = 1.0 / np.sqrt(f / f[0])
    x = (a[:, None] * np.sin(2 * np.pi * f[:, None] * t[None, :] + phi[:, None])).sum(axis=0)
    x *= amplitude / np.max(np.abs(x))
    return x * _ramp(t, ramp_s)


def chirp(duration_s: float, dt: float, f_lo: float, f_hi: float, amplitude: float,
          ramp_s: float = 0.2) -> np.ndarray:
    """Linear sweep from ``f_lo`` to ``f_hi`` Hz, peak ``amplitude``."""
    from scipy import signal as sps  # here: scipy.signal costs about a second of import

    t = _grid(duration_s, dt)
    return amplitude * sps.chirp(t, f_lo, t[-1], f_hi, method="linear", phi=-90) * _ramp(t, ramp_s)


def random_steps(duration_s: float, dt: float, amplitude: float, hold_s: tuple[float, float] = (0.1, 0.6),
                 bandwidth_hz: float = 8.0, seed: int = 0) -> np.ndarray:
    """Random levels in [-amplitude, amplitude] held for random durations, low-passed."""
    t = _grid(duration_s, dt)
    rng = np.random.default_rng(seed)
    x = np.empty_like(t)
    i = 0
    while i < t.size:
        n = max(1, int(rng.uniform(*hold_s) / dt))
        x[i:i + n] = rng.uniform(-amplitude, amplitude)
        i += n
    x[: max(1, int(hold_s[0] / dt))] = 0.0
    from scipy import signal as sps  # here: scipy.signal costs about a second of import

    b, a = sps.butter(2, bandwidth_hz * 2 * dt)
    return sps.lfilter(b, a, x)


def _ramp(t: np.ndarray, ramp_s: float) -> np.ndarray:
    if ramp_s <= 0:
        return np.ones_like(t)
    r = np.clip(t / ramp_s, 0.0, 1.0)
    return r * r * (3 - 2 * r)


KINDS = {"multisine": multisine, "chirp": chirp, "steps": random_steps}
