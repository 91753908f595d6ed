"""The Context Manager: a world model of maps, objects, robots and components.

Shared by the fleet (docs/design.md §6, thesis demo 5; docs/context-manager.md).

* :class:`ContextManager`: one robot's tree, synchronised over the fleet link; also the
  registrar server ``"context"`` (:class:`MaintainRequest`: an item kept while held).
* :class:`ContextClient`: what actions use (``ContextClient.for_action(self)``).
* :class:`Item`, :class:`Removal`, :class:`Pose`, :class:`ContextTree`: the data.
"""

from __future__ import annotations

from temoto.managers.context.client import ContextClient
from temoto.managers.context.manager import (
    CONTEXT_CHANNEL,
    CONTEXT_STATS,
    Change,
    ContextManager,
    MaintainRequest,
    MaintainResponse,
)
from temoto.managers.context.pose import Pose
from temoto.managers.context.tree import ContextTree, Item, Record, Removal

__all__ = [
    "CONTEXT_CHANNEL",
    "CONTEXT_STATS",
    "Change",
    "ContextClient",
    "ContextManager",
    "ContextTree",
    "Item",
    "MaintainRequest",
    "MaintainResponse",
    "Pose",
    "Record",
    "Removal",
]
