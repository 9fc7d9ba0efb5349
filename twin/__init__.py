"""fpdd-twin: first-principle data-driven digital twin of servo-hydraulic test rigs.

The public API (imported on first use, so ``import twin`` stays light)::

    import twin
    model = twin.get_model("msp25")                     # the rig's first-principle model
    result = twin.fit(model, records, ["Ffric", "zeta"])  # batch grey-box fit -> FitResult
    tracker = twin.OnlineTracker(noise={"x": 2e-6})       # augmented-state UKF, block by block
    monitor = twin.DriftMonitor(...)                      # CUSUM drift alarms on its estimates
    diagnosis = twin.diagnose(records, "msp25")           # what the model gets wrong, and why
    twin.track(source), twin.serve(config)                # a log offline, rigs online
    twin.TwinPublisher, twin.AlarmSubscriber              # the Zenoh side
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

__version__ = "0.1.0"

#: public name -> module that defines it
_EXPORTS = {
    "get_model": "twin.models",
    "Timing": "twin.models.base",
    "ParameterSet": "twin.params",
    "Record": "twin.record",
    "load_records": "twin.record",
    "excite": "twin.simulate",
    "measure": "twin.simulate",
    "fit": "twin.fit",
    "FitResult": "twin.fit",
    "OnlineTracker": "twin.tracker",
    "DriftMonitor": "twin.drift",
    "diagnose": "twin.diagnose",
    "Diagnosis": "twin.diagnose",
    "track": "twin.track",
    "serve": "twin.service",
    "load_config": "twin.config",
    "TwinPublisher": "twin.bus",
    "AlarmSubscriber": "twin.bus",
    "AlarmEvent": "twin.events",
    "EstimateEvent": "twin.events",
    "StatusEvent": "twin.events",
    "TwinError": "twin.errors",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'twin' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__


class _Package(types.ModuleType):
    """``twin.fit``, ``twin.track``, ``twin.diagnose`` are functions of the API and modules of the package:
    importing a submodule sets it as an attribute of the package, which would hide the function of the
    same name.  The package keeps the function; the modules stay importable by name (``from twin.fit
    import FitResult``, ``importlib.import_module("twin.fit")``)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if isinstance(value, types.ModuleType) and _EXPORTS.get(name) == f"{__name__}.{name}":
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
