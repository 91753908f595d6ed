"""WaitForComponentData: listen on a component's channel until data arrives."""

from __future__ import annotations

from temoto.core.action import Action
from temoto.managers.component.channels import ChannelReader

#: Seconds between checks for a stop request while waiting.
POLL_S = 0.05


class WaitForComponentData(Action):
    """Wait for datagrams on a component's channel.

    Input ``component_channel`` (or ``pipeline_channel``), optional ``count`` (default 1)
    and ``timeout`` (seconds, real time; 0 or absent: none).

    Binds the channel (it becomes its listener), waits for ``count`` datagrams and outputs the
    last one as text (``data``) and how many arrived (``received``). False on timeout.
    """

    def on_run(self) -> bool:
        """Wait; True when ``count`` datagrams arrived."""
        if "component_channel" in self.inputs:
            channel = self.inputs.get_string("component_channel")
        else:
            channel = self.inputs.get_string("pipeline_channel")
        count = int(self.inputs.get("count", 1))
        timeout = float(self.inputs.get("timeout", 0)) or None
        start = self.clock.monotonic()
        received = 0
        last = b""
        with ChannelReader(channel) as reader:
            while received < count:
                self.check_resources()
                if self.stop_requested:
                    return False
                if timeout is not None and self.clock.monotonic() - start >= timeout:
                    self.log(f"{received} of {count} datagrams on {channel} within {timeout:g} s")
                    self.outputs["received"] = received
                    self.outputs["data"] = last.decode(errors="replace")
                    return False
                data = reader.recv(POLL_S)
                if data is not None:
                    received += 1
                    last = data
        self.outputs["received"] = received
        self.outputs["data"] = last.decode(errors="replace")
        self.log(f"{received} datagrams on {channel}, last: {self.outputs['data']}")
        return True
