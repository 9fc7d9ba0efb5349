"""The exception tree of fpdd-twin, at the bottom layer (:mod:`fpdd`), beneath both ``replay`` and ``twin``.

::

    TwinError                                  base of everything raised on purpose
    ├── ParameterError(TwinError, ValueError)  a parameter unknown, out of bounds, not finite
    ├── DataError(TwinError, ValueError)       measured data unusable: missing signal, NaN,
    │   │                                      time going backwards, wrong unit, too short
    │   └── LogFormatError(DataError)          a log file truncated, corrupt or of unknown format
    ├── SourceError(TwinError, OSError)        a source or sink cannot be opened / reached
    ├── FilterError(TwinError, ArithmeticError) a filter that cannot go on (covariance unrepairable)
    └── ConfigError(TwinError, ValueError)     a rig configuration file that does not validate

Every message names the file (when there is one), the field or record and what
was expected, so that an operator can fix the input without reading code.
"""

from __future__ import annotations


class TwinError(Exception):
    """Base class of every error fpdd-twin raises on purpose."""


class ParameterError(TwinError, ValueError):
    """A model parameter is unknown, not finite or outside its allowed range."""


class DataError(TwinError, ValueError):
    """Measured data cannot be used as given (missing signal, NaN, bad time axis, unit)."""


class LogFormatError(DataError):
    """A log file is truncated, corrupt or in a format that is not understood."""


class SourceError(TwinError, OSError):
    """A data source or sink cannot be opened or reached."""


class FilterError(TwinError, ArithmeticError):
    """The online filter cannot continue (e.g. a covariance that cannot be repaired)."""


class ConfigError(TwinError, ValueError):
    """A rig configuration does not validate."""
