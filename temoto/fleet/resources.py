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

import collections
import functools
import itertools
import logging
import math
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Final, final

from temoto.core.registrar import LoadContext, Resource, ResourceInfo, ResourceServer, Status
from temoto.core.registrar.messages import StatusUpdate
from temoto.errors import (
    NoProviderError,
    ResourceClosedError,
    ResourceError,
    TransportError,
    TransportTimeoutError,
)
from temoto.fleet._common import (
    CallQueue,
    Closing,
    check_name,
    check_seconds,
    decode_or_count,
    new,
)
from temoto.fleet._provider import Provider, remember
from temoto.fleet.resource_types import (
    ERROR,
    OK,
    RESOURCE_CHANNEL,
    RESOURCE_STATS,
    STATUSES,
    RemoteRequest,
    RemoteResponse,
    remote_error,
    remote_request,
    response_of,
)
from temoto.fleet.ris import REMOTE_SERVER, ResourceInfoSync, RobotInfo
from temoto.lcm_types import (
    resource_release_t,
    resource_request_t,
)
from temoto.transport import codec

if TYPE_CHECKING:
    from temoto.core.registrar import Registrar
    from temoto.transport.auth import FleetLink, Opened
    from temoto.transport.base import Subscription

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

_EARLY_PER_REF: Final = 16  # statuses kept for a reference whose reply has not arrived
_EARLY_REFS: Final = 1024
_CONFIRM_RETRY_S: Final = 0.002  # a status for a proxy still being stored: try again soon


# ================================================================================ state


@dataclass(slots=True, eq=False)
class _Call:
    """A request of this consumer waiting for its reply."""

    robot: str
    manager: str
    reply: Any = None
    lost: str | None = None


@dataclass(slots=True, eq=False)
class _Proxy:
    """A loaded proxy: a reference this robot holds on another robot."""

    robot: str
    manager: str
    reference_id: str
    local_id: str  # the proxy resource in the local registrar
    queue: list[tuple[Status, str]] = field(default_factory=list)
    confirmed: bool = False  # the local registrar has stored it (statuses can be delivered)
    retry_at: float = math.inf
    gone: bool = False


@dataclass(slots=True, eq=False)
class _Release:
    """A release of this consumer waiting for its acknowledgement."""

    msg: Any
    robot: str
    tries: int
    next_send: float


class _ProxyServer(ResourceServer[RemoteRequest, RemoteResponse]):
    """The ``"remote"`` server: its resources are references held on other robots."""

    name: ClassVar[str] = REMOTE_SERVER
    request_type: ClassVar[type[Any]] = RemoteRequest
    response_type: ClassVar[type[Any]] = RemoteResponse

    def __init__(self, owner: RemoteResources) -> None:
        self._owner = owner

    def on_load(self, request: RemoteRequest, ctx: LoadContext) -> RemoteResponse:
        return self._owner._load(request, ctx)

    def on_unload(self, request: RemoteRequest, response: RemoteResponse) -> None:
        self._owner._unload(request, response)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        # The remote reference outlived this registrar's process: give it back, and tell
        # the consumers that their link to it is gone.
        response: RemoteResponse = resource.response
        self._owner._release_remote(resource.request.robot, "", response.reference_id)
        return Status.FATAL, f"remote resource on robot '{response.robot}' lost on restart"


# ================================================================================ the service


@final
class RemoteResources(Closing):
    """Requests resources of other robots, and serves this robot's to them (thesis §7.2).

    It registers the ``"remote"`` proxy server on ``registrar``, subscribes to
    :data:`RESOURCE_CHANNEL` and to the RIS's robot events, and starts its threads.
    :meth:`close` stops them and releases the references held for remote consumers; the RIS,
    the fleet link and the transport stay the caller's to close (after this).

    Args:
        link: Sends and receives authenticated fleet messages.
        registrar: This robot's registrar (its name is this manager's name).
        ris: This robot's Resource Info Synchronizer (on the same registrar).
        resend_s: Period of request and release resends.
        timeout_s: How long a request waits for its reply.
        release_tries: How many times a release is sent without acknowledgement.
        workers: Threads serving remote requests and releases (loads may block).
        clock: Monotonic clock in seconds.

    Raises:
        ValueError: A bad duration or count, a RIS of another registrar, or a server named
            ``"remote"`` is registered already.
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
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if ris.manager != registrar.name:
            raise ValueError(f"the RIS serves registrar '{ris.manager}', not '{registrar.name}'")
        for what, count in (("release_tries", release_tries), ("workers", workers)):
            if isinstance(count, bool) or not isinstance(count, int) or count < 1:
                raise ValueError(f"{what} must be an int >= 1, got {count!r}")
        self._link = link
        self._registrar = registrar
        self._ris = ris
        self.manager = registrar.name
        self.resend_s = check_seconds("resend_s", resend_s)
        self.timeout_s = check_seconds("timeout_s", timeout_s)
        self.release_tries = release_tries
        self._clock = clock
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._wake = threading.Condition(self._lock)
        # Guarded by _lock.
        self._closed = False
        self._counts = dict.fromkeys(RESOURCE_STATS, 0)
        self._ids = itertools.count(1)
        self._boot = f"{round(time.time() * 1000):x}"
        self._waiting: dict[str, _Call] = {}
        self._given_up: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._proxies: dict[tuple[str, str], _Proxy] = {}
        self._early: dict[tuple[str, str], tuple[float, list[tuple[Status, str]]]] = {}
        self._releases: dict[str, _Release] = {}
        self._parked: dict[str, list[str]] = {}  # robot -> references to release when heard
        self._provider = Provider(self)
        registrar.register(_ProxyServer(self))
        self._calls = CallQueue("temoto-fleet-resources-calls", "a remote status delivery")
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
        state = "closed" if self._closed else "open"
        return f"<RemoteResources manager={self.manager!r} {state}>"

    @property
    def stats(self) -> dict[str, int]:
        """A copy of the counters, one per name in :data:`RESOURCE_STATS`."""
        with self._lock:
            return dict(self._counts)

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

    # --- consumer side: the proxy server's hooks (the loading / releasing thread) -------------

    def _load(self, request: RemoteRequest, ctx: LoadContext) -> RemoteResponse:
        robot = request.robot
        info = self._ris.robot_info(robot)
        if info is None:
            raise NoProviderError(
                f"robot '{robot}' is not known (no adverts heard from it)",
                server=request.server,
                robot=robot,
            )
        offered = info.servers.get(request.server)
        if offered is None:
            raise NoProviderError(
                f"robot '{robot}' does not offer server '{request.server}'",
                server=request.server,
                robot=robot,
            )
        wanted, has = request.request_type, offered.request_type
        if wanted and has and wanted != has:
            raise TypeError(
                f"server '{request.server}' of robot '{robot}' takes {has} requests, not {wanted}"
            )
        msg = new(resource_request_t)
        msg.provider, msg.consumer, msg.server = info.manager, self.manager, request.server
        msg.request, msg.client = request.request_json, ctx.resource_id
        msg.priority, msg.exclusive = request.priority, request.exclusive
        call = _Call(robot, info.manager)
        with self._lock:
            self._check_open()
            msg.request_id = f"{self.manager}/{self._boot}.{next(self._ids)}"
            self._waiting[msg.request_id] = call
        deadline = self._clock() + self.timeout_s
        try:
            reply = self._wait_reply(msg, call, deadline)
        finally:
            with self._lock:
                del self._waiting[msg.request_id]
                if call.reply is None:
                    remember(self._given_up, msg.request_id, None)
        if reply.code != OK:
            raise remote_error(
                reply.message or f"robot '{robot}' refused the request", reply.errors, robot
            )
        key = (info.manager, reply.reference_id)
        proxy = _Proxy(robot, info.manager, reply.reference_id, ctx.resource_id)
        with self._lock:
            early = self._early.pop(key, None)
            if early is not None:
                proxy.queue.extend(early[1])
            self._proxies[key] = proxy
            if proxy.queue:
                proxy.retry_at = self._clock()
                self._wake.notify()
        return RemoteResponse(robot, reply.reference_id, reply.resource_id, reply.response)

    def _wait_reply(self, msg: Any, call: _Call, deadline: float) -> Any:
        """Send the request until its reply comes; the reply, or raise."""
        while True:
            self._send(msg, "requests_sent")
            next_send = self._clock() + self.resend_s
            with self._lock:
                while True:
                    if call.reply is not None:
                        self._counts["replies_received"] += 1
                        return call.reply
                    if self._closed:
                        raise ResourceClosedError("the remote resources are closed")
                    if call.lost is not None:
                        raise TransportError(
                            f"robot '{call.robot}' was lost before it answered the request"
                            f" for server '{msg.server}': {call.lost}"
                        )
                    now = self._clock()
                    if now >= deadline:
                        self._counts["timeouts"] += 1
                        raise TransportTimeoutError(
                            f"robot '{call.robot}' did not answer the request for server"
                            f" '{msg.server}' within {self.timeout_s:g} s"
                        )
                    if now >= next_send:
                        break
                    self._changed.wait(min(next_send, deadline) - now)

    def _unload(self, request: RemoteRequest, response: RemoteResponse) -> None:
        manager = ""
        with self._lock:
            for key, proxy in list(self._proxies.items()):
                if proxy.reference_id == response.reference_id and proxy.robot == response.robot:
                    manager = proxy.manager
                    proxy.gone = True
                    del self._proxies[key]
        self._release_remote(request.robot, manager, response.reference_id)

    def _release_remote(self, robot: str, manager: str, reference_id: str) -> None:
        """Send a release (not locked); the timer resends it until acknowledged."""
        if not manager:
            info = self._ris.robot_info(robot)
            if info is None:  # e.g. restored before the robot was heard: when it is
                with self._lock:
                    self._parked.setdefault(robot, []).append(reference_id)
                return
            manager = info.manager
        msg = new(resource_release_t)
        msg.provider, msg.consumer, msg.reference_id = manager, self.manager, reference_id
        # A robot that is not heard gets one try: if it comes back, it sees us alive.
        tries = self.release_tries if self._ris.robot_info(robot) is not None else 1
        with self._lock:
            if self._closed:
                tries = 1
            msg.request_id = f"{self.manager}/{self._boot}.{next(self._ids)}"
            if tries > 1:
                self._releases[msg.request_id] = _Release(
                    msg, robot, tries - 1, self._clock() + self.resend_s
                )
                self._wake.notify()
        self._send(msg, "releases_sent")

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
        msg = decode_or_count(opened, handlers, self._counts, self._lock)
        if msg is None:
            return
        if not msg.provider or not msg.consumer:
            with self._lock:
                self._counts["unexpected"] += 1
            return
        handlers[opened.type](msg)

    def _on_request(self, msg: Any) -> None:
        if msg.provider == self.manager:  # else for another manager
            self._provider.on_request(msg)

    def _on_release(self, msg: Any) -> None:
        if msg.provider == self.manager:
            self._provider.on_release(msg)

    def _on_reply(self, msg: Any) -> None:
        if msg.consumer != self.manager:
            return
        late = robot = ""
        with self._lock:
            call = self._waiting.get(msg.request_id)
            if call is not None:
                if call.manager != msg.provider or msg.code not in (OK, ERROR):
                    self._counts["unexpected"] += 1
                elif call.reply is None:
                    call.reply = msg
                    self._changed.notify_all()
                else:
                    self._counts["duplicates"] += 1
                return
            release = self._releases.pop(msg.request_id, None)
            if release is not None:
                if msg.code != OK:
                    logger.warning("release on %r: %s", release.robot, msg.message)
                return
            if msg.request_id in self._given_up and msg.code == OK and msg.reference_id:
                del self._given_up[msg.request_id]
                late = msg.reference_id
                robot = next((r.robot for r in self._ris.robots() if r.manager == msg.provider), "")
            else:
                self._counts["duplicates"] += 1
        if late:  # the request timed out here but was served there: give it back
            self._release_remote(robot, msg.provider, late)

    def _on_status(self, msg: Any) -> None:
        if msg.consumer != self.manager:
            return
        status = STATUSES.get(msg.status)
        with self._lock:
            if self._closed:
                return
            if status is None or not msg.reference_id:
                self._counts["unexpected"] += 1
                return
            self._counts["statuses_received"] += 1
            key = (msg.provider, msg.reference_id)
            proxy = self._proxies.get(key)
            if proxy is None:
                self._keep_early(key, status, msg.message)
                return
            proxy.queue.append((status, f"robot '{proxy.robot}': {msg.message}"))
            flush = len(proxy.queue) == 1 and proxy.retry_at == math.inf
        if flush:
            self._calls.put(lambda: self._flush(proxy))

    def _keep_early(self, key: tuple[str, str], status: Status, message: str) -> None:
        """A status of a reference whose reply has not arrived (yet). Locked."""
        if not any(c.manager == key[0] for c in self._waiting.values()):
            self._counts["unexpected"] += 1  # nothing is being requested there
            return
        entry = self._early.get(key)
        if entry is None:
            if len(self._early) >= _EARLY_REFS:
                self._counts["unexpected"] += 1
                return
            entry = self._early[key] = (self._clock() + self.timeout_s, [])
            self._wake.notify()
        if len(entry[1]) < _EARLY_PER_REF:
            robot = next((c.robot for c in self._waiting.values() if c.manager == key[0]), "")
            entry[1].append((status, f"robot '{robot}': {message}"))

    # --- status delivery (the calls thread) ---------------------------------------------------

    def _flush(self, proxy: _Proxy) -> None:
        """Deliver a proxy's queued statuses once the local registrar has stored it."""
        if not proxy.confirmed:
            try:
                stored = bool(self._registrar.info(proxy.local_id).references)
            except ResourceError:  # the load was rolled back, or it is unloaded
                stored, proxy.gone = False, True
            with self._lock:
                if proxy.gone:
                    proxy.queue.clear()
                    proxy.retry_at = math.inf
                    return
                if not stored:  # on_load returned, the registrar is storing it: soon
                    proxy.retry_at = self._clock() + _CONFIRM_RETRY_S
                    self._wake.notify()
                    return
                proxy.confirmed = True
        with self._lock:
            items, proxy.queue = proxy.queue, []
            proxy.retry_at = math.inf
        for status, message in items:
            try:
                self._registrar.send_status(proxy.local_id, status, message)
            except ResourceError as err:
                logger.debug("status for %s not delivered: %s", proxy.local_id, err)

    # --- robots joining and leaving (the RIS's calls thread) ----------------------------------

    def _on_robot_lost(self, info: RobotInfo, reason: str) -> None:
        releases: list[str] = []
        flushes: list[_Proxy] = []
        with self._lock:
            if self._closed:
                return
            # provider side: what it held here is given back
            releases = self._provider.consumer_lost(info)
            self._counts["released_for_lost"] += len(releases)
            # consumer side: what it provided here has failed
            message = f"robot '{info.robot}' was lost: {reason}"
            for proxy in self._proxies.values():
                if proxy.manager == info.manager:
                    proxy.queue.append((Status.FATAL, message))
                    self._counts["lost_fatal"] += 1
                    flushes.append(proxy)
            for call in self._waiting.values():
                if call.manager == info.manager:
                    call.lost = reason
                    self._changed.notify_all()
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
            self._calls.put(functools.partial(self._flush, proxy))

    def _on_joined(self, info: RobotInfo) -> None:
        with self._lock:
            self._provider.consumer_joined(info)
            parked = self._parked.pop(info.robot, [])
        for reference_id in parked:
            self._release_remote(info.robot, info.manager, reference_id)

    # --- the timer thread ---------------------------------------------------------------------

    def _run_timer(self) -> None:
        """Resends releases, retries status deliveries, sweeps forgotten state."""
        while True:
            sends: list[Any] = []
            flushes: list[_Proxy] = []
            orphans: list[str] = []
            with self._lock:
                if self._closed:
                    return
                now = self._clock()
                wake = now + self._ris.period_s
                for request_id, release in list(self._releases.items()):
                    if now >= release.next_send:
                        sends.append(release.msg)
                        release.tries -= 1
                        release.next_send = now + self.resend_s
                        if release.tries <= 0:
                            del self._releases[request_id]
                            continue
                    wake = min(wake, release.next_send)
                for proxy in self._proxies.values():
                    if now >= proxy.retry_at:
                        proxy.retry_at = math.inf
                        flushes.append(proxy)
                    wake = min(wake, proxy.retry_at)
                for key, (until, _) in list(self._early.items()):
                    if now >= until:
                        del self._early[key]
                    else:
                        wake = min(wake, until)
                orphans = self._provider.sweep(now)
                self._counts["released_for_lost"] += len(orphans)
                if not (sends or flushes or orphans):
                    self._wake.wait(max(0.0, wake - now))
                    continue
            for msg in sends:
                self._send(msg, "releases_sent")
            for proxy in flushes:
                self._calls.put(functools.partial(self._flush, proxy))
            for ref in orphans:
                self._submit(functools.partial(self._provider.release_local, ref))

    # --- internals ----------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise ResourceClosedError("the remote resources are closed")

    def _send(self, msg: Any, counter: str) -> None:
        """Not locked: encode and send; a failure is counted and logged, never raised."""
        try:
            name, payload = codec.encode(msg)
            self._link.send(RESOURCE_CHANNEL, name, payload)
        except (TransportError, ValueError) as err:
            with self._lock:
                self._counts["send_errors"] += 1
            logger.warning("remote resources %r: cannot send: %s", self.manager, err)
            return
        with self._lock:
            self._counts[counter] += 1

    def close(self) -> None:
        """Stop: fail waiting loads, release what remote consumers hold here, join threads.

        Releases still waiting for their acknowledgement are sent once more. The ``"remote"``
        server stays registered (loads then fail with ``ResourceClosedError``). Idempotent.

        Raises:
            Nothing.
        """
        with self._lock:
            if self._closed:
                return
            self._closed = True
            pending = [r.msg for r in self._releases.values()]
            self._releases.clear()
            held = self._provider.take_all()
            self._changed.notify_all()
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
