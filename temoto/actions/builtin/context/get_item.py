"""GetItem: look an item up in the world model (waiting for it, if asked)."""

from __future__ import annotations

from temoto.actions.builtin.context._common import ContextAction


class GetItem(ContextAction):
    """Input ``item``, optional ``timeout`` (clock seconds to wait for it; absent: no wait).

    Outputs ``item_type_found``, ``item_parent``, ``item_maintainer``, ``world_x``,
    ``world_y``, ``world_z``, ``world_yaw`` (its pose composed up to its root). Returns false
    if it is not there (in time).
    """

    def on_run(self) -> bool:
        """Look it up; True when found."""
        ctx = self.context()
        name = self.inputs.get_string("item")
        timeout = self.inputs.get_number("timeout") if "timeout" in self.inputs else 0.0
        item = ctx.wait_for_item(self, name, timeout)
        if item is None:
            self.log(f"no item '{name}' in the world model")
            return False
        world = ctx.world_pose(name)
        self.outputs["item_type_found"] = item.type
        self.outputs["item_parent"] = item.parent
        self.outputs["item_maintainer"] = item.maintainer
        self.outputs["world_x"], self.outputs["world_y"] = world.x, world.y
        self.outputs["world_z"], self.outputs["world_yaw"] = world.z, world.yaw
        self.report(item)
        return True
