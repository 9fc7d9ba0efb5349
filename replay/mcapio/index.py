"""The structure of an MCAP file as the reader keeps it: its chunk index in arrays, the stretches it could
not read, the records it may meet, and what a damaged file raises inside ``mcap``."""

from __future__ import annotations

import dataclasses
import struct
from typing import Any
from collections.abc import Iterator, Sequence

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.opcode import Opcode


MCAP_MAGIC = b"\x89MCAP0\r\n"

#: Errors a damaged file raises inside ``mcap`` (CRC mismatch is a ValueError there).
DAMAGE = (McapError, ValueError, struct.error, EOFError, zstandard.ZstdError)
RECORD_SIZE_LIMIT = 1 << 30  # 1 GiB: a damaged length field must not allocate more
INT64_MAX = (1 << 63) - 1


@dataclasses.dataclass(frozen=True)
class TopicInfo:
    """One channel of an MCAP file."""

    topic: str
    schema: str
    encoding: str
    messages: int | None  # None when the summary is unreadable and the topic was not counted
    signals: tuple[str, ...]
    t_first_ns: int | None = None  # first and last log time, when the messages were scanned
    t_last_ns: int | None = None


@dataclasses.dataclass(frozen=True)
class McapMessage:
    """A decoded JSON message: topic, log time (ns) and payload."""

    topic: str
    t_ns: int
    data: Any


class ChunkRef:
    """What reading one chunk needs of its index record (made from a :class:`ChunkTable` row when read)."""

    __slots__ = ("chunk_start_offset", "chunk_length", "message_start_time", "message_end_time",
                 "message_index_offsets")

    def __init__(self, offset: int, length: int, t0: int, t1: int, index_offsets: dict[int, int]) -> None:
        self.chunk_start_offset = offset
        self.chunk_length = length
        self.message_start_time = t0
        self.message_end_time = t1
        self.message_index_offsets = index_offsets


class ChunkTable:
    """A file's chunk index in arrays: a replayed log keeps it for as long as it is read, and a long one has
    many chunks (a day at 1 kHz: ~10^5); as ``mcap`` records they cost ~650 B each, here ~110 B
    (``tests/test_memory.py``). Iterating yields :class:`ChunkRef` rows in file-index order."""

    def __init__(self, cis: Sequence[Any]) -> None:
        self.offset = np.array([c.chunk_start_offset for c in cis], dtype=np.int64)
        self.length = np.array([c.chunk_length for c in cis], dtype=np.int64)
        self.t0 = np.array([c.message_start_time for c in cis], dtype=np.uint64)
        self.t1 = np.array([c.message_end_time for c in cis], dtype=np.uint64)
        counts = [len(c.message_index_offsets) for c in cis]
        self._bounds = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)
        self._cid = np.array([k for c in cis for k in c.message_index_offsets], dtype=np.int64)
        self._ioff = np.array([v for c in cis for v in c.message_index_offsets.values()], dtype=np.int64)

    def __len__(self) -> int:
        return len(self.offset)

    def __bool__(self) -> bool:
        return len(self.offset) > 0

    def __getitem__(self, k: int) -> ChunkRef:
        a, b = int(self._bounds[k]), int(self._bounds[k + 1])
        return ChunkRef(int(self.offset[k]), int(self.length[k]), int(self.t0[k]), int(self.t1[k]),
                         {int(c): int(o) for c, o in zip(self._cid[a:b], self._ioff[a:b])})

    def __iter__(self) -> Iterator[ChunkRef]:
        return (self[k] for k in range(len(self)))

    def channels(self, k: int) -> set[int]:
        return {int(c) for c in self._cid[int(self._bounds[k]):int(self._bounds[k + 1])]}


@dataclasses.dataclass(frozen=True)
class Lost:
    """A chunk (or stretch of records) that could not be read, in the message stream."""

    t_start: int | None  # first log time the chunk index declares, ns (None: unknown)
    t_end: int | None
    messages: int | None  # messages of the wanted channels in it (from the message index), None: unknown


OPCODES = frozenset(int(o) for o in Opcode)

