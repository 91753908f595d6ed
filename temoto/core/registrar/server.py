"""ResourceServer: the base class of resource managers.

A server loads and unloads one kind of resource. The registrar owns the lifecycle and calls
the hooks; a server never calls its own hooks. The :class:`~temoto.core.registrar.LoadContext`
its ``on_load`` gets is defined beside the registrar it serves (``registry.py``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, ClassVar, Generic, TypeVar

if TYPE_CHECKING:
    from temoto.core.registrar.messages import ResourceInfo, Status
    from temoto.core.registrar.registry import LoadContext

__all__ = ["ResourceServer"]

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
