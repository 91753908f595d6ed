"""FindItems: the items of one type, or below one item."""

from __future__ import annotations

from temoto.actions.builtin.context._common import ContextAction


class FindItems(ContextAction):
    """Optional inputs ``item_type`` and ``below`` (an item: search its subtree only).

    Output ``found_items``: the names, sorted. Returns false if none was found.
    """

    def on_run(self) -> bool:
        """Search; True if something was found."""
        ctx = self.context()
        kind = self.text("item_type")
        below = self.text("below")
        if below:
            items = [i for i in ctx.subtree(below)[1:] if not kind or i.type == kind]
        elif kind:
            items = ctx.find(kind)
        else:
            items = ctx.subtree()
        names = sorted(i.name for i in items)
        self.outputs["found_items"] = names
        self.log(f"found {len(names)}: {', '.join(names[:10])}{' ...' if len(names) > 10 else ''}")
        return bool(names)
