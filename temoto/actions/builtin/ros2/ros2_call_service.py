"""Ros2CallService: call a ROS 2 service."""

from __future__ import annotations

import json

from temoto.actions.builtin.ros2._common import connect, json_object, request, timeout_of
from temoto.core.action import Action


class Ros2CallService(Action):
    """Call ``service`` of ``type`` (e.g. ``std_srvs/srv/Trigger``) with ``request`` (JSON).

    ``timeout`` seconds (default 10; 0: none) for the service to be discovered and to answer;
    a timeout is an error (on_error). Output ``response`` (a JSON object).
    """

    def on_run(self) -> bool:
        """Call; True when it answered."""
        service = self.inputs.get_string("service")
        with connect(self) as bridge:
            result = request(
                self,
                bridge,
                "call_service",
                service=service,
                type=self.inputs.get_string("type"),
                request=json_object(self, "request"),
                timeout=timeout_of(self, 10.0),
            )
        self.outputs["response"] = json.dumps(result.get("response", {}), separators=(",", ":"))
        self.log(f"{service} answered: {self.outputs['response'][:200]}")
        return True
