"""UMRF parameters (the "parameter value format", PVF): types, values, trees.

A parameter tree in JSON nests namespaces; a member whose value holds ``"pvf_type"`` is a
parameter, anything else a namespace. Inside TeMoto parameters are flat, named with ``::``
(``pose::position::x``), and :func:`parse_parameter_tree` / :func:`dump_parameter_tree` convert.

Native types (``string``, ``strings``, ``number``, ``numbers``, ``bool``, ``bools``) may carry
JSON values; any other ``pvf_type`` is allowed (e.g. an in-process handle) but cannot carry a
value in JSON. Numbers are stored as ``float``; lists as ``list``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from temoto.errors import ConfigError

__all__ = [
    "MAX_TREE_DEPTH",
    "NATIVE_TYPES",
    "NO_VALUE",
    "Parameter",
    "ParameterSet",
    "check_value",
    "dump_parameter_tree",
    "kind_of",
    "parse_parameter_tree",
    "values_equal",
]


class _NoValue:
    """Sentinel type: a parameter without data."""

    _instance: _NoValue | None = None

    def __new__(cls) -> _NoValue:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "NO_VALUE"

    def __bool__(self) -> bool:
        return False


#: Marks a parameter that holds no data.
NO_VALUE: Final = _NoValue()

#: Native PVF types and the Python type of one element.
NATIVE_TYPES: Final[dict[str, tuple[type, bool]]] = {
    "string": (str, False),
    "strings": (str, True),
    "number": (float, False),
    "numbers": (float, True),
    "bool": (bool, False),
    "bools": (bool, True),
}

#: Deepest namespace nesting accepted in a parameter tree.
MAX_TREE_DEPTH: Final = 32

_SEP = "::"


def _check_scalar(value: object, elem: type) -> Any:
    if elem is str:
        if isinstance(value, str):
            return value
        raise TypeError("expected a string")
    if elem is bool:
        if isinstance(value, bool):
            return value
        raise TypeError("expected true or false")
    # number
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError("expected a number")
    number = float(value) if isinstance(value, float) else _int_to_float(value)
    if not math.isfinite(number):
        raise TypeError("expected a finite number")
    return number


def _int_to_float(value: int) -> float:
    try:
        return float(value)
    except OverflowError:
        raise TypeError("number too large") from None


def check_value(pvf_type: str, value: object) -> Any:
    """Check a value against a native PVF type and return it in canonical form.

    Args:
        pvf_type: A key of :data:`NATIVE_TYPES`.
        value: The candidate value (JSON-decoded or from Python code).

    Returns:
        The value, with numbers as ``float`` and arrays as new ``list`` objects.

    Raises:
        TypeError: If the value does not fit the type (the message says what was expected).
        KeyError: If ``pvf_type`` is not native.
    """
    elem, is_list = NATIVE_TYPES[pvf_type]
    if not is_list:
        return _check_scalar(value, elem)
    if not isinstance(value, list | tuple):
        raise TypeError(f"expected an array of {pvf_type[:-1]}s")
    out = []
    for i, item in enumerate(value):
        try:
            out.append(_check_scalar(item, elem))
        except TypeError as err:
            raise TypeError(f"element {i}: {err}") from None
    return out


def values_equal(pvf_type: str, a: object, b: object) -> bool:
    """Compare two values of one type the way ``pvf_allowed_values`` does.

    Args:
        pvf_type: The parameter type.
        a: One value.
        b: The other value.

    Returns:
        True if equal. Only ``string``, ``number`` and ``bool`` compare (as upstream); any other
        type never compares equal, so a non-empty allowed list rejects every value.
    """
    if pvf_type not in ("string", "number", "bool"):
        return False
    return type(a) is type(b) and a == b


@dataclass(frozen=True, slots=True)
class Parameter:
    """One (flattened) parameter of an action.

    Attributes:
        name: Full name, namespaces joined with ``::``.
        type: The ``pvf_type`` string.
        value: A literal (``pvf_value``) or :data:`NO_VALUE`.
        required: ``pvf_required``: an input must hold data before the action may start.
        updatable: ``pvf_updatable``: parents and graph modification may overwrite it.
        allowed_values: ``pvf_allowed_values``; empty means any value is accepted.
    """

    name: str
    type: str
    value: Any = NO_VALUE
    required: bool = True
    updatable: bool = True
    allowed_values: tuple[Any, ...] = ()

    @property
    def has_value(self) -> bool:
        """Whether the parameter carries a literal value."""
        return self.value is not NO_VALUE

    @property
    def native(self) -> bool:
        """Whether the type is one of the JSON-native types."""
        return self.type in NATIVE_TYPES

    def accepts(self, value: object) -> bool:
        """Whether an incoming value passes ``pvf_allowed_values``.

        Args:
            value: The incoming value.

        Returns:
            True if there is no allowed list or the value is in it.
        """
        if not self.allowed_values:
            return True
        return any(values_equal(self.type, value, allowed) for allowed in self.allowed_values)


#: Parameters of one side (inputs or outputs) of an action, by full name, in document order.
ParameterSet = Mapping[str, Parameter]


@dataclass(slots=True)
class _TreeParser:
    file: str | None
    make_error: Callable[..., ConfigError]
    warnings: list[str] = field(default_factory=list)

    def fail(self, path: str, message: str) -> ConfigError:
        return self.make_error(message, file=self.file, path=path)

    def tree(
        self, raw: object, path: str, prefix: str, depth: int, out: dict[str, Parameter]
    ) -> None:
        if not isinstance(raw, dict):
            raise self.fail(path, f"expected an object of parameters, got {kind_of(raw)}")
        if depth > MAX_TREE_DEPTH:
            raise self.fail(path, f"parameter namespaces nested deeper than {MAX_TREE_DEPTH}")
        for key, member in raw.items():
            sub = f"{path}.{key}"
            if not key:
                raise self.fail(sub, "empty parameter name")
            if _SEP in key:
                raise self.fail(sub, f"parameter name may not contain '{_SEP}'")
            name = f"{prefix}{_SEP}{key}" if prefix else key
            if isinstance(member, dict) and "pvf_type" in member:
                out[name] = self.leaf(member, sub, name)
            else:
                self.tree(member, sub, name, depth + 1, out)

    def leaf(self, raw: dict[str, Any], path: str, name: str) -> Parameter:
        pvf_type = raw["pvf_type"]
        if not isinstance(pvf_type, str) or not pvf_type:
            raise self.fail(
                f"{path}.pvf_type", f"expected a non-empty string, got {kind_of(pvf_type)}"
            )
        value: Any = NO_VALUE
        if "pvf_value" in raw:
            value = self.value(pvf_type, raw["pvf_value"], f"{path}.pvf_value")
        required = self.flag(raw, "pvf_required", path)
        updatable = self.flag(raw, "pvf_updatable", path)
        allowed: tuple[Any, ...] = ()
        if "pvf_allowed_values" in raw:
            items = raw["pvf_allowed_values"]
            apath = f"{path}.pvf_allowed_values"
            if not isinstance(items, list):
                raise self.fail(apath, f"expected an array, got {kind_of(items)}")
            if pvf_type in NATIVE_TYPES:
                elem_type = pvf_type if pvf_type in ("string", "number", "bool") else pvf_type[:-1]
                allowed = tuple(
                    self.value(elem_type, item, f"{apath}[{i}]") for i, item in enumerate(items)
                )
            elif items:
                raise self.fail(
                    apath, f"type '{pvf_type}' is not a JSON type and cannot list values"
                )
        for key in raw:
            if key not in _LEAF_KEYS:
                self.warnings.append(f"{path}.{key}: unknown key ignored")
        return Parameter(name, pvf_type, value, required, updatable, allowed)

    def value(self, pvf_type: str, raw: object, path: str) -> Any:
        if pvf_type not in NATIVE_TYPES:
            raise self.fail(path, f"type '{pvf_type}' is not a JSON type and cannot carry a value")
        try:
            return check_value(pvf_type, raw)
        except TypeError as err:
            if NATIVE_TYPES[pvf_type][1] and isinstance(raw, list | tuple):  # the wrong element
                for i, item in enumerate(raw):
                    try:
                        check_value(pvf_type[:-1], item)
                    except (TypeError, KeyError) as bad:
                        raise self.fail(
                            f"{path}[{i}]", f"{bad} for type '{pvf_type}', got {kind_of(item)}"
                        ) from None
            raise self.fail(path, f"{err} for type '{pvf_type}', got {kind_of(raw)}") from None

    def flag(self, raw: dict[str, Any], key: str, path: str) -> bool:
        value = raw.get(key, True)
        if not isinstance(value, bool):
            raise self.fail(f"{path}.{key}", f"expected true or false, got {kind_of(value)}")
        return value


_LEAF_KEYS = frozenset(
    {"pvf_type", "pvf_value", "pvf_required", "pvf_updatable", "pvf_allowed_values", "pvf_example"}
)


def kind_of(value: object) -> str:
    """Describe a decoded JSON value for an error message ("string 'x'", "an array", ...).

    Shared by every reader of UMRF documents, so their messages name values alike.

    Args:
        value: Any decoded JSON value.

    Returns:
        A short description: ``null``, ``true``/``false``, ``string '...'`` (cut at 40
        characters), ``number 3``, ``NaN``, ``an array``, ``an object``, or the type's name.
    """
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        shown = value if len(value) <= 40 else value[:37] + "..."
        return f"string {shown!r}"
    if isinstance(value, int | float):
        if value != value:
            return "NaN"
        return f"number {value!r}" if abs(value) < 1e15 else "a huge number"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def parse_parameter_tree(
    raw: object,
    *,
    path: str,
    file: str | None = None,
    error: Callable[..., ConfigError] = ConfigError,
    warnings: list[str] | None = None,
) -> dict[str, Parameter]:
    """Parse ``input_parameters`` / ``output_parameters`` into flat parameters.

    Args:
        raw: The JSON value of the tree.
        path: The key path of the tree in its document (for error messages).
        file: The file the document came from.
        error: The ConfigError subclass to raise.
        warnings: A list that receives a message per unknown key.

    Returns:
        Parameters by full (``::``-joined) name, in document order.

    Raises:
        ConfigError: (the ``error`` subclass) with the key path of the first problem.
    """
    parser = _TreeParser(file, error)
    out: dict[str, Parameter] = {}
    parser.tree(raw, path, "", 0, out)
    if warnings is not None:
        warnings.extend(parser.warnings)
    return out


def dump_parameter_tree(
    params: ParameterSet, values: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Serialise flat parameters back into a nested JSON tree (canonical form).

    Args:
        params: The parameters.
        values: Current data by name, overriding the literals (feedback snapshots); a name
            mapped to :data:`NO_VALUE` emits no value.

    Returns:
        A JSON-ready dict. ``pvf_value`` only when data is present and the type native;
        ``pvf_required`` and ``pvf_updatable`` only when false; ``pvf_allowed_values`` when
        non-empty.
    """
    root: dict[str, Any] = {}
    for name, param in params.items():
        node = root
        *spaces, leaf = name.split(_SEP)
        for space in spaces:
            node = node.setdefault(space, {})
        entry: dict[str, Any] = {"pvf_type": param.type}
        value = param.value if values is None else values.get(name, param.value)
        if value is not NO_VALUE and param.native:
            entry["pvf_value"] = list(value) if isinstance(value, list | tuple) else value
        if not param.required:
            entry["pvf_required"] = False  # upstream never writes it, and loses optional inputs
        if not param.updatable:
            entry["pvf_updatable"] = False
        if param.allowed_values:
            entry["pvf_allowed_values"] = list(param.allowed_values)
        node[leaf] = entry
    return root
