"""RequestComponent: hold a component of a type for the rest of the graph run."""

from __future__ import annotations

from temoto.core.action import Action
from temoto.managers.component.client import ComponentManagerClient


class RequestComponent(Action):
    """Request a component of a type and hold it until the graph run ends.

    Inputs ``component_type``; optional ``component_name``, ``channel`` (where the first
    output should go), ``local_only``, ``failover`` (default true).

    Outputs ``component_channel`` (the first output's channel, stable across failovers),
    ``component_name`` and ``component_robot`` (the candidate chosen). The component is held
    until the graph run ends.
    """

    def on_run(self) -> bool:
        """Request it; True when a candidate runs."""
        client = ComponentManagerClient.for_action(self)
        type_ = self.inputs.get_string("component_type")
        outputs: dict[str, str] = {}
        if "channel" in self.inputs:
            channel = self.inputs.get_string("channel")
            names = [d.outputs[0] for d in client.manager.descriptions(type_) if d.outputs]
            if channel and names:
                outputs[names[0]] = channel
        handle = client.acquire(
            self,
            type_,
            name=str(self.inputs.get("component_name", "")),
            outputs=outputs,
            local_only=bool(self.inputs.get("local_only", False)),
            failover=bool(self.inputs.get("failover", True)),
        )
        response = handle.response
        self.outputs["component_channel"] = response.output() if response.outputs else ""
        self.outputs["component_name"] = response.name
        self.outputs["component_robot"] = response.robot
        self.log(f"{type_}: {response.robot}/{response.name} (pid {response.pid})")
        return True
