"""Live view of the twins in Foxglove: rig signals, estimates with their intervals and bands, statuses and alarms.

:mod:`~twin.service.live_view.messages` the channels and their schemas, :mod:`~twin.service.live_view.signals`
rig signals over Zenoh, :mod:`~twin.service.live_view.server` the WebSocket server (:class:`LiveView`),
:mod:`~twin.service.live_view.layout` the Foxglove layout.
"""

from twin.service.live_view.layout import PARAMETERS, foxglove_layout, write_layout
from twin.service.live_view.messages import EXAMPLE_RIG, SUBPROTOCOLS, TOPICS, estimate_message
from twin.service.live_view.server import LiveView
from twin.service.live_view.signals import SignalDecimator, signals_from_json, signals_key, signals_to_json

__all__ = ["EXAMPLE_RIG", "PARAMETERS", "SUBPROTOCOLS", "TOPICS", "LiveView", "SignalDecimator", "estimate_message",
           "foxglove_layout", "signals_from_json", "signals_key", "signals_to_json", "write_layout"]
