"""The fleet link: a :class:`~temoto.transport.auth.FleetAuth` on a transport (docs/fleet.md).

:class:`FleetLink` seals what it sends and opens what it receives with its ``FleetAuth``, and
carries a keyed fleet's hellos (docs/security.md) along with its own sends and receives. Kept
apart from :mod:`temoto.transport.auth`, which decides what a byte string means and never
touches a transport.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterable
from typing import final

from temoto.transport.auth import HELLO_CHANNEL, FleetAuth, Opened
from temoto.transport.base import LogLimiter, Subscription, Transport

__all__ = ["FleetLink"]

logger = logging.getLogger(__name__)

# wait_for_peers says hello again after this long without news, then twice as long, up to
# the maximum.
_HELLO_RETRY_S = 0.1
_HELLO_RETRY_MAX_S = 1.0

#: Hellos that may wait for the receive thread. A member that starts with N others gets a
#: hello from each of them at once, and LCM keeps 30 per subscription by default: with 50
#: processes most hellos (and the grants in them) were dropped, which made every member ask
#: for them again and again (docs/security.md).
HELLO_QUEUE = 1024


@final
class FleetLink:
    """Sends and receives authenticated fleet messages: a :class:`FleetAuth` on a transport.

    The link owns neither: close the transport yourself. A keyed link listens to
    :data:`HELLO_CHANNEL` from its construction and sends its first hello at once; the hellos
    (and the first messages, re-sent to each peer met in the first seconds) go out with the
    link's sends and receives.

    Args:
        transport: Where envelopes travel.
        auth: Seals outgoing and checks incoming envelopes.

    Raises:
        TransportError: If the transport is closed.
    """

    def __init__(self, transport: Transport, auth: FleetAuth) -> None:
        self.transport = transport
        self.auth = auth
        self._handler_errors = 0
        self._errors_lock = threading.Lock()
        self._log = LogLimiter()
        self._hellos: Subscription | None = None
        self._timer: threading.Timer | None = None
        self._drop_timer: threading.Timer | None = None
        self._timer_lock = threading.Lock()
        self._hello_seen = threading.Condition()
        if not auth.insecure:
            self._hellos = transport.subscribe(
                HELLO_CHANNEL, self._on_hello, queue_capacity=HELLO_QUEUE
            )
            self._flush()

    def _on_hello(self, channel: str, data: bytes) -> None:
        self.auth.open(channel, data)
        self._flush()
        self._summarise_drops()
        with self._hello_seen:
            self._hello_seen.notify_all()

    def wait_for_peers(self, names: Iterable[str], timeout: float) -> bool:
        """Wait until this member can open the messages of every named member.

        Sending needs no wait (what a peer could not open while the hellos crossed is re-sent
        to it); this is for callers that must know the keys are agreed, e.g. tests. Until
        they did, this member says hello again (after 0.1 s, then twice as long each time, up
        to 1 s): its first hello may have been lost, and a member that neither sends nor hears
        anything would never be answered; and each hello asks the peers whose grant is missing
        for it again (the grant may have been lost, and a quiet peer sends nothing that would
        show it).

        Args:
            names: The members.
            timeout: Seconds to wait at most.

        Returns:
            True when they all granted us their session (always True for insecure fleets).
        """
        wanted = set(names)
        if self.auth.insecure:
            return True
        deadline = time.monotonic() + timeout
        retry = _HELLO_RETRY_S
        while True:
            with self._hello_seen:
                self._hello_seen.wait_for(
                    lambda: wanted <= self.auth.peers,
                    max(0.0, min(retry, deadline - time.monotonic())),
                )
            if wanted <= self.auth.peers:
                return True
            if time.monotonic() >= deadline:
                return False
            # Nothing came: our hellos may have been lost (over Zenoh, every one published
            # before the router knew a subscriber), and a member that sends nothing and hears
            # nothing would wait forever. Say hello again, less often each time.
            self.auth.want_hello()
            self._flush()
            retry = min(retry * 2, _HELLO_RETRY_MAX_S)

    def _flush(self) -> None:
        """Publish what the auth wants sent (hellos, re-sent messages); never raises."""
        for channel, data in self.auth.take_outgoing():
            try:
                self.transport.publish(channel, data)
            except Exception as err:  # closed meanwhile: the peers hear us no more anyway
                logger.debug("fleet %r: could not publish on %r: %s", self.auth.fleet, channel, err)
                return
        due = self.auth.hello_due_in()
        if due is None:
            return
        with self._timer_lock:  # one short-lived thread sends a held-back hello when it is due
            if self._timer is not None and self._timer.is_alive():
                return
            self._timer = threading.Timer(due + 0.001, self._flush)
            self._timer.name = "temoto-fleet-hello"
            self._timer.daemon = True
            self._timer.start()

    def _summarise_drops(self) -> None:
        """Have the summary of drops held back written when it is due, more drops or not.

        A short-lived thread (``temoto-fleet-drops``, at most ``DROP_SUMMARY_S``, 1 s, long)
        writes it; before, it waited for the next drop after the interval, or the stop.
        """
        due = self.auth.drop_summary_due_in()
        if due is None:
            return
        with self._timer_lock:
            if self._drop_timer is not None and self._drop_timer.is_alive():
                return
            self._drop_timer = threading.Timer(due + 0.001, self.auth.log_drop_summary)
            self._drop_timer.name = "temoto-fleet-drops"
            self._drop_timer.daemon = True
            self._drop_timer.start()

    def __repr__(self) -> str:
        return f"<FleetLink {self.auth!r} on {self.transport!r}>"

    @property
    def stats(self) -> dict[str, int]:
        """The authentication counters (:attr:`FleetAuth.stats`) plus ``handler_error``."""
        stats = self.auth.stats
        stats["handler_error"] = self._handler_errors
        return stats

    def send(self, channel: str, type_name: str, payload: bytes) -> None:
        """Seal an inner message and publish it.

        Args:
            channel: The channel.
            type_name: The inner message's type name.
            payload: The inner message, LCM-encoded.

        Raises:
            ValueError: If the channel name is invalid.
            TypeError: If ``payload`` is not bytes.
            TransportError: If the transport is closed or sending failed.
        """
        data = self.auth.seal(channel, type_name, payload)
        self._flush()
        self.transport.publish(channel, data)

    def listen(
        self,
        channel: str,
        handler: Callable[[Opened], None],
        *,
        queue_capacity: int | None = None,
    ) -> Subscription:
        """Call ``handler`` on the receive thread with every envelope on ``channel`` that passes.

        Dropped envelopes are only counted (:attr:`stats`); what the handler raises is logged
        and counted as ``handler_error``.

        Args:
            channel: The channel.
            handler: Called with the opened envelope.
            queue_capacity: See :meth:`Transport.subscribe`.

        Returns:
            The transport subscription; unsubscribe it to stop listening.

        Raises:
            ValueError: If the channel name or the capacity is invalid.
            TransportError: If the transport is closed.
        """

        def on_data(rx_channel: str, data: bytes) -> None:
            opened = self.auth.open(rx_channel, data)
            if not self.auth.insecure:
                self._flush()
            if opened is None:
                self._summarise_drops()
                return
            try:
                handler(opened)
            except Exception:
                with self._errors_lock:
                    self._handler_errors += 1
                held = self._log.allow(rx_channel)
                if held is not None:
                    more = f" ({held} more since the last report)" if held else ""
                    logger.exception(
                        "fleet %r: handler %r of channel %r raised on a %r from %r%s",
                        self.auth.fleet,
                        handler,
                        rx_channel,
                        opened.type,
                        opened.sender,
                        more,
                    )

        return self.transport.subscribe(channel, on_data, queue_capacity=queue_capacity)
