"""A rig's input: a replayed log or a live one (``can://``, ``zenoh://``), opened from its configuration."""

from __future__ import annotations

from typing import Any

from twin.service.config import RigConfig


def is_live(uri: str) -> bool:
    return uri.startswith(("can://", "zenoh://"))



def open_rig_source(rig: RigConfig, session=None, timeout_s: float | None = None):
    """The rig's source; a ``zenoh://`` input rides on the service's own Zenoh session."""
    from replay.factory import open_source

    opts: dict[str, Any] = rig.source_options()
    if rig.source.startswith("zenoh://") and session is not None:
        opts["session"] = session
    if is_live(rig.source) and timeout_s is not None:
        opts["timeout_s"] = timeout_s
    from replay.quality import QualityOptions
    from twin.models.records import signal_specs

    specs = signal_specs(rig.model)  # the rig model's signals: their units and physical ranges
    if rig.source.startswith("zenoh://"):  # the runner orders blocks itself and judges a block from the future
        opts["quality"] = QualityOptions(order_across_blocks=False, specs=specs)
    elif rig.source.lower().endswith((".csv", ".csv.gz", ".mcap")):
        opts["quality"] = QualityOptions(specs=specs)
    return open_source(rig.source, **opts)
