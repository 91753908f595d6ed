"""MoveItem: re-parent an item of the world model, or change its pose."""

from __future__ import annotations

from temoto.actions.builtin.context._common import ContextAction


class MoveItem(ContextAction):
    """Inputs ``item``, optional ``parent`` (absent: keep it), pose.

    With a parent and no pose, the item keeps its place in the world (picked up, dropped);
    with a pose, it is relative to the (new) parent. Output ``moved_item``.
    """

    def on_run(self) -> bool:
        """Move it; True when done."""
        ctx = self.context()
        name = self.inputs.get_string("item")
        pose = self.pose()
        if "parent" in self.inputs:
            item = ctx.move(name, self.inputs.get_string("parent"), pose)
        elif pose is not None:
            item = ctx.update(name, pose=pose)
        else:
            raise ValueError(f"MoveItem '{name}': give a parent, a pose, or both")
        self.report(item)
        self.outputs["moved_item"] = item.name
        return True
