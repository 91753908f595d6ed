"""Ros2SendGoal: send a goal to a ROS 2 action server and wait for its result."""

from __future__ import annotations

import json
from typing import Any

from temoto.actions.builtin.ros2._common import connect, json_object, request, timeout_of
from temoto.core.action import Action


class Ros2SendGoal(Action):
    """Send ``goal`` (JSON) to the ROS 2 action server ``action``; feedback into the log.

    ``type`` names the action type (e.g. ``test_msgs/action/Fibonacci``).

    Outputs ``result`` (a JSON object) and ``status`` (``SUCCEEDED``, ``ABORTED``, ...); True
    only when the goal SUCCEEDED. ``timeout`` seconds (default 0: none); on timeout the goal is
    cancelled and it is an error. Stopping the graph cancels the goal and waits for the server
    to confirm; pausing does neither (the goal is held and runs on).
    """

    def on_run(self) -> bool:
        """Send the goal; True when it succeeded."""
        action = self.inputs.get_string("action")

        def on_feedback(event: dict[str, Any]) -> None:
            text = json.dumps(event.get("feedback", {}), separators=(",", ":"))
            self.log(f"feedback from {action}: {text[:200]}")

        with connect(self) as bridge:
            result = request(
                self,
                bridge,
                "send_goal",
                on_event=on_feedback,
                action=action,
                type=self.inputs.get_string("type"),
                goal=json_object(self, "goal"),
                timeout=timeout_of(self, 0.0),
            )
        status = str(result.get("status", ""))
        self.outputs["status"] = status
        self.outputs["result"] = json.dumps(result.get("result", {}), separators=(",", ":"))
        self.log(f"goal on {action} {status}: {self.outputs['result'][:200]}")
        return status == "SUCCEEDED"
