"""The first-principle models, one module each, and the registry that names them.

:data:`MODELS` lists every model by name; :func:`get_model` imports one on first use.  What a model can do
(closed loop, tracked online) is declared on the model (:attr:`Model.CLOSED_LOOP`, :attr:`Model.TRACKABLE`),
never tested by name elsewhere.
"""

from __future__ import annotations

import importlib

from fpdd.errors import ParameterError
from twin.models.base import Model, SimResult

#: model name -> module defining ``MODEL`` (the registry)
REGISTRY = {"msp25": "twin.models.msp25", "oscillator": "twin.models.oscillator"}
MODELS = tuple(REGISTRY)


def get_model(name: str) -> Model:
    """The model called ``name`` (one of :data:`MODELS`)."""
    if name not in REGISTRY:
        raise ParameterError(f"unknown model {name!r}; known: {', '.join(MODELS)}")
    return importlib.import_module(REGISTRY[name]).MODEL


def trackable_models() -> tuple[str, ...]:
    """The models the online twin runs (``twin track``, ``twin serve``)."""
    return tuple(n for n in MODELS if get_model(n).TRACKABLE)


__all__ = ["Model", "SimResult", "get_model", "MODELS", "REGISTRY", "trackable_models"]
