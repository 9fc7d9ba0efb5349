"""The plots of the reports, in one style modelled on MATLAB's identification views.

* :func:`compare_figure`: measured vs simulated per output with Fit % (``compare``),
  the whole record beside a zoom where the models differ most, the residual under each;
* :func:`resid_figure`: residual autocorrelation with its 99 % band and
  cross-correlation with each input with Bartlett's band (``resid``);
* :func:`corr_figure`: a correlation matrix as an annotated heat map;
* :func:`trends_figure`: tracked parameters with their 95 % interval, the healthy
  band and the alarm events.

Every axis carries its unit (display units, see :mod:`twin.reports.units`);
dimensionless axes carry none.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from twin.reports.units import label

#: MATLAB's default line colours (R2014b+)
BLUE, ORANGE, YELLOW, PURPLE, GREEN, CYAN, RED = ("#0072BD", "#D95319", "#EDB120", "#7E2F8E", "#77AC30",
                                                  "#4DBEEE", "#A2142F")
MEASURED = "#8c8c8c"
LEVEL_COLOURS = {"alarm": RED, "warning": ORANGE, "ok": GREEN}
Z99 = 2.5758293035489004
Z95 = 1.959963984540054

RC = {
    "figure.facecolor": "white", "axes.facecolor": "white", "axes.grid": True, "grid.color": "#d9d9d9",
    "grid.linewidth": 0.6, "axes.edgecolor": "#4d4d4d", "axes.linewidth": 0.7, "font.size": 8.5,
    "axes.titlesize": 9.5, "axes.labelsize": 8.5, "legend.fontsize": 7.5, "legend.framealpha": 0.9,
    "xtick.labelsize": 7.5, "ytick.labelsize": 7.5, "lines.linewidth": 1.0,
    "axes.prop_cycle": __import__("cycler").cycler(color=[BLUE, ORANGE, YELLOW, PURPLE, GREEN, CYAN, RED]),
    "axes.formatter.useoffset": False,
}


def plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as pyplot

    return pyplot


#: the zoom beside the whole record: 5 % of it, at least ZOOM_MIN_S and at most ZOOM_MAX_S, so that a long
#: record's response (a solid band at full length) shows its samples and cycles (a servo-hydraulic rig's
#: dynamics of 10-100 Hz make 5-50 cycles in 0.5 s)
ZOOM_MIN_S, ZOOM_MAX_S = 0.2, 0.5


def _zoom_window(t: np.ndarray, err: np.ndarray) -> slice:
    """A short window (``ZOOM_MIN_S`` … ``ZOOM_MAX_S``, 5 % of the record in between) centred where ``|err|``
    is largest."""
    n = t.size
    if n < 50:
        return slice(0, n)
    dt = float(np.median(np.diff(t))) if n > 1 else 1.0
    w = int(min(n, max(ZOOM_MIN_S / max(dt, 1e-12), min(0.05 * n, ZOOM_MAX_S / max(dt, 1e-12)))))
    w = max(w, min(n, 20))
    smooth = np.convolve(np.abs(np.nan_to_num(err)), np.ones(max(w // 4, 1)), mode="same")
    c = int(np.argmax(smooth))
    a = max(0, min(c - w // 2, n - w))
    return slice(a, a + w)


def compare_figure(t: np.ndarray, outputs: Sequence[dict], title: str = ""):
    """Measured vs simulated per output.

    ``outputs``: dicts with ``name``, ``unit`` (display), ``scale`` (SI to display),
    ``measured`` (SI array) and ``models``: a list of ``(label, SI array)``; the
    first model's residual is drawn under the response (and the others' too).
    """
    pl = plt()
    zooms: list[tuple[float, float]] = []
    with pl.rc_context(RC):
        n = len(outputs)
        fig = pl.figure(figsize=(10.5, 3.6 * n + (0.35 if title else 0.0)))
        outer = fig.add_gridspec(n, 1, hspace=0.32)
        colours = [BLUE, ORANGE, PURPLE, GREEN]
        for i, o in enumerate(outputs):
            sc = o["scale"]
            y = np.asarray(o["measured"]) * sc
            sims = [(lbl, np.asarray(s) * sc) for lbl, s in o["models"]]
            zoom = _zoom_window(t, y - sims[0][1]) if sims else slice(0, t.size)
            zooms.append((float(t[zoom][0]), float(t[zoom][-1])))
            gs = outer[i].subgridspec(2, 2, width_ratios=[3, 2], height_ratios=[3, 1.25], hspace=0.1, wspace=0.18)
            for col, sl in ((0, slice(0, t.size)), (1, zoom)):
                ax = fig.add_subplot(gs[0, col])
                axr = fig.add_subplot(gs[1, col], sharex=ax)
                if col == 0:
                    ax.plot(t[sl], y[sl], color=MEASURED, lw=1.6, label="measured", zorder=1)
                else:  # the zoom shows the samples themselves: a line on a line hides one of them
                    every = max(1, (sl.stop - sl.start) // 250)
                    ax.plot(t[sl][::every], y[sl][::every], "o", color=MEASURED, ms=2.4, mew=0, zorder=1,
                            label="measured")
                for k, (lbl, s) in enumerate(sims):
                    ls = "-" if k == 0 else "--"
                    ax.plot(t[sl], s[sl], color=colours[k % 4], lw=1.0, ls=ls, label=lbl, zorder=2 + k)
                    axr.plot(t[sl], (y - s)[sl], color=colours[k % 4], lw=0.7, ls=ls)
                axr.axhline(0.0, color="#4d4d4d", lw=0.6)
                pl.setp(ax.get_xticklabels(), visible=False)
                if col == 0:
                    ax.set_ylabel(label(o["name"], o["unit"]))
                    axr.set_ylabel(label("error", o["unit"]))
                    ax.axvspan(t[zoom][0], t[zoom][-1], color=YELLOW, alpha=0.15, lw=0)
                    ax.set_title(o.get("title") or f"{o['name']}: whole record", loc="left")
                    ax.legend(loc="upper right", ncol=1 + len(sims))
                else:
                    ax.set_title(f"zoom: {t[zoom][0]:.2f} … {t[zoom][-1]:.2f} s (largest error)", loc="left")
                axr.set_xlabel("t [s]")
        if title:
            fig.suptitle(title, x=0.01, ha="left", fontsize=10)
        fig.subplots_adjust(left=0.08, right=0.98, top=1 - 0.45 / fig.get_figheight() - (0.25 / fig.get_figheight() if title else 0),
                            bottom=0.5 / fig.get_figheight())
    fig.zooms = zooms  # (first, last) time of each output's zoom, s
    return fig


def zoom_text(fig) -> str:
    """What a compare figure's zoom panels show, for its caption: ``t = 12.30 … 12.80 s`` per output."""
    spans = sorted(set(getattr(fig, "zooms", [])))
    if not spans:
        return ""
    return "; ".join(f"t = {a:.2f} … {b:.2f} s ({b - a:.2f} s)" for a, b in spans)


def resid_figure(residuals: Mapping[str, np.ndarray], inputs: Mapping[str, np.ndarray], dt: float,
                 max_lag: int = 25, closed_loop: Sequence[str] = ("u",)):
    """Residual whiteness and independence from the inputs (MATLAB's ``resid``).

    Left column: autocorrelation of each output's residual at lags 1..``max_lag``
    with the 99 % band ``±2.58/√N``.  Other columns: cross-correlation with each
    input at lags ``-max_lag..max_lag`` (positive: the input leads) with
    Bartlett's 99 % band.  Inputs in ``closed_loop`` are computed from the
    measurement, so their negative lags are feedback (shaded), not model error.
    """
    from twin.estimation.residuals import autocorrelation, cross_correlation

    pl = plt()
    outs = list(residuals)
    ins = list(inputs)
    lag_ms = dt * 1e3
    with pl.rc_context(RC):
        ncol = 1 + len(ins)
        fig, axes = pl.subplots(len(outs), ncol, figsize=(3.5 * ncol + 0.6, 2.3 * len(outs) + 0.7), squeeze=False)
        for i, o in enumerate(outs):
            r = np.asarray(residuals[o], dtype=float)
            r = r[np.isfinite(r)]
            ac = autocorrelation(r, max_lag)
            band = Z99 / math.sqrt(max(r.size, 1))
            ax = axes[i, 0]
            lags = np.arange(max_lag + 1) * lag_ms
            ax.axhspan(-band, band, color=CYAN, alpha=0.25, lw=0, label="99 % band")
            ax.vlines(lags[1:], 0, ac[1:], color=BLUE, lw=1.2)
            ax.plot(lags[1:], ac[1:], "o", color=BLUE, ms=2.5)
            out = np.abs(ac[1:]) > band
            if out.any():
                ax.plot(lags[1:][out], ac[1:][out], "o", color=RED, ms=3.5, label="outside")
            ax.axhline(0, color="#4d4d4d", lw=0.6)
            ax.set_ylabel(f"autocorrelation of e({o})")
            ax.set_title(f"e({o}): {np.count_nonzero(out)}/{max_lag} lags outside", loc="left")
            if i == 0:
                ax.legend(loc="upper right")
            for j, name in enumerate(ins):
                ax = axes[i, 1 + j]
                s = np.asarray(inputs[name], dtype=float)[: np.asarray(residuals[o]).size]
                ok = np.isfinite(s) & np.isfinite(np.asarray(residuals[o], dtype=float)[: s.size])
                lg, cc, b = cross_correlation(np.asarray(residuals[o], dtype=float)[: s.size][ok], s[ok], max_lag)
                lms = lg * lag_ms
                ax.axhspan(-b, b, color=CYAN, alpha=0.25, lw=0)
                if name in closed_loop:
                    ax.axvspan(lms[0], 0, color="#bdbdbd", alpha=0.25, lw=0, label="feedback (lags < 0)")
                    if i == 0:
                        ax.legend(loc="upper right")
                ax.vlines(lms, 0, cc, color=BLUE, lw=1.0)
                ax.plot(lms, cc, "o", color=BLUE, ms=2.2)
                bad = (np.abs(cc) > b) & ((lg >= 0) if name in closed_loop else True)
                if np.any(bad):
                    ax.plot(lms[bad], cc[bad], "o", color=RED, ms=3.2)
                ax.axhline(0, color="#4d4d4d", lw=0.6)
                ax.set_ylabel(f"correlation of {name} and e({o})")
                ax.set_title(f"{name} → e({o})", loc="left")
        for ax in axes[-1]:
            ax.set_xlabel("lag [ms]")
        fig.tight_layout()
    return fig


def corr_figure(names: Sequence[str], matrix: np.ndarray):
    """A correlation matrix as a heat map with the values written in."""
    pl = plt()
    m = np.asarray(matrix, dtype=float)
    n = len(names)
    with pl.rc_context({**RC, "axes.grid": False}):
        fig, ax = pl.subplots(figsize=(1.0 * n + 2.6, 0.85 * n + 1.2))
        im = ax.imshow(np.nan_to_num(m), cmap="RdBu_r", vmin=-1, vmax=1)
        ax.set_xticks(range(n), names)
        ax.set_yticks(range(n), names)
        for a in range(n):
            for b in range(n):
                v = m[a, b]
                txt = "n/a" if not np.isfinite(v) else f"{v:+.3f}"
                ax.text(b, a, txt, ha="center", va="center", fontsize=8,
                        color="white" if np.isfinite(v) and abs(v) > 0.6 else "black")
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
        cb.set_label("correlation")
        ax.set_title("Correlation of the estimates", loc="left")
        fig.tight_layout()
    return fig


def trends_figure(t: np.ndarray, params: Sequence[dict], alarms: Sequence[dict] = (), title: str = ""):
    """Tracked parameters over time.

    ``params``: dicts with ``label`` (axis label with unit), ``value``, ``lo95``, ``hi95``
    (display units, arrays over ``t``), optional ``band`` ``(lo, hi)`` and ``baseline``,
    ``log`` (log scale) and ``name``; ``alarms``: dicts with ``parameter``,
    ``t_s`` and ``level``.
    """
    pl = plt()
    n = len(params)
    with pl.rc_context(RC):
        fig, axes = pl.subplots(n, 1, figsize=(10.5, 1.95 * n + 0.9), sharex=True, squeeze=False)
        for ax, p in zip(axes[:, 0], params):
            if p.get("band") is not None:
                lo, hi = p["band"]
                ax.axhspan(lo, hi, color=GREEN, alpha=0.13, lw=0, label="healthy band")
            if p.get("baseline") is not None:
                ax.axhline(p["baseline"], color=GREEN, lw=0.8, ls=":", label="baseline")
            if t.size:
                ax.fill_between(t, p["lo95"], p["hi95"], color=BLUE, alpha=0.2, lw=0, label="95 % interval")
                ax.plot(t, p["value"], color=BLUE, lw=1.1, label="estimate")
                _limits(ax, t, p)
            for a in alarms:
                if a.get("parameter") == p.get("name"):
                    ax.axvline(a["t_s"], color=LEVEL_COLOURS.get(a.get("level", ""), GREEN), lw=1.0,
                               ls="-" if a.get("level") != "ok" else "--")
            if p.get("log"):
                ax.set_yscale("log")
            ax.set_ylabel(p["label"])
        handles, labels = axes[0, 0].get_legend_handles_labels()
        from matplotlib.lines import Line2D

        for lvl in ("warning", "alarm", "ok"):
            handles.append(Line2D([], [], color=LEVEL_COLOURS[lvl], lw=1.0, ls="-" if lvl != "ok" else "--"))
            labels.append({"ok": "returned to ok"}.get(lvl, lvl))
        fig.legend(handles, labels, loc="upper center", ncol=len(labels), bbox_to_anchor=(0.5, 1.0), frameon=False)
        axes[-1, 0].set_xlabel("t [s]")
        if title:
            axes[0, 0].set_title(title, loc="left", pad=4)
        fig.tight_layout(rect=(0, 0, 1, 1 - 0.28 / fig.get_figheight()))
    return fig


def _limits(ax, t: np.ndarray, p: dict) -> None:
    """Scale to the settled estimate, its interval and the band, not to the filter's start-up."""
    settle = t > t[0] + 0.1 * (t[-1] - t[0]) if t.size > 10 else np.ones(t.size, bool)
    vals = [np.asarray(p["value"])[settle], np.asarray(p["lo95"])[settle], np.asarray(p["hi95"])[settle]]
    if p.get("band") is not None:
        vals.append(np.asarray(p["band"], dtype=float))
    v = np.concatenate([np.ravel(a) for a in vals])
    v = v[np.isfinite(v)]
    if p.get("log"):
        v = v[v > 0]
    if not v.size:
        return
    lo, hi = float(v.min()), float(v.max())
    if p.get("log"):
        ax.set_ylim(lo / 1.3, hi * 1.3)
    else:
        pad = 0.08 * (hi - lo) if hi > lo else 0.05 * abs(hi) or 1.0
        ax.set_ylim(lo - pad, hi + pad)


def error_figure(t: np.ndarray, outputs: Sequence[dict], t_split: float | None = None):
    """The simulation error per output with its noise band: the whole record beside a zoom.

    ``outputs``: dicts with ``name``, ``unit`` (display), ``scale`` (SI to display), ``errors``: a list of
    ``(label, SI array)`` (measured − simulated) and ``noise`` (the noise std, SI): the band ``±1.96 σ`` holds
    95 % of a white noise's samples, so an error that leaves it for long is the model's, not the sensor's.
    ``t_split``: the start of the held-out part (a dotted line).
    """
    pl = plt()
    zooms: list[tuple[float, float]] = []
    with pl.rc_context(RC):
        n = len(outputs)
        fig, axes = pl.subplots(n, 2, figsize=(10.5, 2.3 * n + 0.8), squeeze=False,
                                gridspec_kw={"width_ratios": [3, 2]})
        colours = [BLUE, ORANGE, PURPLE, GREEN]
        for i, o in enumerate(outputs):
            sc = o["scale"]
            errs = [(lbl, np.asarray(e, float) * sc) for lbl, e in o["errors"]]
            band = Z95 * float(o["noise"]) * sc
            zoom = _zoom_window(t, errs[0][1]) if errs else slice(0, t.size)
            zooms.append((float(t[zoom][0]), float(t[zoom][-1])))
            for col, sl in ((0, slice(0, t.size)), (1, zoom)):
                ax = axes[i, col]
                ax.axhspan(-band, band, color=CYAN, alpha=0.25, lw=0, label="noise band ±1.96 σ (95 %)")
                for k, (lbl, e) in enumerate(errs):
                    ax.plot(t[sl], e[sl], color=colours[k % 4], lw=0.8 if col == 0 else 1.0,
                            ls="-" if k == 0 else "--", label=lbl)
                ax.axhline(0.0, color="#4d4d4d", lw=0.6)
                if t_split is not None and t[sl][0] <= t_split <= t[sl][-1]:
                    ax.axvline(t_split, color="k", lw=0.8, ls=":", label="held-out part starts")
                if col == 0:
                    ax.set_ylabel(label(f"error of {o['name']}", o["unit"]))
                    ax.axvspan(t[zoom][0], t[zoom][-1], color=YELLOW, alpha=0.15, lw=0)
                    inside = [100.0 * float(np.mean(np.abs(e) <= band)) for _, e in errs]
                    ax.set_title(f"{o['name']}: simulation error, "
                                 + ", ".join(f"{lbl} {p:.0f} % inside the band" for (lbl, _), p in zip(errs, inside)),
                                 loc="left")
                    if i == 0:
                        ax.legend(loc="upper right", ncol=2 + len(errs))
                else:
                    ax.set_title(f"zoom: {t[zoom][0]:.2f} … {t[zoom][-1]:.2f} s (largest error)", loc="left")
                ax.set_xlabel("t [s]")
        fig.tight_layout()
    fig.zooms = zooms
    return fig


def binned_means(x: np.ndarray, y: np.ndarray, n: int = 25, min_count: int = 5):
    """Quantile bins of ``x``: (bin centre, mean of ``y``, standard error of that mean) per bin."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    edges = np.unique(np.quantile(x, np.linspace(0, 1, n + 1)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(edges.size - 2, 0))
    cx, cy, se = [], [], []
    for j in range(max(edges.size - 1, 1)):
        m = idx == j
        k = int(m.sum())
        if k >= min_count:
            cx.append(float(np.mean(x[m])))
            cy.append(float(np.mean(y[m])))
            se.append(float(np.std(y[m], ddof=1) / math.sqrt(k)))
    return np.array(cx), np.array(cy), np.array(se)


def signature_figure(sig: Mapping):
    """One cause's signature: the residual before the cause was added against its regime variable (binned
    means with their standard errors, the samples faint behind) and the cause's own contribution.

    ``sig``: ``cause``, ``axis`` and ``axis_unit``/``axis_scale``, ``signal``, ``unit``/``scale``, ``x``,
    ``residual``, ``contribution`` (SI arrays).  The vertical scale is the binned curves', not the raw
    samples' (the noise would flatten the signature); a signature within the bins' own scatter is said so
    in the title (``sig["flat"]``, see :func:`signature_flatness`).
    """
    pl = plt()
    xs, ys = float(sig["axis_scale"]), float(sig["scale"])
    x = np.asarray(sig["x"], float) * xs
    r = np.asarray(sig["residual"], float) * ys
    c = np.asarray(sig["contribution"], float) * ys
    bx, by, bse = binned_means(x, r)
    cx, cy, _ = binned_means(x, c)
    with pl.rc_context(RC):
        fig, ax = pl.subplots(figsize=(7.5, 3.6))
        every = max(1, x.size // 4000)
        ax.plot(x[::every], r[::every], ".", color="#c8c8c8", ms=1.5, zorder=0, label="residual before (samples)")
        ax.errorbar(bx, by, yerr=Z95 * bse, fmt="o", color=BLUE, ms=3, capsize=2, lw=0.8, zorder=2,
                    label="residual before: bin mean ±1.96 s.e.")
        ax.plot(cx, cy, "-", color=RED, lw=1.6, zorder=3, label=f"{sig['cause']}: extended − before")
        vals = np.concatenate([by + Z95 * bse, by - Z95 * bse, cy, [0.0]])  # zero in view: a shift shows
        vals = vals[np.isfinite(vals)]
        if vals.size:
            lo, hi = float(vals.min()), float(vals.max())
            pad = 0.15 * (hi - lo) if hi > lo else max(abs(hi), 1e-12)
            ax.set_ylim(lo - pad, hi + pad)
        ax.axhline(0.0, color="#4d4d4d", lw=0.6)
        ax.set_xlabel(label(sig["axis"], sig["axis_unit"]))
        ax.set_ylabel(label(f"residual of {sig['signal']}", sig["unit"]))
        title = f"Signature of {sig['cause']} against {sig['axis']}"
        if sig.get("flat"):
            title += " (flat: within the bins' scatter)"
        ax.set_title(title, loc="left")
        ax.legend(loc="best", fontsize=7)
        fig.tight_layout()
    return fig


def signature_flatness(x: np.ndarray, contribution: np.ndarray, residual: np.ndarray) -> tuple[bool, float, float]:
    """(flat, span of the contribution's bin means and zero, median standard error of the residual's bin
    means): the signature is flat in this view when the cause changes the binned output (a shape or a shift
    from zero) by less than twice the scatter of a bin mean of the residual (what a bin of noise would show)."""
    _, cy, _ = binned_means(x, contribution)
    _, _, se = binned_means(x, residual)
    span = float(np.ptp(np.append(cy, 0.0)))
    scatter = float(np.median(se)) if se.size else 0.0
    return bool(span < 2.0 * scatter), span, scatter
