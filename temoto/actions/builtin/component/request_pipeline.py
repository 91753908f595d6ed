"""RequestPipeline: hold a pipeline built from a template for the rest of the graph run."""

from __future__ import annotations

from temoto.core.action import Action
from temoto.managers.component.client import ComponentManagerClient


class RequestPipeline(Action):
    """Request a pipeline from a template and hold it until the graph run ends.

    Input ``template``; optional ``channel`` (where the first pipeline output should go),
    ``local_only``, ``failover`` (default true). Output ``pipeline_channel``.
    """

    def on_run(self) -> bool:
        """Request it; True when every segment runs."""
        client = ComponentManagerClient.for_action(self)
        template = self.inputs.get_string("template")
        outputs: dict[str, str] = {}
        channel = str(self.inputs.get("channel", ""))
        if channel:
            first = client.manager.template(template).outputs
            if first:
                outputs[first[0][0]] = channel
        handle = client.acquire_pipeline(
            self,
            template,
            outputs=outputs,
            local_only=bool(self.inputs.get("local_only", False)),
            failover=bool(self.inputs.get("failover", True)),
        )
        self.outputs["pipeline_channel"] = handle.channel()
        names = ", ".join(f"{s}={r.name}" for s, r in handle.segments().items())
        self.log(f"pipeline {template}: {names}")
        return True
