"""ResourceServer: the base class of resource managers, and the LoadContext of a load.

A server loads and unloads one kind of resource. The registrar owns the lifecycle and calls
the hooks; a server never calls its own hooks.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, ClassVar, Generic, TypeVar

if TYPE_CHECKING:
    from temoto.core.registrar.messages import Resource, ResourceInfo, Status, StatusUpdate
    from temoto.core.registrar.registry import Registrar

__all__ = ["LoadContext", "ResourceServer"]

Req = TypeVar("Req")
Resp = TypeVar("Resp")


class LoadContext:
    """What a server's ``on_load`` gets besides the request.

    Attributes:
        registrar: The registrar.
        resource_id: The id the resource will have (use it in later ``send_status`` calls).
        server: The server's name.
    """

    __slots__ = ("_progress", "registrar", "resource_id", "server")

    def __init__(self, registrar: Registrar, resource_id: str, server: str) -> None:
        self.registrar = registrar
        self.resource_id = resource_id
        self.server = server
        self._progress: dict[str, Any] | None = None

    def call(
        self,
        server: str,
        request: Any,
        *,
        priority: int = 0,
        exclusive: bool = False,
        on_status: Callable[[StatusUpdate], None] | None = None,
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
        return self.registrar._call(
            server, request, "", priority, exclusive, on_status, holder=self.resource_id
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
        self._progress = dict(progress)
        self.registrar._checkpoint(self.resource_id, self._progress)


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
