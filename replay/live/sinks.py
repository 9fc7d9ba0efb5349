"""Zenoh sessions of live streams, and the sinks that publish on a key: samples (``fpdd.samples/1``) and raw
CAN frames (``fpdd.can/1``)."""

from __future__ import annotations

import abc
import json
import threading

import zenoh

from fpdd.zenohconf import open_session, zenoh_config
from replay.base import Samples, Sink
from replay.can.decode import split_block
from replay.can.encode import FrameScheduler
from replay.can.codec import Frames, VectorCodec
from fpdd.errors import SourceError
from replay.live.payloads import SAMPLES_FORMAT, frames_to_payload, samples_to_json


# --- URIs and configuration --------------------------------------------------------------


def parse_zenoh_uri(uri: str) -> str:
    """``zenoh://KEYEXPR`` -> key expression."""
    if not uri.startswith("zenoh://") or len(uri) <= len("zenoh://"):
        raise SourceError(f"{uri}: expected a Zenoh URI of the form zenoh://KEY/EXPR, e.g. zenoh://fpdd/msp25/samples")
    return uri[len("zenoh://"):]


def open_live_session(conf: zenoh.Config | None, what: str) -> zenoh.Session:
    """A session from ``conf`` (default: peer, scouting on, to find the rig's publisher on the LAN)."""
    return open_session(conf if conf is not None else zenoh_config(multicast_scouting=True), what)


# --- Zenoh -------------------------------------------------------------------------------------

class ZenohPublisher(Sink):
    def __init__(self, key: str, config: zenoh.Config | None, encoding: zenoh.Encoding,
                 session: zenoh.Session | None) -> None:
        self.key = parse_zenoh_uri(key) if key.startswith("zenoh://") else key
        self._owned = session is None
        self.session = session if session is not None else open_live_session(config, f"zenoh://{self.key}")
        try:  # BLOCK: a replay is lossless (zenoh's default, DROP, may drop even the end marker under load)
            self.publisher = self.session.declare_publisher(self.key, encoding=encoding,
                                                            congestion_control=zenoh.CongestionControl.BLOCK)
        except Exception as e:  # ZError: an invalid key expression
            if self._owned:
                self.session.close()
            raise SourceError(f"zenoh://{self.key}: cannot publish: {e}") from e
        self._matched = threading.Event()
        self._listener = self.publisher.declare_matching_listener(self._on_matching)
        if self.publisher.matching_status.matching:  # type: ignore[attr-defined]  # a MatchingStatus, not the stub's bool
            self._matched.set()
        self._closed = False

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._matched.set()
        else:
            self._matched.clear()

    def wait_for_subscriber(self, timeout_s: float = 5.0) -> bool:
        """Block until a subscriber matches the key (True) or the timeout passes (False)."""
        return self._matched.wait(timeout_s)

    def _put(self, payload: bytes) -> None:
        self.publisher.put(payload)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._send_end()
        self._listener.undeclare()
        self.publisher.undeclare()
        if self._owned:
            self.session.close()

    @abc.abstractmethod
    def _send_end(self) -> None:
        """Publish the end-of-stream marker of the payload format."""


class ZenohSampleSink(ZenohPublisher):
    """Publishes sample blocks as ``fpdd.samples/1`` JSON on a key (``replay play --to zenoh``).

    :param key: key expression or ``zenoh://KEY``.
    :param config: Zenoh config (see :func:`zenoh_config`); ignored if ``session`` is given.
    :param max_block: samples per payload at most (larger blocks are split).
    :param end_marker: publish the end marker on close.
    """

    def __init__(self, key: str, config: zenoh.Config | None = None, *, session: zenoh.Session | None = None,
                 max_block: int = 1000, end_marker: bool = True) -> None:
        super().__init__(key, config, zenoh.Encoding.APPLICATION_JSON, session)
        self.max_block = max_block
        self.end_marker = end_marker

    def write(self, samples: Samples) -> None:
        for part in split_block(samples, self.max_block):
            self._put(samples_to_json(part))

    def _send_end(self) -> None:
        if self.end_marker:
            self._put(json.dumps({"format": SAMPLES_FORMAT, "end": True}).encode())


class ZenohCanSink(ZenohPublisher):
    """Publishes raw CAN frames (``fpdd.can/1``) on a key, e.g. ``fpdd/msp25/can``.

    ``write(samples)`` encodes samples into the rig's frames with the DBC (like
    :class:`~replay.can.logs.CanLogSink`); ``write_frames(frames)`` forwards frames as they
    are (a bus or a log bridged to Zenoh).
    """

    def __init__(self, key: str, dbc=None, config: zenoh.Config | None = None, *,
                 session: zenoh.Session | None = None, decimate: bool = True, end_marker: bool = True) -> None:
        super().__init__(key, config, zenoh.Encoding.APPLICATION_OCTET_STREAM, session)
        self.codec = dbc if isinstance(dbc, VectorCodec) else VectorCodec(dbc)
        self.scheduler = FrameScheduler(self.codec, decimate, f"zenoh://{self.key}")
        self.end_marker = end_marker

    def write(self, samples: Samples) -> None:
        self.write_frames(self.scheduler.frames(samples))

    def write_frames(self, frames: Frames) -> None:
        if len(frames):
            self._put(frames_to_payload(frames))

    def _send_end(self) -> None:
        if self.end_marker:
            self._put(frames_to_payload(Frames.empty()))
