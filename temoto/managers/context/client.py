"""The consumers' side of the Context Manager: :class:`ContextClient`.

Actions find the manager on their engine's registrar (server ``"context"``)::

    ctx = ContextClient.for_action(self)
    ctx.add("trash_1", "object", parent="map", pose=Pose(2.0, 1.0))
    ctx.move("trash_1", "worker")            # picked up: stays where it is in the world
    item = ctx.wait_for_item(self, "bin", timeout=10.0)
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from temoto.core.registrar import Registrar, Resource
from temoto.managers._client import find_manager, registrar_of
from temoto.managers.context.manager import Change, ContextManager, MaintainRequest
from temoto.managers.context.pose import Pose
from temoto.managers.context.tree import Item

if TYPE_CHECKING:
    from temoto.core.action import Action

__all__ = ["ContextClient"]


class ContextClient:
    """Finds the Context Manager on a registrar; every call is the manager's.

    Args:
        registrar: The registrar the Context Manager serves on.

    Raises:
        ResourceNotFoundError: No Context Manager serves there.
    """

    def __init__(self, registrar: Registrar) -> None:
        self.registrar = registrar
        self.manager = find_manager(registrar, ContextManager, "Context Manager")

    @classmethod
    def for_action(cls, action: Action) -> ContextClient:
        """The client on the registrar of the engine running ``action``.

        Raises:
            ResourceNotFoundError: The engine has no registrar, or no Context Manager on it.
        """
        return cls(registrar_of(action))

    # ---- the manager's calls (see ContextManager for arguments and errors) --------------------

    def add(
        self,
        name: str,
        kind: str = "object",
        parent: str = "",
        pose: Pose | None = None,
        *,
        maintainer: str | None = None,
        attributes: Mapping[str, Any] | None = None,
    ) -> Item:
        """Add an item (:meth:`ContextManager.add`)."""
        return self.manager.add(
            name, kind, parent, pose, maintainer=maintainer, attributes=attributes
        )

    def update(
        self,
        name: str,
        *,
        pose: Pose | None = None,
        kind: str | None = None,
        maintainer: str | None = None,
        attributes: Mapping[str, Any] | None = None,
    ) -> Item:
        """Change an item (:meth:`ContextManager.update`)."""
        return self.manager.update(
            name, pose=pose, kind=kind, maintainer=maintainer, attributes=attributes
        )

    def move(self, name: str, parent: str, pose: Pose | None = None) -> Item:
        """Re-parent an item (:meth:`ContextManager.move`)."""
        return self.manager.move(name, parent, pose)

    def remove(self, name: str, *, cascade: bool = False) -> list[str]:
        """Remove an item (:meth:`ContextManager.remove`)."""
        return self.manager.remove(name, cascade=cascade)

    def get(self, name: str) -> Item:
        """An item (:meth:`ContextManager.get`)."""
        return self.manager.get(name)

    def find(self, kind: str) -> list[Item]:
        """Items of a type (:meth:`ContextManager.find`)."""
        return self.manager.find(kind)

    def subtree(self, name: str = "", depth: int | None = None) -> list[Item]:
        """A subtree (:meth:`ContextManager.subtree`)."""
        return self.manager.subtree(name, depth)

    def world_pose(self, name: str) -> Pose:
        """An item's world pose (:meth:`ContextManager.world_pose`)."""
        return self.manager.world_pose(name)

    # ---- inside actions -------------------------------------------------------------------------

    def maintain(
        self,
        action: Action,
        name: str,
        kind: str = "object",
        parent: str = "",
        pose: Pose | None = None,
        *,
        attributes: Mapping[str, Any] | None = None,
        cascade: bool = False,
    ) -> Resource[Any]:
        """Add (or take over) an item for as long as the action's graph runs.

        The item is held as a registrar resource of the action: when the graph ends (or the
        action releases it), the item is removed — with ``cascade``, with what is below it.

        Returns:
            The reference (``.response.item`` is the name).

        Raises:
            ResourceLoadError: The item could not be added (chained to the ContextError).
        """
        request = MaintainRequest(
            name,
            kind,
            parent,
            (pose or Pose()).as_tuple(),
            json.dumps(dict(attributes or {}), sort_keys=True),
            cascade,
        )
        return action.acquire(ContextManager.name, request)

    def wait_for_item(self, action: Action, name: str, timeout: float | None = None) -> Item | None:
        """Inside an action: wait until an item is in the world model (stop- and pause-aware).

        Args:
            action: The running action.
            name: The item.
            timeout: Clock seconds, or None to wait until it appears or the node is stopped.

        Returns:
            The item, or None on timeout.

        Raises:
            StopRequested: The node is being stopped.
        """

        def woken(change: Change) -> None:
            if name in change.names:
                action.wake()

        cancel = self.manager.listen(woken)
        try:
            if not action.wait_for(lambda: name in self.manager, timeout):
                return None
        finally:
            cancel()
        return self.manager.get(name)
