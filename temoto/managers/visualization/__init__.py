"""The Visualization Manager: displays loaded on demand, served live to Foxglove.

See ``docs/visualization.md``. :class:`VisualizationManager` serves ``"display"`` (one display
per distinct :class:`DisplayRequest`, while it is held); :class:`FoxgloveServer` is the live
Foxglove WebSocket server (optional extra ``temoto[foxglove]``, imported only when one is
made) and :class:`LiveRecorder` publishes on it what ``--record`` records.
"""

from __future__ import annotations

from temoto.managers.visualization.manager import Display, VisualizationManager
from temoto.managers.visualization.messages import DISPLAY_FIELDS, DisplayRequest, DisplayResponse

__all__ = [
    "DISPLAY_FIELDS",
    "Display",
    "DisplayRequest",
    "DisplayResponse",
    "VisualizationManager",
]
