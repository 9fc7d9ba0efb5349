"""replay: rig logs in (CSV, MCAP, CAN logs, live CAN, Zenoh), one sample stream out.

The public API (imported on first use)::

    import replay
    with replay.open_source("run.mcap") as src:        # the reader by suffix or URI
        for block in src:                                # replay.Samples: t_ns int64, SI signals
            ...
    print(src.report)                                    # everything skipped, and why
    with replay.open_sink("copy.csv") as sink:
        sink.write(block)
"""

from __future__ import annotations

import importlib
from typing import Any

#: public name -> module that defines it
_EXPORTS = {
    "Samples": "replay.base", "Source": "replay.base", "Sink": "replay.base", "ReadReport": "replay.base",
    "open_source": "replay.factory", "open_sink": "replay.factory",
    "TwinError": "fpdd.errors", "DataError": "fpdd.errors", "LogFormatError": "fpdd.errors",
    "SourceError": "fpdd.errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'replay' has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
