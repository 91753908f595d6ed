"""LCM transport: one ``lcm.LCM`` handle and one thread (``temoto-lcm``) that dispatches.

The thread waits for LCM's file descriptor (and a wake-up pipe of ours) in ``poll``, then
dispatches what came with ``handle_timeout(0)``, until the transport is closed; handlers run
on it, and :meth:`LcmTransport.close` returns within about one timeout (plus the running
handler).

Threading rules of the Python LCM binding that shape this module (lcm-python/pylcm.c):

* ``publish`` releases the GIL and the C library locks it, so any thread may publish.
* ``subscribe`` is **not** safe while another thread dispatches: it registers its C callback
  with the library *before* it fills in the subscription's fields (the handler and the LCM
  object), and the receive thread, in ``handle_timeout`` without the GIL, may dispatch a
  message that arrived meanwhile to that half-made subscription and dereference NULL: a
  SIGSEGV (seen in 5 of about 1,000 ``temoto run`` processes at start-up under load). So
  every ``lc.subscribe`` runs on the receive thread, between two dispatches: a caller on
  another thread queues its subscription, wakes the thread through a pipe and waits until it
  is made (a handler subscribing runs it at once: it is on that thread already).
* ``unsubscribe`` drops the binding's reference to the handler at once, while the receive thread
  may already have picked that subscription for the message it is dispatching. So unsubscribing
  only marks our subscription inactive (no further handler call starts) and queues the LCM
  subscription; the receive thread removes it between two dispatches.

The ``lcm`` wheel is imported when a transport is created, never when this module is imported.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
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


@dataclass(eq=False)
class _Request:
    """A subscription waiting to be made on the receive thread."""

    sub: LcmSubscription
    on_message: Callable[[str, bytes], None]
    done: threading.Event = field(default_factory=threading.Event)
    error: BaseException | None = None


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
        handle_timeout_s: Longest wait of the receive thread in one ``poll`` (a subscription
            or :meth:`close` wakes it at once; this bounds the wait if that wake-up is lost).

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
        # Guarded by _mutex: the live subscriptions, those waiting for the receive thread to
        # remove them from LCM, and those waiting for it to make them.
        self._subs: list[LcmSubscription] = []
        self._released: list[LcmSubscription] = []
        self._requests: list[_Request] = []
        self._stop = threading.Event()
        # The receive thread waits in poll() for LCM's descriptor and this pipe: a byte in it
        # wakes the thread to make a subscription (or to stop) at once.
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
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

        if threading.current_thread() is self._thread:  # a handler subscribing: no race
            lc = self._lcm
            if lc is None or self.closed:
                raise TransportError("LcmTransport is closed")
            self._make(lc, sub, on_message)
            return sub
        request = _Request(sub, on_message)
        with self._mutex:
            if self._lcm is None or self.closed:
                raise TransportError("LcmTransport is closed")
            self._requests.append(request)
            self._wake()
        request.done.wait()  # set by the receive thread, also when it stops
        if request.error is not None:
            raise request.error
        return sub

    def _make(
        self, lc: _lcm.LCM, sub: LcmSubscription, on_message: Callable[[str, bytes], None]
    ) -> None:
        """Subscribe in LCM; on the receive thread only (module docstring)."""
        lcm_sub = lc.subscribe(sub.channel, on_message)
        if sub.queue_capacity is not None:
            lcm_sub.set_queue_capacity(sub.queue_capacity)
        with self._mutex:
            sub._lcm_sub = lcm_sub
            self._subs.append(sub)

    def _wake(self) -> None:
        """Wake the receive thread; ``_mutex`` held (the thread closes the pipe under it)."""
        if self._wake_w >= 0:
            with contextlib.suppress(BlockingIOError):  # full: a wake-up is pending anyway
                os.write(self._wake_w, b"\0")

    def _close(self) -> None:
        self._stop.set()
        with self._mutex:
            self._wake()
        if threading.current_thread() is not self._thread:
            self._thread.join()

    # --- internals ----------------------------------------------------------------------------

    def _release(self, sub: LcmSubscription) -> None:
        with self._mutex:
            if sub in self._subs:
                self._subs.remove(sub)
                self._released.append(sub)

    def _make_requested(self, lc: _lcm.LCM) -> None:
        """Make the subscriptions other threads asked for (on the receive thread)."""
        with self._mutex:
            requests, self._requests = self._requests, []
        for request in requests:
            try:
                self._make(lc, request.sub, request.on_message)
            except Exception as err:  # the caller raises it
                request.error = TransportError(
                    f"LCM subscribe to {request.sub.channel!r} failed: {err}"
                )
            request.done.set()

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
        fd = lc.fileno()
        timeout_s = self._timeout_ms / 1000
        poller = select.poll()  # not select(): a descriptor may be above FD_SETSIZE (1024)
        poller.register(fd, select.POLLIN)
        poller.register(self._wake_r, select.POLLIN)
        try:
            while not self._stop.is_set():
                self._unsubscribe_released(lc)
                self._make_requested(lc)
                try:
                    ready = {ready_fd for ready_fd, _ in poller.poll(self._timeout_ms)}
                    if self._wake_r in ready:
                        os.read(self._wake_r, 4096)
                    if fd in ready:
                        lc.handle_timeout(0)  # what came: no waiting in LCM
                except OSError as err:
                    # A socket error; wait one period so a persistent one does not spin.
                    logger.error("LCM receive on %r failed: %s", self.url, err)
                    self._stop.wait(timeout_s)
        finally:
            with self._mutex:
                for sub in self._subs:
                    sub.detach()
                self._released.extend(self._subs)
                self._subs.clear()
                self._lcm = None
                requests, self._requests = self._requests, []
            for request in requests:
                request.error = TransportError("LcmTransport is closed")
                request.done.set()
            self._unsubscribe_released(lc)
            with self._mutex:
                os.close(self._wake_r)
                os.close(self._wake_w)
                self._wake_r = self._wake_w = -1
