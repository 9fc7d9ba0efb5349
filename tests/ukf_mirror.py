"""filterpy's UnscentedKalmanFilter beside the compiled tracker, following the tracker's per-sample decisions.

filterpy does the unscented predict (its sigma points, weights, ``fx`` through
the model's own ``advance`` via :func:`twin.online.ukf.fx_one`)
and the update; from the tracker's output this mirror takes only *which*
decisions were made on each sample (outputs used, gated, parameters frozen),
never the numbers.  A frozen parameter gets no gain (Schmidt consider update,
Joseph form) on filterpy's own sigma-point statistics.  The process noise is
the tracker's ``Q`` evaluated at filterpy's state.  Noise learning must be off
(``adapt_noise=False``): filterpy has no noise adaptation.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from twin.online import ukf


def mirror(tr, samples, out) -> np.ndarray:
    """filterpy's states ``[T, n]`` for ``samples`` given the tracker ``tr`` (fresh, before ``process``)
    and its output ``out`` (:class:`twin.online.tracker.TrackBlock` of the whole record)."""
    assert tr.guard_settings["adapt"] == 0.0, "the mirror needs adapt_noise=False"
    n, nm = tr.n, tr.nmod
    q = len(tr.outputs)
    a = tr.ch[:, ukf.H_A].copy()
    ticks = tr.timing.ticks(tr.dt)
    mode = tr.timing.intersample_code(tr.dt)
    u = np.asarray(samples.signals["u"], float)
    Z = np.stack([np.asarray(samples.signals[o], float) / tr.scale[tr.meas_index[o]] for o in tr.outputs], axis=1)

    def fx(x, dt, u_before, u_prev, u_now):
        return ukf.fx_one(tr.model, x, u_prev, u_now, tr.pvec, tr.idx, tr.lo_log, tr.width, tr.scale, dt, tr.substeps, a,
                          False, ticks, mode, u_before)

    # filterpy's own sigma points: the tracker's object when it was given one (Julier's), else Merwe's from the
    # tracker's alpha, beta, kappa (the tracker's default weights are its own, checked against these in test_tracker)
    points = tr.points if hasattr(tr.points, "sigma_points") else MerweScaledSigmaPoints(
        n, alpha=tr.alpha, beta=tr.beta, kappa=tr.kappa)
    central = tr.guard_settings["central_mean"] > 0.0  # the tracker's mean is then the central point's prediction
    f = UnscentedKalmanFilter(dim_x=n, dim_z=q, dt=tr.dt, hx=None, fx=fx, points=points,
                              x_mean_fn=(lambda sigmas, Wm: np.array(sigmas[0], dtype=float)) if central else None)
    f.x = tr.x.copy()
    f.P = tr.P.copy()
    f.sigmas_f = points.sigma_points(f.x, f.P)
    R = tr.R_floor
    T = len(samples)
    X = np.empty((T, n))
    u_hist = [u[0], u[0]]
    for k in range(T):
        st = str(out.status[k])
        assert st in ("ok", "gated", "frozen", "stale_input"), (k, st)
        if k > 0:
            f.Q = tr.process_noise(tr.dt, f.x, f.P)
            f.predict(u_before=u_hist[-2], u_prev=u_hist[-1], u_now=u[k])
        u_hist = [u_hist[-1], u[k]]
        use = np.flatnonzero(out.used[k])
        if st != "gated" and use.size:
            idx_m = tr.meas_idx[use]
            idx_e = nm + use

            def hx(x, idx_m=idx_m, idx_e=idx_e):
                return x[idx_m] + x[idx_e]

            frozen = np.flatnonzero(out.kernel_frozen[k]) + tr.ns  # the filter's own freeze, not the drift test's
            if frozen.size == 0:
                f.update(Z[k, use], R=np.diag(R[use]), hx=hx)
            else:  # consider update on filterpy's sigma-point statistics
                sig_h = np.array([hx(s) for s in f.sigmas_f])
                zp = f.Wm @ sig_h
                dz = sig_h - zp
                S = (f.Wc[:, None] * dz).T @ dz + np.diag(R[use])
                Pxz = (f.Wc[:, None] * (f.sigmas_f - f.x)).T @ dz
                K = Pxz @ np.linalg.inv(S)
                K[frozen] = 0.0
                H = np.zeros((use.size, n))
                H[np.arange(use.size), idx_m] = 1.0
                H[np.arange(use.size), idx_e] = 1.0
                f.x = f.x + K @ (Z[k, use] - zp)
                IKH = np.eye(n) - K @ H
                f.P = IKH @ f.P @ IKH.T + K @ np.diag(R[use]) @ K.T
                f.P = 0.5 * (f.P + f.P.T)
        X[k] = f.x
    return X


def ours(tr, out) -> np.ndarray:
    """The tracker's states ``[T, n - q]`` (model states scaled, parameter logits) from its output."""
    z = np.log(np.log(out.estimates) - tr.lo_log) - np.log(tr.lo_log + tr.width - np.log(out.estimates))
    return np.concatenate([out.states / tr.scale, z], axis=1)
