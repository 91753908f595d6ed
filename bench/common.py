"""Helpers shared by the benchmark modules: results, statistics, the no-op action, graphs."""

from __future__ import annotations

import gc
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any


@dataclass
class Metric:
    """One reported number. ``goal`` is (comparison, bound), e.g. ("<=", 50.0)."""

    name: str
    value: float
    unit: str
    note: str = ""
    goal: tuple[str, float] | None = None


@dataclass
class Results:
    """What a benchmark group produced: metrics plus free-form notes (skips, caveats)."""

    metrics: list[Metric] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def add(
        self,
        name: str,
        value: float,
        unit: str,
        note: str = "",
        goal: tuple[str, float] | None = None,
    ) -> None:
        self.metrics.append(Metric(name, float(value), unit, note, goal))


def median(values: Sequence[float]) -> float:
    return statistics.median(values)


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile (0..100), linear interpolation between closest ranks."""
    data = sorted(values)
    if not data:
        return math.nan
    pos = (len(data) - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, len(data) - 1)
    return data[lo] + (data[hi] - data[lo]) * (pos - lo)


def repeat(fn: Callable[[], Any], reps: int, warmup: int = 1) -> list[Any]:
    """Call ``fn`` warmup + reps times, gc before each; keep the last reps."""
    out = []
    for i in range(warmup + reps):
        gc.collect()
        result = fn()
        if i >= warmup:
            out.append(result)
    return out


def now() -> float:
    return time.perf_counter()


# ---------------------------------------------------------------------------------- graphs

NOOP = "BenchNoop"


def _ref(i: int) -> dict[str, Any]:
    return {"name": NOOP, "instance_id": i}


def chain_graph(n: int, name: str = "bench_chain") -> dict[str, Any]:
    """graph_entry -> BenchNoop_0 -> ... -> BenchNoop_{n-1} -> graph_exit (UMRF JSON dict)."""
    actions = []
    for i in range(n):
        action: dict[str, Any] = {"name": NOOP, "instance_id": i, "type": "sync"}
        if i > 0:
            action["parents"] = [_ref(i - 1)]
        if i < n - 1:
            action["children"] = [_ref(i + 1)]
        actions.append(action)
    return {
        "graph_name": name,
        "graph_description": f"benchmark: chain of {n} no-op actions",
        "graph_entry": [_ref(0)],
        "graph_exit": [_ref(n - 1)],
        "actions": actions,
    }


def fanout_graph(n: int, name: str = "bench_fanout") -> dict[str, Any]:
    """graph_entry -> BenchNoop_0..n-1 in parallel -> BenchNoop_n (n required parents) -> exit."""
    join = n
    actions: list[dict[str, Any]] = [
        {"name": NOOP, "instance_id": i, "type": "sync", "children": [_ref(join)]} for i in range(n)
    ]
    actions.append(
        {
            "name": NOOP,
            "instance_id": join,
            "type": "sync",
            "parents": [{**_ref(i), "required": True} for i in range(n)],
        }
    )
    return {
        "graph_name": name,
        "graph_description": f"benchmark: fan-out/fan-in of {n} no-op actions",
        "graph_entry": [_ref(i) for i in range(n)],
        "graph_exit": [_ref(join)],
        "actions": actions,
    }


# ------------------------------------------------------------------------- cyclic graph

COUNTER = "BenchCounter"

#: Layout of :func:`cyclic_graph` (node counts), see bench/README.md.
CYCLIC_PRE = 10  # BenchNoop_0..9 before the outer loop
CYCLIC_OUTER_HEAD = 10  # BenchNoop_10..19: start of the outer loop's body
CYCLIC_INNER = 10  # BenchNoop_20..29: the inner loop's body
CYCLIC_BRANCH = 10  # BenchNoop_30..39 (on_true) and BenchNoop_40..49 (on_false)
CYCLIC_OUTER_TAIL = 10  # BenchNoop_50..59: after the branches' join
CYCLIC_POST = 37  # BenchNoop_60..96 after the outer loop
CYCLIC_INNER_TURNS = 3  # BenchCounter_0's limit: the inner body runs 3 times per outer turn
CYCLIC_OUTER_TURNS = 4  # BenchCounter_2's limit: the outer body runs 4 times
CYCLIC_TOGGLE = 2  # BenchCounter_1's limit: it alternates false, true, false, ...


def _rel(name: str, i: int, *conditions: str, required: bool | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"name": name, "instance_id": i}
    if required is not None:
        out["required"] = required
    if conditions:
        out["conditions"] = list(conditions)
    return out


def cyclic_graph(name: str = "bench_cyclic") -> tuple[dict[str, Any], int]:
    r"""A graph of 100 actions with two nested cycles and a conditional branch.

    97 ``BenchNoop`` and 3 ``BenchCounter`` actions (a counter returns on_true on every
    ``limit``-th run of its instance, on_false otherwise)::

        entry -> N0..N9 -> N10..N19 -> N20..N29 -> C0 (limit 3)
                           ^           ^             |on_false: back to N20 (inner loop)
                           |           +-------------+
                           |                         |on_true
                           |                         v
                           |                         C1 (limit 2, a toggle)
                           |             on_true /          \ on_false
                           |              N30..N39          N40..N49
                           |                     \         /   (join: either parent)
                           |                      N50..N59 -> C2 (limit 4)
                           +-- on_false (outer loop) ----------+ |on_true
                                                                 v
                                                         N60..N96 -> exit

    Every relation is written on both sides; the branch and loop relations carry written
    conditions (``on_true -> ignore``/``on_false -> run`` on the back-edges, the reverse on
    the forward edges). The back-edges are non-required parents, so a node re-runs whenever
    its counter says so (its required parent stays received for the rest of the run).

    Returns:
        The UMRF JSON dict and the number of action runs one run of it makes (307).
    """
    nodes: dict[tuple[str, int], dict[str, Any]] = {}

    def node(nm: str, i: int, **extra: Any) -> dict[str, Any]:
        action: dict[str, Any] = {"name": nm, "instance_id": i, "type": "sync", **extra}
        action.setdefault("parents", [])
        action.setdefault("children", [])
        nodes[(nm, i)] = action
        return action

    def link(
        parent: tuple[str, int], child: tuple[str, int], *cond: str, required: bool | None = None
    ) -> None:
        nodes[parent]["children"].append(_rel(*child))
        nodes[child]["parents"].append(_rel(*parent, *cond, required=required))

    def counter(i: int, limit: int) -> tuple[str, int]:
        node(COUNTER, i, input_parameters={"limit": {"pvf_type": "number", "pvf_value": limit}})
        return (COUNTER, i)

    def chain(first: int, count: int) -> tuple[tuple[str, int], tuple[str, int]]:
        for i in range(first, first + count):
            node(NOOP, i)
            if i > first:
                link((NOOP, i - 1), (NOOP, i))
        return (NOOP, first), (NOOP, first + count - 1)

    back = ("on_true -> ignore", "on_false -> run")
    forward = ("on_true -> run", "on_false -> ignore")
    k = 0
    pre_first, pre_last = chain(k, CYCLIC_PRE)
    k += CYCLIC_PRE
    head_first, head_last = chain(k, CYCLIC_OUTER_HEAD)
    k += CYCLIC_OUTER_HEAD
    inner_first, inner_last = chain(k, CYCLIC_INNER)
    k += CYCLIC_INNER
    true_first, true_last = chain(k, CYCLIC_BRANCH)
    k += CYCLIC_BRANCH
    false_first, false_last = chain(k, CYCLIC_BRANCH)
    k += CYCLIC_BRANCH
    tail_first, tail_last = chain(k, CYCLIC_OUTER_TAIL)
    k += CYCLIC_OUTER_TAIL
    post_first, post_last = chain(k, CYCLIC_POST)
    inner_count = counter(0, CYCLIC_INNER_TURNS)
    toggle = counter(1, CYCLIC_TOGGLE)
    outer_count = counter(2, CYCLIC_OUTER_TURNS)

    link(pre_last, head_first, required=True)
    link(head_last, inner_first, required=True)
    link(inner_last, inner_count)
    link(inner_count, inner_first, *back, required=False)  # inner loop
    link(inner_count, toggle, *forward)
    link(toggle, true_first, "on_true -> run", "on_false -> ignore")
    link(toggle, false_first, "on_true -> ignore", "on_false -> run")
    link(true_last, tail_first, required=False)  # join: whichever branch ran
    link(false_last, tail_first, required=False)
    link(tail_last, outer_count)
    link(outer_count, head_first, *back, required=False)  # outer loop
    link(outer_count, post_first, *forward)

    actions = []
    for action in nodes.values():
        for key in ("parents", "children"):
            if not action[key]:
                del action[key]
        actions.append(action)
    inner_turn = CYCLIC_INNER + 1
    outer_turn = (
        CYCLIC_OUTER_HEAD
        + CYCLIC_INNER_TURNS * inner_turn
        + 1
        + CYCLIC_BRANCH
        + CYCLIC_OUTER_TAIL
        + 1
    )
    runs = CYCLIC_PRE + CYCLIC_OUTER_TURNS * outer_turn + CYCLIC_POST
    doc = {
        "graph_name": name,
        "graph_description": "benchmark: 100 actions, two nested cycles and a conditional branch",
        "graph_entry": [_rel(*pre_first)],
        "graph_exit": [_rel(*post_last)],
        "actions": actions,
    }
    return doc, runs
