"""Plots people would rather look at than tables (PNG, matplotlib's Agg backend)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import os

import numpy as np

if TYPE_CHECKING:
    from twin.estimation.diagnose import Diagnosis


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def fit_convergence(result, records, model, out_dir: str) -> list[str]:
    """The paper's Fig. 3 (model response at chosen iterations vs measured) and Fig. 4
    (parameter trends over the iterations) for a :class:`twin.estimation.fit.FitResult`."""
    plt = _plt()
    os.makedirs(out_dir, exist_ok=True)
    paths = []
    best_start = _best_start(result)
    hist = [h for h in result.history if h["start"] == best_start]
    # Fig. 4: parameter trends
    if hist:
        fig, axes = plt.subplots(len(result.free), 1, figsize=(7, 2.2 * len(result.free) + 0.6), squeeze=False)
        it = [h["iteration"] for h in hist]
        for ax, name in zip(axes[:, 0], result.free):
            spec = result.params.spec(name)
            vals = np.array([h["theta"][name] for h in hist]) * spec.display_scale
            ax.plot(it, vals, "o-", color="0.25")
            ax.axhline(result.estimate[name] * spec.display_scale, color="C3", lw=0.8, ls="--")
            ax.set_ylabel(f"{name} [{spec.display_unit or spec.unit}]")
        axes[-1, 0].set_xlabel("iteration")
        axes[0, 0].set_title("Parameter trends during the fit (cf. paper Fig. 4)")
        fig.tight_layout()
        p = os.path.join(out_dir, "fit_parameter_trends.png")
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    # Fig. 3: response at a few iterations
    rec = records[0]
    out = result.outputs[0]
    picks = [h for h in hist if h["iteration"] in (0, 3, 10, 20)] or hist[:1]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    t = rec.t_s
    n = min(len(t), int(3.0 / rec.dt))
    ax.plot(t[:n], rec[out][:n], color="0.6", lw=2.0, label="measured")
    base = result.params
    drive_name, drive = model.drive_signal(rec.signals)
    exo = {k: v[:n] for k, v in model.exogenous_of(rec.signals).items()}
    for h in picks:
        ps = base.update(h["theta"])
        sim = model.simulate(ps, drive_name, drive[:n], rec.dt, init=result.init[0], exogenous=exo)
        ax.plot(t[:n], sim.outputs[out], lw=1.0, label=f"iteration {h['iteration']}")
    sim = model.simulate(base, drive_name, drive[:n], rec.dt, init=result.init[0], exogenous=exo)
    ax.plot(t[:n], sim.outputs[out], color="k", lw=0.8, ls="--", label="final")
    ax.set_xlabel("t [s]")
    ax.set_ylabel(out)
    ax.legend(fontsize=7, ncol=3)
    ax.set_title("Convergence of the model response (cf. paper Fig. 3)")
    fig.tight_layout()
    p = os.path.join(out_dir, "fit_convergence.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths


def _best_start(result) -> int:
    finals = {}
    for h in result.history:
        finals[h["start"]] = h["cost"]
    return min(finals, key=lambda s: finals[s]) if finals else 0


def paper_table(rows: list[dict], out_dir: str) -> str:
    """Bar chart of our errors beside the paper's, per case and parameter (log scale)."""
    plt = _plt()
    os.makedirs(out_dir, exist_ok=True)
    labels = [f"{r['case']}\n{r['parameter']}" for r in rows]
    ours = np.array([max(r["error_pct"], 1e-14) for r in rows])
    paper = np.array([max(r["paper_error_pct"], 1e-14) for r in rows])
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(7, 0.7 * len(rows)), 4))
    ax.bar(x - 0.2, paper, 0.4, label="paper", color="0.6")
    ax.bar(x + 0.2, ours, 0.4, label="fpdd-twin", color="C0")
    ax.set_yscale("log")
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("error [%] (0 shown as 1e-14)")
    ax.legend()
    ax.set_title("Parameter errors: the paper's tables and ours")
    fig.tight_layout()
    p = os.path.join(out_dir, "paper_errors.png")
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p


def settled_mask(stds: np.ndarray, band) -> np.ndarray:
    """The samples of a tracked parameter's history from the first whose +-2 sigma fits within its healthy band
    (``4 std <= hi - lo``) on: before it the filter has not converged enough to tell the band, and its
    start-up swings must not set the plot's y-range.  A history that never gets there: its later half."""
    stds = np.asarray(stds, dtype=np.float64)
    ok = np.flatnonzero(np.isfinite(stds) & (4.0 * stds <= band.hi - band.lo))
    first = int(ok[0]) if ok.size else stds.size // 2
    mask = np.zeros(stds.size, dtype=bool)
    mask[first:] = True
    return mask


def parameter_trends(twin, baseline, path: str, t_truth=None, truth=None,
                     title: str = "Tracked parameters (cf. paper Fig. 4)") -> str:
    """Estimates with +-2 sigma (log-normal), the healthy band, alarm events and optionally the truth
    (kernel vectors ``truth [T, NP]`` at ``t_truth``) of a :class:`twin.service.rig.RigTwin`."""
    plt = _plt()
    model = twin.tracker.model

    hist = twin.history_arrays()
    names = twin.tracker.tracked
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 2.0 * len(names) + 0.8), sharex=True, squeeze=False)
    for ax, j, name in zip(axes[:, 0], range(len(names)), names):
        spec = model.params().spec(name)
        sc = spec.display_scale
        b = baseline[name]
        ax.axhspan(b.lo * sc, b.hi * sc, color="C2", alpha=0.12, label="healthy band")
        if truth is not None:
            ax.plot(t_truth, truth[:, model.kernel_index(name)] * sc, color="0.3", lw=1.0, ls="--", label="truth")
        if hist["t_s"].size:
            v = hist["values"][:, j] * sc
            rel = hist["stds"][:, j] / np.maximum(hist["values"][:, j], 1e-300)  # std of log(theta)
            ax.plot(hist["t_s"], v, color="C0", lw=1.2, label="estimate")
            ax.fill_between(hist["t_s"], v * np.exp(-2 * rel), v * np.exp(2 * rel), color="C0", alpha=0.2, lw=0,
                            label="±2σ")
            settled = settled_mask(hist["stds"][:, j], b)
            if settled.any():  # scale to the settled estimates, the band and the truth, not the start-up
                true_max = np.max(truth[:, model.kernel_index(name)]) * sc if truth is not None else 0.0
                top = max(np.max(v[settled]), b.hi * sc, true_max)
                bot = min(np.min(v[settled]), b.lo * sc)
                if name == "CdAleak":
                    ax.set_ylim(bot / 1.5, top * 1.5)
                else:
                    ax.set_ylim(bot - 0.2 * (top - bot), top + 0.2 * (top - bot))
        for a in twin.alarms:
            if a.parameter == name:
                ax.axvline(a.t_s, color={"alarm": "C3", "warning": "C1"}.get(a.level, "C2"), lw=1.0)
        if name == "CdAleak":
            ax.set_yscale("log")
        ax.set_ylabel(f"{name}\n[{spec.display_unit or spec.unit}]")
    axes[0, 0].legend(fontsize=7, ncol=4, loc="upper left")
    axes[-1, 0].set_xlabel("t [s]  (vertical lines: alarm events, red = alarm, orange = warning, green = returned)")
    axes[0, 0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --- plots ------------------------------------------------------------------------------------
def _binned(x: np.ndarray, y: np.ndarray, n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    edges = np.quantile(x, np.linspace(0, 1, n + 1))
    edges = np.unique(edges)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, max(edges.size - 2, 0))
    cx, cy = [], []
    for j in range(max(edges.size - 1, 1)):
        m = idx == j
        if m.sum() >= 5:
            cx.append(float(np.mean(x[m])))
            cy.append(float(np.mean(y[m])))
    return np.array(cx), np.array(cy)


def diagnosis_plots(diag: Diagnosis, out_dir: str) -> list[str]:
    """PNG plots of a diagnosis in ``out_dir`` (matplotlib Agg); returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from twin.estimation.residuals import regime_signals
    from twin.reports.signatures import _AXIS_SIGNAL
    from twin.reports.units import label, signal_unit

    os.makedirs(out_dir, exist_ok=True)
    paths = []
    rec = diag.records[0]
    n_fit = diag.n_fit[0]
    t = rec.t_s
    nom = diag.nominal.predicted[0]
    fin = diag.final.predicted[0]
    outs = diag.outputs
    # measured vs nominal vs extended (held-out part)
    fig, axes = plt.subplots(len(outs), 1, figsize=(9, 2.4 * len(outs) + 0.6), squeeze=False, sharex=True)
    sl = slice(n_fit, len(rec))
    for ax, o in zip(axes[:, 0], outs):
        unit, scale = signal_unit(o, diag.model)
        ax.plot(t[sl], rec[o][sl] * scale, color="0.6", lw=1.6, label="measured")
        ax.plot(t[sl], nom[o][sl] * scale, color="C0", lw=0.9, label="nominal")
        if diag.causes:
            ax.plot(t[sl], fin[o][sl] * scale, color="C3", lw=0.9, ls="--", label="extended: " + "+".join(diag.causes))
        ax.set_ylabel(label(o, unit))
    axes[0, 0].legend(fontsize=7, ncol=3)
    axes[0, 0].set_title("Held-out part: measured vs nominal vs extended")
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    p = os.path.join(out_dir, "diagnose_response.png")
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    # residuals before and after
    fig, axes = plt.subplots(len(outs), 1, figsize=(9, 2.4 * len(outs) + 0.6), squeeze=False, sharex=True)
    for ax, o in zip(axes[:, 0], outs):
        unit, scale = signal_unit(o, diag.model)
        ax.plot(t, (rec[o] - nom[o]) * scale, color="C0", lw=0.6, label="nominal")
        if diag.causes:
            ax.plot(t, (rec[o] - fin[o]) * scale, color="C3", lw=0.6, label="extended")
        ax.axvline(t[n_fit], color="k", lw=0.8, ls=":")
        ax.set_ylabel(label(f"residual {o}", unit))
    axes[0, 0].legend(fontsize=7)
    axes[0, 0].set_title("Residuals before and after (dotted: start of the held-out part)")
    axes[-1, 0].set_xlabel("t [s]")
    fig.tight_layout()
    p = os.path.join(out_dir, "diagnose_residuals.png")
    fig.savefig(p, dpi=100)
    plt.close(fig)
    paths.append(p)
    # each effect's own signature: residual before vs the regime variable, and the effect's contribution
    from twin.reports.signatures import signature_data
    from twin.reports.views import signature_figure

    for sig in signature_data(diag):
        fig = signature_figure(sig)
        p = os.path.join(out_dir, f"diagnose_signature_{sig['cause']}.png")
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
    # the residual signature of the final model (what is left), always: regimes, spectrum, correlation
    an = diag.final.analysis
    if an is not None:
        fin_reg = {k: v[:n_fit] for k, v in regime_signals(diag.model, rec, fin).items()}
        keys = [k for k in ("velocity", "position", "dp", "spool_opening", "force") if k in fin_reg]
        fig, axes = plt.subplots(len(outs), len(keys) + 1, figsize=(3.2 * (len(keys) + 1), 2.6 * len(outs)),
                                 squeeze=False)
        for row, o in enumerate(outs):
            r = an.residuals[o]
            unit, sc = signal_unit(o, diag.model)
            for col, k in enumerate(keys):
                k_unit, k_sc = signal_unit(_AXIS_SIGNAL.get(k, k), diag.model)
                bx, by = _binned(fin_reg[k], r)
                axes[row, col].plot(bx * k_sc, by * sc, "o-", ms=2, color="C2")
                axes[row, col].set_xlabel(label(k, k_unit), fontsize=8)
                axes[row, col].set_ylabel(label(f"mean residual {o}", unit), fontsize=8)
            ax = axes[row, -1]
            ax.bar(np.arange(1, an.max_lag + 1), an.acf[o][1:], color="C1")
            ax.axhline(an.acf_band, color="k", ls="--", lw=0.7)
            ax.axhline(-an.acf_band, color="k", ls="--", lw=0.7)
            ax.set_xlabel("lag [samples]", fontsize=8)
            ax.set_ylabel(f"acf {o} (LB p={an.ljung_box[o]['p']:.2g})", fontsize=8)
        fig.suptitle(("UNEXPLAINED residual signature" if diag.unexplained else "Final residuals")
                     + " (fitting data)")
        fig.tight_layout()
        p = os.path.join(out_dir, "diagnose_residual_signature.png")
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
    return paths
