"""Messaging between TeMoto instances: transports, and the authentication of fleet envelopes.

Layering (docs/fleet.md): ``temoto.transport`` sits below ``temoto.fleet`` and imports only
:mod:`temoto.errors` and the generated :mod:`temoto.lcm_types` (and ``cryptography`` and PyYAML,
when a keyed fleet or a roster needs them); ``temoto.core`` never imports it.

* :class:`Transport` moves bytes on named channels: :class:`LcmTransport` over LCM (multicast
  UDP between robots on one segment), :class:`ZenohTransport` over Zenoh (peers, or clients
  through routers, across subnets; docs/zenoh.md), :class:`InProcessTransport` between
  instances in one process (tests). :func:`open_transport` picks one from a URL.
* :class:`FleetAuth` seals and checks the envelopes every fleet message travels in (sessions
  per boot, ChaCha20-Poly1305, replay window, drop counters; docs/security.md);
  :class:`FleetLink` runs it on a transport and its hellos. Identities and the roster (a key
  per member, permissions): :mod:`temoto.transport.identity`.
* :mod:`temoto.transport.codec` encodes and decodes the inner messages.

Importing this package opens nothing and imports neither the ``lcm`` nor the ``zenoh`` wheel.
"""

from __future__ import annotations

from temoto.errors import TransportError
from temoto.transport.auth import (
    DROP_REASONS,
    KEY_ENV,
    FleetAuth,
    Opened,
    key_from_env,
    key_from_text,
)
from temoto.transport.base import Handler, Subscription, Transport, check_channel
from temoto.transport.inprocess import InProcessTransport
from temoto.transport.lcm import DEFAULT_LCM_URL, LcmTransport
from temoto.transport.link import FleetLink
from temoto.transport.zenoh import ZENOH_SCHEME, ZenohTransport

__all__ = [
    "DEFAULT_LCM_URL",
    "DROP_REASONS",
    "KEY_ENV",
    "ZENOH_SCHEME",
    "FleetAuth",
    "FleetLink",
    "Handler",
    "InProcessTransport",
    "LcmTransport",
    "Opened",
    "Subscription",
    "Transport",
    "ZenohTransport",
    "check_channel",
    "key_from_env",
    "key_from_text",
    "open_transport",
]

#: URL scheme of :class:`InProcessTransport`: ``inproc://<bus>``.
INPROC_SCHEME = "inproc://"


def open_transport(url: str = DEFAULT_LCM_URL) -> Transport:
    """Open a transport from a URL.

    Args:
        url: ``inproc://<bus>`` for an :class:`InProcessTransport` on that bus (``default``
            when empty); ``zenoh:...`` for a :class:`ZenohTransport` (see
            :func:`temoto.transport.zenoh.parse_zenoh_url`: ``zenoh:tcp/HOST:7447`` is a
            client of that router); anything else is an LCM provider URL for
            :class:`LcmTransport` (``udpm://239.255.76.67:7667?ttl=1``, ``memq://``, ...).

    Returns:
        The open transport; close it when done.

    Raises:
        TransportError: If LCM or Zenoh cannot open the URL, or a ``zenoh:`` URL is
            malformed (the message names the part at fault).
    """
    if url.startswith(INPROC_SCHEME):
        return InProcessTransport(url[len(INPROC_SCHEME) :] or "default")
    if url.startswith(ZENOH_SCHEME):
        try:
            return ZenohTransport(url)
        except ValueError as err:
            raise TransportError(str(err)) from err
    return LcmTransport(url)
