"""Sigma-point weights for the compiled UKF, and the small protocol a sigma-point object meets.

The filter needs of a sigma-point object only what filterpy's ``UnscentedKalmanFilter`` reads: its
dimension ``n`` and the weights ``Wm``, ``Wc`` of the ``2n + 1`` points ``x``, ``x + U_k``,
``x - U_k`` with ``U = chol((n + lambda) P)``. The spread ``n + lambda`` follows from the centre
weight (``Wm[0] = lambda / (n + lambda)`` for Merwe's scaled points and, with ``lambda = kappa``,
for Julier's), so any object with those three attributes serves, filterpy's
``MerweScaledSigmaPoints`` and ``JulierSigmaPoints`` included, and the filter never asks which
class it was given.

:class:`MerweWeights` computes the weights of Merwe's scaled sigma points with filterpy's formulas
(van der Merwe 2004, eq. 3.11-3.12), so that the online path does not import filterpy (1-2 s of
imports, mostly scipy.stats, paid again by every spawned worker); ``tests/test_ukf.py`` checks it
against filterpy's own object.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class SigmaPoints(Protocol):
    """What the filter reads of a sigma-point object (filterpy's two classes meet it)."""

    n: int
    Wm: np.ndarray
    Wc: np.ndarray


class MerweWeights:
    """The weights of Merwe's scaled sigma points for ``n`` states (``alpha``, ``beta``, ``kappa``)."""

    def __init__(self, n: int, alpha: float, beta: float, kappa: float) -> None:
        self.n = int(n)
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)
        lam = self.alpha**2 * (self.n + self.kappa) - self.n
        c = 0.5 / (self.n + lam)
        self.Wc = np.full(2 * self.n + 1, c)
        self.Wm = np.full(2 * self.n + 1, c)
        self.Wc[0] = lam / (self.n + lam) + (1.0 - self.alpha**2 + self.beta)
        self.Wm[0] = lam / (self.n + lam)

    def num_sigmas(self) -> int:
        return 2 * self.n + 1

    def __repr__(self) -> str:
        return f"MerweWeights(n={self.n}, alpha={self.alpha:g}, beta={self.beta:g}, kappa={self.kappa:g})"


def spread(points: SigmaPoints) -> float:
    """``n + lambda`` of a sigma-point object, from its centre weight; refuses weights that give no spread."""
    n = int(points.n)
    w0 = float(points.Wm[0])
    if not w0 < 1.0:
        raise ValueError(f"sigma points with centre weight {w0:g}: the spread n + lambda = n / (1 - Wm[0]) "
                         "must be positive")
    return n / (1.0 - w0)
