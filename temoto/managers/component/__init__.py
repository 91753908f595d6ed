"""The Component Manager: sensors and algorithms by type, reliability-ranked, with failover.

See ``docs/component-manager.md``. :class:`ComponentManager` serves ``"component"`` (one
component type, its channels, the best candidate behind it) and ``"pipeline"`` (components
composed by a template); :class:`ComponentManagerClient` is the consumers' side.
"""

from __future__ import annotations

from temoto.managers.component.channels import ChannelReader, ChannelSender, check_channel
from temoto.managers.component.client import (
    ComponentHandle,
    ComponentManagerClient,
    PipelineHandle,
)
from temoto.managers.component.description import (
    ComponentDescription,
    PipelineTemplate,
    Segment,
    load_descriptions,
    parse_descriptions,
)
from temoto.managers.component.manager import Candidate, ComponentManager, PipelineServer
from temoto.managers.component.messages import (
    ComponentRequest,
    ComponentResponse,
    PipelineRequest,
    PipelineResponse,
)
from temoto.managers.component.reliability import Reliability

__all__ = [
    "Candidate",
    "ChannelReader",
    "ChannelSender",
    "ComponentDescription",
    "ComponentHandle",
    "ComponentManager",
    "ComponentManagerClient",
    "ComponentRequest",
    "ComponentResponse",
    "PipelineHandle",
    "PipelineRequest",
    "PipelineResponse",
    "PipelineServer",
    "PipelineTemplate",
    "Reliability",
    "Segment",
    "check_channel",
    "load_descriptions",
    "parse_descriptions",
]
