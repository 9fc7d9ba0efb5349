"""What a rig's runner ends with: its :class:`RigSummary`, the failure that ends a rig
(:class:`RigFailure`) and the signal that stops it (:class:`Stopped`)."""

from __future__ import annotations

import dataclasses

from fpdd.errors import TwinError
from twin.service.rig import RigStats


@dataclasses.dataclass
class RigSummary:
    """What one rig did in this run of the service."""

    rig: str
    state: str = "starting"
    message: str = ""
    samples: int = 0
    """Samples processed in this run."""
    alarms: int = 0
    """Alarms journaled and published in this run."""
    duplicates: int = 0
    resumed_samples: int | None = None
    """Samples already processed according to the checkpoint restored (None: fresh start)."""
    lag_max_s: float | None = None
    source_errors: int = 0
    bad_blocks: int = 0
    bad_samples: int = 0
    """Live samples without a finite drive (dropped)."""
    time_backwards: int = 0
    """Live samples at or before the last one processed, or not increasing (dropped)."""
    time_jump: int = 0
    """Live samples stamped far ahead of the rig's present (dropped, see ``TIME_JUMP_S``)."""
    clock_steps: int = 0
    """Times the live input's clock stepped (back or ahead) and its new time was adopted (``CLOCK_STEP_SAMPLES``)."""
    input_gaps: int = 0
    filter_resets: int = 0
    input_dropped: int = 0
    """Messages or samples the live source dropped (its counts per cause are in the status)."""
    input_lost: str = ""
    """What the reader of a replayed log lost on the way (its loss line; "" when nothing): ``twin serve`` warns
    and exits 3."""
    busy_s: float = 0.0
    stats: RigStats = dataclasses.field(default_factory=RigStats)

    def line(self) -> str:
        parts = [f"{self.rig}: {self.state}", f"{self.samples} samples", f"{self.alarms} alarm(s)"]
        if self.resumed_samples is not None:
            parts.append(f"resumed after {self.resumed_samples} samples")
        if self.duplicates:
            parts.append(f"{self.duplicates} alarm(s) already journaled")
        if self.lag_max_s is not None:
            parts.append(f"lag max {self.lag_max_s:.3f} s")
        for name in COUNTED + ("input_dropped",):
            if getattr(self, name):
                parts.append(f"{name} {getattr(self, name)}")
        text = ", ".join(parts)
        text = f"{text}: {self.message}" if self.message else text
        return f"{text}; input lost: {self.input_lost}" if self.input_lost and self.input_lost not in text else text


#: Counters of a :class:`RigSummary` that go into the rig's status when not zero.
COUNTED = ("source_errors", "bad_blocks", "bad_samples", "time_backwards", "time_jump", "clock_steps", "input_gaps",
            "filter_resets")


class RigFailure(TwinError):
    """An unrecoverable error of one rig (named in the message)."""


class Stopped(Exception):
    pass

