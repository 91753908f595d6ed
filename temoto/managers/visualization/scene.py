"""The world model's tree as a ``foxglove.SceneUpdate``: the ``world`` display's messages.

A ``world`` display (``DisplayRequest("world", target=ROOT)``) shows the items of the Context
Manager on the display's registrar (the whole tree, or the subtree under ``ROOT``): one scene
entity per item, in the frame ``world`` (each item's pose composed up its tree), with a cube
(none for a ``map``), its name as a text label, and its type and parent as metadata. A message
is sent when the display is loaded and after every change of the tree (local or received from
another robot): the whole subtree again (at most :data:`MAX_ENTITIES` items), and a deletion
for each item shown before and gone now.

Field names and values follow Foxglove's message schemas (``SceneUpdate``, ``SceneEntity``,
``CubePrimitive``, ``TextPrimitive``, ``SceneEntityDeletion`` at
https://docs.foxglove.dev/docs/visualization/message-schemas/scene-update).
"""

from __future__ import annotations

from typing import Any, Final

from temoto.record.schemas import SCHEMAS, stamp

__all__ = ["MAX_ENTITIES", "SCENE_SCHEMA", "scene_update"]

#: The items a message carries at most (the first by name).
MAX_ENTITIES: Final = 500

#: A cube's edge (metres) and colour (RGBA, 0..1) by item type.
CUBE: Final = 0.2
COLORS: Final[dict[str, tuple[float, float, float, float]]] = {
    "robot": (0.18, 0.49, 0.88, 0.9),
    "object": (0.85, 0.55, 0.1, 0.9),
    "component": (0.58, 0.2, 0.92, 0.9),
}
_OTHER: Final = (0.5, 0.5, 0.5, 0.9)

_POSE: Final = SCHEMAS["foxglove.PoseInFrame"]["properties"]["pose"]
_TIME: Final = SCHEMAS["foxglove.PoseInFrame"]["properties"]["timestamp"]
_STR: Final = {"type": "string"}
_NUM: Final = {"type": "number"}
_COLOR: Final = {
    "type": "object",
    "title": "foxglove.Color",
    "properties": {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM},
}
_LIST: Final = {"type": "array", "items": {"type": "object"}}

#: The JSON schema of the messages (the parts of Foxglove's SceneUpdate they use).
SCENE_SCHEMA: Final[dict[str, Any]] = {
    "title": "foxglove.SceneUpdate",
    "description": "An update to the entities of a 3D scene (the world model's items)",
    "type": "object",
    "properties": {
        "deletions": {
            "type": "array",
            "items": {
                "type": "object",
                "title": "foxglove.SceneEntityDeletion",
                "properties": {"timestamp": _TIME, "type": {"type": "integer"}, "id": _STR},
            },
        },
        "entities": {
            "type": "array",
            "items": {
                "type": "object",
                "title": "foxglove.SceneEntity",
                "properties": {
                    "timestamp": _TIME,
                    "frame_id": _STR,
                    "id": _STR,
                    "lifetime": _TIME,
                    "frame_locked": {"type": "boolean"},
                    "metadata": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "properties": {"key": _STR, "value": _STR},
                        },
                    },
                    "arrows": _LIST,
                    "cubes": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "title": "foxglove.CubePrimitive",
                            "properties": {
                                "pose": _POSE,
                                "size": SCHEMAS["foxglove.FrameTransform"]["properties"][
                                    "translation"
                                ],
                                "color": _COLOR,
                            },
                        },
                    },
                    "spheres": _LIST,
                    "cylinders": _LIST,
                    "lines": _LIST,
                    "triangles": _LIST,
                    "texts": {
                        "type": "array",
                        "items": {
                            "type": "object",
                            "title": "foxglove.TextPrimitive",
                            "properties": {
                                "pose": _POSE,
                                "billboard": {"type": "boolean"},
                                "font_size": _NUM,
                                "scale_invariant": {"type": "boolean"},
                                "color": _COLOR,
                                "text": _STR,
                            },
                        },
                    },
                    "models": _LIST,
                },
            },
        },
    },
}

_MATCHING_ID: Final = 0  # SceneEntityDeletion.type: delete the entity with this id


def _color(rgba: tuple[float, float, float, float]) -> dict[str, float]:
    r, g, b, a = rgba
    return {"r": r, "g": g, "b": b, "a": a}


def _entity(item: Any, pose: Any, ts: dict[str, int]) -> dict[str, Any]:
    """One item as a scene entity: a cube (not for a map) and its name."""
    where = {
        "position": {"x": pose.x, "y": pose.y, "z": pose.z},
        "orientation": {"x": pose.qx, "y": pose.qy, "z": pose.qz, "w": pose.qw},
    }
    above = {
        "position": {**where["position"], "z": pose.z + CUBE},
        "orientation": where["orientation"],
    }
    cubes = []
    if item.type != "map":
        cubes.append(
            {
                "pose": where,
                "size": {"x": CUBE, "y": CUBE, "z": CUBE},
                "color": _color(COLORS.get(item.type, _OTHER)),
            }
        )
    return {
        "timestamp": ts,
        "frame_id": "world",
        "id": item.name,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [
            {"key": "type", "value": item.type},
            {"key": "parent", "value": item.parent},
            {"key": "maintainer", "value": item.maintainer},
        ],
        "arrows": [],
        "cubes": cubes,
        "spheres": [],
        "cylinders": [],
        "lines": [],
        "triangles": [],
        "texts": [
            {
                "pose": above,
                "billboard": True,
                "font_size": 14.0,
                "scale_invariant": True,
                "color": _color((0.1, 0.1, 0.1, 1.0)),
                "text": item.name,
            }
        ],
        "models": [],
    }


def scene_update(
    context: Any, root: str, shown: set[str], ns: int
) -> tuple[dict[str, Any], set[str]]:
    """The world model's (sub)tree now, as a SceneUpdate.

    Args:
        context: The :class:`~temoto.managers.context.ContextManager`.
        root: The subtree's root item ("" = every item).
        shown: The items the previous message showed (their deletions are sent if gone).
        ns: The messages' time, ns since the epoch.

    Returns:
        The message and the items it shows.

    Raises:
        ContextItemNotFoundError: ``root`` is not an item.
    """
    from temoto.errors import ContextError

    ts = stamp(ns)
    items = context.subtree(root) if root else context.items()
    entities = []
    for item in items[:MAX_ENTITIES]:
        try:
            pose = context.world_pose(item.name)
        except ContextError:  # detached: not drawn until it is attached again
            continue
        entities.append(_entity(item, pose, ts))
    now = {e["id"] for e in entities}
    deletions = [
        {"timestamp": ts, "type": _MATCHING_ID, "id": name} for name in sorted(shown - now)
    ]
    return {"deletions": deletions, "entities": entities}, now
