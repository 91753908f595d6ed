"""The fleet layer: TeMoto instances (actors, robots) working together without a coordinator.

Layering (docs/fleet.md): ``temoto.fleet`` sits above :mod:`temoto.transport` (authenticated
envelopes on a transport) and implements the interfaces that :mod:`temoto.core` defines for
what lies outside one engine; ``temoto.core`` never imports it.

* :class:`FleetActorLink` is the engine's :class:`~temoto.core.remote.ActorLink` over a
  :class:`~temoto.transport.FleetLink`: the N-to-N handshake before a shared graph starts
  (thesis Algorithm 3), the notifications of finished actions with their acknowledgements,
  and the liveness of the other actors (channels :data:`HANDSHAKE_CHANNEL`,
  :data:`NOTIFY_CHANNEL`).

Importing this package opens nothing, starts no thread and does not import the ``lcm`` wheel.
"""

from __future__ import annotations

from temoto.fleet.actors import HANDSHAKE_CHANNEL, NOTIFY_CHANNEL, STATS, FleetActorLink

__all__ = ["HANDSHAKE_CHANNEL", "NOTIFY_CHANNEL", "STATS", "FleetActorLink"]
