"""The provider side of remote resources: serving other robots' requests with the registrar.

Private to :mod:`temoto.fleet.resources`. Its :class:`~temoto.fleet.resources.RemoteResources`
owns one :class:`Provider` and one :class:`~temoto.fleet._consumer.Consumer`; the two share the
service's :class:`~temoto.fleet.service.ServiceCore` (lock, counters, clock) and nothing else:
the provider is handed the functions that send on the resource channel and run a job on the
service's worker pool.
"""

from __future__ import annotations

import collections
import functools
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from temoto.core.registrar.messages import StatusUpdate, canonical_json, from_plain
from temoto.errors import ResourceError
from temoto.fleet.common import new
from temoto.fleet.resource_types import ERROR, OK, STATUS_CODES, records_json, remember
from temoto.fleet.ris import REMOTE_SERVER
from temoto.lcm_types import resource_reply_t, resource_status_t

if TYPE_CHECKING:
    from temoto.core.registrar import Registrar
    from temoto.fleet.ris import ResourceInfoSync, RobotInfo
    from temoto.fleet.service import ServiceCore

__all__ = ["Provider"]

logger = logging.getLogger(__name__)


@dataclass(slots=True, eq=False)
class _Served:
    """A request this provider took, with its reply once there is one."""

    consumer: str
    reply: Any = None


@dataclass(slots=True, eq=False)
class _Held:
    """A reference this provider holds for a remote consumer."""

    consumer: str
    request_id: str
    since: float


class Provider:
    """Serves ``resource_request_t`` and ``resource_release_t`` addressed to this manager.

    Requests are served on the service's worker pool (a load may block); a resent request
    gets the remembered reply; status updates of the references go to their consumers;
    references of a consumer robot that is lost, or that the RIS never heard of for
    ``missed`` periods, are released. Everything is guarded by the core's lock.

    Args:
        core: The service's lock, counters and clock.
        registrar: This robot's registrar (its name is this manager's name).
        ris: This robot's Resource Info Synchronizer.
        send: ``send(msg, counter)`` on the resource channel (logs a failure, never raises).
        submit: Runs a job on the service's worker pool (drops it once closed).
    """

    def __init__(
        self,
        core: ServiceCore,
        registrar: Registrar,
        ris: ResourceInfoSync,
        *,
        send: Callable[[Any, str], None],
        submit: Callable[[Callable[[], None]], None],
    ) -> None:
        self._core = core
        self._lock = core.lock
        self._registrar = registrar
        self._ris = ris
        self._send = send
        self._submit = submit
        self.manager = registrar.name
        # Guarded by the lock.
        self._served: collections.OrderedDict[str, _Served] = collections.OrderedDict()
        self._held: dict[str, _Held] = {}
        self._released: collections.OrderedDict[str, None] = collections.OrderedDict()
        self._replies: collections.OrderedDict[str, Any] = collections.OrderedDict()
        self._lost: set[str] = set()  # consumer managers lost and not heard since

    def held(self) -> dict[str, str]:
        """Local reference id to the consumer (manager) it is held for (lock not held)."""
        with self._lock:
            return {ref: h.consumer for ref, h in self._held.items()}

    # --- receiving (the transport's thread) ---------------------------------------------------

    def on_request(self, msg: Any, sender: str = "") -> None:
        """A ``resource_request_t`` for this manager: answer from memory, or serve it.

        Args:
            msg: The request.
            sender: Its authenticated sender (``Opened.sender``), whom the fleet policy's
                ``resource.request`` permission is checked for.
        """
        send: Any = None
        with self._lock:
            if self._core.closed:
                return
            if not msg.request_id or not msg.server or msg.consumer == self.manager:
                self._core.count("unexpected")
                return
            self._core.count("requests_received")
            served = self._served.get(msg.request_id)
            if served is not None:
                if served.consumer != msg.consumer:
                    self._core.count("unexpected")
                    return
                self._core.count("duplicates")
                send = served.reply  # None while it loads: the reply will come
            else:
                remember(self._served, msg.request_id, _Served(msg.consumer))
        if send is not None:
            self._send(send, "replies_sent")
        elif served is None:
            self._submit(functools.partial(self._serve, msg, sender))

    def on_release(self, msg: Any) -> None:
        """A ``resource_release_t`` for this manager: acknowledge, then release (idempotent)."""
        reply = new(resource_reply_t)
        reply.request_id, reply.provider = msg.request_id, self.manager
        reply.consumer, reply.reference_id = msg.consumer, msg.reference_id
        release = ""
        with self._lock:
            if self._core.closed:
                return
            if not msg.request_id or not msg.reference_id:
                self._core.count("unexpected")
                return
            self._core.count("releases_received")
            cached = self._replies.get(msg.request_id)
            if cached is not None:
                self._core.count("duplicates")
                reply = cached
            else:
                held = self._held.get(msg.reference_id)
                if held is not None and held.consumer == msg.consumer:
                    del self._held[msg.reference_id]
                    remember(self._released, msg.reference_id, None)
                    release = msg.reference_id
                    reply.code, reply.message = OK, "released"
                elif held is None and msg.reference_id in self._released:
                    reply.code, reply.message = OK, "already released"
                else:
                    reply.code = ERROR
                    reply.message = f"no reference {msg.reference_id} held for {msg.consumer!r}"
                remember(self._replies, msg.request_id, reply)
        # Acknowledged before the release runs: it may block (a process is given its grace).
        self._send(reply, "replies_sent")
        if release:
            self._submit(functools.partial(self.release_local, release))

    # --- the worker threads -------------------------------------------------------------------

    def _serve(self, msg: Any, sender: str = "") -> None:
        registrar = self._registrar
        consumer: str = msg.consumer
        request_id: str = msg.request_id
        reply = new(resource_reply_t)
        reply.request_id, reply.provider, reply.consumer = request_id, self.manager, consumer
        try:
            refusal = self._core.link.auth.refusal(sender, "resource.request", msg.server)
            if refusal is not None:  # the fleet policy (docs/security.md)
                raise PermissionError(refusal)
            if msg.server == REMOTE_SERVER:
                raise ValueError("requests are not forwarded further: ask the provider itself")
            # the registrar has no public accessor for a server's request type
            kind = registrar.server(msg.server).request_type
            data = json.loads(msg.request)
            if not isinstance(data, dict):
                raise TypeError(f"the request must be a JSON object, not {type(data).__name__}")
            request = from_plain(kind, data)
            client = f"{consumer}/{msg.client}" if msg.client else f"{consumer}:{request_id}"
            status_out: Callable[[StatusUpdate], None] = functools.partial(
                self._status_out, consumer
            )
            resource = registrar.call(
                msg.server,
                request,
                client=client,
                priority=msg.priority,
                exclusive=msg.exclusive,
                on_status=status_out,
            )
        except Exception as err:
            reply.code = ERROR
            reply.message = f"robot '{self._ris.robot}' could not serve '{msg.server}': {err}"
            reply.errors = records_json(err, self.manager)
            with self._lock:
                self._core.count("refused")
            level = logging.WARNING if isinstance(err, PermissionError) else logging.INFO
            logger.log(level, "remote request %s from %r refused: %s", request_id, consumer, err)
        else:
            reply.code = OK
            reply.reference_id, reply.resource_id = resource.id, resource.resource_id
            reply.response = canonical_json(resource.response)
            with self._lock:
                orphan = self._core.closed or consumer in self._lost
                if not orphan:
                    self._held[resource.id] = _Held(consumer, request_id, self._core.now())
            if orphan:  # the consumer was lost (or this closed) while it loaded
                self.release_local(resource.id)
                return
        with self._lock:
            served = self._served.get(request_id)
            if served is not None:
                served.reply = reply
        self._send(reply, "replies_sent")

    def _status_out(self, consumer: str, update: StatusUpdate) -> None:
        """A status of a reference held for a remote consumer (any thread): forward it."""
        msg = new(resource_status_t)
        msg.provider, msg.consumer = self.manager, consumer
        msg.reference_id, msg.resource_id = update.reference_id, update.resource_id
        msg.status, msg.message = STATUS_CODES[update.status], update.message
        msg.origin, msg.hops = update.origin, list(update.hops)
        self._send(msg, "statuses_sent")

    def release_local(self, reference_id: str) -> None:
        """Release a reference held for a remote consumer (a worker thread, or closing)."""
        try:
            self._registrar.release(reference_id)
        except ResourceError as err:
            logger.warning("releasing %s for a remote consumer failed: %s", reference_id, err)

    # --- lost consumers -----------------------------------------------------------------------

    def consumer_lost(self, info: RobotInfo) -> list[str]:
        """Forget what a lost robot held here (lock held); the references to release."""
        self._lost.add(info.manager)
        return self._take(lambda held: held.consumer == info.manager)

    def consumer_joined(self, info: RobotInfo) -> None:
        """A robot is heard (again) (lock held)."""
        self._lost.discard(info.manager)

    def sweep(self, now: float) -> list[str]:
        """References held too long for consumers the RIS never heard (lock held)."""
        ris = self._ris
        limit = ris.missed * ris.period_s
        known = {r.manager for r in ris.robots()}
        return self._take(lambda held: held.consumer not in known and now - held.since > limit)

    def take_all(self) -> list[str]:
        """Every reference held for remote consumers, forgotten (lock held; closing)."""
        return self._take(lambda held: True)

    def _take(self, which: Callable[[_Held], bool]) -> list[str]:
        refs = [ref for ref, held in self._held.items() if which(held)]
        for ref in refs:
            del self._held[ref]
            remember(self._released, ref, None)
        return refs
