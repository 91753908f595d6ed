"""Recordings of a TeMoto process in MCAP, for Foxglove and for replay (``docs/recording.md``).

``--record FILE.mcap`` on ``temoto run``, ``temoto serve`` and the robot command makes a
:class:`Recorder`: graph runs and node transitions, action logs, the robot's telemetry and the
fleet's envelopes, one MCAP channel per stream, with Foxglove's well-known JSON schemas where
they fit (:mod:`temoto.record.schemas`). :func:`read_transitions` and :func:`read_messages`
read a recording back, finished or cut short.
"""

from __future__ import annotations

from temoto.record.reader import RecordedMessage, Transition, read_messages, read_transitions
from temoto.record.recorder import FLUSH_PERIOD_S, TELEMETRY_RATE_HZ, TOPICS, Recorder

__all__ = [
    "FLUSH_PERIOD_S",
    "TELEMETRY_RATE_HZ",
    "TOPICS",
    "RecordedMessage",
    "Recorder",
    "Transition",
    "read_messages",
    "read_transitions",
]
