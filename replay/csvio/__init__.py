"""CSV files: one header row naming the signals, one row per sample.

:mod:`~replay.csvio.reader` the source (the layout it reads), :mod:`~replay.csvio.writer` the sink,
:mod:`~replay.csvio.columns` the column mapping (``--map``) and header units.
"""

from replay.csvio.columns import MAP_SYNTAX, TIME_COLUMN, parse_map, sniff_text, split_unit, suggest_map
from replay.csvio.reader import CsvSource
from replay.csvio.writer import CsvSink, format_t_s

__all__ = ["CsvSource", "CsvSink", "TIME_COLUMN", "format_t_s", "parse_map", "sniff_text", "split_unit", "suggest_map",
           "MAP_SYNTAX"]
