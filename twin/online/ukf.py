"""Augmented-state unscented Kalman filter of any trackable rig model, compiled end to end.

The model is an object (:class:`twin.models.base.Model`) whose :attr:`~twin.models.base.Model.FILTER` names its
compiled filter interface (one log interval of one state, ``advance``, and optionally of many sigma points side by
side, ``lanes``), its state scales and measurement map; :meth:`~twin.models.base.Model.filter_map` gives the
rig-specific numbers.  :func:`kernel_for` builds the model's kernel: copies of :mod:`twin.online.ukf_predict` and
:mod:`twin.online.ukf_loop` whose one marked import each names the model's functions (and that copy), compiled
with ``cache=True`` (a worker process loads it from the cache).  The kernel takes four records (:data:`Setup`, :data:`Carry`,
:data:`Block`, :data:`Out`).

State (``n = ns + p + q``):

* the ``ns`` model states, scaled so the covariance is well conditioned (the model's
  :attr:`~twin.models.base.FilterSpec.state_scale`);
* ``p`` tracked phenomenological parameters, each as a *logit between its
  physical bounds*: ``theta = lo * (hi/lo) ** sigmoid(z)``.  An estimate can
  never leave ``[lo, hi]`` (the bounds are a property of the physics, see
  :meth:`twin.models.base.Model.tracking_bounds`), and no sigma point can either;
* ``q`` sensor-noise states, one per measured output: an AR(1) process
  ``eta' = a eta + w``, ``var(eta) = sigma^2`` (scaled units).  ``a = 0`` is
  white noise; ``a > 0`` is coloured noise, which the filter then separates
  from the signal instead of reading it as a parameter change.  The
  measurement is ``z = (model output) + eta + v`` with a small white floor ``v``.

The algorithm is filterpy's ``UnscentedKalmanFilter`` with
``MerweScaledSigmaPoints`` (sigma points from the Cholesky factor of
``(lambda + n) P``, mean and covariance by the unscented transform plus
``Q``).  The noise states come last: a sigma point along one of them differs
from the mean only in noise coordinates (the Cholesky factor is triangular),
so the rig model is integrated for ``2 (ns + p) + 1`` sigma points only, and on
the open-loop path of a rig without effects they are integrated side by side,
vectorised across sigma points (the model's ``lanes``; the same numbers as one point at a time, bit for
bit).  The
measurement function ``H x`` (model output plus noise state) is linear: the
unscented update is then exactly the Kalman update, which is what we compute.

Prediction honours the loop's timing and the time between samples, read on
the nominal grid (a step is the nearest whole number of sample periods; the
rest is time-stamp jitter, :func:`twin.record.grid_steps`):
one log interval is advanced with the model's ``advance`` (digital
controller at the log's rate, N times faster, or continuous; logged inputs
held, linear or cubic between samples).  A logged ``u`` between samples k-1
and k is interpolated from ``u[k-2], u[k-1], u[k]``: the filter has sample k
when it predicts up to it, so ``foh`` is exact, and ``cubic`` uses a one-sided
end slope (no look-ahead beyond the sample being filtered).  Driven by the
demand, the rig's controller (e.g. a PID with derivative filter, feed-forward,
output limit) keeps its memory from sample to sample (``fs[F_CTRL:]``, moved
on along the central sigma point).  A longer
interval (dropped rows, lost frames) is predicted in as many log steps as it
spans with the input linear across the gap; beyond ``gap_max`` seconds the
model states are re-initialised from the measurement with the prior
covariance (status ``reinitialised``), the parameters keep their estimates
with an inflated covariance.

Per sample the kernel reports innovation, its variance, NIS, log-likelihood,
a filter status (:data:`STATUS`), a guard code (:data:`GUARD`: why the drift
test must hold its evidence on this sample, 0 = it need not) and a sensor
status per output (:data:`SENSOR`).

The consistency guard watches the normalised innovations: an exponential
average of the NIS per measurement (each sample clipped at ``nis_clip`` so a
short transient of a real change does not count as inconsistency) and the
lag-one autocorrelation of each output's normalised innovation (whiteness).
While either is out of its band the filter is ``inconsistent`` with the data
(model mismatch, unlearnt noise): the drift test holds.  A fast average of
the NIS beyond ``div_nis``, a parameter pinned at a bound, or a non-finite
state is *divergence*: the filter goes back to its last consistent checkpoint
(parameters and their covariance, inflated), re-reads the model states from
the measurement, and says ``recovered``.

Noise learning (covariance matching over a window): per output, the average
of the squared normalised innovation ``c`` drives ``log sigma^2`` towards
``c = 1`` and the lag-one autocorrelation ``rho`` drives the AR coefficient
``a`` towards white innovations, both with time constant ``tau_noise``.

Sensor faults are named from the signal and the innovations, per output:
``stuck`` (the same value repeated while the model says it moves),
``clipped`` (held at a value the model says it passes), ``offset`` (this
output alone far from the model for a while), ``wrong_unit`` (off by a power
of ten, or outside the physical range), ``noisy`` (learnt noise beyond
``noisy_factor`` times the rig's nominal).  A faulty output (other than
noisy) is not used in the update until it is consistent again.
"""

from __future__ import annotations

import collections
import hashlib
import importlib
import importlib.util
import os
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

from twin.online.ukf_linalg import _chol_lower, _repair, dlog_dz, sigmoid, theta_of  # noqa: F401
from twin.online.ukf_status import *  # noqa: F401,F403  (the filter's vocabulary and array layouts)
from twin.online.ukf_status import F_CTRL
from twin.online.ukf_update import _update, _update_into, held_variance  # noqa: F401

#: what the kernel reads of the tracker and its model, constant from block to block
Setup = collections.namedtuple("Setup", (
    "mia",          # [q] int: the state each measured output reads (the model's measurement map)
    "dt0",          # the log's sample period, s
    "pvec",         # the rig's complete kernel vector
    "idx",          # [p] int: the tracked parameters' places in it
    "lo_log", "width",  # [p]: each parameter's logit bounds, log(lo) and log(hi / lo)
    "scale",        # [ns]: SI per filter unit of each model state
    "nsub",         # RK4 substeps per sample
    "q_state",      # [ns] process noise of the scaled states per sample
    "q_param",      # [p] parameter random walks, log units^2 per s
    "prior_mod",    # [ns] prior std of the scaled states (re-initialisation)
    "Wm", "Wc", "lam",  # the sigma points' weights and spread - n
    "floor",        # [n] eigenvalue floor of a repaired covariance
    "gate", "max_gated",  # NIS gate of the update and the gated samples in a row that switch it off
    "chan",         # [p] int: each parameter's excitation channel
    "thresh",       # [3] excitation thresholds, SI
    "tau_excite",   # s, the excitation average's time constant
    "cfg",          # [N_CFG] guard and detector settings (twin.online.ukf_status.CFG_NAMES)
    "rest",         # [ns] SI: the model states a re-initialisation starts from
    "input_state", "input_gain",  # the state that follows the drive statically (-1: none), its gain
    "demand_gain",  # the command per unit of demand error (excitation when only the demand is logged)
    "fb_state", "fb_col",  # the state and column of Z a controller reads (-1: none / not measured)
    "out_lo", "out_hi",  # [q] SI: each output's physical range
    "out_centre",   # [q] scaled: each output's centre
    "excitation",   # [3, ns] weights of the excitation channels on the states (SI)
    "lanes", "lane_work",  # sizes of the model's side-by-side integration (0: none)
    "exo_idx",      # [e] int: the parameters set sample by sample by the block's exogenous signals (EXO)
))
#: what carries over from block to block (the filter's state), updated in place
Carry = collections.namedtuple("Carry", ("x", "P", "fs", "ch", "x_ck", "P_ck"))
#: one block of samples: logged drive, demand, scaled measurements [T, q], seconds since the previous sample, and
#: the exogenous signals [T, e] (SI, NaN where not fresh) that set the parameters ``Setup.exo_idx``
Block = collections.namedtuple("Block", ("U", "XREF", "Z", "DT", "EXO"))
#: per-sample outputs, written in place
Out = collections.namedtuple("Out", ("X", "Pd", "nis", "ll", "status", "innov", "S", "frozen", "guard", "sensors",
                                     "noise", "used"))

#: the one line of each kernel source that :func:`kernel_for` swaps: its marker, and the module it names
_MODEL_LINE = ("# kernel: the model's interface", "twin.online.ukf_model")
_PREDICT_LINE = ("# kernel: the model's prediction", "twin.online.ukf_predict")
_KERNEL_TAIL = '''

@nb.njit(cache=True, nogil=True)
def run(setup, carry, block, closed, ticks, mode, out):
    return filter_loop(setup, carry, block, closed, ticks, mode, out)
'''


def _swap_import(text: str, line: tuple[str, str], module: str, source: str) -> str:
    """``text`` with its one import line marked ``line[0]`` naming ``module`` instead of ``line[1]``."""
    marker, slot = line
    rows = text.splitlines(keepends=True)
    hits = [i for i, row in enumerate(rows) if row.rstrip().endswith(marker) and row.startswith(f"from {slot} import ")]
    if len(hits) != 1:
        raise RuntimeError(f"{source}: expected one line 'from {slot} import ...  {marker}', found {len(hits)}")
    rows[hits[0]] = rows[hits[0]].replace(f"from {slot} import ", f"from {module} import ", 1)
    return "".join(rows)


def _kernel_sources(functions: str, predict_name: str) -> tuple[str, str]:
    """The texts of a model's kernel modules: :mod:`twin.online.ukf_predict` with its marked import naming the
    model's compiled filter interface ``functions``, and :mod:`twin.online.ukf_loop` with its marked import naming
    that copy (``predict_name``), plus the kernel's entry ``run``."""
    from twin.online import ukf_loop, ukf_predict

    predict = _swap_import(Path(ukf_predict.__file__).read_text(), _MODEL_LINE, functions,
                           "twin/online/ukf_predict.py")
    loop = _swap_import(Path(ukf_loop.__file__).read_text(), _PREDICT_LINE, predict_name,
                        "twin/online/ukf_loop.py")
    return predict, loop + _KERNEL_TAIL


_KERNELS: dict[str, tuple[object, object]] = {}
#: one thread at a time makes a model's kernel modules: a second thread (a service's next rig) that made them too
#: replaced the first one's half-executed module in ``sys.modules``, and the first's kernel then failed to import
#: ``_predict`` from it
_KERNELS_LOCK = threading.Lock()


def functions_of(model):
    """The module of ``model``'s compiled filter interface (:attr:`twin.models.base.FilterSpec.functions`)."""
    if model.FILTER is None:
        raise ValueError(f"the {model.name} model declares no filter interface")
    return importlib.import_module(model.FILTER.functions)


def _kernel_dir() -> Path:
    """Where the generated kernel modules (and numba's cache of them) live: in ``$NUMBA_CACHE_DIR/fpdd-twin-kernels``
    when numba is told where to cache (the service's unit does: its file system is read-only but there), else
    beside this package where it is writable (a checkout, an editable install), else in the user's cache directory
    (``$XDG_CACHE_HOME``, by default ``~/.cache``, then ``fpdd-twin/kernels``), else in the temporary directory.
    Each outlives a restart but the last (a service's private ``/tmp`` is new at every start: its kernels were
    compiled again each time)."""
    user = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fpdd-twin" / "kernels"
    told = os.environ.get("NUMBA_CACHE_DIR")
    places = [Path(told) / "fpdd-twin-kernels"] if told else []
    for where in (*places, Path(__file__).parent / "__pycache__" / "kernels", user):
        try:
            where.mkdir(parents=True, exist_ok=True)
            if os.access(where, os.W_OK):
                return where
        except OSError:
            pass
    there = Path(tempfile.gettempdir()) / f"twin-kernels-{os.getuid() if hasattr(os, 'getuid') else 0}"
    there.mkdir(parents=True, exist_ok=True)
    return there


def _sources_of(fmod) -> list[Path]:
    """The source files whose compiled code ``fmod``'s functions inline: its own and those of the modules it
    imported, or imported functions from (the rig model, intersample rules, ...), and theirs in turn (a model in
    several modules: the right-hand side reads the parameters' module's constants), within ``fmod``'s package."""
    top = fmod.__name__.split(".")[0]
    files: set[str] = set()
    todo = [fmod]
    seen = {fmod.__name__}
    while todo:
        mod = todo.pop()
        f = getattr(mod, "__file__", None)
        if f:
            files.add(str(f))
        for v in vars(mod).values():
            name = getattr(v, "__name__", None) if isinstance(v, type(sys)) else \
                getattr(getattr(v, "py_func", v), "__module__", None)
            if not isinstance(name, str) or name in seen or name.split(".")[0] != top:
                continue
            dep = sys.modules.get(name)
            if dep is not None:
                seen.add(name)
                todo.append(dep)
    return [Path(f) for f in sorted(files)]


def _load(name: str, path: Path, source: str):
    """Write ``source`` to ``path`` unless there, and import it as the module ``name``."""
    if not path.exists():
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(source)
        os.replace(tmp, path)
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def kernel_modules(model):
    """``model``'s compiled filter kernel as its two modules: the copy of :mod:`twin.online.ukf_predict`
    (``fx_into``, ``_predict``) and the copy of :mod:`twin.online.ukf_loop` (``filter_loop`` and the entry
    ``run(setup, carry, block, closed, ticks, mode, out) -> int``).

    Two modules generated once per model and per source of the filter and the model (their names carry the hash
    of them all), so numba's on-disk cache is keyed to exactly the code it was compiled from: a process that finds
    them loads the machine code from the cache instead of compiling it.
    """
    mod_name = model.FILTER.functions if model.FILTER is not None else ""
    if mod_name in _KERNELS:
        return _KERNELS[mod_name]
    with _KERNELS_LOCK:
        if mod_name not in _KERNELS:
            _KERNELS[mod_name] = _make_kernel_modules(model, mod_name)
    return _KERNELS[mod_name]


def _make_kernel_modules(model, mod_name: str):
    """:func:`kernel_modules`'s work, under its lock."""
    fmod = functions_of(model)
    digest = hashlib.sha256(mod_name.encode())
    online = Path(__file__).parent
    for f in sorted(online.glob("ukf_*.py")) + _sources_of(fmod):
        digest.update(f.read_bytes())
    tag = "".join(c if c.isalnum() else "_" for c in mod_name)
    names = [f"ukf_{part}_{tag}_{digest.hexdigest()[:16]}" for part in ("predict", "kernel")]
    where = _kernel_dir()
    predict, loop = _kernel_sources(mod_name, names[0])
    for part, name in zip(("predict", "kernel"), names):
        if not (where / f"{name}.py").exists():
            for stale in where.glob(f"ukf_{part}_{tag}_*.py"):  # compiled from sources that changed since
                stale.unlink(missing_ok=True)
    return (_load(names[0], where / f"{names[0]}.py", predict), _load(names[1], where / f"{names[1]}.py", loop))


def kernel_for(model):
    """``model``'s compiled filter kernel ``run(setup, carry, block, closed, ticks, mode, out) -> int``
    (:func:`kernel_modules`)."""
    return kernel_modules(model)[1].run


def fx_one(model, s, u_prev, u_now, pvec, idx, lo_log, width, scale, dt, nsub, noise_a, closed=False, ticks=1,
           mode=0, u_before=None, xm=0.0):
    """Propagate one augmented state over one log interval through ``model``'s ``advance`` (for tests and filterpy):
    returns the new state.  ``u_before``, ``u_prev``, ``u_now``: the drive at samples k-2, k-1, k; ``noise_a``:
    AR coefficients of the noise states."""
    fmod = functions_of(model)
    fx_into = kernel_modules(model)[0].fx_into
    ns = scale.shape[0]
    n = s.shape[0]
    nmod = ns + idx.shape[0]
    out = np.empty(n)
    wnd = np.array([u_prev if u_before is None else u_before, u_prev, u_now, u_now], dtype=np.float64)
    fx_into(np.ascontiguousarray(s, dtype=np.float64).reshape(1, n), 0, wnd, closed, ticks, mode, pvec.copy(), idx,
            lo_log, width, scale, dt, nsub, xm, np.zeros(fmod.N_CTRL), fmod.N_CTRL, np.empty(ns), np.empty(ns),
            out.reshape(1, n), nmod)
    for j in range(nmod, n):
        out[j] = noise_a[j - nmod] * s[j]
    return out


def n_fs(model) -> int:
    """Entries of the carried float state ``fs`` of a filter of ``model`` (its controller memory last)."""
    return F_CTRL + functions_of(model).N_CTRL
