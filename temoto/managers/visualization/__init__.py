"""The Visualization Manager: displays loaded on demand, served live to Foxglove.

See ``docs/visualization.md``. :class:`VisualizationManager` serves ``"display"`` (one display
per distinct :class:`DisplayRequest`, while it is held);
:class:`~temoto.managers.visualization.foxglove.FoxgloveServer` is the live Foxglove WebSocket
server (optional extra ``temoto[foxglove]``, imported only when one is made) and
:class:`~temoto.managers.visualization.foxglove.LiveRecorder` publishes on it what
``--record`` records. The names below are imported on first use, so that the command line's
``--foxglove`` option (:mod:`~temoto.managers.visualization.live`) costs nothing unless used.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from temoto.managers.visualization.manager import Display, VisualizationManager
    from temoto.managers.visualization.messages import (
        DISPLAY_FIELDS,
        DisplayRequest,
        DisplayResponse,
    )

__all__ = [
    "DISPLAY_FIELDS",
    "Display",
    "DisplayRequest",
    "DisplayResponse",
    "VisualizationManager",
]

_WHERE = {
    "DISPLAY_FIELDS": "messages",
    "Display": "manager",
    "DisplayRequest": "messages",
    "DisplayResponse": "messages",
    "VisualizationManager": "manager",
}


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
