"""The consumer side of remote resources: the ``"remote"`` proxy server and its requests.

Private to :mod:`temoto.fleet.resources` (``docs/ris.md`` has the protocol). A
:class:`Consumer` loads a proxy by asking the providing robot (a ``resource_request_t``
resent until its reply), re-sends the statuses of the remote reference on the proxy in the
local registrar, and releases it (a ``resource_release_t`` resent until acknowledged). It
shares the remote-resources service's :class:`~temoto.fleet.service.ServiceCore` (lock,
counters, clock) with the provider side and never touches that side; the service's timer
thread calls :meth:`Consumer.due`.
"""

from __future__ import annotations

import collections
import functools
import itertools
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Final

from temoto.core.registrar import LoadContext, ResourceInfo, ResourceServer, Status
from temoto.errors import (
    NoProviderError,
    ResourceClosedError,
    ResourceError,
    TransportError,
    TransportTimeoutError,
)
from temoto.fleet.common import CallQueue, new
from temoto.fleet.resource_types import (
    ERROR,
    OK,
    STATUSES,
    RemoteRequest,
    RemoteResponse,
    remember,
    remote_error,
)
from temoto.fleet.ris import REMOTE_SERVER, ResourceInfoSync, RobotInfo
from temoto.lcm_types import resource_release_t, resource_request_t

if TYPE_CHECKING:
    from temoto.core.registrar import Registrar
    from temoto.fleet.service import ServiceCore

__all__ = ["Consumer", "ProxyServer"]

logger = logging.getLogger(__name__)

_EARLY_PER_REF: Final = 16  # statuses kept for a reference whose reply has not arrived
_EARLY_REFS: Final = 1024
_CONFIRM_RETRY_S: Final = 0.002  # a status for a proxy still being stored: try again soon


@dataclass(slots=True, eq=False)
class _Call:
    """A request of this consumer waiting for its reply."""

    robot: str
    manager: str
    reply: Any = None
    lost: str | None = None


@dataclass(slots=True, eq=False)
class Proxy:
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


class ProxyServer(ResourceServer[RemoteRequest, RemoteResponse]):
    """The ``"remote"`` server: its resources are references held on other robots."""

    name: ClassVar[str] = REMOTE_SERVER
    request_type: ClassVar[type[Any]] = RemoteRequest
    response_type: ClassVar[type[Any]] = RemoteResponse

    def __init__(self, consumer: Consumer) -> None:
        self._consumer = consumer

    def on_load(self, request: RemoteRequest, ctx: LoadContext) -> RemoteResponse:
        return self._consumer.load(request, ctx)

    def on_unload(self, request: RemoteRequest, response: RemoteResponse) -> None:
        self._consumer.unload(request, response)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        # The remote reference outlived this registrar's process: give it back, and tell
        # the consumers that their link to it is gone.
        response: RemoteResponse = resource.response
        self._consumer.release_remote(resource.request.robot, "", response.reference_id)
        return Status.FATAL, f"remote resource on robot '{response.robot}' lost on restart"


class Consumer:
    """Requests, status delivery and releases of the references this robot holds elsewhere.

    Everything is guarded by the core's lock. ``send`` sends on the resource channel and
    logs a failure (never raises); ``calls`` runs status deliveries off the transport's
    thread; ``wake`` is the service timer's condition (a new deadline wakes it).

    Args:
        core: The service's lock, counters and clock.
        registrar: This robot's registrar.
        ris: This robot's Resource Info Synchronizer.
        send: ``send(msg, counter)`` on the resource channel.
        calls: The queue that delivers statuses.
        wake: The condition the service's timer waits on.
        resend_s: Period of request and release resends.
        timeout_s: How long a request waits for its reply.
        release_tries: How many times a release is sent without acknowledgement.
    """

    def __init__(
        self,
        core: ServiceCore,
        registrar: Registrar,
        ris: ResourceInfoSync,
        *,
        send: Callable[[Any, str], None],
        calls: CallQueue,
        wake: threading.Condition,
        resend_s: float,
        timeout_s: float,
        release_tries: int,
    ) -> None:
        self._core = core
        self._lock = core.lock
        self._registrar = registrar
        self._ris = ris
        self._send = send
        self._calls = calls
        self._wake = wake
        self._changed = core.condition()  # a reply came, or a robot was lost, or closing
        self.manager = registrar.name
        self.resend_s = resend_s
        self.timeout_s = timeout_s
        self.release_tries = release_tries
        # Guarded by the lock.
        self._ids = itertools.count(1)
        self._boot = f"{round(core.wall() * 1000):x}"
        self._waiting: dict[str, _Call] = {}
        self._given_up: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._proxies: dict[tuple[str, str], Proxy] = {}
        self._early: dict[tuple[str, str], tuple[float, list[tuple[Status, str]]]] = {}
        self._releases: dict[str, _Release] = {}
        self._parked: dict[str, list[str]] = {}  # robot -> references to release when heard

    # --- the proxy server's hooks (the loading / releasing thread) ----------------------------

    def load(self, request: RemoteRequest, ctx: LoadContext) -> RemoteResponse:
        """Ask the providing robot for the resource; the proxy's response, or raise."""
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
            if self._core.closed:
                raise ResourceClosedError("the remote resources are closed")
            msg.request_id = f"{self.manager}/{self._boot}.{next(self._ids)}"
            self._waiting[msg.request_id] = call
        deadline = self._core.now() + self.timeout_s
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
        proxy = Proxy(robot, info.manager, reply.reference_id, ctx.resource_id)
        with self._lock:
            early = self._early.pop(key, None)
            if early is not None:
                proxy.queue.extend(early[1])
            self._proxies[key] = proxy
            if proxy.queue:
                proxy.retry_at = self._core.now()
                self._wake.notify()
        return RemoteResponse(robot, reply.reference_id, reply.resource_id, reply.response)

    def _wait_reply(self, msg: Any, call: _Call, deadline: float) -> Any:
        """Send the request until its reply comes; the reply, or raise."""
        core = self._core
        while True:
            self._send(msg, "requests_sent")
            next_send = core.now() + self.resend_s
            with self._lock:
                while True:
                    if call.reply is not None:
                        core.count("replies_received")
                        return call.reply
                    if core.closed:
                        raise ResourceClosedError("the remote resources are closed")
                    if call.lost is not None:
                        raise TransportError(
                            f"robot '{call.robot}' was lost before it answered the request"
                            f" for server '{msg.server}': {call.lost}"
                        )
                    now = core.now()
                    if now >= deadline:
                        core.count("timeouts")
                        raise TransportTimeoutError(
                            f"robot '{call.robot}' did not answer the request for server"
                            f" '{msg.server}' within {self.timeout_s:g} s"
                        )
                    if now >= next_send:
                        break
                    core.wait(self._changed, min(next_send, deadline) - now)

    def unload(self, request: RemoteRequest, response: RemoteResponse) -> None:
        """The proxy is unloaded: release the remote reference."""
        manager = ""
        with self._lock:
            for key, proxy in list(self._proxies.items()):
                if proxy.reference_id == response.reference_id and proxy.robot == response.robot:
                    manager = proxy.manager
                    proxy.gone = True
                    del self._proxies[key]
        self.release_remote(request.robot, manager, response.reference_id)

    def release_remote(self, robot: str, manager: str, reference_id: str) -> None:
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
            if self._core.closed:
                tries = 1
            msg.request_id = f"{self.manager}/{self._boot}.{next(self._ids)}"
            if tries > 1:
                self._releases[msg.request_id] = _Release(
                    msg, robot, tries - 1, self._core.now() + self.resend_s
                )
                self._wake.notify()
        self._send(msg, "releases_sent")

    # --- receiving (the transport's thread) ---------------------------------------------------

    def on_reply(self, msg: Any) -> None:
        """A ``resource_reply_t`` for this manager: a request's reply or a release's ack."""
        late = robot = ""
        with self._lock:
            call = self._waiting.get(msg.request_id)
            if call is not None:
                if call.manager != msg.provider or msg.code not in (OK, ERROR):
                    self._core.count("unexpected")
                elif call.reply is None:
                    call.reply = msg
                    self._changed.notify_all()
                else:
                    self._core.count("duplicates")
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
                self._core.count("duplicates")
        if late:  # the request timed out here but was served there: give it back
            self.release_remote(robot, msg.provider, late)

    def on_status(self, msg: Any) -> None:
        """A ``resource_status_t`` for this manager: queue it for its proxy."""
        status = STATUSES.get(msg.status)
        with self._lock:
            if self._core.closed:
                return
            if status is None or not msg.reference_id:
                self._core.count("unexpected")
                return
            self._core.count("statuses_received")
            key = (msg.provider, msg.reference_id)
            proxy = self._proxies.get(key)
            if proxy is None:
                self._keep_early(key, status, msg.message)
                return
            proxy.queue.append((status, f"robot '{proxy.robot}': {msg.message}"))
            flush = len(proxy.queue) == 1 and proxy.retry_at == math.inf
        if flush:
            self._calls.put(lambda: self.flush(proxy))

    def _keep_early(self, key: tuple[str, str], status: Status, message: str) -> None:
        """A status of a reference whose reply has not arrived (yet). Locked."""
        if not any(c.manager == key[0] for c in self._waiting.values()):
            self._core.count("unexpected")  # nothing is being requested there
            return
        entry = self._early.get(key)
        if entry is None:
            if len(self._early) >= _EARLY_REFS:
                self._core.count("unexpected")
                return
            entry = self._early[key] = (self._core.now() + self.timeout_s, [])
            self._wake.notify()
        if len(entry[1]) < _EARLY_PER_REF:
            robot = next((c.robot for c in self._waiting.values() if c.manager == key[0]), "")
            entry[1].append((status, f"robot '{robot}': {message}"))

    # --- status delivery (the calls thread) ---------------------------------------------------

    def flush(self, proxy: Proxy) -> None:
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
                    proxy.retry_at = self._core.now() + _CONFIRM_RETRY_S
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

    # --- robots joining and leaving (lock held) -----------------------------------------------

    def provider_lost(self, info: RobotInfo, reason: str) -> list[Proxy]:
        """A providing robot was lost: its proxies fail (FATAL), its requests fail.

        Lock held. Returns the proxies whose statuses to deliver.
        """
        flushes: list[Proxy] = []
        message = f"robot '{info.robot}' was lost: {reason}"
        for proxy in self._proxies.values():
            if proxy.manager == info.manager:
                proxy.queue.append((Status.FATAL, message))
                self._core.count("lost_fatal")
                flushes.append(proxy)
        for call in self._waiting.values():
            if call.manager == info.manager:
                call.lost = reason
                self._changed.notify_all()
        return flushes

    def take_parked(self, robot: str) -> list[str]:
        """The references of ``robot`` to release now that it is heard. Lock held."""
        return self._parked.pop(robot, [])

    # --- the service's timer thread (lock held) -----------------------------------------------

    def due(self, now: float, wake: float) -> tuple[list[Any], list[Proxy], float]:
        """Releases to resend and proxies to flush now; forget expired early statuses.

        Lock held.

        Args:
            now: The clock's reading.
            wake: When the timer would wake otherwise.

        Returns:
            The release messages to send, the proxies to flush, and when to look next.
        """
        sends: list[Any] = []
        flushes: list[Proxy] = []
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
        return sends, flushes, wake

    def close(self) -> list[Any]:
        """Closing (lock held, ``core.closed`` set): wake the waiting loads.

        Returns:
            The releases still waiting for their acknowledgement (sent once more).
        """
        pending = [r.msg for r in self._releases.values()]
        self._releases.clear()
        self._changed.notify_all()
        return pending

    def flush_later(self, proxy: Proxy) -> None:
        """Queue a delivery of a proxy's statuses (not locked)."""
        self._calls.put(functools.partial(self.flush, proxy))
