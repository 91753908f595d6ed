"""The server's side of the registrar: :class:`ResourceServer`, what its ``on_load`` gets.

A server loads and unloads one kind of resource. The registrar owns the lifecycle and calls
the hooks; a server never calls its own hooks. Its ``on_load`` gets a :class:`LoadContext`,
whose ``registrar`` is typed as :class:`RegistrarAPI`, the registrar's public methods: the
:class:`~temoto.core.registrar.Registrar` (``registry.py``) imports this module, and this
module needs nothing of it, not even for type annotations.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Generic, Protocol, TypeVar

from temoto.core.registrar.messages import (
    Reference,
    Resource,
    ResourceInfo,
    Status,
    StatusCallback,
)

__all__ = ["LoadContext", "RegistrarAPI", "ResourceServer"]

Req = TypeVar("Req")
Resp = TypeVar("Resp")


class ResourceServer(ABC, Generic[Req, Resp]):
    """Base class of resource managers: loads and unloads one kind of resource.

    Subclasses set ``name``, ``request_type`` and ``response_type`` (frozen dataclasses
    whose fields are JSON-serialisable) and implement :meth:`on_load` and :meth:`on_unload`.
    Hooks run in the thread of the consumer that triggered them, outside the registrar's lock.
    """

    name: ClassVar[str]
    request_type: ClassVar[type[Any]]
    response_type: ClassVar[type[Any]]

    @abstractmethod
    def on_load(self, request: Req, ctx: LoadContext) -> Resp:
        """Load a resource the first time it is requested.

        Sub-resources requested here (``ctx.registrar.call`` in this thread, or ``ctx.call``
        from any thread) become its dependencies. Raise to refuse or fail; what was acquired
        is rolled back.

        Args:
            request: The request.
            ctx: The load's context.

        Returns:
            The response (an instance of ``response_type``).
        """

    @abstractmethod
    def on_unload(self, request: Req, response: Resp) -> None:
        """Unload a resource whose last reference was released (after its dependencies).

        Args:
            request: The request that loaded it.
            response: Its response.
        """

    def on_status(self, resource: ResourceInfo, status: Status, message: str) -> None:
        """A status concerns one of this server's resources (its own report or a dependency's).

        Args:
            resource: The resource.
            status: The status.
            message: The message.
        """

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """After a restart from the catalog: is this resource still there?

        Args:
            resource: A restored resource.

        Returns:
            None if it is fine, else a status (usually FATAL) and a message to report to its
            consumers.
        """
        return None

    def on_abandoned(self, request: Req, progress: Mapping[str, Any] | None) -> None:
        """After a restart: a load was interrupted by the crash; undo what it did.

        Args:
            request: The request being loaded.
            progress: The last ``ctx.checkpoint`` data, or None.
        """


class RegistrarAPI(Protocol):
    """The :class:`~temoto.core.registrar.Registrar` as its servers see it: its public methods.

    ``LoadContext.registrar`` is typed as this, so that the servers' module needs nothing of
    the registrar's; the registrar checks against it where it makes a :class:`LoadContext`.
    Each method is the registrar's, documented there.
    """

    @property
    def name(self) -> str:
        """The registrar's name."""

    def servers(self) -> list[str]:
        """Names of the registered servers (``Registrar.servers``)."""

    def server(self, name: str) -> ResourceServer[Any, Any]:
        """The server registered under ``name`` (``Registrar.server``)."""

    def call(
        self,
        server: str,
        request: Any,
        *,
        client: str = "",
        priority: int = 0,
        exclusive: bool = False,
        on_status: StatusCallback | None = None,
        holder: str | None = None,
    ) -> Resource[Any]:
        """Request a resource (``Registrar.call``)."""

    def checkpoint(self, resource_id: str, progress: Mapping[str, Any]) -> None:
        """Record how far a load got (``Registrar.checkpoint``)."""

    def release(self, reference_id: str) -> bool:
        """Release a reference (``Registrar.release``)."""

    def release_client(self, client: str) -> int:
        """Release a consumer's references (``Registrar.release_client``)."""

    def release_consumers(self, select: Callable[[Reference], bool] | None = None) -> int:
        """Release the selected references (``Registrar.release_consumers``)."""

    def send_status(self, resource_id: str, status: Status, message: str = "") -> int:
        """Report a resource's status to its consumers (``Registrar.send_status``)."""

    def subscribe(self, reference_id: str, on_status: StatusCallback) -> None:
        """Add a status callback to a reference (``Registrar.subscribe``)."""

    def info(self, resource_id: str) -> ResourceInfo:
        """A resource's snapshot (``Registrar.info``)."""

    def served(self, server: str) -> list[ResourceInfo]:
        """A server's resources (``Registrar.served``)."""

    def dependencies(self, resource_id: str) -> list[ResourceInfo]:
        """A resource's dependencies (``Registrar.dependencies``)."""

    def references(self, client: str | None = None) -> list[Reference]:
        """The references, of one consumer or all (``Registrar.references``)."""

    def resources(self) -> list[ResourceInfo]:
        """Every loaded resource (``Registrar.resources``)."""

    def update_response(self, resource_id: str, response: Any) -> None:
        """Replace a resource's response (``Registrar.update_response``)."""


class LoadContext:
    """What a server's ``on_load`` gets besides the request.

    Attributes:
        registrar: The registrar (as :class:`RegistrarAPI`: its public methods).
        resource_id: The id the resource will have (use it in later ``send_status`` calls).
        server: The server's name.
    """

    __slots__ = ("registrar", "resource_id", "server")

    def __init__(self, registrar: RegistrarAPI, resource_id: str, server: str) -> None:
        self.registrar = registrar
        self.resource_id = resource_id
        self.server = server

    def call(
        self,
        server: str,
        request: Any,
        *,
        priority: int = 0,
        exclusive: bool = False,
        on_status: StatusCallback | None = None,
    ) -> Resource[Any]:
        """Request a sub-resource as a dependency of this resource, from any thread.

        Calls made with ``registrar.call`` in the thread running ``on_load`` are recorded
        automatically; use this one from other threads.

        Args:
            server: The sub-resource's server.
            request: Its request.
            priority: Priority of the reference.
            exclusive: Whether it wants the sub-resource alone.
            on_status: Extra callback for the sub-resource's status (the server's
                ``on_status`` is called anyway).

        Returns:
            The reference.

        Raises:
            Everything ``Registrar.call`` raises.
        """
        return self.registrar.call(
            server,
            request,
            priority=priority,
            exclusive=exclusive,
            on_status=on_status,
            holder=self.resource_id,
        )

    def checkpoint(self, progress: Mapping[str, Any]) -> None:
        """Record how far the load got (e.g. a spawned pid) before it returns.

        If the process dies before ``on_load`` returns, the restarted registrar hands this to
        ``on_abandoned`` so the server can undo it (no orphaned process).

        Args:
            progress: JSON-serialisable data.

        Returns:
            None.

        Raises:
            TypeError: If the data cannot be serialised.
        """
        self.registrar.checkpoint(self.resource_id, progress)
