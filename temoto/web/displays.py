"""The Visualization Manager's loaded displays, for the live view's panels.

:class:`DisplayWatch` reads the displays of the ``"display"`` server
(:class:`~temoto.managers.visualization.VisualizationManager`) on a registrar, looked up at every
call (a manager registered later is found), and keeps each display's newest messages (a
watcher on the display: nothing is missed between two of the page's polls, no thread of its
own). ``GET /api/displays`` answers :meth:`DisplayWatch.state`; the page draws one panel per
display, of the kind its schema asks for (:data:`PANELS`), that appears when the display is
loaded and goes when it is released.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import TYPE_CHECKING, Any, Final, final

from temoto.errors import ResourceNotFoundError

if TYPE_CHECKING:
    from temoto.core.registrar import Registrar

__all__ = ["MAX_HISTORY", "PANELS", "DisplayWatch", "panel_of"]

#: Each display's messages the view keeps (the newest), for a plot's or a log's history.
MAX_HISTORY: Final = 120

#: The panels drawn from the newest message alone (the answer carries that one only).
_NEWEST_ONLY: Final = frozenset({"scan", "image", "cloud", "rawimage", "grid", "scene", "table"})

#: The panel each display kind (Foxglove schema) is drawn as; any other kind: ``text``.
PANELS: Final[dict[str, str]] = {
    "temoto.JointStates": "plot",  # each joint's position over time
    "foxglove.PoseInFrame": "map",  # an overlay on the map: the pose and its track
    "foxglove.PosesInFrame": "map",  # a robot's path travelled: its poses are the track
    "foxglove.FrameTransform": "map",
    "foxglove.LocationFix": "map",
    "foxglove.Log": "log",
    "foxglove.SceneUpdate": "scene",  # the world model's items, seen from above
    "foxglove.LaserScan": "scan",  # the newest scan's points around the sensor
    "foxglove.CompressedImage": "image",  # the newest image
    "foxglove.PointCloud": "cloud",  # the newest cloud seen from above, coloured by height
    "foxglove.RawImage": "rawimage",  # the newest image, drawn to a canvas
    "foxglove.Grid": "grid",  # the newest grid as a heat map seen from above
    "temoto.ComponentData": "text",  # a datagram as text (numbers in it: plotted too)
    "temoto.VehicleState": "table",
    "temoto.RobotHealth": "table",
}


def panel_of(kind: str) -> str:
    """The panel a display of this kind is drawn as (``plot``, ``map``, ``log``, ...)."""
    return PANELS.get(kind, "text")


@final
class DisplayWatch:
    """The loaded displays of a registrar's Visualization Manager, with their newest messages.

    Args:
        registrar: The registrar the manager serves on.
        history: Messages kept per display (the newest).
    """

    def __init__(self, registrar: Registrar, history: int = MAX_HISTORY) -> None:
        self.registrar = registrar
        self.history = history
        self._lock = threading.Lock()
        self._kept: dict[str, deque[dict[str, Any]]] = {}  # by resource id
        self._closed = False

    def _manager(self) -> Any:
        from temoto.managers.visualization.manager import VisualizationManager

        try:
            server = self.registrar.server(VisualizationManager.name)
        except ResourceNotFoundError:
            return None
        return server if isinstance(server, VisualizationManager) else None

    def state(self) -> list[dict[str, Any]]:
        """Every loaded display, by name: what it shows, its panel, its newest messages.

        Returns:
            ``[{"name", "kind", "panel", "source", "field", "target", "topic", "count",
            "messages": [...]}]`` (oldest message first; at most :attr:`history`; the newest
            only for a panel drawn from it: a scan, an image, a cloud, a grid, a scene, a
            table).
        """
        manager = self._manager()
        if manager is None:
            return []
        out = []
        live = set()
        for name, display in sorted(manager.displays().items()):
            key = display.resource_id
            live.add(key)
            with self._lock:
                kept = self._kept.get(key)
                new = kept is None
                if kept is None:
                    kept = self._kept[key] = deque(maxlen=self.history)
                    if display.last is not None:
                        kept.append(display.last)  # what it had before it was watched
            if new:  # outside our lock: the watcher runs under the display's, then takes ours
                display.watch(self._keeper(kept))
            request = display.request
            with self._lock:
                messages = list(kept)
            if panel_of(request.kind) in _NEWEST_ONLY:
                messages = messages[-1:]
            out.append(
                {
                    "name": name,
                    "kind": request.kind,
                    "panel": panel_of(request.kind),
                    "source": request.source,
                    "field": request.field,
                    "target": request.target,
                    "topic": request.topic,
                    "count": display.count,
                    "messages": messages,
                }
            )
        with self._lock:  # forget released displays
            for key in [k for k in self._kept if k not in live]:
                del self._kept[key]
        return out

    def _keeper(self, kept: deque[dict[str, Any]]) -> Any:
        def keep(message: dict[str, Any]) -> None:
            if self._closed:
                return
            with self._lock:
                kept.append(message)

        return keep

    def close(self) -> None:
        """Stop keeping messages (the watchers stay on their displays and do nothing)."""
        self._closed = True
        with self._lock:
            self._kept.clear()
