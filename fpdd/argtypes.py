"""argparse types shared by every command of both packages (one home, one wording of each error)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def positive_int(text: str) -> int:
    """An integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} must be >= 1")
    return value


def _seconds(text: str, ok: Callable[[float], bool], expected: str) -> float:
    """A finite number of seconds for which ``ok`` holds, else an error saying it ``must be {expected}``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(value) and ok(value)):
        raise argparse.ArgumentTypeError(f"{value} must be {expected}")
    return value


def positive_seconds(text: str) -> float:
    """A finite number of seconds > 0."""
    return _seconds(text, lambda v: v > 0, "a positive number of seconds")


def non_negative_seconds(text: str) -> float:
    """A finite number of seconds >= 0."""
    return _seconds(text, lambda v: v >= 0, "a number of seconds >= 0")
