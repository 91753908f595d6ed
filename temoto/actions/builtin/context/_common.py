"""What the built-in context actions share: the client, the pose inputs, the item outputs."""

from __future__ import annotations

import json
from typing import Any

from temoto.core.action import Action
from temoto.managers.context import ContextClient, Item, Pose

__all__ = ["ContextAction"]

_POSE_INPUTS = ("x", "y", "z", "roll", "pitch", "yaw")


class ContextAction(Action):
    """Base of the context actions."""

    def context(self) -> ContextClient:
        """The Context Manager's client on this engine's registrar."""
        return ContextClient.for_action(self)

    def text(self, name: str, default: str = "") -> str:
        """An optional string input."""
        return self.inputs.get_string(name) if name in self.inputs else default

    def flag(self, name: str) -> bool:
        """An optional bool input (absent: false)."""
        return self.inputs.get_bool(name) if name in self.inputs else False

    def pose(self) -> Pose | None:
        """The pose from the optional inputs ``x y z`` (m) ``roll pitch yaw`` (rad).

        Returns:
            None if none of them is given; otherwise the pose, the missing ones 0.
        """
        given = {n: self.inputs.get_number(n) for n in _POSE_INPUTS if n in self.inputs}
        return Pose.from_euler(**given) if given else None

    def attributes(self) -> dict[str, Any] | None:
        """The optional ``attributes`` input (a JSON object as text), or None."""
        if "attributes" not in self.inputs:
            return None
        value = json.loads(self.inputs.get_string("attributes"))
        if not isinstance(value, dict):
            raise ValueError("the attributes input must be a JSON object")
        return value

    def report(self, item: Item) -> None:
        """Log an item and where it is."""
        self.log(f"{item.name} ({item.type}) under '{item.parent or '-'}' by {item.writer}")
