"""The fleet layer: TeMoto instances (actors, robots) working together without a coordinator.

Layering (docs/fleet.md): ``temoto.fleet`` sits above :mod:`temoto.transport` (authenticated
envelopes on a transport) and implements the interfaces that :mod:`temoto.core` defines for
what lies outside one engine; ``temoto.core`` never imports it.

* :class:`FleetActorLink` is the engine's :class:`~temoto.core.remote.ActorLink` over a
  :class:`~temoto.transport.FleetLink`: the N-to-N handshake before a shared graph starts
  (thesis Algorithm 3), the notifications of finished actions with their acknowledgements,
  and the liveness of the other actors (channels :data:`HANDSHAKE_CHANNEL`,
  :data:`NOTIFY_CHANNEL`).
* :class:`ResourceInfoSync` (RIS) advertises what this robot's managers serve and tracks the
  other robots (:data:`RIS_CHANNEL`); :class:`RemoteResources` forwards requests for what only
  another robot serves through a local ``"remote"`` server and serves the requests of others
  (:data:`RESOURCE_CHANNEL`); see ``docs/ris.md``.
* :mod:`temoto.fleet.control`: remote graph commands and feedback (``temoto graph ...``).
* :mod:`temoto.fleet.service`: :class:`~temoto.fleet.service.ServiceCore`, the lock,
  counters, sending and clock that the parts of one service share (each service takes a
  :class:`temoto.clock.Clock`); :mod:`temoto.fleet.common`: helpers for code that speaks on
  the fleet link (message construction and decoding, argument checks, a call queue).

Importing this package opens nothing, starts no thread and does not import the ``lcm`` wheel.
"""

from __future__ import annotations

from temoto.fleet.actors import HANDSHAKE_CHANNEL, NOTIFY_CHANNEL, STATS, FleetActorLink
from temoto.fleet.resources import (
    RESOURCE_CHANNEL,
    RESOURCE_STATS,
    RemoteRequest,
    RemoteResources,
    RemoteResponse,
    remote_request,
    response_of,
)
from temoto.fleet.ris import RIS_CHANNEL, RIS_STATS, ResourceInfoSync, RobotInfo, ServerInfo

__all__ = [
    "HANDSHAKE_CHANNEL",
    "NOTIFY_CHANNEL",
    "RESOURCE_CHANNEL",
    "RESOURCE_STATS",
    "RIS_CHANNEL",
    "RIS_STATS",
    "STATS",
    "FleetActorLink",
    "RemoteRequest",
    "RemoteResources",
    "RemoteResponse",
    "ResourceInfoSync",
    "RobotInfo",
    "ServerInfo",
    "remote_request",
    "response_of",
]
