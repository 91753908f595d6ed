"""The request and response of the ``"display"`` server (registrar values).

A :class:`DisplayRequest` names where the data comes from (``source`` and ``target``), which
of its streams (``field``) and the Foxglove schema it is shown as (``kind``). Equal requests
are equal values, so they share one display.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Final

__all__ = ["DISPLAY_FIELDS", "OTHER_KINDS", "DisplayRequest", "DisplayResponse"]

#: What each source can show: field -> the schema (``kind``) it is shown as.
DISPLAY_FIELDS: Final[dict[str, dict[str, str]]] = {
    # A robot of the Robot Manager (target: its name, "" = the manager's robot).
    "robot": {
        "pose": "foxglove.PoseInFrame",
        "path": "foxglove.PosesInFrame",  # the path travelled: a pose per 2 cm, the newest 200
        "plan": "foxglove.PosesInFrame",  # the path planned: the straight segment to the goal
        "tf": "foxglove.FrameTransform",
        "joints": "temoto.JointStates",
        "location": "foxglove.LocationFix",
        "vehicle": "temoto.VehicleState",
        "health": "temoto.RobotHealth",
    },
    # An action's log (target: the logger below temoto.action, e.g. "patrol.Navigate_3";
    # "" = every action's).
    "log": {"log": "foxglove.Log"},
    # A component's first output (target: the component type; candidate: one of its
    # descriptions, "" = the Component Manager's choice, with failover).
    "component": {"data": "temoto.ComponentData"},
    # The world model of the Context Manager on the same registrar (target: the subtree's
    # root item, "" = every item).
    "world": {"scene": "foxglove.SceneUpdate"},
}

#: Other kinds a field may be shown as, decoding its data (the first kind of the field's is the
#: default): a component's datagrams as a laser scan (a JSON object of LaserScan's fields), a
#: compressed image (the bytes of a PNG or JPEG image), a point cloud, a raw image or a grid;
#: see ``decode.py``.
OTHER_KINDS: Final[dict[tuple[str, str], tuple[str, ...]]] = {
    ("component", "data"): (
        "foxglove.LaserScan",
        "foxglove.CompressedImage",
        "foxglove.PointCloud",
        "foxglove.RawImage",
        "foxglove.Grid",
    ),
}

_NAME: Final = re.compile(r"[A-Za-z0-9_.-]+")


@dataclass(frozen=True)
class DisplayRequest:
    """Ask for a display (the ``"display"`` server).

    Attributes:
        source: Where the data comes from: ``robot``, ``log`` or ``component``
            (:data:`DISPLAY_FIELDS`).
        field: Which of the source's streams (``pose``, ``joints`` ...; ``log`` for a log;
            ``data`` for a component).
        target: The robot's name ("" = the Robot Manager's robot), the action logger below
            ``temoto.action`` ("" = every action's), or the component type (required).
        kind: The Foxglove schema it is shown as ("" = the field's; another is refused).
        name: The display's name, its topics' prefix ``/display/<name>/`` ("" = made from
            the source, target and field).
        rate_hz: Samples per second of a polled source (a robot's streams).
        candidate: A component display: this candidate only, without failover (its failure
            is the display's); "" = the manager's best, substituted when it fails.

    Raises:
        TypeError: A field of the wrong type.
        ValueError: An unknown source or field, a kind the field cannot be shown as, a bad
            name, a rate that is not positive.
    """

    source: str
    field: str = ""
    target: str = ""
    kind: str = ""
    name: str = ""
    rate_hz: float = 10.0
    candidate: str = ""

    def __post_init__(self) -> None:
        for attr in ("source", "field", "target", "kind", "name", "candidate"):
            value = getattr(self, attr)
            if not isinstance(value, str):
                raise TypeError(f"a display's {attr} must be a str, not {type(value).__name__}")
        fields = DISPLAY_FIELDS.get(self.source)
        if fields is None:
            raise ValueError(
                f"unknown display source '{self.source}' (one of: {', '.join(DISPLAY_FIELDS)})"
            )
        field = self.field or next(iter(fields))
        kind = fields.get(field)
        if kind is None:
            raise ValueError(
                f"a {self.source} display has no field '{field}' (one of: {', '.join(fields)})"
            )
        if self.source == "component" and not self.target:
            raise ValueError("a component display needs a target (the component type)")
        if self.candidate and self.source != "component":
            raise ValueError(f"a {self.source} display has no candidate")
        other = OTHER_KINDS.get((self.source, field), ())
        if self.kind and self.kind != kind and self.kind not in other:
            shown = " or ".join((kind, *other))
            what = f"a {self.source} {field} display"
            raise ValueError(f"{what} is shown as {shown}, not {self.kind}")
        decoded = self.kind if self.kind in other else ""
        if isinstance(self.rate_hz, bool) or not isinstance(self.rate_hz, int | float):
            raise TypeError(f"a display's rate_hz must be a number, not {self.rate_hz!r}")
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ValueError(f"a display's rate_hz must be positive: {self.rate_hz!r}")
        parts = (
            self.source,
            self.target,
            self.candidate,
            field,
            decoded.rpartition(".")[2].lower(),  # component_scanner_data_laserscan
        )
        name = self.name or "_".join(p for p in parts if p)
        name = name.replace("/", ".")
        if not _NAME.fullmatch(name):
            raise ValueError(f"a display's name may hold letters, digits, '_', '.', '-': {name!r}")
        object.__setattr__(self, "field", field)
        object.__setattr__(self, "kind", decoded or kind)
        object.__setattr__(self, "name", name)
        object.__setattr__(self, "rate_hz", float(self.rate_hz))

    @property
    def topic(self) -> str:
        """The display's topic on the live server: ``/display/<name>/<field>``."""
        return f"/display/{self.name}/{self.field}"


@dataclass(frozen=True)
class DisplayResponse:
    """A loaded display.

    Attributes:
        name: The display's name.
        topics: Its topics on the live server.
        kind: The schema they carry.
        source: What it shows, in words (``robot sim_arm joints``).
        resource_id: The display's registrar resource (tells a display from an earlier one of
            the same name, lost in a restart).
    """

    name: str
    topics: tuple[str, ...]
    kind: str
    source: str
    resource_id: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "topics", tuple(self.topics))
