"""Live sources and sinks on Zenoh (a live CAN bus through python-can is :mod:`replay.can.bus`).

URIs
====

* ``can://INTERFACE/CHANNEL`` — any python-can interface, opened with
  ``can.Bus(interface=INTERFACE, channel=CHANNEL)``; e.g. ``can://virtual/rig1``,
  ``can://socketcan/can0``, ``can://pcan/PCAN_USBBUS1``.
* ``zenoh://KEYEXPR`` — e.g. ``zenoh://fpdd/msp25/samples``.

:mod:`~replay.live.payloads` the two payloads, :mod:`~replay.live.watch` what every live source
shares (drops per cause, staleness), :mod:`~replay.live.sinks` the publishers, :mod:`~replay.live.source`
the source.
"""

from replay.live.payloads import PayloadError, frames_to_payload, json_to_samples, payload_to_frames, samples_to_json
from replay.live.sinks import ZenohCanSink, ZenohSampleSink, parse_zenoh_uri
from replay.live.source import ZenohSource

__all__ = ["PayloadError", "ZenohCanSink", "ZenohSampleSink", "ZenohSource", "frames_to_payload", "json_to_samples",
           "parse_zenoh_uri", "payload_to_frames", "samples_to_json"]
