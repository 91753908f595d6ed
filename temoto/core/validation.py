"""Checks that a parsed UMRF graph can run as written.

Upstream TeMoto has no validator: a graph that parses is started, and mistakes show up as
crashes, silent hangs or actions that never run (the thesis names the missing validator as a
gap). :func:`validate_graph` looks for those mistakes before a run. It never raises; it returns
a :class:`ValidationReport` of *errors* (the graph cannot run as written) and *warnings*
(upstream accepts it, but it is probably not what the author meant).
:meth:`ValidationReport.raise_for_errors` turns the errors into one
:class:`~temoto.errors.GraphDefinitionError`.

Errors: a relation naming an unknown action, a self-loop, a relation written on one side only
(either side), a relation listed twice; a remap from an unknown output, to an unknown input, or
between different types; a required input without a literal that no parent can fill (inputs of
entry actions are the graph's inputs); an empty ``graph_entry``; a cycle of required relations
(its actions wait for each other forever) and, more generally, actions that can never start
because each waits for another of them (a required parent, the parent that fills a required
input, or their only parents); with ``supplied``: a required graph input that is missing, or an
unknown one.

Warnings: no ``graph_exit``; actions or exits that cannot be reached from ``graph_entry``, and
actions waiting for a parent that cannot; a same-name transfer between different types; a remap
into an input that is not updatable; two remaps to one input; ``pvf_allowed_values`` that reject
everything; type ``async`` or an unknown type; ``pause``/``stop``/``restart`` on ``graph_exit``;
and the parser's own warnings (unknown keys, legacy conversion).

Every check is linear in the number of actions plus relations (and their parameters), so
graphs of tens of thousands of actions validate quickly; the cycle checks use an iterative
Tarjan, free of recursion limits. Action results are not predicted: a relation counts as able to
start its child whatever its conditions say.

Issue paths are key paths in the graph document: ``actions[i]`` is the i-th action in document
order, then ``.parents[j]``, ``.children[j]``, ``.children[j].remap[k]``,
``.input_parameters.<name>`` (namespaces joined with ``.``), or ``graph_entry[i]`` /
``graph_exit[i]``; ``""`` is the whole graph.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field

from temoto.core._scc import strongly_connected
from temoto.core.graph import UmrfGraph
from temoto.core.params import Parameter
from temoto.core.states import Response
from temoto.core.umrf import ENTRY_NAME, EXIT_NAME, ChildRelation, ParentRelation, Umrf
from temoto.errors import GraphDefinitionError

__all__ = ["Issue", "ValidationReport", "validate_graph"]

#: Action types upstream knows (only ``spontaneous`` changes behaviour).
_KNOWN_TYPES = frozenset({"sync", "async", "spontaneous"})

#: Types whose ``pvf_allowed_values`` compare at all (upstream compares only these).
_COMPARABLE_TYPES = frozenset({"string", "number", "bool"})

#: At most this many names are spelled out in one message.
_MAX_NAMES = 8


@dataclass(frozen=True, slots=True)
class Issue:
    """One finding of :func:`validate_graph`.

    Attributes:
        path: Key path in the graph document (``actions[2].parents[0]``); ``""`` means the
            whole graph.
        message: What is wrong and, where possible, how to fix it.
    """

    path: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}" if self.path else self.message


@dataclass(frozen=True, slots=True)
class ValidationReport:
    """The outcome of :func:`validate_graph`.

    Attributes:
        graph: The graph's name.
        errors: Findings that stop the graph from running as written.
        warnings: Findings upstream accepts but that are probably mistakes.
    """

    graph: str
    errors: tuple[Issue, ...] = ()
    warnings: tuple[Issue, ...] = ()

    @property
    def ok(self) -> bool:
        """Whether there are no errors (warnings do not count)."""
        return not self.errors

    def raise_for_errors(self, file: str | None = None) -> None:
        """Raise if the report holds errors.

        Args:
            file: The graph's file, named in the exception's message.

        Returns:
            None, when there are no errors.

        Raises:
            GraphDefinitionError: Listing every error, one per line, after a first line
                ``graph '<name>' cannot run (<n> errors):``; its ``path`` is the first
                error's path.
        """
        if not self.errors:
            return
        count = len(self.errors)
        lines = [f"graph '{self.graph}' cannot run ({count} error{'s' if count > 1 else ''}):"]
        lines.extend(f"  {issue}" for issue in self.errors)
        # The path is set after construction so the message's prefix names only the file:
        # every listed error carries its own path already.
        err = GraphDefinitionError("\n".join(lines), file=file)
        err.path = self.errors[0].path
        raise err


def validate_graph(
    graph: UmrfGraph, *, supplied: Collection[str] | None = None
) -> ValidationReport:
    """Check that a parsed graph can run as written.

    Every problem becomes an :class:`Issue` of the report; nothing is raised for them.

    Args:
        graph: The graph (as returned by :func:`~temoto.core.graph.parse_graph`, or built in
            code).
        supplied: Names of the external graph inputs the caller will supply at start; each
            required external input must be among them and each of them must be an external
            input. ``None`` skips these checks (e.g. when validating a file on its own).

    Returns:
        The report; :attr:`ValidationReport.ok` is true when no errors were found.
    """
    checker = _Checker(graph)
    checker.run(supplied)
    return ValidationReport(graph.name, tuple(checker.errors), tuple(checker.warnings))


# --- implementation --------------------------------------------------------------------------


@dataclass(slots=True)
class _Edge:
    """One parent→child relation, gathered from both sides of the document.

    Attributes:
        parent: Parent's index in ``graph.actions``.
        child: Child's index.
        as_parent: The child's ``parents`` entry for the parent, if written.
        as_child: The parent's ``children`` entry for the child, if written.
        parent_pos: Position of ``as_parent`` in the child's ``parents``.
        provides: The child's required inputs (without literal) this parent can fill.
    """

    parent: int
    child: int
    as_parent: ParentRelation | None = None
    as_child: ChildRelation | None = None
    parent_pos: int = -1
    provides: list[str] = field(default_factory=list)


@dataclass(slots=True)
class _Checker:
    """State shared by the checks of one :func:`validate_graph` call."""

    graph: UmrfGraph
    errors: list[Issue] = field(default_factory=list)
    warnings: list[Issue] = field(default_factory=list)
    index: dict[str, int] = field(default_factory=dict)
    instances: dict[str, list[int]] = field(default_factory=dict)
    entry: set[int] = field(default_factory=set)
    # Per child index: parent index -> edge (insertion order = first mention).
    incoming: list[dict[int, _Edge]] = field(default_factory=list)
    reachable: list[bool] = field(default_factory=list)
    # Per action: required literal-less input -> the parents that can fill it.
    providers: dict[int, dict[str, list[int]]] = field(default_factory=dict)
    unfillable: set[int] = field(default_factory=set)

    def error(self, path: str, message: str) -> None:
        self.errors.append(Issue(path, message))

    def warn(self, path: str, message: str) -> None:
        self.warnings.append(Issue(path, message))

    def run(self, supplied: Collection[str] | None) -> None:
        acts = self.graph.actions
        for i, act in enumerate(acts):
            first = self.index.setdefault(act.full_name, i)
            if first != i:  # parse_graph rejects this; graphs built in code may not
                self.error(
                    f"actions[{i}]",
                    f"duplicate action '{act.full_name}' (also"
                    f" actions[{first}]); give one of them another instance_id",
                )
            self.instances.setdefault(act.name, []).append(act.instance_id)
        self.incoming = [{} for _ in acts]
        self.parser_warnings()
        self.entry_and_exit()
        for i, act in enumerate(acts):
            self.action_kind(i, act)
            self.parents(i, act)
        for i, act in enumerate(acts):
            self.children(i, act)
        for i, act in enumerate(acts):
            self.one_sided_parents(i, act)
            self.inputs(i, act)
        in_cycles = self.deadlocks()
        self.reachability()
        self.stalls(in_cycles)
        if supplied is not None:
            self.graph_inputs(supplied)

    # --- helpers ---------------------------------------------------------------------------

    def describe_missing(self, kind: str, rel: ParentRelation | ChildRelation) -> str:
        if rel.name in (ENTRY_NAME, EXIT_NAME):
            return (
                f"{kind} '{rel.name}' is not an action of this graph: the graph's own"
                f" {rel.name} node is implicit; list the action in the graph's '{rel.name}'"
                f" array instead"
            )
        known = self.instances.get(rel.name)
        hint = ""
        if known:
            ids = ", ".join(str(n) for n in known[:_MAX_NAMES])
            more = ", ..." if len(known) > _MAX_NAMES else ""
            hint = f" ('{rel.name}' exists with instance_id {ids}{more})"
        return f"{kind} '{rel.full_name}' is not an action of this graph{hint}"

    @staticmethod
    def param_path(i: int, side: str, name: str) -> str:
        return f"actions[{i}].{side}.{name.replace('::', '.')}"

    @staticmethod
    def names(items: Iterable[str]) -> str:
        listed = list(items)
        shown = ", ".join(f"'{n}'" for n in listed[:_MAX_NAMES])
        if len(listed) > _MAX_NAMES:
            shown += f" and {len(listed) - _MAX_NAMES} more"
        return shown

    # --- checks ----------------------------------------------------------------------------

    def parser_warnings(self) -> None:
        for text in self.graph.warnings:
            head, sep, rest = text.partition(": ")
            if sep and head and not any(ch.isspace() for ch in head):
                self.warn(head, rest)
            else:
                self.warn("", text)

    def entry_and_exit(self) -> None:
        graph = self.graph
        if not graph.entry:
            self.error(
                "graph_entry",
                "the graph has no entry: nothing would ever start; list the first action(s)"
                " in 'graph_entry'",
            )
        for i, rel in enumerate(graph.entry):
            pos = self.index.get(rel.full_name)
            if pos is None:
                self.error(f"graph_entry[{i}]", self.describe_missing("entry action", rel))
            else:
                self.entry.add(pos)
        if not graph.exit:
            self.warn("graph_exit", "the graph has no exit: it runs until stopped")
        for i, prel in enumerate(graph.exit):
            path = f"graph_exit[{i}]"
            if prel.full_name not in self.index:
                self.error(path, self.describe_missing("exit action", prel))
            for result, response in prel.conditions.items():
                if response is Response.RESTART:
                    self.warn(
                        path,
                        f"'{result.value} -> restart' on graph_exit is meaningless: the graph's"
                        " end cannot be restarted; it finishes the graph like 'run'",
                    )
                elif response in (Response.PAUSE, Response.STOP):
                    self.warn(
                        path,
                        f"'{result.value} -> {response.value}' on graph_exit: the graph's end"
                        f" cannot be {'paused' if response is Response.PAUSE else 'stopped'};"
                        " it finishes the graph like 'run'",
                    )

    def action_kind(self, i: int, act: Umrf) -> None:
        if act.type == "async":
            self.warn(
                f"actions[{i}].type",
                "type 'async' behaves exactly like 'sync' (upstream never implemented it)",
            )
        elif act.type not in _KNOWN_TYPES:
            self.warn(
                f"actions[{i}].type",
                f"unknown type '{act.type}' (expected sync, async or spontaneous); it runs"
                " like 'sync'",
            )
        for name, param in act.input_parameters.items():
            if param.allowed_values and param.type not in _COMPARABLE_TYPES:
                self.warn(
                    self.param_path(i, "input_parameters", name) + ".pvf_allowed_values",
                    f"pvf_allowed_values on type '{param.type}' rejects every incoming value"
                    " (only string, number and bool values can be compared)",
                )

    def parents(self, i: int, act: Umrf) -> None:
        seen: dict[str, int] = {}
        for j, rel in enumerate(act.parents):
            path = f"actions[{i}].parents[{j}]"
            full = rel.full_name
            if full in seen:
                self.error(path, f"parent '{full}' is listed twice (also parents[{seen[full]}])")
                continue
            seen[full] = j
            if full == act.full_name:
                self.error(path, f"'{full}' lists itself as a parent (a self-loop)")
                continue
            pos = self.index.get(full)
            if pos is None:
                self.error(path, self.describe_missing("parent", rel))
                continue
            self.incoming[i][pos] = _Edge(pos, i, as_parent=rel, parent_pos=j)

    def children(self, i: int, act: Umrf) -> None:
        seen: dict[str, int] = {}
        for j, rel in enumerate(act.children):
            path = f"actions[{i}].children[{j}]"
            full = rel.full_name
            if full in seen:
                self.error(path, f"child '{full}' is listed twice (also children[{seen[full]}])")
                continue
            seen[full] = j
            if full == act.full_name:
                self.error(path, f"'{full}' lists itself as a child (a self-loop)")
                continue
            pos = self.index.get(full)
            if pos is None:
                self.error(path, self.describe_missing("child", rel))
                continue
            child = self.graph.actions[pos]
            edges = self.incoming[pos]
            edge = edges.get(i)
            if edge is None:
                edge = edges[i] = _Edge(i, pos)
                back = json.dumps({"name": act.name, "instance_id": act.instance_id})
                self.error(
                    path,
                    f"'{act.full_name}' lists '{full}' as a child, but '{full}' does not list"
                    f" '{act.full_name}' among its parents (upstream crashes when the result"
                    f" arrives); add {back} to the parents of '{full}' (actions[{pos}]), or"
                    " remove this child",
                )
            edge.as_child = rel
            self.remaps(i, j, act, rel, child)

    def one_sided_parents(self, i: int, act: Umrf) -> None:
        for edge in self.incoming[i].values():
            if edge.as_parent is None or edge.as_child is not None:
                continue
            parent = self.graph.actions[edge.parent]
            fix = json.dumps({"name": act.name, "instance_id": act.instance_id})
            self.error(
                f"actions[{i}].parents[{edge.parent_pos}]",
                f"'{act.full_name}' lists '{parent.full_name}' as a parent, but"
                f" '{parent.full_name}' does not list '{act.full_name}' among its children, so"
                f" its results never reach '{act.full_name}'; add {fix} to the children of"
                f" '{parent.full_name}' (actions[{edge.parent}]), or remove this parent",
            )

    def remaps(self, i: int, j: int, parent: Umrf, rel: ChildRelation, child: Umrf) -> None:
        targets: dict[str, int] = {}
        remapped: set[str] = set()
        for k, remap in enumerate(rel.remap):
            path = f"actions[{i}].children[{j}].remap[{k}]"
            remapped.add(remap.from_)
            out = parent.output_parameters.get(remap.from_)
            inp = child.input_parameters.get(remap.to)
            if out is None:
                self.error(
                    path,
                    f"remap from '{remap.from_}': '{parent.full_name}' has no output of that"
                    f" name (its outputs: {self.names(parent.output_parameters) or 'none'})",
                )
            if inp is None:
                self.error(
                    path,
                    f"remap to '{remap.to}': '{child.full_name}' has no input of that name"
                    f" (its inputs: {self.names(child.input_parameters) or 'none'})",
                )
            if out is None or inp is None:
                continue
            if out.type != inp.type:
                self.error(
                    path,
                    f"remap '{remap.from_}' -> '{remap.to}' joins types that differ: output"
                    f" '{remap.from_}' of '{parent.full_name}' is '{out.type}', input"
                    f" '{remap.to}' of '{child.full_name}' is '{inp.type}'",
                )
            if not inp.updatable:
                literal = " and keeps its literal value" if inp.has_value else ""
                self.warn(
                    path,
                    f"input '{remap.to}' of '{child.full_name}' is not updatable"
                    f" (pvf_updatable false){literal}: the remapped value will never arrive",
                )
            if remap.to in targets:
                self.warn(
                    path,
                    f"remap[{targets[remap.to]}] already maps an output to '{remap.to}'; only"
                    " one of the two values arrives",
                )
            targets.setdefault(remap.to, k)
        for name, out in parent.output_parameters.items():
            if name in remapped:
                continue
            inp = child.input_parameters.get(name)
            if inp is not None and inp.type != out.type:
                self.warn(
                    f"actions[{i}].children[{j}]",
                    f"output '{name}' of '{parent.full_name}' is '{out.type}' but input"
                    f" '{name}' of '{child.full_name}' is '{inp.type}': the value is silently"
                    " not transferred",
                )

    def inputs(self, i: int, act: Umrf) -> None:
        if i in self.entry or not self.incoming[i]:
            # Entry actions' literal-less inputs are the graph's inputs; an action without
            # parents never runs at all (reported as unreachable).
            return
        needed = {
            name: p
            for name, p in act.input_parameters.items()
            if p.required and not p.has_value and p.updatable
        }
        offered: dict[str, set[str]] = {}
        providers: dict[str, list[int]] = {}
        for p, edge in self.incoming[i].items():
            parent = self.graph.actions[edge.parent]
            renames = {r.from_: r.to for r in edge.as_child.remap} if edge.as_child else {}
            for name, out in parent.output_parameters.items():
                target = renames.get(name, name)
                offered.setdefault(target, set()).add(out.type)
                param = needed.get(target)
                if param is not None and param.type == out.type:
                    providers.setdefault(target, []).append(p)
                    edge.provides.append(target)
        self.providers[i] = providers
        for param in act.input_parameters.values():
            if not param.required or param.has_value or param.name in providers:
                continue
            self.unfillable.add(i)
            self.error(
                self.param_path(i, "input_parameters", param.name),
                self.unfilled_message(i, act, param, offered),
            )

    def unfilled_message(
        self, i: int, act: Umrf, param: Parameter, offered: Mapping[str, set[str]]
    ) -> str:
        parents = self.names(self.graph.actions[p].full_name for p in self.incoming[i])
        head = f"required input '{param.name}' of '{act.full_name}' has no value"
        if not param.updatable:
            return (
                f"{head} and is not updatable (pvf_updatable false), so no parent can fill"
                f" it; give it a pvf_value or make it updatable"
            )
        types = offered.get(param.name)
        found = ""
        if types:
            found = f" (a parent offers '{param.name}' as {self.names(sorted(types))}, not"
            found += f" '{param.type}')"
        return (
            f"{head} and no parent can fill it{found}; parents considered: {parents}; give it"
            " a pvf_value, or remap a parent output of the same type to it"
        )

    def deadlocks(self) -> set[int]:
        # A cycle made of required parent relations can never start: each member waits for
        # another member to have finished first. This is checked on the strongly connected
        # components of the required relations only, which finds every cycle whose members all
        # have a required parent inside it, and also such a cycle through an entry action (the
        # entry action waits for its required parent in the cycle like any other action).
        acts = self.graph.actions
        succ: list[list[int]] = [[] for _ in acts]
        for i, edges in enumerate(self.incoming):
            for p, edge in edges.items():
                if edge.as_parent is not None and edge.as_parent.required:
                    succ[p].append(i)
        in_cycles: set[int] = set()
        for comp in strongly_connected(succ):
            if len(comp) < 2:
                continue
            comp.sort()
            in_cycles.update(comp)
            members = self.names(acts[k].full_name for k in comp)
            self.error(
                f"actions[{comp[0]}]",
                f"actions {members} wait for each other: each has a required parent inside this"
                " cycle, so none of them can ever start first; make one of these parent"
                ' relations "required": false (as upstream\'s semantics_test_9_infinite_loop'
                " does)",
            )
        return in_cycles

    def reachability(self) -> None:
        acts = self.graph.actions
        seen = self.reachable = [False] * len(acts)
        todo = list(self.entry)
        for k in todo:
            seen[k] = True
        while todo:
            k = todo.pop()
            for rel in acts[k].children:
                pos = self.index.get(rel.full_name)
                if pos is not None and not seen[pos]:
                    seen[pos] = True
                    todo.append(pos)
        for k, act in enumerate(acts):
            if not seen[k]:
                self.warn(
                    f"actions[{k}]",
                    f"'{act.full_name}' cannot be reached from graph_entry along child"
                    " relations: it never runs",
                )
        for n, prel in enumerate(self.graph.exit):
            pos = self.index.get(prel.full_name)
            if pos is not None and not seen[pos]:
                self.warn(
                    f"graph_exit[{n}]",
                    f"exit action '{prel.full_name}' cannot be reached from graph_entry: the"
                    " graph never finishes through it",
                )

    def stalls(self, in_cycles: set[int]) -> None:
        # Which actions can ever start, whatever results the actions produce: an action starts
        # once some parent (or graph_entry) has finished, all its required parents have, and
        # every required input without a literal has a finished parent that fills it. (Failed
        # actions may still bypass theirs; that is not counted as starting.)
        acts = self.graph.actions
        n = len(acts)
        outgoing: list[list[_Edge]] = [[] for _ in acts]
        waiting = [len(self.providers.get(c, ())) for c in range(n)]
        for c, edges in enumerate(self.incoming):
            for p, edge in edges.items():
                outgoing[p].append(edge)
                if _required(edge):
                    waiting[c] += 1
        for c in self.unfillable:
            waiting[c] += 1  # never satisfied
        filled: list[set[str]] = [set() for _ in acts]
        started = [False] * n
        todo = [k for k in self.entry if not waiting[k]]
        for k in todo:
            started[k] = True
        while todo:
            p = todo.pop()
            for edge in outgoing[p]:
                c = edge.child
                if started[c]:
                    continue
                if _required(edge):
                    waiting[c] -= 1
                for name in edge.provides:
                    if name not in filled[c]:
                        filled[c].add(name)
                        waiting[c] -= 1
                if not waiting[c]:
                    started[c] = True
                    todo.append(c)
        # Reachable actions that never start, other than those already reported (members of
        # required cycles, actions with an input nobody fills). Each waits for "blockers": its
        # required parents that never start; else the parents that would fill its missing
        # inputs; else all its parents, none of which ever starts. The root causes are the
        # source components of the blocker graph; what is downstream of them is a consequence
        # and not reported again.
        explained = in_cycles | self.unfillable
        stuck = [k for k in range(n) if self.reachable[k] and not started[k] and k not in explained]
        if not stuck:
            return
        local = {k: j for j, k in enumerate(stuck)}
        blockers: list[list[int]] = []
        for c in stuck:
            edges = self.incoming[c]
            found = [p for p, e in edges.items() if _required(e) and not started[p]]
            if not found:
                providers = self.providers.get(c, {})
                found = [
                    p
                    for name, parents in providers.items()
                    if name not in filled[c]
                    for p in parents
                    if not started[p]
                ]
            blockers.append(found or [p for p in edges if not started[p]])
        succ: list[list[int]] = [[] for _ in stuck]
        for j, found in enumerate(blockers):
            for b in found:
                if b in local:
                    succ[local[b]].append(j)
        comps = strongly_connected(succ)
        comp_of = [0] * len(stuck)
        for num, comp in enumerate(comps):
            for j in comp:
                comp_of[j] = num
        fed = [False] * len(comps)
        for j, targets in enumerate(succ):
            for t in targets:
                if comp_of[t] != comp_of[j]:
                    fed[comp_of[t]] = True
        for num, comp in enumerate(comps):
            if fed[num]:
                continue
            members = sorted(stuck[j] for j in comp)
            if len(comp) > 1:
                self.error(
                    f"actions[{members[0]}]",
                    f"actions {self.names(acts[k].full_name for k in members)} can never start:"
                    " each waits for another of them (a required parent, the parent that fills"
                    ' a required input, or its only parents); make a relation "required":'
                    " false, give the input a pvf_value, or start one of them from graph_entry",
                )
                continue
            k = members[0]
            lost = [b for b in blockers[comp[0]] if not self.reachable[b]]
            if lost:
                self.warn(
                    f"actions[{k}]",
                    f"'{acts[k].full_name}' never runs: it waits for"
                    f" {self.names(acts[b].full_name for b in lost)}, which cannot be reached"
                    " from graph_entry",
                )

    def graph_inputs(self, supplied: Collection[str]) -> None:
        names = (supplied,) if isinstance(supplied, str) else supplied
        inputs = self.graph.signature().inputs
        given = set(names)
        for name, param in inputs.items():
            if param.required and name not in given:
                self.error(
                    self.input_path(name),
                    f"required graph input '{name}' was not supplied (upstream never starts"
                    " such a graph)",
                )
        for name in sorted(given - inputs.keys()):
            known = self.names(inputs) or "none"
            self.error("", f"unknown graph input '{name}' (the graph's inputs are: {known})")

    def input_path(self, name: str) -> str:
        for rel in self.graph.entry:
            pos = self.index.get(rel.full_name)
            if pos is not None and name in self.graph.actions[pos].input_parameters:
                return self.param_path(pos, "input_parameters", name)
        return ""


def _required(edge: _Edge) -> bool:
    return edge.as_parent is not None and edge.as_parent.required
