"""ShowDisplay: hold a display of the Visualization Manager for the node's lifetime."""

from __future__ import annotations

from temoto.core.action import Action
from temoto.managers.visualization.messages import DisplayRequest


class ShowDisplay(Action):
    """Show a display (a :class:`~temoto.managers.visualization.DisplayRequest`) for the node.

    Inputs ``source``; optional ``field``, ``target``, ``kind``, ``display_name``, ``rate_hz``,
    ``duration``.

    Outputs ``display_name`` and ``display_topic``. The display is held until the graph run
    ends or the node is removed; with ``duration`` (clock seconds), it is released after that
    long and the action returns.
    """

    def on_run(self) -> bool:
        """Load it; True once it is shown (and, with a duration, released again)."""
        request = DisplayRequest(
            self.inputs.get_string("source"),
            field=str(self.inputs.get("field", "")),
            target=str(self.inputs.get("target", "")),
            kind=str(self.inputs.get("kind", "")),
            name=str(self.inputs.get("display_name", "")),
            rate_hz=float(self.inputs.get("rate_hz", 10.0)),
        )
        resource = self.acquire("display", request)
        response = resource.response
        self.outputs["display_name"] = response.name
        self.outputs["display_topic"] = response.topics[0]
        self.log(f"display: showing {response.source} on {response.topics[0]}")
        if "duration" in self.inputs:
            self.sleep(self.inputs.get_number("duration"))
            self.release(resource)
        return True
