"""Remote resources: a registrar call served by another robot's registrar (thesis §7.2).

``docs/ris.md`` describes the protocol. In short, on the channel :data:`RESOURCE_CHANNEL`:

* **Consumer side.** :class:`RemoteResources` registers a proxy server named ``"remote"`` on
  the local registrar. Its request, :class:`RemoteRequest`, names a robot, a server there and
  the request as JSON; so reference counting, deduplication and dependencies of remote
  resources are the local registrar's, exactly as for local ones (two equal requests share
  one proxy, hence one remote reference; a proxy loaded inside another resource's ``on_load``
  is its dependency and is released in cascade). The proxy's load sends a
  ``resource_request_t`` to the robot's manager, re-sent every ``resend_s`` with the same
  ``request_id`` until the ``resource_reply_t`` arrives or ``timeout_s`` passes. Status
  reports (``resource_status_t``) of the remote reference are re-sent locally with
  ``send_status`` on the proxy, so every local consumer and dependent hears them. Unloading the
  proxy sends a ``resource_release_t``, re-sent until the provider acknowledges it (a
  ``resource_reply_t`` with the release's ``request_id``) or ``release_tries`` sends were made.
  A provider robot that the RIS reports lost makes every proxy of it ``FATAL``.
* **Provider side.** A ``resource_request_t`` addressed to this manager is served on a worker
  thread with ``registrar.call``; the reply (reference id, resource id, response as JSON, or an
  ERROR with the error chain) is remembered, so a resent request gets the same reply and never
  a second reference. Status updates of the reference go to the consumer as
  ``resource_status_t``. ``resource_release_t`` releases it (idempotent). When the RIS reports a
  consumer robot lost, every reference held for it is released (its processes are stopped).

Bad messages (undecodable, wrong type, empty ids, an unknown status) are dropped and counted
in :attr:`RemoteResources.stats`, never raised.
"""

from __future__ import annotations

import functools
import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, final

from temoto.core.registrar import Resource
from temoto.core.registrar.messages import StatusUpdate
from temoto.errors import NoProviderError, TransportError
from temoto.fleet._consumer import Consumer, Proxy, ProxyServer
from temoto.fleet._provider import Provider
from temoto.fleet.common import CallQueue, Closing, check_name, check_seconds
from temoto.fleet.resource_types import (
    RESOURCE_CHANNEL,
    RESOURCE_STATS,
    RemoteRequest,
    RemoteResponse,
    remote_request,
    response_of,
)
from temoto.fleet.ris import REMOTE_SERVER, ResourceInfoSync, RobotInfo
from temoto.fleet.service import ServiceCore

if TYPE_CHECKING:
    from temoto.clock import Clock
    from temoto.core.registrar import Registrar
    from temoto.transport.auth import Opened
    from temoto.transport.base import Subscription
    from temoto.transport.link import FleetLink

__all__ = [
    "RESOURCE_CHANNEL",
    "RESOURCE_STATS",
    "RemoteRequest",
    "RemoteResources",
    "RemoteResponse",
    "remote_request",
    "response_of",
]

logger = logging.getLogger(__name__)


@final
class RemoteResources(Closing):
    """Requests resources of other robots, and serves this robot's to them (thesis §7.2).

    It registers the ``"remote"`` proxy server on ``registrar``, subscribes to
    :data:`RESOURCE_CHANNEL` and to the RIS's robot events, and starts its threads.
    :meth:`close` stops them and releases the references held for remote consumers; the RIS,
    the fleet link and the transport stay the caller's to close (after this).

    The work is done by two parts that share one :class:`~temoto.fleet.service.ServiceCore`
    (lock, counters, clock): the consumer side (``temoto.fleet._consumer``: the proxy server,
    requests, status delivery, releases) and the provider side (``temoto.fleet._provider``).
    This object routes the messages of the channel and the RIS's robot events to them, and
    runs the timer thread that resends releases and sweeps forgotten state.

    Args:
        link: Sends and receives authenticated fleet messages.
        registrar: This robot's registrar (its name is this manager's name).
        ris: This robot's Resource Info Synchronizer (on the same registrar).
        resend_s: Period of request and release resends.
        timeout_s: How long a request waits for its reply.
        release_tries: How many times a release is sent without acknowledgement.
        workers: Threads serving remote requests and releases (loads may block).
        clock: Where time is read (default: :class:`~temoto.clock.MonotonicClock`).

    Raises:
        ValueError: A bad duration or count, a RIS of another registrar, or a server named
            ``"remote"`` is registered already.
        TypeError: If ``clock`` is not a :class:`~temoto.clock.Clock`.
        TransportError: If the link's transport is closed.
    """

    def __init__(
        self,
        link: FleetLink,
        registrar: Registrar,
        ris: ResourceInfoSync,
        *,
        resend_s: float = 0.1,
        timeout_s: float = 10.0,
        release_tries: int = 10,
        workers: int = 4,
        clock: Clock | None = None,
    ) -> None:
        if ris.manager != registrar.name:
            raise ValueError(f"the RIS serves registrar '{ris.manager}', not '{registrar.name}'")
        for what, count in (("release_tries", release_tries), ("workers", workers)):
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise ValueError(f"{what} must be an int >= 1, got {count!r}")
        self._core = core = ServiceCore(link, RESOURCE_STATS, clock)
        self._registrar = registrar
        self._ris = ris
        self.manager = registrar.name
        self.resend_s = check_seconds("resend_s", resend_s)
        self.timeout_s = check_seconds("timeout_s", timeout_s)
        self.release_tries = release_tries
        self._lock = core.lock
        self._wake = core.condition()  # the timer's: a new deadline, or closing
        self._calls = CallQueue("temoto-fleet-resources-calls", "a remote status delivery")
        self._consumer = Consumer(
            core,
            registrar,
            ris,
            send=self._send,
            calls=self._calls,
            wake=self._wake,
            resend_s=self.resend_s,
            timeout_s=self.timeout_s,
            release_tries=release_tries,
        )
        self._provider = Provider(core, registrar, ris, send=self._send, submit=self._submit)
        try:
            registrar.register(ProxyServer(self._consumer))
        except BaseException:
            self._calls.close()
            raise
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="temoto-fleet-resources-work")
        self._sub: Subscription | None = None
        try:
            self._sub = link.listen(RESOURCE_CHANNEL, self._on_message)
        except BaseException:
            self._calls.close()
            self._pool.shutdown()
            raise
        self._cancel_ris = ris.subscribe(on_lost=self._on_robot_lost, on_joined=self._on_joined)
        self._timer = threading.Thread(
            target=self._run_timer, name="temoto-fleet-resources", daemon=True
        )
        self._timer.start()

    def __repr__(self) -> str:
        state = "closed" if self._core.closed else "open"
        return f"<RemoteResources manager={self.manager!r} {state}>"

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the counters, one per name in :data:`RESOURCE_STATS`."""
        return self._core.stats()

    def held(self) -> dict[str, str]:
        """The references this provider holds for remote consumers.

        Returns:
            Local reference id to the consumer (manager) it is held for.
        """
        return self._provider.held()

    # --- consumer API -------------------------------------------------------------------------

    def choose(self, server: str, robot: str | None = None) -> str | None:
        """Which robot serves a request: None for this robot's registrar, else a robot name.

        Args:
            server: The server's name.
            robot: A robot to use, or None for this robot if it has the server, else the
                first robot (by name) that advertises it.

        Returns:
            None for local, or the providing robot.

        Raises:
            NoProviderError: No robot (the named one, or any) offers the server.
        """
        check_name("server", server)
        local = server != REMOTE_SERVER and server in self._registrar.servers()
        if robot is None or robot == self._ris.robot:
            if local:
                return None
            if robot is not None:
                raise NoProviderError(
                    f"this robot ('{robot}') has no server '{server}'", server=server, robot=robot
                )
            providers = self._ris.providers(server)
            if not providers:
                heard = ", ".join(f"'{r.robot}'" for r in self._ris.robots()) or "none"
                raise NoProviderError(
                    f"no robot offers server '{server}' (robots heard: {heard})", server=server
                )
            return providers[0]
        info = self._ris.robot_info(robot)
        if info is None:
            raise NoProviderError(
                f"robot '{robot}' is not known (no adverts heard from it)",
                server=server,
                robot=robot,
            )
        if server not in info.servers:
            offered = ", ".join(f"'{s}'" for s in sorted(info.servers)) or "none"
            raise NoProviderError(
                f"robot '{robot}' does not offer server '{server}' (it offers: {offered})",
                server=server,
                robot=robot,
            )
        return robot

    def remote_request(self, server: str, request: Any, robot: str | None = None) -> RemoteRequest:
        """The ``"remote"`` request for ``server`` on ``robot`` (or the first that offers it).

        Args:
            server: The server's name.
            request: Its request.
            robot: The providing robot, or None for the first (by name) that advertises it.

        Returns:
            The remote request.

        Raises:
            NoProviderError: No other robot (the named one, or any) offers the server.
            TypeError: If the request cannot be serialised.
        """
        if robot is None:
            providers = self._ris.providers(server)
            if not providers:
                raise NoProviderError(f"no other robot offers server '{server}'", server=server)
            robot = providers[0]
        target = self.choose(server, robot)
        assert target is not None
        return RemoteRequest.of(target, server, request)

    def request(
        self,
        server: str,
        request: Any,
        *,
        robot: str | None = None,
        client: str = "",
        priority: int = 0,
        exclusive: bool = False,
        on_status: Callable[[StatusUpdate], None] | None = None,
    ) -> Resource[Any]:
        """Request a resource here or on another robot, through the local registrar.

        Without ``robot``, the local registrar serves it if it has the server, else the first
        robot (by name) that advertises it. Called inside a server's ``on_load``, the
        reference is a dependency of the resource being loaded, as with ``registrar.call``.
        :func:`response_of` gets the server's response from the result either way.

        Args:
            server: The server's name.
            request: Its request.
            robot: The providing robot, or None to choose (see above).
            client: The consumer's name.
            priority: Priority of the reference (on the providing robot too).
            exclusive: Want the resource alone (on the providing robot too).
            on_status: Called with every status update of the reference.

        Returns:
            The local reference (to the resource, or to its ``"remote"`` proxy).

        Raises:
            NoProviderError: No robot offers the server.
            ResourceLoadError: The provider refused or failed (the message includes its
                message), or did not answer within ``timeout_s``.
            ResourceError: Everything ``Registrar.call`` raises.
        """
        target = self.choose(server, robot)
        if target is None:
            return self._registrar.call(
                server,
                request,
                client=client,
                priority=priority,
                exclusive=exclusive,
                on_status=on_status,
            )
        return self._registrar.call(
            REMOTE_SERVER,
            RemoteRequest.of(target, server, request, priority=priority, exclusive=exclusive),
            client=client,
            priority=priority,
            exclusive=exclusive,
            on_status=on_status,
        )

    # --- provider jobs ------------------------------------------------------------------------

    def _submit(self, job: Callable[[], None]) -> None:
        """Run a provider job on a worker (not locked); dropped once closed."""
        try:
            self._pool.submit(job)
        except RuntimeError:  # shut down
            logger.debug("remote resources closed: a job was dropped")

    # --- receiving (the transport's thread) ---------------------------------------------------

    def _on_message(self, opened: Opened) -> None:
        handlers = {
            "resource_request_t": self._on_request,
            "resource_reply_t": self._on_reply,
            "resource_release_t": self._on_release,
            "resource_status_t": self._on_status,
        }
        msg = self._core.decode(opened, handlers)
        if msg is None:
            return
        if not msg.provider or not msg.consumer:
            with self._lock:
                self._core.count("unexpected")
            return
        if not self._from_its_manager(opened, msg):
            return
        handlers[opened.type](msg, opened.sender)

    def _from_its_manager(self, opened: Opened, msg: Any) -> bool:
        """Whether the manager a message comes from belongs to its authenticated sender.

        A request or release comes from its ``consumer``, a reply or status from its
        ``provider``: a manager the RIS knows as another robot's (or as ours), or a sender
        the RIS knows with another manager, is a member speaking as another (dropped, counted
        ``impostor``, logged; docs/security.md). A manager and a sender the RIS has not heard
        of yet (its first advert is on its way) cannot be checked and are let through.
        """
        requests = ("resource_request_t", "resource_release_t")
        field = "consumer" if opened.type in requests else "provider"
        manager: str = getattr(msg, field)
        if manager == self.manager:
            owner: str | None = self._ris.robot
        else:
            robots = self._ris.robots()
            owner = next((r.robot for r in robots if r.manager == manager), None)
            if owner is None:
                known = next((r for r in robots if r.robot == opened.sender), None)
                if known is None or known.manager == manager:
                    return True
                owner = f"not {opened.sender!r} (whose manager is {known.manager!r})"
        return self._core.speaks_as(opened, owner, f"{field} {manager!r} (of robot)")

    def _on_request(self, msg: Any, sender: str) -> None:
        if msg.provider == self.manager:  # else for another manager
            self._provider.on_request(msg, sender)

    def _on_release(self, msg: Any, sender: str = "") -> None:
        if msg.provider == self.manager:
            self._provider.on_release(msg)

    def _on_reply(self, msg: Any, sender: str = "") -> None:
        if msg.consumer == self.manager:
            self._consumer.on_reply(msg)

    def _on_status(self, msg: Any, sender: str = "") -> None:
        if msg.consumer == self.manager:
            self._consumer.on_status(msg)

    # --- robots joining and leaving (the RIS's calls thread) ----------------------------------

    def _on_robot_lost(self, info: RobotInfo, reason: str) -> None:
        with self._lock:
            if self._core.closed:
                return
            # provider side: what it held here is given back
            releases = self._provider.consumer_lost(info)
            self._core.count("released_for_lost", len(releases))
            # consumer side: what it provided here has failed
            flushes = self._consumer.provider_lost(info, reason)
        if releases:
            logger.warning(
                "robot '%s' was lost (%s): releasing the %d references held for it",
                info.robot,
                reason,
                len(releases),
            )
        for ref in releases:
            self._submit(functools.partial(self._provider.release_local, ref))
        for proxy in flushes:
            self._consumer.flush_later(proxy)

    def _on_joined(self, info: RobotInfo) -> None:
        with self._lock:
            self._provider.consumer_joined(info)
            parked = self._consumer.take_parked(info.robot)
        for reference_id in parked:
            self._consumer.release_remote(info.robot, info.manager, reference_id)

    # --- the timer thread ---------------------------------------------------------------------

    def _run_timer(self) -> None:
        """Resends releases, retries status deliveries, sweeps forgotten state."""
        core = self._core
        while True:
            sends: list[Any] = []
            flushes: list[Proxy] = []
            orphans: list[str] = []
            with self._lock:
                if core.closed:
                    return
                now = core.now()
                sends, flushes, wake = self._consumer.due(now, now + self._ris.period_s)
                orphans = self._provider.sweep(now)
                core.count("released_for_lost", len(orphans))
                if not (sends or flushes or orphans):
                    core.wait(self._wake, max(0.0, wake - now))
                    continue
            for msg in sends:
                self._send(msg, "releases_sent")
            for proxy in flushes:
                self._consumer.flush_later(proxy)
            for ref in orphans:
                self._submit(functools.partial(self._provider.release_local, ref))

    # --- internals ----------------------------------------------------------------------------

    def _send(self, msg: Any, counter: str) -> None:
        """Not locked: encode and send; a failure is counted and logged, never raised."""
        try:
            self._core.send(RESOURCE_CHANNEL, msg, counter)
        except (TransportError, ValueError) as err:
            logger.warning("remote resources %r: cannot send: %s", self.manager, err)

    def close(self) -> None:
        """Stop: fail waiting loads, release what remote consumers hold here, join threads.

        Releases still waiting for their acknowledgement are sent once more. The ``"remote"``
        server stays registered (loads then fail with ``ResourceClosedError``). Idempotent.
        """
        with self._lock:
            if self._core.closed:
                return
            self._core.closed = True
            pending = self._consumer.close()
            held = self._provider.take_all()
            self._wake.notify()
        self._cancel_ris()
        if self._sub is not None:
            self._sub.unsubscribe()
        for msg in pending:
            self._send(msg, "releases_sent")
        self._timer.join()
        self._calls.close()
        self._pool.shutdown(wait=True)  # queued releases still run: processes get stopped
        for ref in held:
            self._provider.release_local(ref)
