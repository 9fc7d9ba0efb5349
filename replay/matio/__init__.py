"""Records held as named columns: MATLAB ``.mat`` files (:class:`MatSource`, through ``scipy.io``) and
whitespace- or tab-separated text (:class:`TextSource`); both map their columns with ``--map`` as CSV does
(:func:`replay.csvio.parse_map`) and go through the same quality gate (:class:`ColumnSource`)."""

from replay.matio.columns import ColumnSource
from replay.matio.mat import MatSource
from replay.matio.text import TextSource

__all__ = ["ColumnSource", "MatSource", "TextSource"]
