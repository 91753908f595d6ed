"""The JSON schemas of a recording: Foxglove's well-known ones, and TeMoto's own.

Foxglove recognises a channel's schema by its name (``foxglove.PoseInFrame`` ...) and its
encoding (``jsonschema``); the panels then know what to draw. The field names here are the
ones of Foxglove's published schemas (timestamps are ``{"sec", "nsec"}`` objects). Where no
well-known schema fits (a node's transition, a graph's run, joint states, a vehicle's mode),
the schema is TeMoto's own, named ``temoto.*``, and every field is a plain number, string or
array, so Foxglove's Plot, Raw Messages and State Transitions panels show it.
"""

from __future__ import annotations

import json
from typing import Any, Final

__all__ = ["SCHEMAS", "schema_bytes", "stamp"]

_TIME: Final[dict[str, Any]] = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}
_VECTOR3: Final[dict[str, Any]] = {
    "type": "object",
    "title": "foxglove.Vector3",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z")},
}
_QUATERNION: Final[dict[str, Any]] = {
    "type": "object",
    "title": "foxglove.Quaternion",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z", "w")},
}
_STRING: Final = {"type": "string"}
_NUMBER: Final = {"type": "number"}
_NUMBERS: Final = {"type": "array", "items": {"type": "number"}}
_STRINGS: Final = {"type": "array", "items": {"type": "string"}}


def _object(title: str, description: str, **properties: Any) -> dict[str, Any]:
    return {
        "title": title,
        "description": description,
        "type": "object",
        "properties": properties,
    }


#: Every schema a recording may hold, by name.
SCHEMAS: Final[dict[str, dict[str, Any]]] = {
    "foxglove.Log": _object(
        "foxglove.Log",
        "A log message",
        timestamp=_TIME,
        level={
            "title": "foxglove.LogLevel",
            "oneOf": [
                {"title": name, "const": value}
                for value, name in enumerate(
                    ("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL")
                )
            ],
        },
        message=_STRING,
        name=_STRING,
        file=_STRING,
        line={"type": "integer", "minimum": 0},
    ),
    "foxglove.PoseInFrame": _object(
        "foxglove.PoseInFrame",
        "A timestamped pose in a reference frame",
        timestamp=_TIME,
        frame_id=_STRING,
        pose={
            "type": "object",
            "title": "foxglove.Pose",
            "properties": {"position": _VECTOR3, "orientation": _QUATERNION},
        },
    ),
    "foxglove.FrameTransform": _object(
        "foxglove.FrameTransform",
        "A transform between two reference frames",
        timestamp=_TIME,
        parent_frame_id=_STRING,
        child_frame_id=_STRING,
        translation=_VECTOR3,
        rotation=_QUATERNION,
    ),
    "foxglove.LocationFix": _object(
        "foxglove.LocationFix",
        "A navigation satellite fix",
        timestamp=_TIME,
        frame_id=_STRING,
        latitude=_NUMBER,
        longitude=_NUMBER,
        altitude=_NUMBER,
        position_covariance={**_NUMBERS, "minItems": 9, "maxItems": 9},
        position_covariance_type={
            "title": "foxglove.PositionCovarianceType",
            "oneOf": [
                {"title": name, "const": value}
                for value, name in enumerate(("UNKNOWN", "APPROXIMATED", "DIAGONAL_KNOWN", "KNOWN"))
            ],
        },
    ),
    "temoto.GraphEvent": _object(
        "temoto.GraphEvent",
        "A graph run started or ended (result: on_true, on_false, ... when it ended)",
        timestamp=_TIME,
        t={**_NUMBER, "description": "the engine's clock, seconds"},
        graph=_STRING,
        event={"type": "string", "enum": ["started", "finished"]},
        result=_STRING,
    ),
    "temoto.NodeTransition": _object(
        "temoto.NodeTransition",
        "A node of a graph run changed state (node: <Name>_<instance id>)",
        timestamp=_TIME,
        t={**_NUMBER, "description": "the engine's clock, seconds"},
        graph=_STRING,
        node=_STRING,
        old=_STRING,
        new=_STRING,
        result={
            **_STRING,
            "description": "the node's result (on_true, on_false, ...) on the change that ends"
            " its run; absent otherwise",
        },
    ),
    "temoto.JointStates": _object(
        "temoto.JointStates",
        "Joint positions (rad) in profile order, as sensor_msgs/JointState names them",
        timestamp=_TIME,
        name=_STRINGS,
        position=_NUMBERS,
        velocity=_NUMBERS,
        effort=_NUMBERS,
    ),
    "temoto.VehicleState": _object(
        "temoto.VehicleState",
        "A vehicle's newest telemetry (altitude: metres above home)",
        timestamp=_TIME,
        armed={"type": "boolean"},
        mode=_STRING,
        latitude=_NUMBER,
        longitude=_NUMBER,
        altitude=_NUMBER,
        roll=_NUMBER,
        pitch=_NUMBER,
        yaw=_NUMBER,
        battery_voltage=_NUMBER,
        battery_remaining={"type": "integer"},
        heartbeat_age=_NUMBER,
    ),
    "temoto.RobotHealth": _object(
        "temoto.RobotHealth",
        "Whether every device of the robot works",
        timestamp=_TIME,
        robot=_STRING,
        healthy={"type": "boolean"},
    ),
    "temoto.FleetMessage": _object(
        "temoto.FleetMessage",
        "A fleet envelope as heard on the transport (not checked, payload not decoded)",
        timestamp=_TIME,
        channel=_STRING,
        sender=_STRING,
        type=_STRING,
        seq={"type": "integer"},
        stamp_us={"type": "integer"},
        session={"type": "integer"},
        size={"type": "integer"},
        signed={"type": "boolean"},
    ),
}


def schema_bytes(name: str) -> bytes:
    """The JSON schema ``name`` as an MCAP schema record's data.

    Args:
        name: A key of :data:`SCHEMAS`.

    Returns:
        UTF-8 JSON.

    Raises:
        KeyError: An unknown schema.
    """
    return json.dumps(SCHEMAS[name], separators=(",", ":")).encode()


def stamp(ns: int) -> dict[str, int]:
    """A Foxglove ``time`` object from nanoseconds since the epoch.

    Args:
        ns: Nanoseconds (≥ 0).

    Returns:
        ``{"sec": ..., "nsec": ...}``.
    """
    sec, nsec = divmod(max(ns, 0), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}
