"""Value types of the Resource Registrar: statuses, updates, resources, references.

All of them are transport-independent, immutable, and cheap to copy across threads; the fleet
link (later) encodes them for other robots.
"""

from __future__ import annotations

import dataclasses
import operator
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Any, Generic, TypeVar

from temoto.core.registrar._json import make_encoder

__all__ = [
    "Reference",
    "Resource",
    "ResourceInfo",
    "Status",
    "StatusCallback",
    "StatusUpdate",
    "canonical_json",
    "from_plain",
    "request_key",
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


#: What a consumer gives to be told of its reference's status updates.
StatusCallback = Callable[[StatusUpdate], None]


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


def _resource_maker() -> Callable[[str, str, str, Any, Any], Resource[Any]]:
    """A maker of :class:`Resource` values that skips the frozen ``__init__``'s checks.

    The frozen dataclass's ``__init__`` sets each field through ``object.__setattr__`` (a
    global lookup and a call per field); on the registrar's every ``call`` that is a good part
    of the cost. The maker stores the same five fields through the slots' own descriptors:
    the value is the same ``Resource`` (equal, hashable, frozen against later changes).
    """
    new = object.__new__
    set_id, set_resource_id, set_server, set_request, set_response = (
        Resource.__dict__[name].__set__
        for name in ("id", "resource_id", "server", "request", "response")
    )

    def make(
        id: str,  # noqa: A002  # the field's name
        resource_id: str,
        server: str,
        request: Any,
        response: Any,
    ) -> Resource[Any]:
        value: Resource[Any] = new(Resource)
        set_id(value, id)
        set_resource_id(value, resource_id)
        set_server(value, server)
        set_request(value, request)
        set_response(value, response)
        return value

    return make


#: ``new_resource(id, resource_id, server, request, response)``: ``Resource(...)``, faster.
new_resource = _resource_maker()


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
        ValueError: If it holds a NaN or an infinity, or contains itself.
    """
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    try:
        _CHECK(value, 0)  # validates: raises TypeError / ValueError, as json.dumps would
    except RecursionError:
        raise ValueError("Circular reference detected") from None
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
        return _CANONICAL(_shallow(value), 0)[0]
    except (TypeError, ValueError, RecursionError) as err:
        raise TypeError(f"cannot serialise {type(value).__name__}: {_reason(err)}") from None


def request_key(value: Any) -> str:
    """The registrar's key of a request: equal for two requests iff :func:`canonical_json` is.

    For a dataclass it is the class's field names (sorted, as JSON) followed by a JSON array of
    the field values in that order: one call of the compiled JSON encoder on a tuple, without
    building a dict. Anything else gets its canonical JSON.

    Args:
        value: A request.

    Returns:
        The key.

    Raises:
        TypeError: If the value cannot be serialised (with what could not).
    """
    layout = _LAYOUTS.get(type(value))
    try:
        if layout is None:
            if not dataclasses.is_dataclass(value) or isinstance(value, type):
                return _CANONICAL(value, 0)[0]
            layout = _layout(type(value))
        return layout[0] + _CANONICAL(layout[1](value), 0)[0]
    except (TypeError, ValueError, RecursionError) as err:
        raise TypeError(f"cannot serialise {type(value).__name__}: {_reason(err)}") from None


def _reason(err: BaseException) -> str:
    return "a circular reference" if isinstance(err, RecursionError) else str(err)


def _shallow(value: Any) -> Any:
    """A dataclass as a dict of its fields (nested ones are converted by the encoder)."""
    names = _FIELD_NAMES.get(type(value))
    if names is None:
        if not dataclasses.is_dataclass(value) or isinstance(value, type):
            return value
        names = _field_names(type(value))
    return {name: getattr(value, name) for name in names}


#: Field names by dataclass: the layout of a request class, looked up once per class instead
#: of asking ``dataclasses.fields`` for every key.
_FIELD_NAMES: dict[type, tuple[str, ...]] = {}

#: Request-key layouts by dataclass: (the sorted field names as a JSON array, a getter of the
#: field values in that order, as a tuple).
_LAYOUTS: dict[type, tuple[str, Callable[[Any], tuple[Any, ...]]]] = {}


def _field_names(cls: type) -> tuple[str, ...]:
    names = tuple(f.name for f in dataclasses.fields(cls))
    _FIELD_NAMES[cls] = names  # one entry per class; a racing thread writes the same tuple
    return names


def _layout(cls: type) -> tuple[str, Callable[[Any], tuple[Any, ...]]]:
    names = sorted(_FIELD_NAMES.get(cls) or _field_names(cls))
    if names:
        get = operator.attrgetter(*names)
        getter = (lambda v: (get(v),)) if len(names) == 1 else get
    else:
        getter = _no_fields
    layout = (_CANONICAL(names, 0)[0], getter)
    _LAYOUTS[cls] = layout  # one entry per class; a racing thread writes an equal one
    return layout


def _no_fields(value: Any) -> tuple[Any, ...]:
    return ()


def _nested(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _shallow(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


#: ``_CANONICAL(value, 0)[0]``: the canonical JSON text of ``value``.
_CANONICAL = make_encoder(
    default=_nested, ensure_ascii=False, separators=(",", ":"), sort_keys=True, allow_nan=False
)
#: What ``json.dumps(value, allow_nan=False)`` checks: ``to_plain``'s test of JSON data.
_CHECK = make_encoder(
    default=None, ensure_ascii=True, separators=(", ", ": "), sort_keys=False, allow_nan=False
)
