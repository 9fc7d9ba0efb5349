"""Residual analysis of a fitted model on a record: what the simulation gets wrong, and where.

Given a record and a model's prediction of it, :func:`analyse` returns a
:class:`ResidualAnalysis` with

* the residuals (measured - predicted) per output over time;
* the noise floor of each residual, estimated from its sample-to-sample
  differences (``std(diff r) / sqrt 2``: a white residual has its whole power
  there, a model error mostly sits at low frequency), and the *excess ratio*
  ``mean(r^2) / noise^2`` (1 for a residual that is only noise);
* where the residuals concentrate by operating regime: velocity sign and
  magnitude, near direction reversals, rod position, chamber pressure
  difference, spool opening proxy (the controller output ``u``), and
  frequency band (Welch spectrum against the white-noise level);
* validation statistics with confidence bands: residual autocorrelation
  (99 % band ``2.576 / sqrt N``) and the Ljung-Box portmanteau test;
  cross-correlation of each residual with the demanded displacement, the
  velocity and the controller output, with Bartlett's band (which accounts
  for the residual's own colour, as MATLAB's ``resid`` does).

Closed loop: the rig's controller output ``u`` is computed *from* the
measured displacement, so a residual is always correlated with ``u`` at
negative lags (residual leading ``u``): that is feedback, not a model error.
Only lags >= 0 (the signal leading the residual) count toward the verdict;
the other lags are still reported, marked ``feedback``.

Lag convention of :func:`cross_correlation`: at lag ``k`` the value pairs
``s[t - k]`` with ``r[t]`` (``k > 0``: the signal leads the residual).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence

import numpy as np
from scipy.special import chdtrc  # chi2.sf without importing scipy.stats

from twin.models import get_model

#: two-sided 99 % normal quantile used for every correlation band
Z99 = 2.5758293035489004
#: default significance level of the whiteness and correlation verdicts
ALPHA = 1e-3
#: frequency bands (Hz) of the spectral table; clipped to the Nyquist frequency
BANDS_HZ = ((0.0, 1.0), (1.0, 5.0), (5.0, 20.0), (20.0, 60.0), (60.0, 150.0), (150.0, 500.0))
#: a window of this many seconds either side of a velocity sign change counts as a reversal
REVERSAL_S = 0.02


# --- elementary statistics ---------------------------------------------------------------
def noise_level(r: np.ndarray) -> float:
    """Noise standard deviation of ``r`` from its first differences (robust to slow model errors)."""
    r = np.asarray(r, dtype=float)
    if r.size < 3:
        return float(np.std(r))
    return float(np.std(np.diff(r)) / math.sqrt(2.0))


def autocorrelation(r: np.ndarray, max_lag: int) -> np.ndarray:
    """Normalised autocorrelation of ``r`` at lags ``0..max_lag`` (FFT, biased estimator)."""
    r = np.asarray(r, dtype=float) - np.mean(r)
    n = r.size
    nfft = 1 << int(math.ceil(math.log2(2 * n)))
    f = np.fft.rfft(r, nfft)
    ac = np.fft.irfft(f * np.conj(f), nfft)[: max_lag + 1]
    return ac / ac[0] if ac[0] > 0 else np.zeros(max_lag + 1)


def ljung_box(r: np.ndarray, lags: int, df: int | None = None) -> dict:
    """Ljung-Box statistic ``Q = N (N + 2) sum rho_k^2 / (N - k)`` over lags 1..``lags``, its p-value.

    ``df``: degrees of freedom (default ``lags``); residuals of a fitted AR(p) model have ``lags - p``.
    """
    n = np.asarray(r).size
    rho = autocorrelation(r, lags)[1:]
    k = np.arange(1, lags + 1)
    q = float(n * (n + 2) * np.sum(rho * rho / (n - k)))
    df = int(lags if df is None else max(1, df))
    return {"Q": q, "df": df, "lags": int(lags), "p": float(chdtrc(df, q))}


def cross_correlation(r: np.ndarray, s: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray, float]:
    """Normalised cross-correlation of residual ``r`` with signal ``s``: (lags, values, 99 % band).

    ``values[i]`` pairs ``s[t - lags[i]]`` with ``r[t]``.  The band is Bartlett's
    ``Z99 sqrt(sum_k rho_r(k) rho_s(k) / N)``, exact for white residuals and
    honest for coloured ones.
    """
    r = np.asarray(r, dtype=float) - np.mean(r)
    s = np.asarray(s, dtype=float) - np.mean(s)
    n = r.size
    lags = np.arange(-max_lag, max_lag + 1)
    den = math.sqrt(float(r @ r) * float(s @ s))
    if den == 0:
        return lags, np.zeros(lags.size), float("inf")
    nfft = 1 << int(math.ceil(math.log2(2 * n)))
    c = np.fft.irfft(np.fft.rfft(r, nfft) * np.conj(np.fft.rfft(s, nfft)), nfft)
    vals = np.concatenate([c[nfft - max_lag:], c[: max_lag + 1]]) / den
    m = min(n - 1, 4 * max_lag)
    rr = autocorrelation(r, m)
    ss = autocorrelation(s, m)
    var = (1.0 + 2.0 * float(np.sum(rr[1:] * ss[1:]))) / n
    return lags, vals, Z99 * math.sqrt(max(var, 1.0 / n))


# --- operating regimes -------------------------------------------------------------------
def _quantile_bins(v: np.ndarray, n: int) -> np.ndarray:
    edges = np.unique(np.quantile(v, np.linspace(0, 1, n + 1)))
    if edges.size < 2:
        return np.zeros(v.size, dtype=int)
    return np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)


def regime_signals(model_name: str, record, predicted: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The operating-regime variables of a record, from the (noise-free) prediction where possible."""
    dt = record.dt
    out: dict[str, np.ndarray] = {}
    if {"x", "pA", "pB"} <= set(predicted):  # a hydraulic actuator's regime: stroke, speed, load pressure
        x = np.asarray(predicted["x"])
        out["position"] = x
        out["velocity"] = np.gradient(x, dt)
        out["dp"] = np.asarray(predicted["pA"]) - np.asarray(predicted["pB"])
        u = predicted.get("u", record.signals.get("u"))
        if u is not None:
            out["spool_opening"] = np.asarray(u)
        if "x_ref" in record:
            out["demand"] = record["x_ref"]
    else:  # a mechanical model: its first measured output is a position, its drive a force (or its command)
        from twin.models import get_model

        m = get_model(model_name)
        y = np.asarray(predicted[next(o for o in m.OUTPUTS if o in predicted)])
        out["position"] = y
        out["velocity"] = np.gradient(y, dt)
        drive = predicted.get(m.drive_name, record.signals.get(m.drive_name))
        if drive is not None:
            out["force"] = np.asarray(drive)
    return out


#: the regime variables' display units in the bin labels (position in mm, pressure difference in MPa, ...)
_REGIME_SHOWN = {"position": (" mm", 1e3), "dp": (" MPa", 1e-6), "spool_opening": (" V", 1.0), "force": (" N", 1.0)}


def regime_table(r: np.ndarray, regimes: Mapping[str, np.ndarray], noise: float, dt: float,
                 n_bins: int = 5) -> list[dict]:
    """RMS of ``r`` per operating-regime bin, as a ratio to the noise floor ``noise``.

    Velocity is split by sign and magnitude, plus a reversal window; the other
    variables into ``n_bins`` quantile bins.
    """
    rows: list[dict] = []
    noise = noise if noise > 0 else float(np.std(r)) or 1.0

    def add(regime, label, mask):
        n = int(mask.sum())
        if n < 10:
            return
        rms = float(np.sqrt(np.mean(r[mask] ** 2)))
        rows.append({"regime": regime, "bin": label, "n": n, "mean": float(np.mean(r[mask])), "rms": rms,
                     "ratio": rms / noise})

    v = regimes.get("velocity")
    if v is not None:
        vmax = float(np.max(np.abs(v))) or 1.0
        for sign, sm in (("+", v > 0), ("-", v < 0)):
            mag = np.abs(v)
            for lo, hi, lab in ((0.0, 0.1, "slow"), (0.1, 0.5, "medium"), (0.5, 1.01, "fast")):
                add("velocity", f"{sign}{lab} (|v| {lo * vmax * 1e3:.3g}..{hi * vmax * 1e3:.3g} mm/s)",
                    sm & (mag >= lo * vmax) & (mag < hi * vmax))
        rev = np.flatnonzero(np.diff(np.signbit(v)))
        near = np.zeros(v.size, dtype=bool)
        w = max(1, int(round(REVERSAL_S / dt)))
        for i in rev:
            near[max(0, i - w): i + w + 1] = True
        add("reversal", f"within {REVERSAL_S * 1e3:.0f} ms of a reversal", near)
        add("reversal", "away from reversals", ~near)
    for name in ("position", "dp", "spool_opening", "force"):
        s = regimes.get(name)
        if s is None:
            continue
        unit, k = _REGIME_SHOWN.get(name, ("", 1.0))
        b = _quantile_bins(s, n_bins)
        for j in range(int(b.max()) + 1):
            m = b == j
            if m.any():  # the bin's range in display units (a label a person reads)
                add(name, f"q{j + 1} ({float(s[m].min()) * k:.4g}..{float(s[m].max()) * k:.4g}{unit})", m)
    return rows


def _welch(x: np.ndarray, fs: float, nperseg: int) -> tuple[np.ndarray, np.ndarray]:
    """Welch's one-sided power spectral density of ``x``, as ``scipy.signal.welch(x, fs, nperseg=nperseg)`` computes
    it (periodic Hann window, half-overlapping segments, each segment's mean removed, density scaling) without
    importing scipy.signal (a second of a fit command's start-up)."""
    step = nperseg - nperseg // 2
    win = 0.5 - 0.5 * np.cos(2.0 * np.pi * np.arange(nperseg) / nperseg)
    nseg = (x.size - nperseg) // step + 1
    seg = x[np.arange(nperseg)[None, :] + step * np.arange(nseg)[:, None]]
    seg = seg - seg.mean(axis=1, keepdims=True)
    p = np.abs(np.fft.rfft(seg * win, axis=1)) ** 2 / (fs * float(np.sum(win * win)))
    if nperseg % 2:
        p[:, 1:] *= 2.0
    else:
        p[:, 1:-1] *= 2.0
    return np.fft.rfftfreq(nperseg, 1.0 / fs), p.mean(axis=0)


def band_table(r: np.ndarray, dt: float, noise: float) -> list[dict]:
    """Residual power per frequency band relative to the white-noise level of ``noise``."""
    n = r.size
    nper = int(min(n, max(256, 2 ** int(math.log2(max(n // 8, 2))))))
    f, pxx = _welch(r - np.mean(r), 1.0 / dt, nper)
    white = 2.0 * noise * noise * dt  # one-sided PSD of white noise of std `noise`
    rows = []
    nyq = 0.5 / dt
    for lo, hi in BANDS_HZ:
        if lo >= nyq:
            break
        m = (f >= lo) & (f < min(hi, nyq + 1e-9))
        if not m.any():
            continue
        ratio = float(np.mean(pxx[m]) / white) if white > 0 else float("inf")
        rows.append({"f_lo_hz": lo, "f_hi_hz": min(hi, nyq), "power_ratio": ratio})
    return rows


# --- the analysis --------------------------------------------------------------------------
@dataclasses.dataclass
class ResidualAnalysis:
    """Residuals of one model on one record and the statistics that judge them."""

    outputs: tuple[str, ...]
    dt: float
    residuals: dict[str, np.ndarray] = dataclasses.field(repr=False)
    noise: dict[str, float]           # noise floor per output (from differences)
    rms: dict[str, float]
    excess: dict[str, float]          # mean(r^2) / noise^2
    max_lag: int
    acf: dict[str, np.ndarray] = dataclasses.field(repr=False)
    acf_band: float
    ljung_box: dict[str, dict]
    xcorr: dict[str, dict] = dataclasses.field(repr=False)
    regimes: dict[str, list[dict]]
    bands: dict[str, list[dict]]
    alpha: float

    @property
    def white(self) -> dict[str, bool]:
        return {o: self.ljung_box[o]["p"] >= self.alpha for o in self.outputs}

    @property
    def correlated_inputs(self) -> list[str]:
        """``output~signal`` pairs whose cross-correlation leaves its band at a lag >= 0."""
        return [k for k, v in self.xcorr.items() if v["significant"]]

    @property
    def adequate(self) -> bool:
        """Residuals white on every output (Ljung-Box at level ``alpha``)."""
        return all(self.white.values())

    def concentration(self, output: str, top: int = 3) -> list[dict]:
        """The regime bins where ``output``'s residual is largest relative to its noise."""
        return sorted(self.regimes[output], key=lambda row: -row["ratio"])[:top]

    def summary(self) -> dict:
        """As JSON: residual levels in SI with their unit beside (``rms_unit``, ``noise_unit``, a row's ``unit``)."""
        from twin.units import SIGNAL_UNITS

        unit = {o: SIGNAL_UNITS.get(o, "") for o in self.outputs}
        return {
            "outputs": list(self.outputs),
            "noise": self.noise, "noise_unit": unit, "rms": self.rms, "rms_unit": unit, "excess": self.excess,
            "ljung_box": self.ljung_box, "white": self.white, "adequate": self.adequate,
            "acf_band": self.acf_band,
            "acf": {o: np.round(self.acf[o][: min(11, self.max_lag + 1)], 4).tolist() for o in self.outputs},
            "xcorr": {k: {kk: vv for kk, vv in v.items() if kk not in ("lags", "values")}
                      for k, v in self.xcorr.items()},
            "concentration": {o: [dict(row, unit=unit[o]) for row in self.concentration(o)] for o in self.outputs},
            "bands": self.bands,
        }

    def text(self) -> str:
        from twin.units import signal_unit

        lines = []
        for o in self.outputs:
            lb = self.ljung_box[o]
            shown, k = signal_unit(o)
            lines.append(f"  {o}: rms {self.rms[o] * k:.4g} {shown}, noise floor {self.noise[o] * k:.4g} {shown}, "
                         f"excess x{self.excess[o]:.3g}, Ljung-Box Q={lb['Q']:.4g} (df {lb['df']}) "
                         f"p={lb['p']:.3g} -> {'white' if self.white[o] else 'NOT white'}")
            conc = self.concentration(o, 2)
            if conc and not self.white[o]:
                lines.append("      largest in: " + "; ".join(f"{c['regime']} {c['bin']} x{c['ratio']:.3g}"
                                                           for c in conc))
        bad = self.correlated_inputs
        if bad:
            lines.append("  cross-correlated (lags >= 0): " + ", ".join(bad))
        return "\n".join(lines)


def analyse(model_name: str, record, predicted: Mapping[str, np.ndarray], outputs: Sequence[str],
            start: int = 0, stop: int | None = None, max_lag: int = 25, alpha: float = ALPHA,
            closed_loop: bool | None = None) -> ResidualAnalysis:
    """Residual analysis of ``predicted`` (a simulation of the whole ``record``) on samples ``start:stop``."""
    stop = len(record) if stop is None else stop
    sl = slice(start, stop)
    regimes = {k: v[sl] for k, v in regime_signals(model_name, record, predicted).items()}
    if closed_loop is None:
        closed_loop = get_model(model_name).CLOSED_LOOP and "x_ref" in record
    res, noise, rms, excess, acf, lb, reg, bands, xc = {}, {}, {}, {}, {}, {}, {}, {}, {}
    n = stop - start
    max_lag = int(max(1, min(max_lag, n // 4)))
    for o in outputs:
        r = np.asarray(record[o][sl]) - np.asarray(predicted[o][sl])
        res[o] = r
        nz = noise_level(r)
        noise[o] = nz
        rms[o] = float(np.sqrt(np.mean(r * r)))
        excess[o] = rms[o] ** 2 / nz ** 2 if nz > 0 else float("inf")
        acf[o] = autocorrelation(r, max_lag)
        lb[o] = ljung_box(r, max_lag)
        reg[o] = regime_table(r, regimes, nz, record.dt)
        bands[o] = band_table(r, record.dt, nz)
        against = {"demand": regimes.get("demand"), "velocity": regimes.get("velocity"),
                   "u": (record["u"][sl] if "u" in record else None)}
        for name, s in against.items():
            if s is None:
                continue
            lags, vals, band = cross_correlation(r, s, max_lag)
            feedback = closed_loop and name == "u"
            counted = lags >= 0
            out = np.abs(vals) > band
            i = int(np.argmax(np.where(counted, np.abs(vals), -1.0)))
            xc[f"{o}~{name}"] = {
                "lags": lags, "values": vals, "band": band,
                "max_abs": float(abs(vals[i])), "lag_of_max": int(lags[i]),
                "significant": bool(np.any(out & counted)),
                "feedback_lags_outside_band": int(np.sum(out & ~counted)) if feedback else 0,
                "note": ("closed loop: lags < 0 (residual leading u) are feedback, not a model error"
                         if feedback else "lags >= 0 counted (signal leading the residual)"),
            }
    return ResidualAnalysis(tuple(outputs), record.dt, res, noise, rms, excess, max_lag, acf,
                            Z99 / math.sqrt(n), lb, xc, reg, bands, alpha)
