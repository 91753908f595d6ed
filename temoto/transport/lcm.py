"""LCM transport: one ``lcm.LCM`` handle and one thread (``temoto-lcm``) that dispatches.

The thread loops on ``handle_timeout`` until the transport is closed, so handlers run on it and
:meth:`LcmTransport.close` returns within about one timeout (plus the running handler).

Threading rules of the Python LCM binding that shape this module (lcm-python/pylcm.c):

* ``publish`` releases the GIL and the C library locks it, so any thread may publish.
* ``subscribe`` from another thread is safe: the C library guards its handler lists.
* ``unsubscribe`` drops the binding's reference to the handler at once, while the receive thread
  may already have picked that subscription for the message it is dispatching. So unsubscribing
  only marks our subscription inactive (no further handler call starts) and queues the LCM
  subscription; the receive thread removes it between two ``handle_timeout`` calls.

The ``lcm`` wheel is imported when a transport is created, never when this module is imported.
"""

from __future__ import annotations

import logging
import threading
from typing import TYPE_CHECKING, final

from temoto.errors import TransportError
from temoto.transport.base import Handler, Subscription, Transport

if TYPE_CHECKING:
    import lcm as _lcm

__all__ = ["DEFAULT_LCM_URL", "LcmSubscription", "LcmTransport"]

logger = logging.getLogger(__name__)

#: LCM's default multicast group and port, kept on this host (``ttl=0``).
DEFAULT_LCM_URL = "udpm://239.255.76.67:7667?ttl=0"

_MULTICAST_HINT = (
    "; udpm:// needs a multicast route: on a host without a network, "
    "`ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo` gives one "
    "(https://lcm-proj.github.io/lcm/content/multicast-setup.html); "
    "the LCM library printed its reason on stderr"
)


@final
class LcmSubscription(Subscription):
    """A subscription of an :class:`LcmTransport`.

    Attributes:
        channel: The channel name.
        queue_capacity: LCM's per-subscription queue length, if it was set.
    """

    def __init__(
        self, transport: LcmTransport, channel: str, handler: Handler, queue_capacity: int | None
    ) -> None:
        super().__init__(channel, handler)
        self.queue_capacity = queue_capacity
        self._transport = transport
        self._lcm_sub: _lcm.LCMSubscription | None = None

    def _on_unsubscribe(self) -> None:
        self._transport._release(self)


@final
class LcmTransport(Transport):
    """A transport over LCM (multicast UDP by default).

    Args:
        url: The LCM provider URL, e.g. ``udpm://239.255.76.67:7667?ttl=1`` between robots or
            ``memq://`` in tests (delivers only within this one instance).
        handle_timeout_s: Longest wait of one ``handle_timeout`` call; bounds how long
            :meth:`close` waits for the receive thread.

    Raises:
        TransportError: If the ``lcm`` package is missing or LCM cannot open ``url`` (an
            unknown provider, or multicast without a route).
        ValueError: If ``handle_timeout_s`` is not positive.
    """

    def __init__(self, url: str = DEFAULT_LCM_URL, *, handle_timeout_s: float = 0.1) -> None:
        if handle_timeout_s <= 0:
            raise ValueError(f"handle_timeout_s must be positive, got {handle_timeout_s}")
        super().__init__()
        self.url = url
        self._timeout_ms = max(1, round(handle_timeout_s * 1000))
        try:
            import lcm
        except ImportError as err:
            raise TransportError(
                "the LCM transport needs the lcm package (pip install lcm)"
            ) from err
        try:
            self._lcm: lcm.LCM | None = lcm.LCM(url)
        except (RuntimeError, TypeError, ValueError) as err:
            hint = _MULTICAST_HINT if url.startswith("udpm") else ""
            raise TransportError(f"LCM cannot open {url!r}{hint}") from err
        self._mutex = threading.Lock()
        # Guarded by _mutex: the live subscriptions, and those waiting for the receive thread to
        # remove them from LCM.
        self._subs: list[LcmSubscription] = []
        self._released: list[LcmSubscription] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="temoto-lcm", daemon=True)
        self._thread.start()

    def __repr__(self) -> str:
        state = "closed" if self.closed else "open"
        return f"<LcmTransport {self.url!r} {state}>"

    # --- Transport hooks ----------------------------------------------------------------------

    def _publish(self, channel: str, data: bytes) -> None:
        lc = self._lcm
        if lc is None:
            raise TransportError("LcmTransport is closed")
        try:
            lc.publish(channel, data)
        except OSError as err:
            raise TransportError(f"LCM publish on {channel!r} failed: {err}") from err

    def _subscribe(
        self, channel: str, handler: Handler, queue_capacity: int | None
    ) -> LcmSubscription:
        sub = LcmSubscription(self, channel, handler, queue_capacity)

        def on_message(rx_channel: str, data: bytes) -> None:
            # LCM matches the channel as a regular expression; only '.' can widen it here.
            if rx_channel == channel:
                self._deliver(sub, rx_channel, data)

        with self._mutex:
            lc = self._lcm
            if lc is None or self.closed:
                raise TransportError("LcmTransport is closed")
            lcm_sub = lc.subscribe(channel, on_message)
            if queue_capacity is not None:
                lcm_sub.set_queue_capacity(queue_capacity)
            sub._lcm_sub = lcm_sub
            self._subs.append(sub)
        return sub

    def _close(self) -> None:
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join()

    # --- internals ----------------------------------------------------------------------------

    def _release(self, sub: LcmSubscription) -> None:
        with self._mutex:
            if sub in self._subs:
                self._subs.remove(sub)
                self._released.append(sub)

    def _unsubscribe_released(self, lc: _lcm.LCM) -> None:
        with self._mutex:
            released, self._released = self._released, []
        for sub in released:
            if sub._lcm_sub is not None:
                lc.unsubscribe(sub._lcm_sub)
                sub._lcm_sub = None

    def _run(self) -> None:
        lc = self._lcm
        assert lc is not None
        try:
            while not self._stop.is_set():
                self._unsubscribe_released(lc)
                try:
                    lc.handle_timeout(self._timeout_ms)
                except OSError as err:
                    # A socket error; wait one period so a persistent one does not spin.
                    logger.error("LCM receive on %r failed: %s", self.url, err)
                    self._stop.wait(self._timeout_ms / 1000)
        finally:
            with self._mutex:
                for sub in self._subs:
                    sub._active = False
                self._released.extend(self._subs)
                self._subs.clear()
                self._lcm = None
            self._unsubscribe_released(lc)
