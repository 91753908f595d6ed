"""What every manager client does first: find its manager on a registrar (or an action's)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeVar

from temoto.errors import ResourceNotFoundError

if TYPE_CHECKING:
    from temoto.core.action import Action
    from temoto.core.registrar import Registrar, ResourceServer

__all__ = ["find_manager", "registrar_of"]

M = TypeVar("M", bound="ResourceServer[Any, Any]")


def find_manager(registrar: Registrar, manager: type[M], what: str) -> M:
    """The server a manager registers under its ``name``, checked to be that manager.

    Args:
        registrar: Where to look.
        manager: The manager's class (its ``name`` is the server's name).
        what: How messages call it ("Component Manager").

    Returns:
        The manager.

    Raises:
        ResourceNotFoundError: No server of that name, or another kind of server.
    """
    server = registrar.server(manager.name)
    if not isinstance(server, manager):
        raise ResourceNotFoundError(f"the '{manager.name}' server is not a {what}")
    return server


def registrar_of(action: Action) -> Registrar:
    """The registrar of the engine running ``action``.

    Args:
        action: A running action.

    Returns:
        The registrar.

    Raises:
        ResourceNotFoundError: The engine has no registrar.
    """
    if action.registrar is None:
        raise ResourceNotFoundError(f"{action.name}: this engine has no resource registrar")
    return action.registrar
