"""Planning: turn a UMRF graph into a :class:`~temoto.core._runtime.Plan` the engine can run.

Every action is resolved — remote if its ``actor`` is another actor; local if an action
description has the same name and the same input and output parameter names (its class is
imported now, so a broken module fails this graph only, before anything runs); else a sub-graph
if an indexed graph has that name and signature (planned recursively; a graph using itself is
an error). Parameters are merged (the description's definitions with the graph's literals and
allowed values; a type conflict is an error), and the effective graph is validated.

To check a shared graph on a machine that is none of its actors (``temoto validate``), a
planner with an ``elsewhere`` callback tries every actor's actions here: those that resolve are
checked like local ones, those that do not (no description or indexed graph of that name and
signature) are reported to the callback and planned as remote, left to their actor.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from temoto.core._runtime import NodeKind, Plan, ResolvedAction
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.graph import GraphSignature, UmrfGraph
from temoto.core.params import NATIVE_TYPES, NO_VALUE, Parameter, check_value
from temoto.core.umrf import Umrf
from temoto.core.validation import validate_graph
from temoto.errors import ActionNotFoundError, GraphDefinitionError, GraphInputError

if TYPE_CHECKING:
    from temoto.core.action import Action

__all__ = ["MAX_SUBGRAPH_DEPTH", "Planner", "graph_inputs"]

logger = logging.getLogger(__name__)


#: How deep sub-graphs may be nested (a graph using a graph using a graph ...): the engine ends
#: a sub-graph's run by ending its parent's node, one call inside the other, so a deeper chain
#: would exhaust Python's recursion limit in a worker and leave the run without an end.
MAX_SUBGRAPH_DEPTH = 100

#: How many plans a planner remembers (by graph object; see :meth:`Planner.plan`).
PLAN_CACHE_SIZE = 64


class Planner:
    """Resolves, merges and validates graphs against an action catalog and a graph index.

    Plans are remembered per graph *object* (``UmrfGraph`` is immutable), so starting the same
    indexed graph again skips resolution and validation; a change of the catalog or of the
    index (their ``generation``) makes every remembered plan stale.

    Args:
        actor: The local actor's name (actions of other actors are remote).
        catalog: Where action descriptions and classes come from.
        graphs: Where sub-graphs come from.
        remote: Whether actions of other actors may be planned (the engine has a fleet link);
            without, a graph naming another actor is refused.
        elsewhere: For checking a shared graph without being one of its actors: actions of
            other actors are resolved here too; one that does not resolve (no description or
            indexed graph of its name and parameters) is passed to this callback with the
            reason and planned as remote. Other actors' actions are then allowed without
            ``remote``. None (the default): they are remote without being looked at. Called
            only while a plan is made, not when a remembered plan is returned.
    """

    def __init__(
        self,
        actor: str,
        catalog: ActionCatalog,
        graphs: GraphIndex,
        *,
        remote: bool = False,
        elsewhere: Callable[[Umrf, str], None] | None = None,
    ) -> None:
        self.actor = actor
        # actions of other actors are allowed (a fleet link exists, or only checked here)
        self.remote = remote or elsewhere is not None
        self.elsewhere = elsewhere
        self.catalog = catalog
        self.graphs = graphs
        self._local: dict[type[Action], ResolvedAction] = {}
        #: id(graph) -> (graph, catalog generation, index generation, plan), least recent first
        self._cache: OrderedDict[int, tuple[UmrfGraph, int, int, Plan]] = OrderedDict()
        self._cache_lock = threading.Lock()

    def plan(self, graph: UmrfGraph) -> Plan:
        """Resolve and validate a graph.

        Args:
            graph: The graph.

        Returns:
            The plan: effective actions and how each runs.

        Raises:
            GraphDefinitionError: The graph cannot run (all problems listed), names other actors,
                uses itself as a sub-graph, or nests sub-graphs more than
                :data:`MAX_SUBGRAPH_DEPTH` deep.
            ActionNotFoundError, PluginConflictError, PluginLoadError: An action cannot be
                loaded.
        """
        generations = (self.catalog.generation, self.graphs.generation)
        key = id(graph)
        with self._cache_lock:
            hit = self._cache.get(key)
            if hit is not None and hit[0] is graph and (hit[1], hit[2]) == generations:
                self._cache.move_to_end(key)
                return hit[3]
        plan = self._plan(graph, (graph.name,))
        with self._cache_lock:
            self._cache[key] = (graph, *generations, plan)  # holds graph: its id stays unique
            self._cache.move_to_end(key)
            while len(self._cache) > PLAN_CACHE_SIZE:
                self._cache.popitem(last=False)
        return plan

    def _plan(self, graph: UmrfGraph, stack: tuple[str, ...]) -> Plan:
        actions: list[Umrf] = []
        resolved: dict[str, ResolvedAction] = {}
        remote: list[str] = []
        for umrf in graph.actions:
            if umrf.actor and umrf.actor != self.actor:
                found = self._resolve_elsewhere(graph, umrf, stack)
                if found is not None:
                    actions.append(found[0])
                    resolved[umrf.full_name] = found[1]
                    continue
                resolved[umrf.full_name] = ResolvedAction(NodeKind.REMOTE)
                remote.append(f"{umrf.full_name} ({umrf.actor})")
                actions.append(umrf)
                continue
            effective, how = self._resolve(graph, umrf, stack)
            actions.append(effective)
            resolved[umrf.full_name] = how
        if remote and not self.remote:
            raise GraphDefinitionError(
                f"graph '{graph.name}' has actions for other actors: {', '.join(remote)};"
                f" this engine"
                f" (actor '{self.actor}') has no fleet link to run them with",
                file=graph.source,
            )
        effective_graph = dataclasses.replace(graph, actions=tuple(actions))
        report = validate_graph(effective_graph)
        report.raise_for_errors(graph.source)
        for issue in report.warnings:
            logger.warning("graph '%s': %s", graph.name, issue)
        return Plan(effective_graph, resolved, tuple(str(w) for w in report.warnings))

    def _resolve_elsewhere(
        self, graph: UmrfGraph, umrf: Umrf, stack: tuple[str, ...]
    ) -> tuple[Umrf, ResolvedAction] | None:
        """Resolve another actor's action here when checking (``elsewhere``); None: remote."""
        if self.elsewhere is None:
            return None
        try:
            return self._resolve(graph, umrf, stack)
        except ActionNotFoundError:
            reason = f"no action description and no indexed graph named '{umrf.name}'"
        except _MismatchError as err:
            reason = err.mismatch
        self.elsewhere(umrf, reason)
        return None

    def _resolve(
        self, graph: UmrfGraph, umrf: Umrf, stack: tuple[str, ...]
    ) -> tuple[Umrf, ResolvedAction]:
        description = self.catalog.find(umrf.name)
        mismatch = ""
        if description is not None:
            mismatch = _param_mismatch(umrf, description)
            if not mismatch:
                cls = self.catalog.load_class(umrf.name)
                how = self._local.get(cls)
                if how is None:  # one per class: a big graph need not hold one per action
                    how = self._local[cls] = ResolvedAction(NodeKind.LOCAL, cls=cls)
                return _merge(graph, umrf, description), how
        sub = self.graphs.find_subgraph(umrf)
        if sub is not None:
            if len(stack) > MAX_SUBGRAPH_DEPTH:
                shown = [*stack[:3], "...", *stack[-2:], sub.name]
                raise GraphDefinitionError(
                    f"sub-graphs nested more than {MAX_SUBGRAPH_DEPTH} deep (the limit):"
                    f" {' -> '.join(shown)}",
                    file=graph.source,
                )
            if sub.name in stack:
                chain = " -> ".join((*stack, sub.name))
                raise GraphDefinitionError(
                    f"graph uses itself as a sub-graph: {chain}", file=graph.source
                )
            return umrf, ResolvedAction(NodeKind.GRAPH, plan=self._plan(sub, (*stack, sub.name)))
        where = f"graph '{graph.name}': action '{umrf.full_name}'"
        if mismatch:
            raise _MismatchError(f"{where}: {mismatch}", file=graph.source, mismatch=mismatch)
        raise ActionNotFoundError(
            f"{where}: no action description and no indexed graph named '{umrf.name}'"
            " (add its folder with --actions, or its graph's folder with --graphs)"
        )


class _MismatchError(GraphDefinitionError):
    """An action's parameters differ from the description of its name (and no graph fits).

    Args:
        message: The whole message.
        file: The graph's file.
        mismatch: How the parameters differ.
    """

    def __init__(self, message: str, *, file: str | None, mismatch: str) -> None:
        super().__init__(message, file=file)
        self.mismatch = mismatch


def _param_mismatch(umrf: Umrf, description: Umrf) -> str:
    problems = []
    for side, mine, theirs in (
        ("inputs", umrf.input_parameters, description.input_parameters),
        ("outputs", umrf.output_parameters, description.output_parameters),
    ):
        # A graph may leave out what it does not use: optional inputs and outputs (upstream
        # wants every parameter written out; the description supplies them here).
        missing = sorted(
            n for n in set(theirs) - set(mine) if side == "inputs" and theirs[n].required
        )
        extra = sorted(set(mine) - set(theirs))
        if missing:
            problems.append(f"lacks {side} {', '.join(missing)}")
        if extra:
            problems.append(f"has {side} {', '.join(extra)} that the description does not")
    if not problems:
        return ""
    return f"does not match the description of '{description.name}': it " + "; ".join(problems)


def _merge(graph: UmrfGraph, umrf: Umrf, description: Umrf) -> Umrf:
    """The description's parameters, with the graph's literals and allowed values."""
    if not description.input_parameters and not description.output_parameters:
        return umrf  # nothing to merge (the parameter sets match, so the graph's are empty too)

    def side(
        mine: Mapping[str, Parameter], theirs: Mapping[str, Parameter], what: str
    ) -> dict[str, Parameter]:
        out = {}
        for name, desc in theirs.items():
            own = mine.get(name)
            if own is None:  # left out of the graph (optional input, or an output)
                out[name] = desc
                continue
            if own.type != desc.type:
                raise GraphDefinitionError(
                    f"action '{umrf.full_name}': {what} '{name}' is {own.type} in the graph but"
                    f" {desc.type} in the description of '{description.name}'",
                    file=graph.source,
                )
            out[name] = dataclasses.replace(
                desc,
                value=own.value if own.has_value else desc.value,
                updatable=desc.updatable and own.updatable,
                allowed_values=own.allowed_values or desc.allowed_values,
            )
        return out

    return dataclasses.replace(
        umrf,
        input_parameters=side(umrf.input_parameters, description.input_parameters, "input"),
        output_parameters=side(umrf.output_parameters, description.output_parameters, "output"),
    )


def graph_inputs(
    graph: UmrfGraph, params: Mapping[str, Any], signature: GraphSignature | None = None
) -> dict[str, Any]:
    """Check the values given for a graph's external inputs.

    Args:
        graph: The graph.
        params: The values, by input name.
        signature: The graph's signature if the caller has it (a plan's wiring keeps it);
            made from the graph otherwise.

    Returns:
        The values, checked (numbers and booleans as their native type).

    Raises:
        GraphInputError: An input is unknown, of the wrong type, or required and missing.
    """
    inputs = (signature if signature is not None else graph.signature()).inputs
    values: dict[str, Any] = {}
    for name, value in params.items():
        param = inputs.get(name)
        if param is None:
            known = ", ".join(sorted(inputs)) or "none"
            raise GraphInputError(
                f"graph '{graph.name}' has no input '{name}' (its inputs: {known})",
                file=graph.source,
            )
        if param.type in NATIVE_TYPES:
            try:
                value = check_value(param.type, value)
            except TypeError as err:
                raise GraphInputError(
                    f"graph input '{name}' ({param.type}): {err}", file=graph.source
                ) from None
        values[name] = value
    missing = sorted(
        n for n, p in inputs.items() if p.required and n not in values and p.value is NO_VALUE
    )
    if missing:
        raise GraphInputError(
            f"graph '{graph.name}' needs input {', '.join(repr(m) for m in missing)}"
            " (pass it as a parameter; upstream would silently never start)",
            file=graph.source,
        )
    return values


def graph_inputs_from_text(graph: UmrfGraph, texts: Mapping[str, str]) -> dict[str, Any]:
    """Turn ``NAME=VALUE`` texts (a command line, a remote command) into graph input values.

    A string input takes the text as it is; a number, boolean or array input takes it as JSON.
    An input the graph does not declare keeps the text (:func:`graph_inputs` refuses it later
    with the list of the graph's inputs).

    Args:
        graph: The graph whose inputs these are.
        texts: The values as text, by input name.

    Returns:
        The values, by name.

    Raises:
        GraphInputError: A value is not JSON of the input's type.
    """
    inputs = graph.signature().inputs
    values: dict[str, Any] = {}
    for name, raw in texts.items():
        param = inputs.get(name)
        if param is None or param.type == "string" or param.type not in NATIVE_TYPES:
            values[name] = raw
            continue
        try:
            values[name] = json.loads(raw)
        except json.JSONDecodeError:
            raise GraphInputError(
                f"graph input {name}: {raw!r} is not a JSON {param.type} value",
                file=graph.source,
            ) from None
    return values
