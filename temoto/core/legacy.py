"""Importer for the legacy (pre-2023) UMRF format: ROS1 demos, old examples, GPT parser prompts.

The legacy engine wrote graphs as ``{"graph_name", "graph_state": <number>, "umrf_actions": [...]}``
with actions keyed by ``id`` (instead of ``instance_id``) and ``effect`` (``synchronous`` /
``asynchronous``, instead of ``type``), relations keyed by ``id`` with an optional
``stop_when_received`` flag, no ``graph_entry``/``graph_exit`` and no result conditions.
Stand-alone action descriptions (``umrf.json``) had ``package_name`` and ``effect``.

Nothing here builds model objects. Each document is rewritten into a CURRENT-format raw dict
and handed to the normal parser (:func:`temoto.core.graph.parse_graph`, or
:func:`temoto.core.umrf.parse_umrf` for descriptions), so every check and error message is
shared. Problems the rewrite itself meets (a relation without a name, an ``id`` that is not an
integer, ``umrf_actions`` that is not an array, ...) are reported as the same
:class:`~temoto.errors.ConfigError` subclasses with the file and the LEGACY key path
(``umrf_actions[2].id``); errors the parser finds in a converted graph have their path mapped
back (``actions[2]...`` becomes ``umrf_actions[2]...``; the action order is kept).

The rewrite, rule by rule (docs/design.md §3.2 has the legacy semantics):

* ``umrf_actions`` -> ``actions``; ``id`` -> ``instance_id`` on actions and relations (a
  missing id means 0).
* ``effect``: ``synchronous`` -> ``sync``, ``asynchronous`` -> ``async``; an action without
  one (GPT prompt examples) becomes ``sync``; another non-empty string is kept as the type.
* ``graph_state`` numbers follow the legacy ``UmrfGraphCommon::State`` enum: 0 UNINITIALIZED,
  1 INITIALIZED, 2 ACTIVE (RUNNING), 3 STOP_REQUESTED (STOPPING), 4 PREEMTIVELY_STOPPED
  (STOPPED), 5 FINISHED, 6 ERROR. The numbering of the legacy node ``state`` changed between
  engine versions (0 was always NOT_SET, 1 was UNINITIALIZED in one and INITIALIZED in
  another), so 0 becomes UNINITIALIZED and other numbers are dropped. States in a document are
  informational only.
* Relations: legacy children started only on a normal return of their parent; a stopped or
  failed parent started nothing. Every parent relation therefore gets the conditions
  ``on_true -> run, on_false -> run, on_stopped -> ignore, on_error -> ignore``, or, with
  ``stop_when_received: true``, ``on_true -> stop, on_false -> stop`` instead of the two
  ``run``. A missing ``required`` becomes true. A relation declared on one side only gets its
  counterpart (a parent relation is added ``required``).
* ``graph_entry``: the actions without parents or with ``execute_first: true``, in document
  order (a graph without any could not start in the legacy engine either: error).
* ``graph_exit``: the legacy graph ended when every action was synchronous and finished; the
  exit is every synchronous action without children (required, same conditions as above).
  With none (cycles, all-async graphs) the exit is empty and the graph runs until stopped.
  A graph of one action has it as entry and exit.
* ``package_name``, ``notation``, ``library_path`` and the parameter leaves' ``pvf_example``
  are dropped; a single-value ``pvf_allowed_values`` becomes a one-element array, and
  ``"true"``/``"false"`` strings in ``pvf_required``/``pvf_updatable`` become booleans.

Every conversion adds ONE warning, first in the list, that says what was changed.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Final

from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.params import MAX_TREE_DEPTH, kind_of
from temoto.core.states import GraphState, NodeState
from temoto.core.umrf import UmrfReader
from temoto.errors import ConfigError, GraphDefinitionError, UmrfError

__all__ = [
    "LEGACY_GRAPH_STATES",
    "LEGACY_NODE_STATES",
    "convert_graph",
    "convert_umrf",
    "is_legacy_graph",
    "is_legacy_umrf",
]

#: Legacy numeric ``graph_state`` (``UmrfGraphCommon::State`` order) -> current state.
LEGACY_GRAPH_STATES: Final[dict[int, GraphState]] = {
    0: GraphState.UNINITIALIZED,
    1: GraphState.INITIALIZED,
    2: GraphState.RUNNING,  # ACTIVE
    3: GraphState.STOPPING,  # STOP_REQUESTED
    4: GraphState.STOPPED,  # PREEMTIVELY_STOPPED
    5: GraphState.FINISHED,
    6: GraphState.ERROR,
}

#: Legacy numeric node ``state`` -> current state (only 0 = NOT_SET is stable across versions).
LEGACY_NODE_STATES: Final[dict[int, NodeState]] = {0: NodeState.UNINITIALIZED}

_EFFECTS: Final = {"synchronous": "sync", "asynchronous": "async"}
_PARENT_CONDITIONS: Final = (
    "on_true -> run",
    "on_false -> run",
    "on_stopped -> ignore",
    "on_error -> ignore",
)
_STOP_CONDITIONS: Final = (
    "on_true -> stop",
    "on_false -> stop",
    "on_stopped -> ignore",
    "on_error -> ignore",
)
_INTRO: Final = "converted from the legacy (pre-2023) UMRF format: "
_INTRO_UMRF: Final = "converted from the legacy (pre-2023) action description format: "
#: Action keys dropped without replacement.
_DROPPED_ACTION_KEYS: Final = ("package_name", "notation", "library_path")
#: Action keys the conversion handles itself (everything else is passed to the parser as is).
_HANDLED_ACTION_KEYS: Final = frozenset(
    {
        "id",
        "instance_id",
        "effect",
        "type",
        "state",
        "execute_first",
        "parents",
        "children",
        "input_parameters",
        "output_parameters",
        *_DROPPED_ACTION_KEYS,
    }
)
_GRAPH_KEYS: Final = frozenset(
    {"graph_name", "graph_description", "graph_state", "umrf_actions", "graph_entry", "graph_exit"}
)
_NAMES_SHOWN: Final = 8
_DROP: Final = object()  # marks a value the conversion drops
_TIMES: Final = "\u00d7"  # multiplication sign


def is_legacy_graph(raw: object) -> bool:
    """Whether a decoded document is a legacy graph (``umrf_actions`` and no ``actions``).

    Args:
        raw: The decoded JSON document.

    Returns:
        True for a legacy graph.
    """
    return isinstance(raw, dict) and "umrf_actions" in raw and "actions" not in raw


def is_legacy_umrf(raw: object) -> bool:
    """Whether a decoded document is a legacy stand-alone action description.

    A legacy description has no ``type`` but ``effect`` or ``package_name``, and is not a graph.

    Args:
        raw: The decoded JSON document.

    Returns:
        True for a legacy action description.
    """
    if not isinstance(raw, dict) or "type" in raw:
        return False
    if "umrf_actions" in raw or "actions" in raw:
        return False
    return "effect" in raw or "package_name" in raw


def convert_graph(raw: object, *, file: str | None = None) -> UmrfGraph:
    """Convert a legacy graph document and parse it.

    Args:
        raw: The decoded legacy document (see :func:`is_legacy_graph`).
        file: The file it came from, for messages.

    Returns:
        The graph. ``warnings`` starts with one message saying what was converted, followed by
        the parser's own warnings (key paths in legacy form).

    Raises:
        GraphDefinitionError: With the file and legacy key path of the first problem.
    """
    reader = UmrfReader(file, GraphDefinitionError)
    converted, summary = _GraphConverter(reader).convert(raw)
    try:
        graph = parse_graph(converted, file=file)
    except ConfigError as err:
        raise type(err)(err.reason, file=err.file, path=_legacy_path(err.path)) from None
    warnings = tuple(_legacy_path(w) for w in graph.warnings)
    return dataclasses.replace(graph, warnings=(summary, *warnings))


def convert_umrf(
    raw: object, *, file: str | None = None, warnings: list[str] | None = None
) -> dict[str, Any]:
    """Convert a legacy stand-alone action description into a current-format raw dict.

    The result is meant for :func:`temoto.core.umrf.parse_umrf`, which does all other checks
    (the key paths of a description are the same in both formats).

    Args:
        raw: The decoded legacy description (see :func:`is_legacy_umrf`).
        file: The file it came from, for messages.
        warnings: A list that receives one message saying what was converted.

    Returns:
        The current-format description.

    Raises:
        UmrfError: With the file and key path of a problem the conversion meets.
    """
    reader = UmrfReader(file, UmrfError)
    notes = _Notes()
    action = _ActionConverter(reader, notes, in_graph=False).convert(raw, "")
    if action.execute_first:
        notes.dropped.setdefault("execute_first", None)
    if warnings is not None:
        warnings.append(_INTRO_UMRF + ("; ".join(notes.parts(graph=False)) or "nothing to change"))
    return action.out


# --- conversion --------------------------------------------------------------------------------


@dataclass(slots=True)
class _Notes:
    """What the conversion did, for the summary warning."""

    ids: list[int] = field(default_factory=lambda: [0, 0])  # [actions, relations]
    missing_ids: list[int] = field(default_factory=lambda: [0, 0])
    effects: Counter[tuple[str, str]] = field(default_factory=Counter)
    no_effect: list[str] = field(default_factory=list)
    kept_types: list[str] = field(default_factory=list)
    graph_state: str = ""
    node_states: Counter[str] = field(default_factory=Counter)
    run_relations: int = 0
    stop_relations: list[str] = field(default_factory=list)
    written_conditions: int = 0
    required_defaulted: int = 0
    added_parents: list[str] = field(default_factory=list)
    added_children: list[str] = field(default_factory=list)
    allowed_wrapped: int = 0
    examples_dropped: int = 0
    flag_strings: int = 0
    roots: list[str] = field(default_factory=list)
    first: list[str] = field(default_factory=list)
    first_with_required: list[str] = field(default_factory=list)
    exit: list[str] | None = None
    single: str = ""
    dropped: dict[str, None] = field(default_factory=dict)

    def parts(self, *, graph: bool) -> list[str]:
        """The summary, one clause per kind of change that occurred.

        Args:
            graph: Whether a graph (not a stand-alone description) was converted.

        Returns:
            The clauses.
        """
        out: list[str] = ["umrf_actions -> actions"] if graph else []
        if any(self.ids):
            out.append(f"id -> instance_id ({_counts(self.ids)})")
        if any(self.missing_ids):
            out.append(f"missing id -> instance_id 0 ({_counts(self.missing_ids)})")
        if self.effects:
            done = ", ".join(
                f"{old} -> {new} {_TIMES}{n}" for (old, new), n in self.effects.items()
            )
            out.append(f"effect -> type ({done})")
        if self.kept_types:
            out.append(f"unknown effect kept as type ({_names(self.kept_types)})")
        if self.no_effect:
            out.append(f"no effect -> type sync ({_names(self.no_effect)})")
        if self.graph_state:
            out.append(self.graph_state)
        out.extend(f"{text} ({_count(n, 'action')})" for text, n in self.node_states.items())
        self._relation_parts(out)
        self._parameter_parts(out)
        if self.single:
            out.append(f"single action: graph_entry = graph_exit = {self.single}")
        else:
            self._entry_exit_parts(out)
        if self.dropped:
            out.append("dropped keys: " + ", ".join(self.dropped))
        return out

    def _relation_parts(self, out: list[str]) -> None:
        if self.run_relations:
            out.append(
                "parent relations -> '" + "', '".join(_PARENT_CONDITIONS) + "' "
                f"({_count(self.run_relations, 'relation')}; legacy children started only "
                "on a normal return)"
            )
        if self.stop_relations:
            out.append(
                "stop_when_received -> 'on_true -> stop', 'on_false -> stop' "
                f"({_count(len(self.stop_relations), 'relation')}: {_names(self.stop_relations)})"
            )
        if self.written_conditions:
            out.append(f"written conditions kept ({_count(self.written_conditions, 'relation')})")
        if self.required_defaulted:
            out.append(f"missing required -> true ({_count(self.required_defaulted, 'relation')})")
        if self.added_parents:
            out.append(f"added missing parent relations, required ({_names(self.added_parents)})")
        if self.added_children:
            out.append(f"added missing child relations ({_names(self.added_children)})")

    def _parameter_parts(self, out: list[str]) -> None:
        if self.allowed_wrapped:
            out.append(
                "single pvf_allowed_values -> one-element array "
                f"({_count(self.allowed_wrapped, 'parameter')})"
            )
        if self.flag_strings:
            out.append(f"'true'/'false' strings -> booleans ({self.flag_strings}{_TIMES})")
        if self.examples_dropped:
            out.append(f"pvf_example dropped ({_count(self.examples_dropped, 'parameter')})")

    def _entry_exit_parts(self, out: list[str]) -> None:
        if self.roots:
            out.append(f"graph_entry = actions without parents ({_names(self.roots)})")
        if self.first:
            out.append(f"execute_first -> graph_entry ({_names(self.first)})")
        if self.first_with_required:
            out.append(
                "execute_first actions with required parents start only after those parents "
                f"({_names(self.first_with_required)})"
            )
        if self.exit:
            out.append(f"graph_exit = synchronous actions without children ({_names(self.exit)})")
        elif self.exit is not None:
            out.append(
                "graph_exit = [] (no synchronous action without children: the graph runs "
                "until stopped)"
            )


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _counts(pair: list[int]) -> str:
    return ", ".join(
        _count(n, noun) for n, noun in zip(pair, ("action", "relation"), strict=True) if n
    )


def _names(names: list[str]) -> str:
    shown = ", ".join(names[:_NAMES_SHOWN])
    more = len(names) - _NAMES_SHOWN
    return f"{shown}, ... {more} more" if more > 0 else shown


def _integral(value: object) -> int | None:
    """The value as an int if it is an integral JSON number (not a bool), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return None


def _legacy_path(text: str) -> str:
    """Map a converted graph's key path (or a message starting with one) to the legacy form."""
    return "umrf_" + text if text.startswith("actions[") else text


@dataclass(slots=True)
class _Action:
    """One converted action and what the graph-level steps need to know about it."""

    path: str
    out: dict[str, Any]
    name: str
    instance_id: int
    execute_first: bool
    parents: list[dict[str, Any]]
    children: list[dict[str, Any]]

    @property
    def full_name(self) -> str:
        return f"{self.name}_{self.instance_id}"


@dataclass(slots=True)
class _ActionConverter:
    """Rewrites one legacy action object (in a graph, or a stand-alone description)."""

    reader: UmrfReader
    notes: _Notes
    in_graph: bool = True

    def fail(self, path: str, message: str) -> ConfigError:
        return self.reader.fail(path, message)

    def convert(self, raw: object, path: str) -> _Action:
        obj = self.reader.obj(raw, path)
        name = self.reader.string(obj, "name", path, required=True, empty=False)
        instance_id = self.instance_id(obj, path, relation=False)
        out: dict[str, Any] = {"name": name, "instance_id": instance_id}
        full_name = f"{name}_{instance_id}"
        out["type"] = self.type(obj, path, full_name)
        if "state" in obj:
            state = self.state(obj["state"])
            if state is not _DROP:
                out["state"] = state
        execute_first = self.flag(obj, "execute_first", path)
        if execute_first is False:
            self.notes.dropped.setdefault("execute_first (false)", None)
        for key in _DROPPED_ACTION_KEYS:
            if key in obj:
                self.notes.dropped.setdefault(key, None)
        for key in ("input_parameters", "output_parameters"):
            if key in obj:
                out[key] = self.tree(obj[key], 0)
        out.update((k, v) for k, v in obj.items() if k not in _HANDLED_ACTION_KEYS)
        parents = [
            self.parent(r, f"{_join(path, 'parents')}[{i}]", full_name)
            for i, r in enumerate(self.reader.array(obj, "parents", path))
        ]
        children = [
            self.child(r, f"{_join(path, 'children')}[{i}]")
            for i, r in enumerate(self.reader.array(obj, "children", path))
        ]
        if parents or "parents" in obj or self.in_graph:
            out["parents"] = parents
        if children or "children" in obj or self.in_graph:
            out["children"] = children
        return _Action(path, out, name, instance_id, bool(execute_first), parents, children)

    def instance_id(self, obj: dict[str, Any], path: str, *, relation: bool) -> int:
        if "id" in obj:
            legacy = self.reader.instance_id(obj, path, key="id")
            if "instance_id" in obj and legacy != self.reader.instance_id(obj, path):
                raise self.fail(path, "both 'id' and 'instance_id' given, and they differ")
            self.notes.ids[relation] += 1
            return legacy
        if "instance_id" in obj:
            return self.reader.instance_id(obj, path)
        if self.in_graph:
            self.notes.missing_ids[relation] += 1
        return 0

    def type(self, obj: dict[str, Any], path: str, full_name: str) -> object:
        if "effect" not in obj:
            if "type" in obj:  # a half-converted document: the parser judges the type
                return obj["type"]
            self.notes.no_effect.append(full_name)
            return "sync"
        effect = self.reader.string(obj, "effect", path, empty=False)
        if "type" in obj:
            raise self.fail(path, "both 'effect' (legacy) and 'type' given")
        if effect in _EFFECTS:
            self.notes.effects[(effect, _EFFECTS[effect])] += 1
            return _EFFECTS[effect]
        self.notes.kept_types.append(f"{full_name}: {effect!r}")
        return effect

    def state(self, value: object) -> object:
        number = _integral(value)
        if number is not None:
            state = LEGACY_NODE_STATES.get(number)
            if state is not None:
                self.notes.node_states[f"state {number} -> {state.value}"] += 1
                return state.value
            self.notes.node_states[f"state {number} dropped (legacy numbering varies)"] += 1
            return _DROP
        if isinstance(value, float):
            self.notes.node_states[f"state {value!r} dropped"] += 1
            return _DROP
        return value  # a string, or something for the parser to reject

    def tree(self, raw: object, depth: int) -> object:
        """Copy a parameter tree, rewriting legacy leaf keys (the parser checks the rest)."""
        if not isinstance(raw, dict) or depth > MAX_TREE_DEPTH:
            return raw
        if "pvf_type" in raw:
            return self.leaf(raw)
        return {key: self.tree(member, depth + 1) for key, member in raw.items()}

    def leaf(self, raw: dict[str, Any]) -> dict[str, Any]:
        out = dict(raw)
        if "pvf_example" in out:
            del out["pvf_example"]
            self.notes.examples_dropped += 1
        allowed = out.get("pvf_allowed_values")
        if isinstance(allowed, str | int | float):  # legacy single value (bool is an int)
            out["pvf_allowed_values"] = [allowed]
            self.notes.allowed_wrapped += 1
        for key in ("pvf_required", "pvf_updatable"):
            flag = out.get(key)
            if flag in ("true", "false"):
                out[key] = flag == "true"
                self.notes.flag_strings += 1
        return out

    def relation(self, raw: object, path: str) -> tuple[dict[str, Any], dict[str, Any]]:
        rel = self.reader.obj(raw, path)
        name = self.reader.string(rel, "name", path, required=True, empty=False)
        out: dict[str, Any] = {
            "name": name,
            "instance_id": self.instance_id(rel, path, relation=True),
        }
        out.update((k, v) for k, v in rel.items() if k not in _RELATION_KEYS)
        return rel, out

    def parent(self, raw: object, path: str, child: str) -> dict[str, Any]:
        rel, out = self.relation(raw, path)
        stop = self.flag(rel, "stop_when_received", path)
        required = self.flag(rel, "required", path)
        if required is None:
            self.notes.required_defaulted += 1
            required = True
        out["required"] = required
        if stop is False:
            self.notes.dropped.setdefault("stop_when_received (false)", None)
        if "conditions" in rel:  # a half-converted document: written conditions win
            out["conditions"] = rel["conditions"]
            self.notes.written_conditions += 1
        elif stop:
            out["conditions"] = list(_STOP_CONDITIONS)
            self.notes.stop_relations.append(f"{_full(out)} -> {child}")
        else:
            out["conditions"] = list(_PARENT_CONDITIONS)
            self.notes.run_relations += 1
        return out

    def child(self, raw: object, path: str) -> dict[str, Any]:
        rel, out = self.relation(raw, path)
        for key in ("required", "stop_when_received", "conditions"):
            if key in rel:
                if key != "conditions":
                    self.flag(rel, key, path)
                self.notes.dropped.setdefault(f"children[].{key}", None)
        return out

    def flag(self, obj: dict[str, Any], key: str, path: str) -> bool | None:
        if key not in obj:
            return None
        value = obj[key]
        if not isinstance(value, bool):
            raise self.fail(_join(path, key), f"expected true or false, got {kind_of(value)}")
        return value


_RELATION_KEYS: Final = frozenset(
    {"name", "id", "instance_id", "required", "stop_when_received", "conditions"}
)


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


@dataclass(slots=True)
class _GraphConverter:
    """Rewrites a legacy graph document into a current-format one."""

    reader: UmrfReader
    notes: _Notes = field(default_factory=_Notes)

    def convert(self, raw: object) -> tuple[dict[str, Any], str]:
        reader = self.reader
        doc = reader.obj(raw, "")
        if "umrf_actions" not in doc:
            raise reader.fail("", "not a legacy graph: missing 'umrf_actions'")
        if "actions" in doc:
            raise reader.fail("", "both 'actions' and legacy 'umrf_actions' given")
        items = doc["umrf_actions"]
        if not isinstance(items, list):
            raise reader.fail("umrf_actions", f"expected an array, got {kind_of(items)}")
        if not items:
            raise reader.fail("umrf_actions", "a graph needs at least one action")
        out: dict[str, Any] = {k: v for k, v in doc.items() if k not in _GRAPH_KEYS}
        for key in ("graph_name", "graph_description"):
            if key in doc:
                out[key] = doc[key]
        for key in ("graph_entry", "graph_exit"):
            if key in doc:
                self.notes.dropped.setdefault(f"{key} (recomputed)", None)
        if "graph_state" in doc:
            state = self.graph_state(doc["graph_state"])
            if state is not None:
                out["graph_state"] = state
        converter = _ActionConverter(reader, self.notes)
        actions = [converter.convert(item, f"umrf_actions[{i}]") for i, item in enumerate(items)]
        by_name = self.index(actions)
        self.repair(actions, by_name)
        out["graph_entry"], out["graph_exit"] = self.entry_exit(actions)
        out["actions"] = [a.out for a in actions]
        return out, _INTRO + "; ".join(self.notes.parts(graph=True))

    def graph_state(self, value: object) -> object:
        number = _integral(value)
        if number is not None:
            state = LEGACY_GRAPH_STATES.get(number)
            if state is None:
                self.notes.graph_state = f"graph_state {number} dropped (no such legacy state)"
                return None
            self.notes.graph_state = f"graph_state {number} -> {state.value}"
            return state.value
        if isinstance(value, float):
            self.notes.graph_state = f"graph_state {value!r} dropped (no such legacy state)"
            return None
        return value  # a string (or garbage) for the parser to judge

    def index(self, actions: list[_Action]) -> dict[str, _Action]:
        by_name: dict[str, _Action] = {}
        for act in actions:
            other = by_name.get(act.full_name)
            if other is not None:
                raise self.reader.fail(
                    act.path,
                    f"duplicate action '{act.full_name}' (also {other.path}); give one of them "
                    "another id",
                )
            by_name[act.full_name] = act
        return by_name

    def repair(self, actions: list[_Action], by_name: dict[str, _Action]) -> None:
        """Add the missing side of relations declared on one side only."""
        for act in actions:
            for j, rel in enumerate(act.children):
                child = self.target(by_name, rel, f"{act.path}.children[{j}]")
                if not any(_full(r) == act.full_name for r in child.parents):
                    child.parents.append(
                        {
                            "name": act.name,
                            "instance_id": act.instance_id,
                            "required": True,
                            "conditions": list(_PARENT_CONDITIONS),
                        }
                    )
                    self.notes.run_relations += 1
                    self.notes.added_parents.append(f"{act.full_name} -> {child.full_name}")
            for j, rel in enumerate(act.parents):
                parent = self.target(by_name, rel, f"{act.path}.parents[{j}]")
                if not any(_full(r) == act.full_name for r in parent.children):
                    parent.children.append({"name": act.name, "instance_id": act.instance_id})
                    self.notes.added_children.append(f"{parent.full_name} -> {act.full_name}")

    def target(self, by_name: dict[str, _Action], rel: dict[str, Any], path: str) -> _Action:
        found = by_name.get(_full(rel))
        if found is None:
            raise self.reader.fail(path, f"unknown action '{_full(rel)}'")
        return found

    def entry_exit(
        self, actions: list[_Action]
    ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        if len(actions) == 1:
            only = actions[0]
            self.notes.single = only.full_name
            return [_child_ref(only)], [_exit_ref(only)]
        entry: list[dict[str, Any]] = []
        for act in actions:
            if act.execute_first:
                self.notes.first.append(act.full_name)
                if any(p.get("required") is True for p in act.parents):
                    self.notes.first_with_required.append(act.full_name)
            elif not act.parents:
                self.notes.roots.append(act.full_name)
            else:
                continue
            entry.append(_child_ref(act))
        if not entry:
            raise self.reader.fail(
                "umrf_actions",
                "no root action: every action has parents and none has 'execute_first': true "
                "(the legacy engine could not start this graph either)",
            )
        exits = [a for a in actions if a.out["type"] == "sync" and not a.children]
        self.notes.exit = [a.full_name for a in exits]
        return entry, [_exit_ref(a) for a in exits]


def _full(rel: dict[str, Any]) -> str:
    return f"{rel['name']}_{rel['instance_id']}"


def _child_ref(act: _Action) -> dict[str, Any]:
    return {"name": act.name, "instance_id": act.instance_id}


def _exit_ref(act: _Action) -> dict[str, Any]:
    return {
        "name": act.name,
        "instance_id": act.instance_id,
        "required": True,
        "conditions": list(_PARENT_CONDITIONS),
    }
