"""What every model offers: named signals, parameter metadata, effects, batched simulation.

A model is a fixed, pure right-hand side compiled with numba and evaluated over
a leading batch axis (sigma points, finite-difference columns, candidate
models, rigs).  Its parameter vector is *flat and complete*: the base
parameters first, then every effect of the catalogue in a fixed order.  An
effect that is switched off sits at its neutral value, so switching effects on
by name never touches the compiled core.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Iterable, Mapping

import numpy as np

from fpdd.errors import DataError, ParameterError
from twin.params import Effect, ParameterSet, ParamSpec, Tracking, check_names


@dataclasses.dataclass
class SimResult:
    """A batched simulation: outputs ``[K, T]`` per name, states ``[K, T, n_states]``."""

    t_s: np.ndarray
    outputs: dict[str, np.ndarray]
    states: np.ndarray
    inputs: dict[str, np.ndarray]

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self.outputs:
            return self.outputs[name]
        if name in self.inputs:
            return self.inputs[name]
        raise KeyError(name)


#: how a logged input behaves between its samples (MATLAB iddata's InterSample)
INTERSAMPLE = ("zoh", "foh", "cubic")
INTERSAMPLE_CODE = {"zoh": 0, "foh": 1, "cubic": 2}


@dataclasses.dataclass(frozen=True)
class Timing:
    """The loop's timing, a property of the rig.

    ``controller``: ``"digital"`` (runs at ``rate_hz``, default the log's rate,
    and holds its output between ticks) or ``"continuous"`` (analog: the output
    follows the measurement at every instant).  ``intersample``: how a logged
    input (``x_ref``, ``u``, a force) behaves between samples: ``zoh``, ``foh`` or
    ``cubic`` (a C1 piecewise cubic through the samples).  ``None`` means: ``zoh``
    when the controller is digital at the log's rate, else ``cubic`` (a demand or
    a controller output that is not held by a digital controller at the log's
    rate is smooth between samples).
    """

    controller: str = "digital"
    rate_hz: float | None = None
    intersample: str | None = None

    def __post_init__(self) -> None:
        if self.controller not in ("digital", "continuous"):
            raise ParameterError(f"controller {self.controller!r}: expected 'digital', 'digital:RATE' "
                                 "(a rate in Hz, e.g. digital:5000) or 'continuous'")
        if self.rate_hz is not None and not (np.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ParameterError(f"controller rate {self.rate_hz} Hz must be a positive number of Hz")
        if self.rate_hz is not None and self.controller != "digital":
            raise ParameterError("a controller rate goes with a digital controller only")
        if self.intersample is not None and self.intersample not in INTERSAMPLE:
            raise ParameterError(f"intersample {self.intersample!r}: expected one of {', '.join(INTERSAMPLE)}")

    @classmethod
    def parse(cls, controller: str | None = None, intersample: str | None = None) -> Timing:
        """From the command-line / config spelling: ``digital``, ``digital:5000``, ``continuous``."""
        controller = (controller or "digital").strip().lower()
        rate = None
        if controller.startswith("digital:"):
            text = controller.split(":", 1)[1].strip().lower().removesuffix("hz").strip()
            try:
                rate = float(text)
            except ValueError:
                raise ParameterError(f"controller {controller!r}: the rate after 'digital:' must be a number "
                                     "of Hz, e.g. digital:5000") from None
            controller = "digital"
        elif controller in ("analog", "analogue"):
            controller = "continuous"
        isamp = None if intersample in (None, "", "auto") else intersample.strip().lower()
        return cls(controller, rate, isamp)

    @property
    def label(self) -> str:
        c = "continuous" if self.controller == "continuous" else (
            f"digital:{self.rate_hz:g}" if self.rate_hz else "digital")
        return c if self.intersample is None else f"{c}, intersample {self.intersample}"

    def ticks(self, dt: float) -> int:
        """Controller ticks per log sample: 0 for a continuous controller."""
        if self.controller == "continuous":
            return 0
        if self.rate_hz is None:
            return 1
        n = self.rate_hz * dt
        if n < 0.999 or abs(n - round(n)) > 1e-3 * n:
            raise ParameterError(f"controller rate {self.rate_hz:g} Hz is not a whole multiple of the log's "
                                 f"rate {1.0 / dt:g} Hz")
        return int(round(n))

    def is_default(self, dt: float) -> bool:
        return self.ticks(dt) == 1 and self.intersample in (None, "zoh")

    def intersample_code(self, dt: float) -> int:
        if self.intersample is not None:
            return INTERSAMPLE_CODE[self.intersample]
        return 0 if self.ticks(dt) == 1 else INTERSAMPLE_CODE["cubic"]

    def to_dict(self) -> dict:
        return {"controller": self.controller, "rate_hz": self.rate_hz, "intersample": self.intersample}


DEFAULT_TIMING = Timing()


@dataclasses.dataclass(frozen=True)
class FilterSpec:
    """What the online filter needs of a model besides its parameters (a trackable model declares one).

    ``functions``: the module of the model's compiled filter interface (``advance``, ``N_CTRL``, ``LANES``,
    ``LANE_WORK``, ``lanes_applicable``, ``lanes``; see ``twin/models/msp25_lanes.py``).  ``state_scale``: SI per
    filter unit of each state (a well-conditioned covariance).  ``measures``: the measurement map, each measured
    output and the state it reads (``z = state + sensor noise``).  ``q_state``: process noise of the scaled states
    (variance per sample at the log's rate).  ``prior_state``: prior standard deviation of the scaled states (and
    after a re-initialisation).  ``noise``: nominal sensor noise, standard deviation in SI per output.
    ``excite``: the excitation thresholds of :data:`twin.params.EXCITATION`'s channels, SI.
    ``feedback``: the output a closed loop's controller reads (``None``: no controller).
    ``exogenous``: logged signals that set a parameter sample by sample (signal -> parameter, e.g. the oil
    temperature ``T_oil``); the last fresh value holds between a slow signal's samples.
    ``second_order``: a second-order lag among the states (its rate state's index, its damping-ratio and its
    natural-frequency parameter): the drift test holds the two while the recent motion does not tell them apart
    (:mod:`twin.online.split`); ``None``: none.
    """

    functions: str
    state_scale: tuple[float, ...]
    measures: Mapping[str, int]
    q_state: tuple[float, ...]
    prior_state: tuple[float, ...]
    noise: Mapping[str, float]
    excite: tuple[float, float, float]
    feedback: str | None = None
    exogenous: Mapping[str, str] = dataclasses.field(default_factory=dict)
    second_order: tuple[int, str, str] | None = None


@dataclasses.dataclass(frozen=True)
class FilterMap:
    """The rig-specific numbers of a model's filter for one parameter set (:meth:`Model.filter_map`), SI.

    ``rest``: the model states a re-initialised filter starts from before the measured ones are read in.
    ``input_state``, ``input_gain``: the state that follows the drive statically (``gain x u``; -1: none).
    ``demand_gain``: the drive per unit of demand error a closed loop's controller applies (the excitation of
    the command when only the demand is logged).  ``ranges``: each output's physical range (outside it, a reading
    is a wrong unit or a broken sensor).  ``centres``: each output's centre (a clipped reading sits at its largest
    excursion from it).  ``excitation [3, n_states]``: each excitation channel's weights on the states, the
    channel reads ``|weights . states|`` (a zero row: the channel is the drive's rate).
    """

    rest: np.ndarray
    input_state: int
    input_gain: float
    demand_gain: float
    ranges: Mapping[str, tuple[float, float]]
    centres: Mapping[str, float]
    excitation: np.ndarray


#: what a logged signal is to a model: the drive it is simulated from (a controller output, a force), the demand
#: its controller follows, a measured output it predicts, an exogenous input that sets a parameter sample by sample
#: (an oil temperature), or logged beside them and read by none of these
ROLES = ("drive", "demand", "output", "exogenous", "logged")


@dataclasses.dataclass(frozen=True)
class Signal:
    """One signal of a model's records: its role (:data:`ROLES`), SI unit, physical range in that unit, meaning,
    nominal sensor noise (SI standard deviation; ``None``: no sensor of its own) and the other SI units a column
    mapped onto it may be in (``"*"``: any, a signal whose units follow the record)."""

    name: str
    role: str
    unit: str
    lo: float
    hi: float
    meaning: str
    noise: float | None = None
    accepts: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.role not in ROLES:
            raise ValueError(f"signal {self.name}: role {self.role!r} not in {ROLES}")

    @property
    def spec(self):
        """The :class:`fpdd.units.SignalSpec` the readers and the quality gate take."""
        from fpdd.units import SignalSpec

        return SignalSpec(self.name, self.unit, self.lo, self.hi, self.meaning, self.accepts, self.noise)


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A model's default identification experiment: an excitation ``kind`` (multisine, chirp, steps) of the
    signal ``drive`` with ``amplitude`` (peak, SI) over ``f_lo`` .. ``f_hi`` Hz."""

    kind: str
    drive: str
    amplitude: float
    f_lo: float
    f_hi: float


class Model(abc.ABC):
    """Base class of the first-principle models (one instance per model kind)."""

    name: str
    STATES: tuple[str, ...]
    INPUTS: tuple[str, ...]       # signals that can drive the model
    OUTPUTS: tuple[str, ...]      # signals the model predicts (measured ones)
    BASE: tuple[ParamSpec, ...]   # base parameters, kernel order
    NOMINAL: Mapping[str, float]  # reference values of the base parameters
    EFFECTS: Mapping[str, Effect]  # catalogue, kernel order after BASE
    substeps: int = 3             # RK4 substeps per sample
    INIT: tuple[str, ...] = ()    # initial-state quantities
    INIT_IF_MOVING: tuple[str, ...] = ()  # estimated by default when a record does not start at rest
    PHENOMENOLOGICAL: tuple[str, ...]  # the model's phenomenological parameters
    # --- capabilities (what the rest of the product may ask of this model) -------------
    CLOSED_LOOP: bool = False     # has a controller: driven by a demand (x_ref) as well as open loop
    TRACKABLE: bool = False       # the online twin's compiled filter runs this model (twin track / serve)
    NOISE_FROM_DATA: bool = False  # outputs in the record's own units: residual weights follow the record
    FILTER: FilterSpec | None = None  # what the online filter needs (a trackable model has one)
    SIGNALS: tuple[Signal, ...] = ()  # every signal of its records, with its role, unit and range
    EXPERIMENT: Experiment | None = None  # the default identification experiment (twin simulate)

    # --- signals --------------------------------------------------------------------------
    def signals(self, role: str | None = None) -> dict[str, Signal]:
        """The model's signals (of ``role`` only, when given), by name."""
        return {s.name: s for s in self.SIGNALS if role is None or s.role == role}

    @property
    def drive_name(self) -> str:
        """The signal the model is simulated from open loop (a controller output, a force)."""
        return next(iter(self.signals("drive")))

    @property
    def demand_name(self) -> str | None:
        """The demand its controller follows (``None``: no controller)."""
        return next(iter(self.signals("demand")), None)

    def signal_specs(self) -> dict:
        """``{name: fpdd.units.SignalSpec}`` of the model's signals (what the readers and the quality gate take)."""
        return {s.name: s.spec for s in self.SIGNALS}

    def signal_unit(self, name: str) -> str:
        """The SI unit of the model's signal ``name`` ("" for a signal it does not declare)."""
        s = self.signals().get(name)
        return s.unit if s is not None else ""

    def nominal_noise(self) -> dict[str, float]:
        """Nominal sensor noise of each measured output (SI standard deviation): what a simulation adds."""
        return {n: float(s.noise) for n, s in self.signals("output").items() if s.noise is not None}

    def fast_controller(self, ps: ParameterSet) -> bool:
        """True when the model's digital controller can drive it from the demand between the log's samples (a
        law the model reproduces exactly, e.g. a P controller); the tracker then runs the loop itself when the
        controller ticks faster than the log.  False by default."""
        return False

    # --- the online filter ----------------------------------------------------------------
    def filter_map(self, ps: ParameterSet) -> FilterMap:
        """The filter's rig-specific numbers for ``ps`` (a trackable model overrides this)."""
        raise ParameterError(f"the online twin does not run the {self.name} model")

    # --- parameters -----------------------------------------------------------------
    def tracking(self, name: str) -> Tracking:
        """What the online twin needs of parameter ``name`` (its spec's :class:`~twin.params.Tracking`)."""
        for s in self.kernel_specs:
            if s.name == name:
                if s.tracking is None:
                    raise ParameterError(f"{self.name}: {name} is not a parameter the online twin tracks; "
                                         f"trackable: {', '.join(self.trackable)}")
                return s.tracking
        raise ParameterError(f"{self.name} has no parameter {name!r}; known: {', '.join(self.kernel_names)}")

    @property
    def trackable(self) -> tuple[str, ...]:
        """The parameters the online twin can track (those whose spec has a tracking entry)."""
        return tuple(s.name for s in self.kernel_specs if s.tracking is not None)

    def tracking_bounds(self, ps: ParameterSet, name: str) -> tuple[float, float]:
        """(lo, hi) in SI between which the online twin moves ``name`` on the rig ``ps``: the tracking
        factors around the rig's value, within the spec's bounds (a model adds its physical limits)."""
        v = ps[name]
        f_lo, f_hi = self.tracking(name).bounds
        spec = ps.spec(name)
        return max(v * f_lo, spec.lo if spec.lo > 0 else v * f_lo), min(v * f_hi, spec.hi)

    def untracked(self, ps: ParameterSet) -> str | None:
        """Why the online filter cannot run the rig ``ps`` (an effect whose states it does not carry), or None."""
        return None

    @property
    def kernel_specs(self) -> tuple[ParamSpec, ...]:
        specs = list(self.BASE)
        for e in self.EFFECTS.values():
            specs.extend(e.params)
        return tuple(specs)

    @property
    def kernel_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.kernel_specs)

    def kernel_index(self, name: str) -> int:
        names = self.kernel_names
        if name not in names:
            raise ParameterError(f"{self.name} has no parameter {name!r}; known: {', '.join(names)}")
        return names.index(name)

    def params(self, effects: Iterable[str] = (), **values: float | str) -> ParameterSet:
        """The nominal parameter set with ``effects`` switched on and ``values`` overriding."""
        effects = tuple(dict.fromkeys(effects))
        check_names(self.EFFECTS, effects, f"effect of model {self.name}")
        specs = list(self.BASE)
        vals = [self.NOMINAL[s.name] for s in self.BASE]
        for name in self.EFFECTS:  # keep catalogue order
            if name in effects:
                e = self.EFFECTS[name]
                specs.extend(e.params)
                vals.extend(e.typical)
        ps = ParameterSet(self.name, tuple(specs), tuple(vals), tuple(n for n in self.EFFECTS if n in effects))
        return ps.update(values) if values else ps

    def vector(self, ps: ParameterSet) -> np.ndarray:
        """The complete kernel vector of ``ps`` (inactive effects at their neutral values)."""
        if ps.model != self.name:
            raise ParameterError(f"parameter set of model {ps.model!r} given to model {self.name!r}")
        out = []
        given = ps.as_dict()
        for s in self.BASE:
            out.append(given[s.name])
        for name, e in self.EFFECTS.items():
            if name in ps.effects:
                out.extend(given[p.name] for p in e.params)
            else:
                out.extend(e.neutral)
        return np.ascontiguousarray(out, dtype=np.float64)

    def effect_of(self, param: str) -> str | None:
        for name, e in self.EFFECTS.items():
            if param in e.names:
                return name
        return None

    # --- simulation -------------------------------------------------------------------
    @abc.abstractmethod
    def initial_state(self, P: np.ndarray, init: Mapping[str, float] | None = None) -> np.ndarray:
        """Initial states ``[K, n_states]`` for kernel vectors ``P [K, n_p]`` (rest by default)."""

    @abc.abstractmethod
    def drive_signal(self, signals: Mapping[str, np.ndarray], drive: str = "auto") -> tuple[str, np.ndarray]:
        """Choose the driving input among ``signals``: returns (name, values)."""

    @abc.abstractmethod
    def simulate_batch(
        self,
        P: np.ndarray,
        drive_name: str,
        drive: np.ndarray,
        dt: float,
        x0: np.ndarray | None = None,
        substeps: int | None = None,
        timing: Timing | None = None,
        exogenous: Mapping[str, np.ndarray] | None = None,
    ) -> SimResult:
        """Simulate ``K`` parameter vectors ``P [K, n_p]`` over one driving signal ``[T]``; ``exogenous``: logged
        signals that set a parameter sample by sample (:meth:`exogenous_of`), ``[T]`` each."""

    def exogenous_of(self, signals: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The logged signals of a record that set a parameter sample by sample (``FILTER.exogenous``, e.g. the
        oil temperature ``T_oil``): the simulation reads them as the tracker does (the value at a sample holds
        over the interval after it; a non-finite one leaves the last value)."""
        names = self.FILTER.exogenous if self.FILTER is not None else {}
        return {k: np.asarray(signals[k], dtype=np.float64) for k in names if k in signals}

    def exogenous_table(self, exogenous: Mapping[str, np.ndarray] | None, n: int) -> tuple[np.ndarray, np.ndarray]:
        """``(kernel indices [e], values [n, e])`` of the exogenous signals for a simulation of ``n`` samples;
        a value outside its parameter's range is refused in one line (a temperature in degC where K is due)."""
        declared = self.FILTER.exogenous if self.FILTER is not None else {}
        names = [k for k in (exogenous or {})]
        unknown = [k for k in names if k not in declared]
        if unknown:
            raise DataError(f"{self.name} reads no exogenous signal {unknown[0]!r} (it reads: "
                            f"{', '.join(declared) or 'none'})")
        EXO = np.full((n, len(names)), np.nan)
        for j, k in enumerate(names):
            v = np.asarray((exogenous or {})[k], dtype=np.float64)
            if v.shape != (n,):
                raise DataError(f"exogenous signal {k!r} must have {n} samples (the drive's), got shape {v.shape}")
            spec = self.kernel_specs[self.kernel_index(declared[k])]
            bad = np.isfinite(v) & ((v < spec.lo) | (v > spec.hi))
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise DataError(f"signal {k!r}: {v[i]:g} {spec.unit} at sample {i} is outside {spec.name}'s "
                                f"range [{spec.lo:g}, {spec.hi:g}] {spec.unit} ({spec.meaning})")
            EXO[:, j] = v
        return np.array([self.kernel_index(declared[k]) for k in names], dtype=np.int64), EXO

    def controller_response(self, ps: ParameterSet, q: np.ndarray, dt: float) -> np.ndarray | None:
        """The digital controller's response from the position error to the command at ``q = 1 - z^-1`` (its
        backward-difference operator on the unit circle), for a closed-loop model; ``None``: no controller."""
        return None

    def effect_typicals(self, ps: ParameterSet, signals: Mapping[str, np.ndarray],
                        predicted: Mapping[str, np.ndarray], dt: float) -> dict[str, tuple[float, ...]]:
        """Each effect's typical size on this record given the fitted nominal model ``ps`` and its
        prediction (a model whose units follow the record scales them; default: the catalogue's)."""
        return {name: tuple(e.typical) for name, e in self.EFFECTS.items()}

    def starts_from_data(self, signals: Mapping[str, np.ndarray], dt: float) -> list[dict[str, float]]:
        """Fit starts of base parameters read off a record (a model that can, e.g. from its linear response)."""
        return []

    def intersample_code(self, timing: Timing | None, dt: float) -> int:
        """How this model's simulation treats a logged input between samples under ``timing``."""
        return (timing or DEFAULT_TIMING).intersample_code(dt)

    def initial_from_data(self, signals: Mapping[str, np.ndarray], dt: float) -> dict[str, float]:
        """Initial-state quantities read off a record's first samples (none by default)."""
        return {}

    def check_record(self, ps: ParameterSet, signals: Mapping[str, np.ndarray], name: str = "record") -> None:
        """Raise a :class:`DataError` (one line, naming the numbers) when the record is impossible for the
        rig ``ps`` describes (nothing is checked by default)."""
        return None

    def simulate(self, ps: ParameterSet, drive_name: str, drive: np.ndarray, dt: float,
                 init: Mapping[str, float] | None = None, substeps: int | None = None,
                 timing: Timing | None = None, exogenous: Mapping[str, np.ndarray] | None = None) -> SimResult:
        """Simulate one parameter set; outputs are ``[T]`` arrays (batch axis removed)."""
        P = self.vector(ps)[None, :]
        x0 = self.initial_state(P, init)
        res = self.simulate_batch(P, drive_name, np.asarray(drive, float), dt, x0, substeps, timing, exogenous)
        return SimResult(res.t_s, {k: v[0] for k, v in res.outputs.items()}, res.states[0],
                         {k: (v[0] if v.ndim == 2 else v) for k, v in res.inputs.items()})


def start_of(y: np.ndarray, dt: float, window_s: float = 0.02) -> tuple[float, float, float, float]:
    """Value and slope of a noisy signal at its first sample, with their standard errors.

    A cubic least-squares fit over the first ``window_s`` (at least 8 samples):
    noise averages out and a signal already accelerating is not mistaken for a
    moving one.
    """
    y = np.asarray(y, dtype=float)
    n = int(min(max(8, round(window_s / dt)), y.size))
    t = np.arange(n) * dt
    X = np.vander(t, min(4, n - 1), increasing=True)
    coef, *_ = np.linalg.lstsq(X, y[:n], rcond=None)
    res = y[:n] - X @ coef
    s2 = float(res @ res) / max(n - X.shape[1], 1)
    cov = s2 * np.linalg.pinv(X.T @ X)
    return float(coef[0]), float(coef[1]), float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))


def check_drive(name: str, drive: np.ndarray, dt: float) -> np.ndarray:
    drive = np.ascontiguousarray(drive, dtype=np.float64)
    if drive.ndim != 1 or drive.size < 2:
        raise DataError(f"driving signal {name!r} must be a 1-D array of at least 2 samples, got shape {drive.shape}")
    if not np.all(np.isfinite(drive)):
        i = int(np.flatnonzero(~np.isfinite(drive))[0])
        raise DataError(f"driving signal {name!r} has a non-finite value at sample {i}")
    if not (dt > 0 and np.isfinite(dt)):
        raise DataError(f"sample time dt (={dt}) must be a positive number of seconds")
    return drive
