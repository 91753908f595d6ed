"""AddItem: add an item to the shared world model."""

from __future__ import annotations

from temoto.actions.builtin.context._common import ContextAction


class AddItem(ContextAction):
    """Inputs ``item``, optional ``item_type``, ``parent``, pose, ``attributes``, ``temporary``.

    Output ``added_item``: the item's name. With ``temporary``, the item is held as a
    registrar resource of the action and removed when the graph ends (with what is below it).
    """

    def on_run(self) -> bool:
        """Add it; True when it is in the world model."""
        ctx = self.context()
        name = self.inputs.get_string("item")
        kind = self.text("item_type", "object")
        parent = self.text("parent")
        pose = self.pose()
        if self.flag("temporary"):
            ctx.maintain(self, name, kind, parent, pose, attributes=self.attributes(), cascade=True)
            item = ctx.get(name)
        else:
            item = ctx.add(name, kind, parent, pose, attributes=self.attributes())
        self.report(item)
        self.outputs["added_item"] = item.name
        return True
