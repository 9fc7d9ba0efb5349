"""The first-principle models, one module each; :func:`get_model` picks one by name."""

from __future__ import annotations

from twin.errors import ParameterError
from twin.models.base import Model, SimResult


def get_model(name: str) -> Model:
    """The model called ``name`` (``msp25`` or ``oscillator``)."""
    if name == "msp25":
        from twin.models import msp25
        return msp25.MODEL
    if name == "oscillator":
        from twin.models import oscillator
        return oscillator.MODEL
    raise ParameterError(f"unknown model {name!r}; known: msp25, oscillator")


MODELS = ("msp25", "oscillator")
__all__ = ["Model", "SimResult", "get_model", "MODELS"]
