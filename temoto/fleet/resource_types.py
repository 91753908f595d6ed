"""The messages' side of remote resources: the ``"remote"`` server's request and response types.

:class:`RemoteRequest` names a robot, a server there and the request as JSON; the local
registrar's ``"remote"`` server (:class:`~temoto.fleet.resources.RemoteResources`) loads it
by asking that robot. :class:`RemoteResponse` is what it returns. ``docs/ris.md`` has the
protocol.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import time
from dataclasses import dataclass
from typing import Any, Final, TypeVar

from temoto.core.registrar import Resource, Status
from temoto.core.registrar.messages import canonical_json, from_plain
from temoto.errors import ErrorRecord, RemoteError, TemotoError
from temoto.fleet.ris import type_name

__all__ = [
    "RESOURCE_CHANNEL",
    "RESOURCE_STATS",
    "RemoteRequest",
    "RemoteResponse",
    "remote_request",
    "response_of",
]

T = TypeVar("T")

#: Channel of ``resource_request_t``, ``resource_reply_t``, ``resource_release_t`` and
#: ``resource_status_t``.
RESOURCE_CHANNEL: Final = "TEMOTO_RESOURCE"

#: The counters of :attr:`RemoteResources.stats`.
RESOURCE_STATS: Final = (
    "requests_sent",  # resends included
    "requests_received",  # resends included
    "replies_sent",
    "replies_received",
    "releases_sent",  # resends included
    "releases_received",
    "statuses_sent",
    "statuses_received",
    "duplicates",  # resent requests or releases answered from memory, late replies
    "decode_errors",  # payloads that codec.decode refused
    "unexpected",  # well-formed but meaningless: wrong type, empty ids, unknown status, ...
    "send_errors",  # sends that failed (logged)
    "refused",  # requests this provider answered with ERROR
    "timeouts",  # requests of this consumer that got no reply in time
    "lost_fatal",  # proxies made FATAL because their provider robot was lost
    "released_for_lost",  # references released here because their consumer robot was lost
    "impostor",  # naming another member than their authenticated sender (dropped)
)

#: resource_reply_t.OK and .ERROR (the generated constants are untyped).
OK: Final = 1
ERROR: Final = 2
#: Status to resource_status_t.status.
STATUS_CODES: Final = {
    Status.OK: 1,
    Status.UPDATE: 2,
    Status.WARNING: 3,
    Status.ERROR: 4,
    Status.FATAL: 5,
}
#: resource_status_t.status to Status.
STATUSES: Final = {code: status for status, code in STATUS_CODES.items()}
#: Replies, released references and given-up requests remembered (the oldest are forgotten).
MEMORY: Final = 10_000


def remember(memory: collections.OrderedDict[str, Any], key: str, value: Any) -> None:
    """Add to a bounded memory, forgetting the oldest entry beyond :data:`MEMORY`.

    Args:
        memory: The memory.
        key: The key.
        value: The value.
    """
    memory[key] = value
    if len(memory) > MEMORY:
        memory.popitem(last=False)


# ================================================================================ request types


@dataclass(frozen=True)
class RemoteRequest:
    """A resource of another robot, as the local ``"remote"`` server takes it.

    Equal requests (same robot, server and request) share one proxy resource, hence one
    reference on the providing robot.

    Attributes:
        robot: The providing robot's name (as its RIS adverts give it).
        server: The server's name on that robot.
        request_json: The request as JSON (an object); stored in canonical form.
        request_type: The request's class as ``"module:QualName"``, or "" not to check it
            against the type the robot advertises.
        priority: The priority of the reference on the providing robot.
        exclusive: Whether this robot wants the remote resource alone (against the providing
            robot's other consumers; locally, the ``"remote"`` reference has its own).

    Raises:
        TypeError: A field is not a string.
        ValueError: An empty robot or server, or ``request_json`` is not a JSON object.
    """

    robot: str
    server: str
    request_json: str
    request_type: str = ""
    priority: int = 0
    exclusive: bool = False

    def __post_init__(self) -> None:
        for name in ("robot", "server", "request_json", "request_type"):
            if not isinstance(getattr(self, name), str):
                raise TypeError(f"{name} must be a str, not {type(getattr(self, name)).__name__}")
        if isinstance(self.priority, bool) or not isinstance(self.priority, int):
            raise TypeError(f"priority must be an int, not {type(self.priority).__name__}")
        if not isinstance(self.exclusive, bool):
            raise TypeError(f"exclusive must be a bool, not {type(self.exclusive).__name__}")
        if not self.robot or not self.server:
            raise ValueError("robot and server must not be empty")
        try:
            data = json.loads(self.request_json)
        except ValueError as err:
            raise ValueError(f"request_json is not JSON: {err}") from None
        if not isinstance(data, dict):
            raise ValueError(f"request_json must be a JSON object, not {type(data).__name__}")
        object.__setattr__(self, "request_json", canonical_json(data))

    @classmethod
    def of(
        cls, robot: str, server: str, request: Any, *, priority: int = 0, exclusive: bool = False
    ) -> RemoteRequest:
        """Wrap a request for a server of another robot.

        Args:
            robot: The providing robot.
            server: The server there.
            request: The request (a dataclass instance, or a dict of its fields).
            priority: The priority of the reference on the providing robot.
            exclusive: Whether to want the remote resource alone.

        Returns:
            The remote request.

        Raises:
            TypeError: If the request cannot be serialised.
            ValueError: If robot or server is empty.
        """
        kind = "" if isinstance(request, dict) else type_name(type(request))
        return cls(robot, server, canonical_json(request), kind, priority, exclusive)


@dataclass(frozen=True)
class RemoteResponse:
    """What the ``"remote"`` server returns: the providing robot's reference and response.

    Attributes:
        robot: The providing robot.
        reference_id: The reference held on that robot (for this robot's proxy).
        resource_id: The resource on that robot.
        response_json: Its server's response as JSON.
    """

    robot: str
    reference_id: str
    resource_id: str
    response_json: str

    def decode(self, cls: type[T]) -> T:
        """The remote server's response as an instance of its class.

        Args:
            cls: The response class (e.g. ``ProcessResponse``).

        Returns:
            The response.

        Raises:
            TypeError: If the JSON does not fit ``cls``.
            ValueError: If ``response_json`` is not JSON.
        """
        return from_plain(cls, json.loads(self.response_json))


def remote_request(
    server: str, request: Any, robot: str, *, priority: int = 0, exclusive: bool = False
) -> RemoteRequest:
    """Build the request of the ``"remote"`` server for ``server`` on ``robot``.

    Use it with ``registrar.call("remote", ...)`` or an action's ``self.acquire("remote",
    ...)``; :meth:`RemoteResources.request` also picks the robot.

    Args:
        server: The server on the robot.
        request: Its request (a dataclass instance).
        robot: The providing robot.
        priority: The priority of the reference on the providing robot.
        exclusive: Whether to want the remote resource alone.

    Returns:
        The remote request.

    Raises:
        TypeError: If the request cannot be serialised.
        ValueError: If robot or server is empty.
    """
    return RemoteRequest.of(robot, server, request, priority=priority, exclusive=exclusive)


def response_of(resource: Resource[Any], cls: type[T]) -> T:
    """The server's response of a resource, whether it was served locally or remotely.

    Args:
        resource: What ``registrar.call`` or :meth:`RemoteResources.request` returned.
        cls: The server's response class.

    Returns:
        The response.

    Raises:
        TypeError: If the response is neither ``cls`` nor a remote response that fits it.
    """
    response = resource.response
    if isinstance(response, RemoteResponse):
        return response.decode(cls)
    if isinstance(response, cls):
        return response
    raise TypeError(f"{type(response).__name__} is not a {cls.__name__}")


def records_json(err: BaseException, origin: str) -> str:
    """(Internal) an error chain as the JSON list of ErrorRecord objects, newest first."""
    if isinstance(err, TemotoError):
        records = err.to_records()
    else:
        records, seen, now = [], set(), time.time()
        exc: BaseException | None = err
        while exc is not None and id(exc) not in seen:
            seen.add(id(exc))
            records.append(ErrorRecord(type(exc).__name__, str(exc), origin, now))
            exc = exc.__cause__ or exc.__context__
    return json.dumps([dataclasses.asdict(r) for r in records])


def remote_error(message: str, errors: str, origin: str) -> RemoteError:
    """(Internal) the error a provider reported: its message, chained to its records."""
    err = RemoteError(message, origin=origin)
    try:
        data = json.loads(errors) if errors else []
        records = [ErrorRecord(str(r["type"]), str(r["message"]), str(r["origin"])) for r in data]
    except (ValueError, TypeError, KeyError, RecursionError):
        records = []
    if records:
        err.__cause__ = RemoteError.from_records(records)
    return err
