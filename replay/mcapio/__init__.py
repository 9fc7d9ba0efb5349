"""MCAP files (the ``mcap`` library): rig samples and the twin's own messages.

:mod:`~replay.mcapio.layout` the topics and schemas, :mod:`~replay.mcapio.writer` the sink,
:mod:`~replay.mcapio.reader` the source (its file walk) with :mod:`~replay.mcapio.decode` (samples from
messages) and :mod:`~replay.mcapio.index` (the chunk index it keeps).
"""

from replay.mcapio.layout import (BLOCK_SCHEMA, BLOCK_TOPIC, LAYOUT_METADATA, SIGNALS_SCHEMA, SIGNALS_TOPIC,
                                  block_schema, encode_json, foxglove_time, signals_schema, with_time_schema)
from replay.mcapio.index import McapMessage, TopicInfo
from replay.mcapio.reader import McapSource, inspect
from replay.mcapio.writer import McapSink

__all__ = ["McapSink", "McapSource", "McapMessage", "TopicInfo", "SIGNALS_TOPIC", "BLOCK_TOPIC",
           "SIGNALS_SCHEMA", "BLOCK_SCHEMA", "LAYOUT_METADATA", "signals_schema", "block_schema",
           "encode_json", "foxglove_time", "with_time_schema", "inspect"]
