"""The exception tree (defined at the bottom layer, :mod:`replay.errors`; re-exported for ``twin``)."""

from replay.errors import (ConfigError, DataError, FilterError, LogFormatError, ParameterError, SourceError,
                           TwinError)

__all__ = ["TwinError", "ParameterError", "DataError", "LogFormatError", "SourceError", "FilterError",
           "ConfigError"]
