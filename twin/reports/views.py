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


def _zoom_window(t: np.ndarray, err: np.ndarray) -> slice:
    """A window of about 5 % of the record (0.2 s at least) centred where ``|err|`` is largest."""
    n = t.size
    if n < 50:
        return slice(0, n)
    dt = float(np.median(np.diff(t))) if n > 1 else 1.0
    w = int(min(n, max(0.2 / max(dt, 1e-12), 0.05 * n)))
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
    return fig


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
