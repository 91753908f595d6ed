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
