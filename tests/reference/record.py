"""A simulated record: time, logged signals (SI), the truth behind them, and how it was made."""

from __future__ import annotations

import dataclasses
import json
import os
from typing import Any

import numpy as np

COLUMNS = {"msp25": ("x_ref", "u", "x", "pA", "pB", "T_oil"), "oscillator": ("u", "y")}


@dataclasses.dataclass
class Record:
    """``t`` [s] from 0 at the log rate; ``signals`` as logged (SI); ``truth``: true parameter values
    (a description for time-varying ones); ``meta``: controller, rates, intersample, noise, effects
    with their drawn sizes, seed, initial state; ``hidden``: noise-free states and time-varying
    parameters at the log instants."""

    t: np.ndarray
    signals: dict[str, np.ndarray]
    truth: dict[str, Any]
    meta: dict[str, Any]
    hidden: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def dt(self) -> float:
        return float(1.0 / self.meta["log_rate_hz"])

    @property
    def model(self) -> str:
        return str(self.meta["model"])

    def to_csv(self, path: str | os.PathLike) -> None:
        """Write ``t,x_ref,u,x,pA,pB[,T_oil]`` (msp25) or ``t,u,y`` (oscillator), SI, full precision."""
        cols = [c for c in COLUMNS[self.model] if c in self.signals]
        data = np.column_stack([self.t] + [self.signals[c] for c in cols])
        np.savetxt(path, data, delimiter=",", header=",".join(["t", *cols]), comments="",
                   fmt=["%.9f"] + ["%.17g"] * len(cols))

    # --- storage (the cache) ---------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        arrays = {"t": self.t}
        arrays.update({f"s.{k}": v for k, v in self.signals.items()})
        arrays.update({f"h.{k}": v for k, v in self.hidden.items()})
        text = json.dumps({"truth": self.truth, "meta": self.meta}, default=_jsonable)
        arrays["json"] = np.frombuffer(text.encode(), dtype=np.uint8)
        tmp = f"{os.fspath(path)}.{os.getpid()}.tmp"
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Record:
        with np.load(path) as z:
            info = json.loads(bytes(z["json"]).decode())
            signals = {k[2:]: z[k] for k in z.files if k.startswith("s.")}
            hidden = {k[2:]: z[k] for k in z.files if k.startswith("h.")}
            return cls(z["t"], signals, info["truth"], info["meta"], hidden)


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")
