"""RemoveItem: remove an item from the world model."""

from __future__ import annotations

from temoto.actions.builtin.context._common import ContextAction


class RemoveItem(ContextAction):
    """Inputs ``item``, optional ``cascade``; output ``removed_items`` (the names removed).

    Without ``cascade`` an item with children is refused; with it, its subtree goes too.
    """

    def on_run(self) -> bool:
        """Remove it; True when done."""
        removed = self.context().remove(
            self.inputs.get_string("item"), cascade=self.flag("cascade")
        )
        self.log(f"removed {', '.join(removed)}")
        self.outputs["removed_items"] = removed
        return True
