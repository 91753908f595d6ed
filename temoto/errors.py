"""The whole TeMoto exception hierarchy.

Every error TeMoto raises on purpose derives from :class:`TemotoError`. Categories name the
situation, and inherit the matching builtin so generic callers can catch what they expect::

    Exception
    └── TemotoError                         root; .origin, to_records()
        ├── ConfigError (+ValueError)       a bad document (file + key path)
        │   ├── UmrfError                   an action description (*.umrf.json) is invalid
        │   ├── GraphDefinitionError        a graph is invalid (parse or validation)
        │   │   └── GraphInputError         a required graph input was not supplied
        │   ├── PipelineError               a component pipeline template is invalid (cycle, ...)
        │   ├── TaskParseError              a task in words that no graph can be made of
        │   └── ProfileError                a hardware profile is invalid
        │       └── DeviceLimitError (+DriverInitError)  it asks more than the device allows
        ├── PluginError                     discovery and loading of actions and drivers
        │   ├── ActionNotFoundError (+LookupError)
        │   ├── GraphNotFoundError (+LookupError)
        │   ├── DriverNotFoundError (+LookupError)
        │   ├── PluginConflictError         the same name offered by two sources
        │   └── PluginLoadError             found, but importing it failed (cause chained)
        ├── StateError (+RuntimeError)      an illegal transition or a command in the wrong state
        ├── ActionError                     user action code failed; names graph and node
        ├── ContextError                    the shared world model refused a change
        │   ├── ContextItemNotFoundError (+LookupError)  no item of that name (or parent)
        │   └── ContextCycleError           a re-parent would make an item its own ancestor
        ├── ResourceError
        │   ├── ResourceNotFoundError (+LookupError)
        │   │   └── NoProviderError         no robot of the fleet offers the server (RIS)
        │   ├── ResourceBusyError
        │   ├── ResourceClosedError
        │   ├── ResourceBrokenError
        │   ├── ResourceLoadError           a server failed to load (cause chained per hop)
        │   ├── CatalogCorruptError         the registrar's journal is damaged (file + offset)
        │   └── ComponentNotFoundError (+LookupError) no candidate provides a component type
        ├── DriverError
        │   ├── DriverUnavailableError
        │   ├── DriverInitError
        │   ├── DriverOperationError
        │   │   ├── DynamixelHardwareError  a servo's hardware-error bits (servo id, error byte)
        │   │   ├── MavlinkCommandError     a vehicle refused a command (MAV_CMD, MAV_RESULT)
        │   │   └── MotorFaultError         a CAN motor controller's error bits (node id)
        │   └── DriverTimeoutError (+TimeoutError)
        ├── TransportError
        │   ├── DecodeError                 a fleet message's payload cannot be decoded
        │   ├── FleetError                  another actor of a shared graph did not answer
        │   └── TransportTimeoutError (+TimeoutError)
        └── RemoteError                     an error reported by another robot

    BaseException
    └── StopRequested                       raised by action helpers when the node is stopped

Errors cross process and robot boundaries as a list of :class:`ErrorRecord` (see
:meth:`TemotoError.to_records`), which replaces upstream TeMoto's "error stack".
"""

from __future__ import annotations

import time
from dataclasses import dataclass

__all__ = [
    "ActionError",
    "ActionNotFoundError",
    "CatalogCorruptError",
    "ComponentNotFoundError",
    "ConfigError",
    "ContextCycleError",
    "ContextError",
    "ContextItemNotFoundError",
    "DecodeError",
    "DeviceLimitError",
    "DriverError",
    "DriverInitError",
    "DriverNotFoundError",
    "DriverOperationError",
    "DriverTimeoutError",
    "DriverUnavailableError",
    "DynamixelHardwareError",
    "ErrorRecord",
    "FleetError",
    "GraphDefinitionError",
    "GraphInputError",
    "GraphNotFoundError",
    "MavlinkCommandError",
    "MavlinkMissionError",
    "MotorFaultError",
    "NoProviderError",
    "PipelineError",
    "PluginConflictError",
    "PluginError",
    "PluginLoadError",
    "ProfileError",
    "RemoteError",
    "ResourceBrokenError",
    "ResourceBusyError",
    "ResourceClosedError",
    "ResourceError",
    "ResourceLoadError",
    "ResourceNotFoundError",
    "StateError",
    "StopRequested",
    "TaskParseError",
    "TemotoError",
    "TransportError",
    "TransportTimeoutError",
    "UmrfError",
]


@dataclass(frozen=True, slots=True)
class ErrorRecord:
    """One link of an error chain in a serialisable form.

    Attributes:
        type: The exception class name.
        message: ``str()`` of the exception.
        origin: Where it was raised (a component or actor name), empty if unknown.
        timestamp: Seconds since the epoch when the record was made.
    """

    type: str
    message: str
    origin: str = ""
    timestamp: float = 0.0


class TemotoError(Exception):
    """Root of every error TeMoto raises on purpose.

    Args:
        message: What went wrong, for a person.
        origin: The component (or actor) that raised it.
    """

    def __init__(self, message: str = "", *, origin: str = "") -> None:
        super().__init__(message)
        self.origin = origin

    def to_records(self) -> list[ErrorRecord]:
        """Flatten this error, its notes and its cause chain into records, newest first.

        Returns:
            One record per exception in the ``__cause__``/``__context__`` chain; notes added
            with ``add_note`` become records of type ``"note"``.
        """
        records: list[ErrorRecord] = []
        now = time.time()
        seen: set[int] = set()
        exc: BaseException | None = self
        while exc is not None and id(exc) not in seen:
            seen.add(id(exc))
            origin = getattr(exc, "origin", "")
            records.append(ErrorRecord(type(exc).__name__, str(exc), str(origin), now))
            records.extend(
                ErrorRecord("note", note, str(origin), now)
                for note in getattr(exc, "__notes__", ())
            )
            exc = exc.__cause__ or exc.__context__
        return records

    def __reduce__(self) -> tuple[object, ...]:
        return (_rebuild, (type(self), self.args, self.__dict__))


def _rebuild(
    cls: type[TemotoError], args: tuple[object, ...], state: dict[str, object]
) -> TemotoError:
    err = cls.__new__(cls)
    Exception.__init__(err, *args)
    err.__dict__.update(state)
    return err


class ConfigError(TemotoError, ValueError):
    """A document (graph, action description, settings, profile) is invalid.

    The message starts with the file and the JSON/YAML key path of the problem, e.g.
    ``graph.json: actions[2].parents[0].conditions[1]: unknown response 'runn' (...)``.

    Args:
        message: What is wrong at that place.
        file: The file the document came from, if any.
        path: The key path inside the document (``actions[2].name``), if any.
    """

    def __init__(self, message: str, *, file: str | None = None, path: str = "") -> None:
        self.file = file
        self.path = path
        self.reason = message
        prefix = "".join(f"{part}: " for part in (file, path) if part)
        super().__init__(prefix + message)

    def __reduce__(self) -> tuple[object, ...]:
        return (_rebuild, (type(self), self.args, self.__dict__))


class UmrfError(ConfigError):
    """An action description (``*.umrf.json``) is invalid."""


class GraphDefinitionError(ConfigError):
    """A UMRF graph is invalid: it does not parse, or it cannot run as written."""


class GraphInputError(GraphDefinitionError):
    """A graph was started without a required external input."""


class ProfileError(ConfigError):
    """A hardware profile is invalid."""


class TaskParseError(ConfigError):
    """A task source cannot turn a task given in words into a graph (the message says where)."""


class PipelineError(ConfigError):
    """A component pipeline template is invalid (an unknown component type, a cycle, ...)."""


class PluginError(TemotoError):
    """Finding or loading an action or driver plugin failed."""


class ActionNotFoundError(PluginError, LookupError):
    """No implementation is known for an action named in a graph."""


class GraphNotFoundError(PluginError, LookupError):
    """No indexed or running graph has the given name."""


class DriverNotFoundError(PluginError, LookupError):
    """No driver is registered under the given name."""


class PluginConflictError(PluginError):
    """Two sources offer a plugin of the same name."""


class PluginLoadError(PluginError):
    """A plugin was found but importing or instantiating it failed (the cause is chained)."""


class StateError(TemotoError, RuntimeError):
    """An operation is not allowed in the current state (of a node, graph, driver, resource)."""


class ActionError(TemotoError):
    """User action code failed.

    Args:
        message: What failed.
        graph: The graph the action ran in.
        node: The node's full name (``<Name>_<instance_id>``).
    """

    def __init__(self, message: str, *, graph: str = "", node: str = "") -> None:
        super().__init__(message, origin=f"{graph}/{node}" if graph or node else "")
        self.graph = graph
        self.node = node


class ResourceError(TemotoError):
    """A resource could not be loaded, used or kept."""


class ResourceNotFoundError(ResourceError, LookupError):
    """No resource or server with that identity."""


class NoProviderError(ResourceNotFoundError):
    """No robot of the fleet offers the server a resource was asked of.

    Raised when a remote resource is requested and neither the local registrar nor any robot
    heard by the Resource Info Synchronizer serves it, or the robot named does not.

    Args:
        message: What is missing, for a person.
        server: The server asked for.
        robot: The robot named in the request ("" if any robot would do).
        origin: The component that raised it.
    """

    def __init__(
        self, message: str = "", *, server: str = "", robot: str = "", origin: str = ""
    ) -> None:
        super().__init__(message, origin=origin)
        self.server = server
        self.robot = robot


class ResourceBusyError(ResourceError):
    """An exclusive resource is held by another consumer."""


class ResourceClosedError(ResourceError):
    """A resource was used after it was released by its owner."""


class ResourceBrokenError(ResourceError):
    """A resource failed from outside (a process died, a device stopped answering)."""


class ResourceLoadError(ResourceError):
    """A server failed to load a resource; the cause is chained, each registrar hop adds a link."""


class CatalogCorruptError(ResourceError):
    """The registrar's catalog (journal) file is damaged and was not loaded.

    Raised for damage that is not a torn last record: a bad or missing header, an unsupported
    format version, a bad record followed by good ones, a sequence-number gap or repeat, or a
    record that is not a JSON object. The file is left untouched for inspection.

    Args:
        message: What is wrong.
        file: The journal file.
        offset: The byte offset in the file where the damage starts, if known.
    """

    def __init__(self, message: str, *, file: str = "", offset: int | None = None) -> None:
        self.file = file
        self.offset = offset
        self.reason = message
        where = f"{file}: " if file else ""
        if offset is not None:
            where += f"byte {offset}: "
        super().__init__(where + message)


class ComponentNotFoundError(ResourceNotFoundError):
    """No candidate (local or on another robot) provides the component type asked for."""


class ContextError(TemotoError):
    """The Context Manager refused a change to the world model (the tree is unchanged)."""


class ContextItemNotFoundError(ContextError, LookupError):
    """No item of that name, or a change names a parent that does not exist."""


class ContextCycleError(ContextError):
    """A re-parent would make an item its own ancestor."""


class DriverError(TemotoError):
    """A hardware driver failed."""


class DriverUnavailableError(DriverError):
    """An optional dependency, vendor library or port is missing."""


class DriverInitError(DriverError):
    """The device did not answer or rejected its settings while being configured."""


class DeviceLimitError(ProfileError, DriverInitError):
    """A profile's limit is beyond what the device, as it is configured, allows.

    Found while the device is configured (its settings read from it), before anything is
    written to it: a :class:`ProfileError` (the message names the file and the key; the robot
    command exits 2) that is a :class:`DriverInitError` too (configure failed).
    """


class DriverOperationError(DriverError):
    """A bad reply, checksum, negative acknowledgement or hardware error while running."""


class DynamixelHardwareError(DriverOperationError):
    """A Dynamixel servo reported a hardware error (overheating, overload, input voltage, ...).

    Args:
        message: What happened.
        servo_id: The servo's id on its chain.
        error: The status packet's error byte, or the Hardware Error Status register's value.
    """

    def __init__(self, message: str, *, servo_id: int, error: int) -> None:
        super().__init__(message)
        self.servo_id = servo_id
        self.error = error


class MavlinkCommandError(DriverOperationError):
    """A MAVLink vehicle refused or failed a command (its ``COMMAND_ACK`` result).

    Args:
        message: What happened.
        command: The ``MAV_CMD`` id.
        result: The ``MAV_RESULT`` value.
    """

    def __init__(self, message: str, *, command: int, result: int) -> None:
        super().__init__(message)
        self.command = command
        self.result = result


class MavlinkMissionError(DriverOperationError):
    """A MAVLink vehicle refused a mission transfer (its ``MISSION_ACK`` result).

    Args:
        message: What happened.
        result: The ``MAV_MISSION_RESULT`` value.
    """

    def __init__(self, message: str, *, result: int) -> None:
        super().__init__(message)
        self.result = result


class MotorFaultError(DriverOperationError):
    """A CAN motor controller reported an error (its error bits, decoded in the message).

    Args:
        message: What happened.
        node_id: The controller's node id on the bus.
        error: The raw error bits.
    """

    def __init__(self, message: str, *, node_id: int, error: int) -> None:
        super().__init__(message)
        self.node_id = node_id
        self.error = error


class DriverTimeoutError(DriverError, TimeoutError):
    """The device did not answer in time."""


class TransportError(TemotoError):
    """Messaging between robots failed."""


class FleetError(TransportError):
    """Another actor of a shared graph did not take part.

    Raised when the handshake before a multi-actor run does not complete in time, when an
    actor does not acknowledge a notification, and given to the engine when an actor falls
    silent during a run. The message names the actors concerned.
    """


class DecodeError(TransportError):
    """A fleet message's payload cannot be decoded into its inner type.

    Raised by :func:`temoto.transport.codec.decode` for an unknown type name, an unknown
    version, bytes of another type (an LCM fingerprint mismatch), or a truncated or overlong
    payload. The receiver counts and drops such a message; handlers never see it.
    """


class TransportTimeoutError(TransportError, TimeoutError):
    """A peer did not answer in time."""


class RemoteError(TemotoError):
    """An error reported by another robot, rebuilt from its records."""

    @classmethod
    def from_records(cls, records: list[ErrorRecord]) -> RemoteError:
        """Rebuild an error chain from records made by :meth:`TemotoError.to_records`.

        Args:
            records: The records, newest first.

        Returns:
            A RemoteError whose message is the newest record and whose ``__cause__`` chain
            holds the older ones.

        Raises:
            ValueError: If ``records`` is empty.
        """
        if not records:
            raise ValueError("no error records")
        head: RemoteError | None = None
        for record in reversed(records):
            err = cls(f"{record.type}: {record.message}", origin=record.origin)
            err.__cause__ = head
            head = err
        assert head is not None
        return head


class StopRequested(BaseException):
    """Raised inside an action by the engine's helpers when its node is being stopped.

    It derives from ``BaseException`` so that ``except Exception`` in action code does not
    swallow it. Let it propagate: the engine turns it into the ``on_stopped`` result.
    """
