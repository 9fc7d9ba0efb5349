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
from typing import Iterable, Mapping

import numpy as np

from twin.errors import DataError, ParameterError
from twin.params import Effect, ParameterSet, ParamSpec, check_names


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

    # --- parameters -----------------------------------------------------------------
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

    def params(self, effects: Iterable[str] = (), **values: float) -> ParameterSet:
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
    ) -> SimResult:
        """Simulate ``K`` parameter vectors ``P [K, n_p]`` over one driving signal ``[T]``."""

    def simulate(self, ps: ParameterSet, drive_name: str, drive: np.ndarray, dt: float,
                 init: Mapping[str, float] | None = None, substeps: int | None = None) -> SimResult:
        """Simulate one parameter set; outputs are ``[T]`` arrays (batch axis removed)."""
        P = self.vector(ps)[None, :]
        x0 = self.initial_state(P, init)
        res = self.simulate_batch(P, drive_name, np.asarray(drive, float), dt, x0, substeps)
        return SimResult(res.t_s, {k: v[0] for k, v in res.outputs.items()}, res.states[0],
                         {k: (v[0] if v.ndim == 2 else v) for k, v in res.inputs.items()})


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
