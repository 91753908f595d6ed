"""ROS 2 messages to and from JSON objects (runs in the bridge, where rclpy is imported).

Types are named like ``std_srvs/srv/Trigger``: ``<package>/<msg|srv|action>/<Name>``. Fields are
filled from a JSON object by name (nested messages from nested objects, sequences from lists);
an unknown field is an error naming it. Messages become JSON objects the same way, with numpy
arrays and ``bytes`` as lists.
"""

from __future__ import annotations

import importlib
import re
from typing import Any, Final

__all__ = ["fill", "import_type", "to_json"]

_TYPE_NAME: Final = re.compile(
    r"^([A-Za-z_][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)$"
)


def import_type(name: str, kind: str) -> Any:
    """The class of a ROS 2 interface named like ``std_srvs/srv/Trigger``.

    Args:
        name: The type's name.
        kind: ``msg``, ``srv`` or ``action``, what the caller needs.

    Returns:
        The class.

    Raises:
        ValueError: A malformed name, the wrong kind, or a type that is not installed.
    """
    match = _TYPE_NAME.match(name)
    if match is None:
        raise ValueError(f"{name!r} is not a ROS 2 type name like 'std_msgs/{kind}/String'")
    package, found_kind, cls = match.groups()
    if found_kind != kind:
        raise ValueError(f"{name!r} is a {found_kind} type; this needs a {kind} type")
    try:
        module = importlib.import_module(f"{package}.{kind}")
    except ImportError:
        raise ValueError(
            f"{name!r}: the interface package {package!r} is not installed "
            f"(pip install ros-{package.replace('_', '-')})"
        ) from None
    try:
        return getattr(module, cls)
    except AttributeError:
        raise ValueError(f"{name!r}: {package}/{kind} has no type {cls!r}") from None


def fill(msg: Any, values: dict[str, Any], where: str = "") -> Any:
    """Set a message's fields from a JSON object.

    Args:
        msg: A message instance.
        values: Field names to values.
        where: The path of ``msg`` for error messages.

    Returns:
        ``msg``.

    Raises:
        ValueError: An unknown field, or a value of the wrong type.
    """
    fields = msg.get_fields_and_field_types()
    for key, value in values.items():
        path = f"{where}.{key}" if where else key
        if key not in fields:
            known = ", ".join(fields) or "none"
            raise ValueError(f"{type(msg).__name__} has no field {path!r} (fields: {known})")
        current = getattr(msg, key)
        try:
            if hasattr(current, "get_fields_and_field_types"):
                if not isinstance(value, dict):
                    raise TypeError(f"an object, not {type(value).__name__}")
                fill(current, value, path)
                continue
            if isinstance(current, bytes) and isinstance(value, int) and len(current) == 1:
                value = bytes([value])  # an ``octet``/``byte`` field (DiagnosticStatus.level)
            if isinstance(value, list):
                element = _element_class(msg, key)
                if element is not None:
                    value = [fill(element(), v, f"{path}[{i}]") for i, v in enumerate(value)]
            setattr(msg, key, value)
        except (TypeError, AssertionError, ValueError) as exc:
            if isinstance(exc, ValueError) and " has no field " in str(exc):
                raise
            raise ValueError(f"field {path!r} of {type(msg).__name__}: {exc}") from None
    return msg


def _element_class(msg: Any, key: str) -> Any:
    """The message class of a sequence field's elements, or None for a sequence of primitives."""
    slot_types = getattr(type(msg), "SLOT_TYPES", ())
    names = list(msg.get_fields_and_field_types())
    if key not in names or len(slot_types) != len(names):
        return None
    slot = slot_types[names.index(key)]
    value_type = getattr(slot, "value_type", None)
    namespaces = getattr(value_type, "namespaces", None)
    if value_type is None or namespaces is None:
        return None
    module = importlib.import_module(".".join(namespaces))
    return getattr(module, value_type.name)


def to_json(msg: Any) -> Any:
    """A message (or a field's value) as JSON-compatible data.

    Args:
        msg: A message, or a value of one of its fields.

    Returns:
        An object, list, number, string, bool or None.
    """
    if hasattr(msg, "get_fields_and_field_types"):
        return {key: to_json(getattr(msg, key)) for key in msg.get_fields_and_field_types()}
    if isinstance(msg, (bytes, bytearray)):
        return list(msg)
    if isinstance(msg, (list, tuple)):
        return [to_json(v) for v in msg]
    tolist = getattr(msg, "tolist", None)  # numpy arrays and scalars
    if tolist is not None:
        return tolist()
    return msg
