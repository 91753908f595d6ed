"""Value types of the Resource Registrar: statuses, updates, resources, references.

All of them are transport-independent, immutable, and cheap to copy across threads; the fleet
link (later) encodes them for other robots.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from enum import Enum
from typing import Any, Generic, TypeVar

__all__ = [
    "Reference",
    "Resource",
    "ResourceInfo",
    "Status",
    "StatusUpdate",
    "canonical_json",
    "from_plain",
    "to_plain",
]

T = TypeVar("T")


class Status(Enum):
    """Status of a resource, as its provider reports it."""

    __hash__ = object.__hash__

    OK = "OK"
    UPDATE = "UPDATE"
    WARNING = "WARNING"
    ERROR = "ERROR"
    FATAL = "FATAL"


@dataclass(frozen=True, slots=True)
class StatusUpdate:
    """A status report as one consumer receives it.

    Attributes:
        reference_id: The receiving consumer's reference (what it got from ``call``).
        resource_id: The resource whose status this is (for a propagated update: the
            resource the consumer holds, not the one that failed first).
        status: The status.
        message: What happened, for a person.
        origin: The resource where the report started.
        hops: The servers the report passed through, from the origin up.
    """

    reference_id: str
    resource_id: str
    status: Status
    message: str
    origin: str
    hops: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class Resource(Generic[T]):
    """What a ``call`` returns: one reference to a loaded resource.

    Attributes:
        id: This reference's id (release it with ``registrar.release(id)``).
        resource_id: The resource's id (shared by every reference to it).
        server: The server that loaded it.
        request: The request.
        response: The server's response.
    """

    id: str
    resource_id: str
    server: str
    request: Any
    response: T


@dataclass(frozen=True, slots=True)
class Reference:
    """One consumer's reference to a resource (a snapshot).

    Attributes:
        id: The reference id.
        resource_id: The resource it refers to.
        client: The consumer's name.
        priority: Its priority (higher wins).
        exclusive: Whether it wants the resource alone.
        suspended: Whether a higher-priority consumer has pre-empted it.
        holder: The resource that holds it as a dependency, or "" for a direct consumer.
    """

    id: str
    resource_id: str
    client: str
    priority: int
    exclusive: bool
    suspended: bool
    holder: str


@dataclass(frozen=True, slots=True)
class ResourceInfo:
    """A loaded resource (a snapshot).

    Attributes:
        id: The resource id.
        server: Its server.
        request: The request that loaded it.
        response: The response.
        references: Its references, in the order they were taken.
        dependencies: Reference ids it holds on other resources.
        failed: Whether a FATAL status was reported for it.
    """

    id: str
    server: str
    request: Any
    response: Any
    references: tuple[Reference, ...]
    dependencies: tuple[str, ...]
    failed: bool

    @property
    def consumers(self) -> list[str]:
        """Client names of the references (one per reference)."""
        return [r.client for r in self.references]


def to_plain(value: Any) -> Any:
    """A request or response as plain JSON data (dataclasses become dicts).

    Args:
        value: A dataclass instance, or plain JSON data.

    Returns:
        JSON-ready data.

    Raises:
        TypeError: If it holds something JSON cannot represent.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    json.dumps(value, allow_nan=False)  # validates: raises TypeError / ValueError
    return value


def from_plain(cls: type[T], data: Any) -> T:
    """Rebuild a request or response of type ``cls`` from :func:`to_plain` data.

    Args:
        cls: The dataclass (or ``dict``) type.
        data: Plain data.

    Returns:
        The value.

    Raises:
        TypeError: If the data does not fit ``cls``.
    """
    if dataclasses.is_dataclass(cls) and isinstance(data, dict):
        return cls(**data)
    if isinstance(data, cls):
        return data
    raise TypeError(f"cannot rebuild {cls.__name__} from {type(data).__name__}")


def canonical_json(value: Any) -> str:
    """The identity of a request: compact JSON with sorted keys.

    Args:
        value: A request (dataclass) or plain data.

    Returns:
        The JSON text.

    Raises:
        TypeError: If the value cannot be serialised (with what could not).
    """
    try:
        return _CANONICAL.encode(_shallow(value))
    except (TypeError, ValueError) as err:
        raise TypeError(f"cannot serialise {type(value).__name__}: {err}") from None


def _shallow(value: Any) -> Any:
    """A dataclass as a dict of its fields (nested ones are converted by the encoder)."""
    names = _FIELD_NAMES.get(type(value))
    if names is None:
        if not dataclasses.is_dataclass(value) or isinstance(value, type):
            return value
        names = _field_names(type(value))
    return {name: getattr(value, name) for name in names}


#: Field names by dataclass: the layout of a request class, looked up once per class instead
#: of asking ``dataclasses.fields`` for every key (the dedup path makes a key per call).
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}


def _field_names(cls: type) -> tuple[str, ...]:
    names = tuple(f.name for f in dataclasses.fields(cls))
    _FIELD_NAMES[cls] = names  # one entry per class; a racing thread writes the same tuple
    return names


def _nested(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _shallow(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


# One encoder for every key: json.dumps with options builds a new encoder per call.
_CANONICAL = json.JSONEncoder(
    sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False, default=_nested
)
