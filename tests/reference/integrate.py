"""One call of scipy's adaptive integrator over a smooth piece of a record, with failures raised.

Drivers: ``odeint`` (ODEPACK's LSODA through scipy's compiled driver loop; the default,
about three times less overhead per restart than ``solve_ivp``, which matters when a
digital controller restarts the integration at every tick) and ``solve_ivp`` with
``LSODA``, ``Radau`` or ``BDF``.  Both use the same tolerances and ``max_step``.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.integrate import odeint, solve_ivp

DRIVERS = ("odeint", "solve_ivp")
METHODS = ("LSODA", "Radau", "BDF")


class IntegrationError(RuntimeError):
    """The adaptive integrator did not reach the end of a piece."""


def piece(fun, ta: float, tb: float, y: np.ndarray, t_eval: np.ndarray, *, driver: str, method: str,
          rtol: float, atol: np.ndarray, max_step: float) -> np.ndarray:
    """States ``[len(t_eval), n]`` at ``t_eval`` (increasing, in (ta, tb], ending at tb), from ``y`` at ``ta``.

    ``fun(t, y)``; the solver never evaluates it beyond ``tb``.  Solver warnings and failures
    raise :class:`IntegrationError`.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            if driver == "odeint":
                if method != "LSODA":
                    raise ValueError(f"driver odeint is LSODA only, got method {method!r}")
                tt = np.concatenate(([ta], t_eval))
                out, info = odeint(fun, y, tt, rtol=rtol, atol=atol, hmax=max_step, tcrit=[tb], tfirst=True,
                                   full_output=True, mxstep=1_000_000)
                if info["message"] != "Integration successful.":
                    raise IntegrationError(f"odeint on [{ta:.6g}, {tb:.6g}] s: {info['message']}")
                return out[1:]
            sol = solve_ivp(fun, (ta, tb), y, method=method, rtol=rtol, atol=atol, max_step=max_step,
                            t_eval=t_eval)
        except Warning as w:  # scipy's excess-work or accuracy warnings
            raise IntegrationError(f"{driver}/{method} on [{ta:.6g}, {tb:.6g}] s: {w}") from None
    if sol.status != 0:
        raise IntegrationError(f"solve_ivp/{method} on [{ta:.6g}, {tb:.6g}] s: {sol.message}")
    return sol.y.T
