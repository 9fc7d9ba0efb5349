"""The model slot of the filter's kernel: the functions :mod:`twin.online.ukf_predict` imports in the one line
marked ``# kernel: the model's interface``.

A kernel is compiled for one model (:func:`twin.online.ukf.kernel_for`): a copy of ``ukf_predict`` whose marked
import names that model's compiled filter interface (:attr:`twin.models.base.FilterSpec.functions`) instead of this
module, and a copy of :mod:`twin.online.ukf_loop` whose marked import names that copy.  Nothing else in the two
sources is edited.  The functions below only declare the interface's signatures; they are never compiled into a
kernel, and calling one says so.
"""

from __future__ import annotations

import numba as nb

_SLOT = "twin.online.ukf_model: the filter's model slot; run a kernel made by twin.online.ukf.kernel_for"


@nb.njit
def advance(s, k, drive, closed, ticks, mode, p, dt, nsub, xm_k, ctrl, out):  # pragma: no cover - a signature
    """One log interval of one state ``s`` (SI) from sample ``k``; writes ``out``, returns the command at t_k."""
    raise RuntimeError(_SLOT)


@nb.njit
def lanes_applicable(p):  # pragma: no cover - a signature
    """True when the side-by-side ``lanes`` are exact for the kernel vector ``p``."""
    raise RuntimeError(_SLOT)


@nb.njit
def lanes(S, TH, m, p, idx, wnd, mode, dt, nsub, W):  # pragma: no cover - a signature
    """One log interval, open loop, of the states ``S[ln]`` with the parameters ``idx`` at ``TH[ln]``, in place."""
    raise RuntimeError(_SLOT)
