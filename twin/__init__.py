"""fpdd-twin: first-principle data-driven digital twin of servo-hydraulic test rigs.

The public API (imported on first use, so ``import twin`` stays light)::

    import twin
    model = twin.get_model("msp25")                     # the rig's first-principle model
    result = twin.fit(model, records, ["Ffric", "zeta"], params=model.params(A="2000mm^2"))  # -> FitResult
    tracker = twin.OnlineTracker(noise={"x": 2e-6})       # augmented-state UKF, block by block
    monitor = twin.DriftMonitor(...)                      # CUSUM drift alarms on its estimates
    diagnosis = twin.diagnose(records, "msp25")           # what the model gets wrong, and why
    twin.track(source, map={"x": "pos_mm:mm"}), twin.serve(config)  # a log offline, rigs online
    twin.TwinPublisher, twin.AlarmSubscriber              # the Zenoh side
    twin.reports.fit_report(result, records, model, "out/") # the subpackages too, on first use
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: public name -> module that defines it
_EXPORTS = {
    "get_model": "twin.models",
    "Timing": "twin.models.base",
    "ParameterSet": "twin.params",
    "Record": "twin.record",
    "load_records": "twin.models.records",
    "excite": "twin.models.simulate",
    "measure": "twin.models.simulate",
    "fit": "twin.estimation.fit_checked",
    "FitResult": "twin.estimation.fit",
    "OnlineTracker": "twin.online.tracker",
    "DriftMonitor": "twin.online.drift",
    "diagnose": "twin.estimation.diagnose",
    "Diagnosis": "twin.estimation.diagnose",
    "track": "twin.service.track",
    "serve": "twin.service.serve",
    "load_config": "twin.service.config",
    "TwinPublisher": "twin.service.bus",
    "AlarmSubscriber": "twin.service.subscriber",
    "AlarmEvent": "twin.online.events",
    "EstimateEvent": "twin.online.events",
    "StatusEvent": "twin.online.events",
    "TwinError": "fpdd.errors",
}

#: subpackages and modules reached as attributes (``twin.reports.fit_report(...)``), imported on first use
_SUBMODULES = ("commands", "estimation", "models", "online", "params", "record", "reports", "service", "units")

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        module = importlib.import_module(f"twin.{name}")
        globals()[name] = module
        return module
    raise AttributeError(f"module 'twin' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*__all__, *_SUBMODULES})
