"""The first-principle models, one module each, and the registry that names them.

:data:`MODELS` lists every model by name; :func:`get_model` imports one on first use.  What a model can do
(closed loop, tracked online) is declared on the model (:attr:`Model.CLOSED_LOOP`, :attr:`Model.TRACKABLE`),
never tested by name elsewhere.
"""

from __future__ import annotations

import importlib

from fpdd.errors import ParameterError
from twin.models.base import Model, SimResult

#: model name -> module defining ``MODEL`` (the registry; :func:`register` adds one)
REGISTRY = {"msp25": "twin.models.msp25", "oscillator": "twin.models.oscillator", "axis": "twin.models.axis"}
MODELS = tuple(REGISTRY)
#: the model a command, a rig or a tracker runs when none is named
DEFAULT_MODEL = "msp25"


def get_model(name: str) -> Model:
    """The model called ``name`` (one of :data:`MODELS`)."""
    if name not in REGISTRY:
        raise ParameterError(f"unknown model {name!r}; known: {', '.join(MODELS)}")
    return importlib.import_module(REGISTRY[name]).MODEL


def register(name: str, module: str) -> None:
    """Add the model ``MODEL`` of ``module`` to the registry as ``name`` (a module importable by that name)."""
    global MODELS
    if not name.isidentifier():
        raise ParameterError(f"model name {name!r} must be an identifier")
    REGISTRY[name] = module
    MODELS = tuple(REGISTRY)


def trackable_models() -> tuple[str, ...]:
    """The models the online twin runs (``twin track``, ``twin serve``)."""
    return tuple(n for n in MODELS if get_model(n).TRACKABLE)


__all__ = ["DEFAULT_MODEL", "Model", "SimResult", "get_model", "MODELS", "REGISTRY", "register", "trackable_models"]
