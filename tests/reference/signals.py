"""Continuous-time signals of the reference simulator: demands, inputs, noise, time-varying parameters.

A sampled signal between its samples is held (``zoh``), linearly interpolated
(``foh``) or a not-a-knot cubic spline (``cubic``).  All are stored as one table
of local polynomials ``c0 + c1 s + c2 s^2 + c3 s^3`` (``s`` = time since the
sample) that the compiled right-hand side evaluates; before the first sample a
signal keeps its first value, after the last its last value.  A ``multisine``
is evaluated analytically, and so are the test engineer's demands:

* ``chirp``: a sine whose frequency rises linearly, ``f(t) = f0 + (f1 - f0) t / T``, phase
  ``2 pi (f0 t + (f1 - f0) t^2 / (2 T))``; ``sweep``: the same with a logarithmic rise,
  ``f(t) = f0 (f1 / f0)^(t / T)``, phase ``2 pi f0 T ((f1 / f0)^(t / T) - 1) / ln(f1 / f0)``.  Both at
  amplitude ``min(A, v_max / (2 pi f(t)))``: the rod's speed stays at the rig's limit ``v_max`` once the
  frequency has risen past ``v_max / (2 pi A)``.
* ``blocks`` (block loading): consecutive blocks of constant-frequency sines of different amplitudes,
  each faded in and out by a raised cosine (the signal and its rate stay continuous).
* a road-load profile (band-limited random): a multisine of many lines at random frequencies in the
  band, random phases, amplitudes falling as ``1/f`` (a road's displacement spectrum), scaled to its peak
  and to the speed limit.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from scipy.interpolate import CubicSpline

INTERSAMPLE = ("zoh", "foh", "cubic")
K_ZOH, K_FOH, K_CUBIC, K_MULTISINE, K_CHIRP, K_BLOCKS = 0, 1, 2, 3, 4, 5
TV_CONST, TV_STEP, TV_RAMP, TV_EXP, TV_TABLE = 0, 1, 2, 3, 4


def poly_table(values: np.ndarray, dt: float, intersample: str, t0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(SIGP, SC)`` of samples ``values`` at ``t0 + k dt`` with the given intersample behaviour."""
    y = np.ascontiguousarray(values, dtype=np.float64)
    n = y.size
    if n < 2:
        raise ValueError("a sampled signal needs at least 2 samples")
    sc = np.zeros((n, 4))
    sc[:, 0] = y
    if intersample == "zoh":
        kind = K_ZOH
    elif intersample == "foh":
        kind = K_FOH
        sc[:-1, 1] = np.diff(y) / dt
    elif intersample == "cubic":
        kind = K_CUBIC
        cs = CubicSpline(t0 + dt * np.arange(n), y, bc_type="not-a-knot")
        c = cs.c  # highest power first, shape (4, n-1)
        sc[:-1, 0] = c[3]
        sc[:-1, 1] = c[2]
        sc[:-1, 2] = c[1]
        sc[:-1, 3] = c[0]
    else:
        raise ValueError(f"intersample must be one of {INTERSAMPLE}, got {intersample!r}")
    sigp = np.array([kind, t0, dt, n, 0.0, 0.0])
    return sigp, sc


def multisine_table(amplitude: float, f_lo: float, f_hi: float, n_lines: int, seed: int,
                    ramp_s: float = 0.5, offset: float = 0.0, t_norm: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """``(SIGP, SC)`` of a multisine: lines log-spaced on [f_lo, f_hi] Hz, amplitudes ~ f^-1/2,
    random phases from ``seed``, scaled to peak ``amplitude`` over ``t_norm`` s, raised-cosine ramp-in."""
    rng = np.random.default_rng([int(seed), 7001])
    f = np.geomspace(f_lo, f_hi, n_lines)
    a = (f / f[0]) ** -0.5
    ph = rng.uniform(0.0, 2.0 * math.pi, n_lines)
    tt = np.arange(0.0, t_norm, 1e-3)
    peak = np.max(np.abs((a[:, None] * np.sin(2 * math.pi * f[:, None] * tt[None, :] + ph[:, None])).sum(0)))
    sc = np.zeros((n_lines, 4))
    sc[:, 0] = a * amplitude / peak
    sc[:, 1] = f
    sc[:, 2] = ph
    sigp = np.array([K_MULTISINE, 0.0, 0.0, n_lines, ramp_s, offset])
    return sigp, sc


def chirp_table(amplitude: float, f0: float, f1: float, duration: float, v_max: float, log: bool = False,
                ramp_s: float = 0.5, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(SIGP, SC)`` of a chirp (linear rise) or sweep (``log``) from ``f0`` to ``f1`` Hz over ``duration`` s,
    amplitude ``min(amplitude, v_max / (2 pi f))``, raised-cosine ramp-in of ``ramp_s``."""
    if not (0 < f0 < f1 and duration > 0 and amplitude > 0 and v_max > 0):
        raise ValueError(f"chirp needs 0 < f_lo < f_hi, duration, amplitude, v_max > 0; got {f0}, {f1}, "
                         f"{duration}, {amplitude}, {v_max}")
    sc = np.array([[amplitude, f0, f1, duration], [v_max, 1.0 if log else 0.0, 0.0, 0.0]])
    sigp = np.array([K_CHIRP, 0.0, 0.0, 2.0, ramp_s, offset])
    return sigp, sc


def blocks_table(amplitudes, freqs, block_s: float, fade_s: float, offset: float = 0.0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """``(SIGP, SC)`` of block loading: block ``i`` on ``[i block_s, (i + 1) block_s)`` is
    ``amplitudes[i] sin(2 pi freqs[i] (t - t_i))`` faded in and out over ``fade_s``."""
    a = np.asarray(amplitudes, float)
    f = np.asarray(freqs, float)
    if a.shape != f.shape or a.ndim != 1 or not a.size or not 0 < 2 * fade_s <= block_s:
        raise ValueError("blocks: matching amplitudes and frequencies, 0 < 2 fade_s <= block_s")
    t0 = block_s * np.arange(a.size)
    sc = np.stack([t0, t0 + block_s, a, f], axis=1)
    sigp = np.array([K_BLOCKS, 0.0, 0.0, float(a.size), fade_s, offset])
    return sigp, sc


def road_table(amplitude: float, f_lo: float, f_hi: float, n_lines: int, seed: int, v_max: float,
               duration: float, ramp_s: float = 0.5, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(SIGP, SC)`` of a road-load profile: ``n_lines`` sines at frequencies drawn uniformly in
    ``[f_lo, f_hi]`` Hz (seeded), amplitudes ~ ``1/f`` times a Rayleigh draw, random phases; scaled so the
    peak over ``duration`` is ``amplitude`` and the peak speed at most ``v_max``."""
    rng = np.random.default_rng([int(seed), 7003])
    f = np.sort(rng.uniform(f_lo, f_hi, n_lines))
    a = rng.rayleigh(1.0, n_lines) / f
    ph = rng.uniform(0.0, 2.0 * math.pi, n_lines)
    tt = np.arange(0.0, max(duration, 1.0), 1e-3)
    arg = 2 * math.pi * f[:, None] * tt[None, :] + ph[:, None]
    peak = float(np.max(np.abs((a[:, None] * np.sin(arg)).sum(0))))
    vpeak = float(np.max(np.abs((2 * math.pi * f[:, None] * a[:, None] * np.cos(arg)).sum(0))))
    k = min(amplitude / peak, v_max / vpeak)
    sc = np.zeros((n_lines, 4))
    sc[:, 0] = a * k
    sc[:, 1] = f
    sc[:, 2] = ph
    sigp = np.array([K_MULTISINE, 0.0, 0.0, n_lines, ramp_s, offset])
    return sigp, sc


@nb.njit(cache=True)
def sig_eval(sigp, sc, t, seg):
    """Value of a signal table at ``t``; ``seg >= 0`` forces the sample interval (for held inputs)."""
    kind = int(sigp[0])
    if kind == K_CHIRP:
        if t <= 0.0:
            return sigp[5]
        A = sc[0, 0]
        f0 = sc[0, 1]
        f1 = sc[0, 2]
        T = sc[0, 3]
        tc = min(t, T)
        if sc[1, 1] > 0.0:  # logarithmic sweep
            k = math.log(f1 / f0)
            f = f0 * math.exp(k * tc / T)
            ph = 2.0 * math.pi * f0 * T * (math.exp(k * tc / T) - 1.0) / k
        else:
            f = f0 + (f1 - f0) * tc / T
            ph = 2.0 * math.pi * (f0 * tc + 0.5 * (f1 - f0) * tc * tc / T)
        ph += 2.0 * math.pi * f * (t - tc)  # beyond T: on at the end frequency
        a = min(A, sc[1, 0] / (2.0 * math.pi * f))
        v = a * math.sin(ph)
        ramp = sigp[4]
        if t < ramp:
            v *= 0.5 * (1.0 - math.cos(math.pi * t / ramp))
        return v + sigp[5]
    if kind == K_BLOCKS:
        fade = sigp[4]
        v = 0.0
        for i in range(sc.shape[0]):
            ta = sc[i, 0]
            tb = sc[i, 1]
            if ta <= t < tb:
                v = sc[i, 2] * math.sin(2.0 * math.pi * sc[i, 3] * (t - ta))
                if t - ta < fade:
                    v *= 0.5 * (1.0 - math.cos(math.pi * (t - ta) / fade))
                elif tb - t < fade:
                    v *= 0.5 * (1.0 - math.cos(math.pi * (tb - t) / fade))
                break
        return v + sigp[5]
    if kind == K_MULTISINE:
        if t <= 0.0:
            return sigp[5]
        v = 0.0
        for i in range(sc.shape[0]):
            v += sc[i, 0] * math.sin(2.0 * math.pi * sc[i, 1] * t + sc[i, 2])
        ramp = sigp[4]
        if t < ramp:
            v *= 0.5 * (1.0 - math.cos(math.pi * t / ramp))
        return v + sigp[5]
    n = int(sigp[3])
    t0 = sigp[1]
    h = sigp[2]
    if seg >= 0:
        i = seg
    else:
        i = int(math.floor((t - t0) / h))
    if i < 0:
        return sc[0, 0]
    if i > n - 1:
        i = n - 1
    s = t - (t0 + i * h)
    if kind == K_ZOH:
        return sc[i, 0]
    if kind == K_FOH:
        return sc[i, 0] + sc[i, 1] * s
    return sc[i, 0] + s * (sc[i, 1] + s * (sc[i, 2] + s * sc[i, 3]))


# --- noise ----------------------------------------------------------------------------------
def noise_sequence(rng: np.random.Generator, n: int, sigma: float, dt: float, tau: float = 0.0) -> np.ndarray:
    """``n`` samples of zero-mean noise of standard deviation ``sigma``: white, or AR(1) with
    correlation time ``tau`` [s] (stationary from the first sample)."""
    w = rng.standard_normal(n)
    if sigma == 0.0:
        return np.zeros(n)
    if tau <= 0.0:
        return sigma * w
    a = math.exp(-dt / tau)
    return sigma * _ar1(w, a)


@nb.njit(cache=True)
def _ar1(w, a):
    out = np.empty_like(w)
    out[0] = w[0]
    c = math.sqrt(1.0 - a * a)
    for i in range(1, w.size):
        out[i] = a * out[i - 1] + c * w[i]
    return out


def quantise(v: np.ndarray, lsb: float) -> np.ndarray:
    return v if not lsb else lsb * np.round(v / lsb)


# --- time-varying parameters ------------------------------------------------------------------
def tv_row(spec, default: float, table_rows: list, t_lo: float, t_hi: float) -> tuple[list[float], str | float]:
    """One row ``[kind, t0, t1, v0, v1]`` of the time-variation table, and the truth description.

    ``spec``: a number, ``{"kind": "step", "t0", "before", "after"}``, ``{"kind": "ramp", "t0", "t1",
    "start", "end"}``, ``{"kind": "exp", "t0", "tau", "start", "end"}``, ``{"kind": "table", "t": [...],
    "value": [...]}`` (piecewise linear) or a callable of time (sampled at 1 kHz on [t_lo, t_hi]).
    ``start``/``before`` default to ``default``.  Table rows are appended to ``table_rows``.
    """
    if spec is None:
        return [TV_CONST, 0.0, 0.0, default, default], default
    if callable(spec):
        tt = np.linspace(t_lo, t_hi, int(round((t_hi - t_lo) * 1000)) + 1)
        spec = {"kind": "table", "t": tt.tolist(), "value": [float(spec(t)) for t in tt]}
    if isinstance(spec, (int, float)):
        return [TV_CONST, 0.0, 0.0, float(spec), float(spec)], float(spec)
    kind = spec.get("kind")
    if kind == "step":
        row = [TV_STEP, spec["t0"], 0.0, spec.get("before", default), spec["after"]]
    elif kind == "ramp":
        row = [TV_RAMP, spec["t0"], spec["t1"], spec.get("start", default), spec["end"]]
        if not spec["t1"] > spec["t0"]:
            raise ValueError(f"ramp needs t1 > t0, got {spec}")
    elif kind == "exp":
        row = [TV_EXP, spec["t0"], spec["tau"], spec.get("start", default), spec["end"]]
    elif kind == "table":
        t = np.asarray(spec["t"], float)
        v = np.asarray(spec["value"], float)
        if t.ndim != 1 or t.shape != v.shape or t.size < 2 or np.any(np.diff(t) < 0):
            raise ValueError("a table needs matching increasing 't' and 'value' lists of >= 2 entries")
        row = [TV_TABLE, float(len(table_rows)), float(t.size), v[0], v[-1]]
        table_rows.append(np.stack([t, v], axis=1))
    else:
        raise ValueError(f"time variation kind must be step, ramp, exp or table, got {kind!r}")
    desc = {k: (v if not isinstance(v, (list, np.ndarray)) else f"{len(v)} points") for k, v in spec.items()}
    return [float(r) for r in row], desc


def tv_breaks(tv: np.ndarray) -> list[float]:
    """Times where a parameter jumps (steps), where the integrator must restart."""
    return sorted({float(r[1]) for r in tv if int(r[0]) == TV_STEP})


@nb.njit(cache=True)
def tv_eval(tv, tab, i, t):
    """Value of time-varying parameter row ``i`` at time ``t``."""
    kind = int(tv[i, 0])
    t0 = tv[i, 1]
    v0 = tv[i, 3]
    v1 = tv[i, 4]
    if kind == TV_CONST:
        return v0
    if kind == TV_STEP:
        return v0 if t < t0 else v1
    if kind == TV_RAMP:
        t1 = tv[i, 2]
        if t <= t0:
            return v0
        if t >= t1:
            return v1
        return v0 + (v1 - v0) * (t - t0) / (t1 - t0)
    if kind == TV_EXP:
        if t <= t0:
            return v0
        return v1 + (v0 - v1) * math.exp(-(t - t0) / tv[i, 2])
    j = int(t0)
    n = int(tv[i, 2])
    if t <= tab[j, 0, 0]:
        return tab[j, 0, 1]
    if t >= tab[j, n - 1, 0]:
        return tab[j, n - 1, 1]
    lo = 0
    hi = n - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if tab[j, mid, 0] <= t:
            lo = mid
        else:
            hi = mid
    ta = tab[j, lo, 0]
    tb = tab[j, hi, 0]
    if tb <= ta:
        return tab[j, hi, 1]
    return tab[j, lo, 1] + (tab[j, hi, 1] - tab[j, lo, 1]) * (t - ta) / (tb - ta)


def tv_tables(rows: list[list[float]], table_rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    tv = np.array(rows, dtype=np.float64)
    nmax = max([2] + [r.shape[0] for r in table_rows])
    tab = np.zeros((max(1, len(table_rows)), nmax, 2))
    for j, r in enumerate(table_rows):
        tab[j, : r.shape[0]] = r
    return tv, tab


def pade_delay(tau: float, order: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """State-space (A, Bv, C, D) of the [order/order] Pade approximant of ``exp(-s tau)``
    (controllable canonical form, ``order`` <= 4)."""
    from math import factorial

    n = order
    # exp(-s tau) ~ N(-s)/N(s) with N(s) = sum_k c_k (s tau)^k, c_k = (2n-k)! n! / ((2n)! k! (n-k)!)
    c = np.array([factorial(2 * n - k) * factorial(n) / (factorial(2 * n) * factorial(k) * factorial(n - k))
                  for k in range(n + 1)])
    den = c * tau ** np.arange(n + 1)               # ascending powers of s
    num = den * (-1.0) ** np.arange(n + 1)
    den_m = den / den[n]                            # monic
    num_m = num / den[n]
    D = num_m[n]
    A = np.zeros((n, n))
    A[:-1, 1:] = np.eye(n - 1)
    A[-1, :] = -den_m[:n]
    Bv = np.zeros(n)
    Bv[-1] = 1.0
    C = num_m[:n] - D * den_m[:n]
    return A, Bv, C, float(D)
