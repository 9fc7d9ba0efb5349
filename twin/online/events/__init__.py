"""Events the twin publishes: alarms, estimates, forecasts and service status (:mod:`~twin.online.events.schema` what they
share, :mod:`~twin.online.events.alarm`, :mod:`~twin.online.events.estimate`, :mod:`~twin.online.events.status`)."""

from twin.online.events.schema import (ALARM_KINDS, ALARM_LEVELS, EVENT_LEVELS, RIG_PATTERN, SERVICE_STATES,
                                       event_to_json, validate)
from twin.online.events.alarm import AlarmEvent, AlarmIdentity, format_alarm
from twin.online.events.estimate import EstimateEncoder, EstimateEvent, ParamEstimate, interval95
from twin.online.events.status import StatusEvent

__all__ = ["ALARM_KINDS", "ALARM_LEVELS", "EVENT_LEVELS", "SERVICE_STATES", "RIG_PATTERN", "AlarmEvent",
           "AlarmIdentity", "EstimateEncoder", "EstimateEvent", "ParamEstimate", "StatusEvent", "event_to_json",
           "format_alarm", "interval95", "validate"]
