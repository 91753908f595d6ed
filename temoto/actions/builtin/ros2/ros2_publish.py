"""Ros2Publish: publish one message on a ROS 2 topic."""

from __future__ import annotations

from temoto.actions.builtin.ros2._common import connect, json_object, request, timeout_of
from temoto.core.action import Action


class Ros2Publish(Action):
    """Publish ``message`` (a JSON object) of ``type`` (e.g. ``std_msgs/msg/String``) on ``topic``.

    Waits up to ``timeout`` seconds (default 2) for a subscriber to be matched, then publishes
    anyway. Output ``subscribers``: how many were matched. True once published.
    """

    def on_run(self) -> bool:
        """Publish; True once done."""
        topic = self.inputs.get_string("topic")
        with connect(self) as bridge:
            result = request(
                self,
                bridge,
                "publish",
                topic=topic,
                type=self.inputs.get_string("type"),
                message=json_object(self, "message"),
                timeout=timeout_of(self, 2.0),
            )
        self.outputs["subscribers"] = int(result.get("subscribers", 0))
        self.log(f"published on {topic} ({self.outputs['subscribers']} subscribers)")
        return True
