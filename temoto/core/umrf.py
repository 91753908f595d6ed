"""UMRF actions: the node object of a graph, and stand-alone action descriptions.

One dataclass, :class:`Umrf`, serves both uses, as in the UMRF format itself: inside a graph it
carries relations, literal values and a state; in a ``<snake_name>.umrf.json`` file beside an
action's module it describes the action's name, type and parameters.

:func:`parse_umrf` is the only code that reads a raw action object; it raises
:class:`~temoto.errors.ConfigError` subclasses that name the file and the key path. Reading
files and writing documents is :mod:`temoto.core.documents`' job.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

from temoto.core.params import Parameter, kind_of, parse_parameter_tree
from temoto.core.states import NodeState, Response, Result
from temoto.errors import ConfigError, UmrfError

__all__ = [
    "CONDITION_RESULTS",
    "DEFAULT_CONDITIONS",
    "ENTRY_NAME",
    "EXIT_NAME",
    "MAX_INSTANCE_ID",
    "ChildRelation",
    "LogMessage",
    "ParentRelation",
    "Remap",
    "Umrf",
    "UmrfReader",
    "parse_umrf",
    "snake_case",
]

#: Default response of every relation, for each action result.
DEFAULT_CONDITIONS: Final[Mapping[Result, Response]] = {
    Result.TRUE: Response.RUN,
    Result.FALSE: Response.RUN,
    Result.STOPPED: Response.IGNORE,
    Result.ERROR: Response.BYPASS,
}

#: Names of the synthetic nodes every graph gets; user actions may not use them.
ENTRY_NAME: Final = "graph_entry"
EXIT_NAME: Final = "graph_exit"

#: Instance ids are unsigned 32-bit integers (as upstream).
MAX_INSTANCE_ID: Final = 2**32 - 1

#: The results a relation's conditions are written for, in upstream's order.
CONDITION_RESULTS: Final = (Result.TRUE, Result.FALSE, Result.STOPPED, Result.ERROR)
_RESULT_NAMES = ", ".join(r.value for r in CONDITION_RESULTS)
_RESPONSE_NAMES = ", ".join(r.value for r in Response)

ErrorFactory = Callable[..., ConfigError]


def snake_case(name: str) -> str:
    """Convert an action's CamelCase name to snake_case (``TaAddString`` → ``ta_add_string``).

    Args:
        name: The action name.

    Returns:
        The snake_case form used for description files and modules.
    """
    out: list[str] = []
    for i, ch in enumerate(name):
        if (
            ch.isupper()
            and i
            and (not name[i - 1].isupper() or (i + 1 < len(name) and name[i + 1].islower()))
        ):
            out.append("_")
        out.append(ch.lower())
    return "".join(out)


@dataclass(frozen=True, slots=True)
class Remap:
    """Rename of a parent's output (``from_``) to a child's input (``to``)."""

    from_: str
    to: str


@dataclass(frozen=True, slots=True)
class ParentRelation:
    """A parent as seen from the child (also the form of a ``graph_exit`` entry).

    Attributes:
        name: Parent action name.
        instance_id: Parent instance.
        required: The child starts only after this parent has finished at least once.
        conditions: Responses written in the document; the rest use the defaults.
    """

    name: str
    instance_id: int = 0
    required: bool = True
    conditions: Mapping[Result, Response] = field(default_factory=dict)

    @property
    def full_name(self) -> str:
        """``<name>_<instance_id>``."""
        return f"{self.name}_{self.instance_id}"

    def response(self, result: Result) -> Response:
        """How the child reacts to this parent's result.

        Args:
            result: The parent's result.

        Returns:
            The written response, or the default one.

        Raises:
            KeyError: For ``Result.HALTED`` (not an action result).
        """
        written = self.conditions.get(result)
        return written if written is not None else DEFAULT_CONDITIONS[result]


@dataclass(frozen=True, slots=True)
class ChildRelation:
    """A child as seen from the parent (also the form of a ``graph_entry`` entry).

    Attributes:
        name: Child action name.
        instance_id: Child instance.
        remap: Renames applied to the parent's outputs before they reach this child.
    """

    name: str
    instance_id: int = 0
    remap: tuple[Remap, ...] = ()

    @property
    def full_name(self) -> str:
        """``<name>_<instance_id>``."""
        return f"{self.name}_{self.instance_id}"


@dataclass(frozen=True, slots=True)
class LogMessage:
    """One entry of an action's runtime log."""

    timestamp_ms: int
    message: str


@dataclass(frozen=True, slots=True)
class Umrf:
    """An action: a node of a graph, or a stand-alone action description.

    Attributes:
        name: CamelCase action name (or the name of a graph used as a sub-graph).
        type: ``sync``, ``async`` or ``spontaneous`` (free string; only spontaneous differs).
        instance_id: Distinguishes several instances of one action in a graph.
        actor: The actor (robot) that executes it; empty means the local actor.
        description: Free text.
        state: The node state written in the document, if any.
        parents: Parent relations.
        children: Child relations.
        input_parameters: Inputs by full name.
        output_parameters: Outputs by full name.
        gui_attributes: Arbitrary JSON echoed back verbatim (None if absent).
        runtime_messages: The action's log, newest first.
    """

    name: str
    type: str
    instance_id: int = 0
    actor: str = ""
    description: str = ""
    state: NodeState = NodeState.UNINITIALIZED
    parents: tuple[ParentRelation, ...] = ()
    children: tuple[ChildRelation, ...] = ()
    input_parameters: Mapping[str, Parameter] = field(default_factory=dict)
    output_parameters: Mapping[str, Parameter] = field(default_factory=dict)
    gui_attributes: Any = None
    runtime_messages: tuple[LogMessage, ...] = ()

    @property
    def full_name(self) -> str:
        """``<name>_<instance_id>``, the node's key inside a graph."""
        return f"{self.name}_{self.instance_id}"

    @property
    def spontaneous(self) -> bool:
        """Whether the action re-runs by itself after each run."""
        return self.type == "spontaneous"


_ACTION_KEYS = frozenset(
    {
        "name",
        "type",
        "instance_id",
        "actor",
        "description",
        "state",
        "parents",
        "children",
        "input_parameters",
        "output_parameters",
        "gui_attributes",
        "runtime",
    }
)


@dataclass(slots=True)
class UmrfReader:
    """Reads raw UMRF JSON pieces; shared by action descriptions and graphs.

    Attributes:
        file: The file being read, for messages.
        error: The ConfigError subclass to raise.
        warnings: Collected messages about things upstream accepts but we doubt.
    """

    file: str | None = None
    error: ErrorFactory = UmrfError
    warnings: list[str] = field(default_factory=list)

    def fail(self, path: str, message: str) -> ConfigError:
        """Build an error at a key path.

        Args:
            path: The key path.
            message: The problem.

        Returns:
            The error, to be raised by the caller.
        """
        return self.error(message, file=self.file, path=path)

    def obj(self, raw: object, path: str) -> dict[str, Any]:
        """Require a JSON object.

        Args:
            raw: The value.
            path: Its key path.

        Returns:
            The object.

        Raises:
            ConfigError: If it is not an object.
        """
        if not isinstance(raw, dict):
            raise self.fail(path, f"expected an object, got {kind_of(raw)}")
        return raw

    def array(self, raw: dict[str, Any], key: str, path: str) -> list[Any]:
        """Read an optional array member (absent means empty).

        Args:
            raw: The enclosing object.
            key: The member.
            path: The object's key path.

        Returns:
            The list.

        Raises:
            ConfigError: If the member is not an array.
        """
        value = raw.get(key, [])
        if not isinstance(value, list):
            raise self.fail(_join(path, key), f"expected an array, got {kind_of(value)}")
        return value

    def string(
        self,
        raw: dict[str, Any],
        key: str,
        path: str,
        *,
        required: bool = False,
        empty: bool = True,
    ) -> str:
        """Read a string member.

        Args:
            raw: The enclosing object.
            key: The member.
            path: The object's key path.
            required: Whether the member must be present.
            empty: Whether an empty string is accepted.

        Returns:
            The string ("" if absent and not required).

        Raises:
            ConfigError: If missing, not a string, or empty when not allowed.
        """
        if key not in raw:
            if required:
                raise self.fail(path, f"missing required key '{key}'")
            return ""
        value = raw[key]
        if not isinstance(value, str):
            raise self.fail(_join(path, key), f"expected a string, got {kind_of(value)}")
        if not empty and not value:
            raise self.fail(_join(path, key), "must not be empty")
        return value

    def instance_id(self, raw: dict[str, Any], path: str, key: str = "instance_id") -> int:
        """Read an instance id (default 0).

        Args:
            raw: The enclosing object.
            path: The object's key path.
            key: The member name (``id`` in the legacy format).

        Returns:
            The id.

        Raises:
            ConfigError: If not an unsigned 32-bit integer.
        """
        value = raw.get(key, 0)
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if (
            isinstance(value, bool)
            or not isinstance(value, int)
            or not 0 <= value <= MAX_INSTANCE_ID
        ):
            raise self.fail(
                _join(path, key),
                f"expected an integer from 0 to {MAX_INSTANCE_ID}, got {kind_of(value)}",
            )
        return value

    def node_state(self, raw: dict[str, Any], key: str, path: str) -> NodeState:
        """Read an optional node state string.

        Args:
            raw: The enclosing object.
            key: The member.
            path: The object's key path.

        Returns:
            The state (UNINITIALIZED if absent).

        Raises:
            ConfigError: If not one of the state strings.
        """
        if key not in raw:
            return NodeState.UNINITIALIZED
        value = raw[key]
        try:
            return NodeState(value)
        except (ValueError, TypeError):
            names = ", ".join(s.value for s in NodeState)
            raise self.fail(
                _join(path, key), f"unknown state {kind_of(value)} (expected one of {names})"
            ) from None

    def parent(self, raw: object, path: str) -> ParentRelation:
        """Read a parent relation (also a ``graph_exit`` entry).

        Args:
            raw: The relation object.
            path: Its key path.

        Returns:
            The relation.

        Raises:
            ConfigError: On any malformed member.
        """
        rel = self.obj(raw, path)
        name = self.string(rel, "name", path, required=True, empty=False)
        instance = self.instance_id(rel, path)
        required = rel.get("required", True)
        if not isinstance(required, bool):
            raise self.fail(
                _join(path, "required"), f"expected true or false, got {kind_of(required)}"
            )
        conditions: dict[Result, Response] = {}
        for i, text in enumerate(self.array(rel, "conditions", path)):
            cpath = f"{path}.conditions[{i}]"
            result, response = self.condition(text, cpath)
            if result in conditions and conditions[result] is not response:
                raise self.fail(
                    cpath,
                    f"second condition for '{result.value}'"
                    f" ('{conditions[result].value}' already given)",
                )
            conditions[result] = response
        self.unknown(rel, {"name", "instance_id", "required", "conditions"}, path)
        return ParentRelation(name, instance, required, conditions)

    def condition(self, text: object, path: str) -> tuple[Result, Response]:
        """Parse ``"<result> -> <response>"``.

        Args:
            text: The condition string.
            path: Its key path.

        Returns:
            The pair.

        Raises:
            ConfigError: If malformed or naming an unknown result or response.
        """
        if not isinstance(text, str):
            raise self.fail(
                path, f"expected a string '<result> -> <response>', got {kind_of(text)}"
            )
        left, arrow, right = text.replace(" ", "").partition("->")
        if not arrow or not left or not right:
            raise self.fail(path, f"expected '<result> -> <response>', got {text!r}")
        try:
            result = Result(left)
            if result is Result.HALTED:
                raise ValueError(left)
        except ValueError:
            raise self.fail(path, f"unknown result '{left}' (expected {_RESULT_NAMES})") from None
        try:
            response = Response(right)
        except ValueError:
            raise self.fail(
                path, f"unknown response '{right}' (expected {_RESPONSE_NAMES})"
            ) from None
        return result, response

    def child(self, raw: object, path: str) -> ChildRelation:
        """Read a child relation (also a ``graph_entry`` entry).

        Args:
            raw: The relation object.
            path: Its key path.

        Returns:
            The relation.

        Raises:
            ConfigError: On any malformed member, or a duplicate remap source.
        """
        rel = self.obj(raw, path)
        name = self.string(rel, "name", path, required=True, empty=False)
        instance = self.instance_id(rel, path)
        remaps: list[Remap] = []
        seen: set[str] = set()
        for i, item in enumerate(self.array(rel, "remap", path)):
            rpath = f"{path}.remap[{i}]"
            entry = self.obj(item, rpath)
            src = self.string(entry, "from", rpath, required=True, empty=False)
            dst = self.string(entry, "to", rpath, required=True, empty=False)
            if src in seen:
                raise self.fail(f"{rpath}.from", f"'{src}' is remapped twice")
            seen.add(src)
            remaps.append(Remap(src, dst))
        self.unknown(rel, {"name", "instance_id", "remap"}, path)
        return ChildRelation(name, instance, tuple(remaps))

    def unknown(self, raw: dict[str, Any], known: frozenset[str] | set[str], path: str) -> None:
        """Record a warning for each key the format does not know.

        Args:
            raw: The object.
            known: Its known keys.
            path: Its key path.

        Returns:
            None.
        """
        for key in raw:
            if key not in known:
                self.warnings.append(f"{_join(path, key) or key}: unknown key ignored")

    def umrf(self, raw: object, path: str) -> Umrf:
        """Read an action object.

        Args:
            raw: The action object.
            path: Its key path ("" for a stand-alone description).

        Returns:
            The action.

        Raises:
            ConfigError: On any malformed member.
        """
        obj = self.obj(raw, path)
        name = self.string(obj, "name", path, required=True, empty=False)
        type_ = self.string(obj, "type", path, required=True, empty=False)
        params: list[dict[str, Parameter]] = []
        for key in ("input_parameters", "output_parameters"):
            tree = obj.get(key, {})
            params.append(
                parse_parameter_tree(
                    tree,
                    path=_join(path, key),
                    file=self.file,
                    error=self.error,
                    warnings=self.warnings,
                )
            )
        runtime: tuple[LogMessage, ...] = ()
        if "runtime" in obj:
            runtime = self.runtime(obj["runtime"], _join(path, "runtime"))
        self.unknown(obj, _ACTION_KEYS, path)
        return Umrf(
            name=name,
            type=type_,
            instance_id=self.instance_id(obj, path),
            actor=self.string(obj, "actor", path),
            description=self.string(obj, "description", path),
            state=self.node_state(obj, "state", path),
            parents=tuple(
                self.parent(r, f"{_join(path, 'parents')}[{i}]")
                for i, r in enumerate(self.array(obj, "parents", path))
            ),
            children=tuple(
                self.child(r, f"{_join(path, 'children')}[{i}]")
                for i, r in enumerate(self.array(obj, "children", path))
            ),
            input_parameters=params[0],
            output_parameters=params[1],
            gui_attributes=obj.get("gui_attributes"),
            runtime_messages=runtime,
        )

    def runtime(self, raw: object, path: str) -> tuple[LogMessage, ...]:
        """Read ``runtime.messages``.

        Args:
            raw: The runtime object.
            path: Its key path.

        Returns:
            The log messages.

        Raises:
            ConfigError: On malformed entries.
        """
        obj = self.obj(raw, path)
        out = []
        for i, item in enumerate(self.array(obj, "messages", path)):
            mpath = f"{path}.messages[{i}]"
            entry = self.obj(item, mpath)
            stamp = entry.get("timestamp", 0)
            if isinstance(stamp, bool) or not isinstance(stamp, int) or not 0 <= stamp < 2**63:
                raise self.fail(
                    f"{mpath}.timestamp",
                    f"expected milliseconds since the epoch, got {kind_of(stamp)}",
                )
            out.append(LogMessage(stamp, self.string(entry, "message", mpath)))
        return tuple(out)


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def parse_umrf(raw: object, *, file: str | None = None, warnings: list[str] | None = None) -> Umrf:
    """Parse a stand-alone action description (the content of a ``*.umrf.json`` file).

    Args:
        raw: The decoded JSON document.
        file: The file it came from, for messages.
        warnings: A list that receives warnings (unknown keys).

    Returns:
        The description.

    Raises:
        UmrfError: With the file and key path of the first problem.
    """
    reader = UmrfReader(file, UmrfError)
    umrf = reader.umrf(raw, "")
    if warnings is not None:
        warnings.extend(reader.warnings)
    return umrf
