"""Ros2WaitForMessage: wait for the next message on a ROS 2 topic."""

from __future__ import annotations

import json

from temoto.actions.builtin.ros2._common import connect, request, timeout_of
from temoto.core.action import Action


class Ros2WaitForMessage(Action):
    """Wait for the next message of ``type`` on ``topic``; output it as JSON (``message``).

    ``timeout`` seconds (default 10; 0: none). A timeout is an error (on_error).
    """

    def on_run(self) -> bool:
        """Wait; True when a message arrived."""
        topic = self.inputs.get_string("topic")
        with connect(self) as bridge:
            result = request(
                self,
                bridge,
                "wait_message",
                topic=topic,
                type=self.inputs.get_string("type"),
                timeout=timeout_of(self, 10.0),
            )
        self.outputs["message"] = json.dumps(result.get("message", {}), separators=(",", ":"))
        self.log(f"message on {topic}: {self.outputs['message'][:200]}")
        return True
