"""Ros2LifecycleNode: hold a ROS 2 lifecycle node ACTIVE for the graph run."""

from __future__ import annotations

import shlex

from temoto.actions.builtin.ros2._common import acquire
from temoto.core.action import Action
from temoto.ros2.lifecycle import Ros2LifecycleRequest, Ros2LifecycleResponse


class Ros2LifecycleNode(Action):
    """Hold the lifecycle node ``node`` ACTIVE (configured and activated on load).

    ``timeout``: seconds per lifecycle service call (default 10). The node is shared with the
    other holders and deactivated and cleaned up when the last one releases it: this run's
    reference goes when the run ends, or after ``duration`` seconds if given (the action then
    returns; while it holds, a node that leaves ACTIVE on its own, or is gone, fails it).
    Output ``state``: the state the node was found in (1 unconfigured, 2 inactive, 3 active).
    ``program`` (optional): the node's program and its arguments (shell-like words; a ``.py``
    file runs with the interpreter that has rclpy), started first by the Process Manager and
    stopped once the node is brought down.
    """

    def on_run(self) -> bool:
        """Hold it; True once it is ACTIVE (and, with a duration, released again)."""
        request = Ros2LifecycleRequest(
            self.inputs.get_string("node"),
            timeout=float(self.inputs.get("timeout", 10.0)),
            domain_id=int(self.inputs.get("domain_id", -1)),
            program=tuple(shlex.split(str(self.inputs.get("program", "")))),
        )
        resource = acquire(self, "ros2_lifecycle", request)
        response = resource.response
        assert isinstance(response, Ros2LifecycleResponse)
        self.outputs["state"] = response.initial_state
        self.log(f"lifecycle node {response.node} is active")
        if "duration" in self.inputs:
            self.sleep(self.inputs.get_number("duration"))
            self.release(resource)
        return True
