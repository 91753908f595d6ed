"""The evolution kernel alone, compiled against pure Python (``python -m bench --only evolution``).

The kernel is ``Evolution`` and ``default_evolution`` of ``temoto.core._fast._evolution_py``
(pure) and of ``temoto.core._fast._evolution_c`` (the same source compiled by Cython). Both
modules are imported directly, so the measurement does not depend on which build the engine
selected (``TEMOTO_NO_EXTENSIONS``). Workloads (see bench/README.md):

- ``dag``: full evolution of a random layered DAG of 1,000 nodes (10 layers x 100, 10 edges
  per node into the next layer, written conditions on ~20 % of the edges, ~10 % error
  results, so bypass waves run through the later layers): one pass = ``propagate(node,
  result)`` for every node in topological order on a freshly built ``Evolution``;
- ``chain``: a 1,000-node chain, one edge per ``propagate`` call (call overhead dominates);
- ``eq61``: ``default_evolution(rows, 1000)`` over a one-hot ``array('b')`` of 1,000 rows.

Building an ``Evolution`` is not timed: each pass is timed alone (``perf_counter`` around it)
and a sample adds up enough passes to last at least ``MIN_SAMPLE_S``, calibrated on the faster
of two untimed passes (the warm-up). The pure and compiled samples alternate (who goes first
alternates too), so a change of the machine's speed hits both alike. ``gc.collect()`` runs
before each sample (the collector stays enabled).
"""

from __future__ import annotations

import gc
import importlib
import math
import random
from array import array
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from bench.common import Results, median, now

SEED = 20261121
LAYERS = 10
WIDTH = 100
FANOUT = 10
COND_SHARE = 0.2  # share of edges with written conditions
REQUIRED_SHARE = 0.5  # share of (child, parent) slots that are required
# result codes R_TRUE, R_FALSE, R_STOPPED, R_ERROR and their shares
RESULT_WEIGHTS = (0.6, 0.25, 0.05, 0.1)
CHAIN_N = 1_000
EQ61_ROWS = 1_000
MIN_SAMPLE_S = 0.025

GOAL_SPEEDUP = (">=", 10.0)


@dataclass
class Topology:
    """Arguments of ``Evolution(...)`` plus the result each node reports."""

    args: tuple[Any, ...]
    results: list[int]
    n_edges: int


def _build(
    n_nodes: int, edges: list[list[tuple[int, list[int]]]], required: dict[tuple[int, int], bool]
) -> tuple[Any, ...]:
    """Evolution's constructor arguments from ``edges[parent] = [(child, responses), ...]``."""
    parents_of: list[list[int]] = [[] for _ in range(n_nodes)]
    for p in range(n_nodes):
        for child, _ in edges[p]:
            parents_of[child].append(p)
    slot_start = [0]
    slot_required: list[int] = []
    slot_of: dict[tuple[int, int], int] = {}
    for c in range(n_nodes):
        for p in parents_of[c]:
            slot_of[(c, p)] = len(slot_required)
            slot_required.append(1 if required[(c, p)] else 0)
        slot_start.append(len(slot_required))
    edge_start = [0]
    edge_child: list[int] = []
    edge_slot: list[int] = []
    edge_response: list[int] = []
    for p in range(n_nodes):
        for child, responses in edges[p]:
            edge_child.append(child)
            edge_slot.append(slot_of[(child, p)])
            edge_response.extend(responses)
        edge_start.append(len(edge_child))
    return (n_nodes, edge_start, edge_child, edge_slot, edge_response, slot_start, slot_required)


def layered_dag(rng: random.Random) -> Topology:
    """LAYERS x WIDTH nodes; each node has FANOUT edges to random nodes of the next layer."""
    n = LAYERS * WIDTH
    edges: list[list[tuple[int, list[int]]]] = [[] for _ in range(n)]
    required: dict[tuple[int, int], bool] = {}
    n_edges = 0
    for layer in range(LAYERS - 1):
        nxt = range((layer + 1) * WIDTH, (layer + 2) * WIDTH)
        for p in range(layer * WIDTH, (layer + 1) * WIDTH):
            for child in sorted(rng.sample(nxt, FANOUT)):
                if rng.random() < COND_SHARE:
                    responses = [rng.randint(-1, 5) for _ in range(4)]
                else:
                    responses = [-1] * 4
                edges[p].append((child, responses))
                required[(child, p)] = rng.random() < REQUIRED_SHARE
                n_edges += 1
    results = rng.choices(range(4), weights=RESULT_WEIGHTS, k=n)
    return Topology(_build(n, edges, required), results, n_edges)


def chain(n: int) -> Topology:
    """0 -> 1 -> ... -> n-1, required parents, default conditions, every result on_true."""
    edges: list[list[tuple[int, list[int]]]] = [[(i + 1, [-1] * 4)] for i in range(n - 1)]
    edges.append([])
    required = {(i + 1, i): True for i in range(n - 1)}
    return Topology(_build(n, edges, required), [0] * n, n - 1)


def _propagate_all(ev: Any, results: list[int]) -> int:
    """One pass: propagate every node's result in order; returns the steps (edges) visited."""
    steps = 0
    propagate = ev.propagate
    for node, result in enumerate(results):
        steps += len(propagate(node, result))
    return steps


def _signature(mod: ModuleType, topo: Topology) -> list[list[int]]:
    ev = mod.Evolution(*topo.args)
    return [ev.propagate(node, result) for node, result in enumerate(topo.results)]


@dataclass
class Timing:
    per_pass_s: list[float]  # one value per sample: its time / its passes
    passes: int  # passes per sample
    units: int  # edges (or calls, rows) per pass


class Sampler:
    """Times ``work(make())`` with ``make`` untimed; a sample adds up >= target_s of passes."""

    def __init__(
        self, make: Callable[[], Any], work: Callable[[Any], int], target_s: float
    ) -> None:
        self.make = make
        self.work = work
        fastest = math.inf
        for _ in range(2):  # calibrate on the faster of two passes (the first one is cold)
            obj = make()
            t0 = now()
            self.units = work(obj)
            fastest = min(fastest, now() - t0)
        self.passes = max(1, math.ceil(target_s / max(fastest, 1e-9)))

    def sample(self) -> float:
        """One sample: its time / its passes, in seconds."""
        gc.collect()
        total = 0.0
        for _ in range(self.passes):
            obj = self.make()
            t0 = now()
            got = self.work(obj)
            total += now() - t0
            if got != self.units:
                raise RuntimeError(f"a pass visited {got} units, the first one {self.units}")
        return total / self.passes


def _interleaved(samplers: dict[str, Sampler], samples: int) -> dict[str, Timing]:
    """``samples`` rounds of one sample per build; the builds alternate who goes first, so a
    drift of the machine's speed hits both alike. (The calibration passes were the warm-up.)"""
    names = list(samplers)
    out: dict[str, list[float]] = {name: [] for name in names}
    for i in range(samples):
        for name in names if i % 2 == 0 else names[::-1]:
            out[name].append(samplers[name].sample())
    return {n: Timing(out[n], samplers[n].passes, samplers[n].units) for n in names}


def _load_compiled() -> tuple[ModuleType | None, str]:
    try:
        return importlib.import_module("temoto.core._fast._evolution_c"), ""
    except ImportError as err:
        return None, f"compiled build not installed ({err})"


def bench_evolution(quick: bool) -> Results:
    out = Results()
    samples = 5 if quick else 15
    target = MIN_SAMPLE_S if quick else 2 * MIN_SAMPLE_S
    pure = importlib.import_module("temoto.core._fast._evolution_py")
    compiled, missing = _load_compiled()
    if missing:
        out.notes.append(f"evolution: {missing}; speedups reported as 1.0, not measured")
    mods: dict[str, ModuleType] = {"pure": pure}
    if compiled is not None:
        mods["compiled"] = compiled

    dag = layered_dag(random.Random(SEED))
    line = chain(CHAIN_N)
    rng = random.Random(SEED + 1)
    rows = array("b", bytes(EQ61_ROWS * pure.N_STATES))
    for i in range(EQ61_ROWS):
        # mostly idle parents, a few stopped / other, one in error (so both sums matter)
        state = rng.choices(range(pure.N_STATES), weights=(40, 40, 10, 0, 10))[0]
        rows[i * pure.N_STATES + state] = 1
    rows[(EQ61_ROWS // 2) * pure.N_STATES + pure.S_ERROR] = 1
    rows[(EQ61_ROWS // 2) * pure.N_STATES + pure.S_IDLE_TRUE] = 0

    if compiled is not None:  # both builds must agree before they are compared
        for topo, what in ((dag, "DAG"), (line, "chain")):
            if _signature(pure, topo) != _signature(compiled, topo):
                raise RuntimeError(f"evolution: compiled and pure builds differ on the {what}")
        if pure.default_evolution(rows, EQ61_ROWS) != compiled.default_evolution(rows, EQ61_ROWS):
            raise RuntimeError("evolution: compiled and pure default_evolution differ")

    def samplers(mod: ModuleType) -> dict[str, Sampler]:
        cls = mod.Evolution
        eq61 = mod.default_evolution
        reps61 = 100

        def eq61_work(_: Any) -> int:
            for _ in range(reps61):
                eq61(rows, EQ61_ROWS)
            return reps61 * EQ61_ROWS

        return {
            "dag": Sampler(
                lambda: cls(*dag.args), lambda ev: _propagate_all(ev, dag.results), target
            ),
            "chain": Sampler(
                lambda: cls(*line.args), lambda ev: _propagate_all(ev, line.results), target
            ),
            "eq61": Sampler(lambda: None, eq61_work, target),
        }

    by_build = {name: samplers(mod) for name, mod in mods.items()}
    timings: dict[str, dict[str, Timing]] = {name: {} for name in mods}
    for key in ("dag", "chain", "eq61"):
        got = _interleaved({name: by_build[name][key] for name in mods}, samples)
        for name in mods:
            timings[name][key] = got[name]
    p = timings["pure"]
    c = timings.get("compiled", p)
    build = "compiled" if compiled is not None else "pure (compiled build not installed)"

    def ratio(key: str) -> float:
        if compiled is None:
            return 1.0
        return median(p[key].per_pass_s) / median(c[key].per_pass_s)

    def ns(t: Timing) -> float:
        return median(t.per_pass_s) / t.units * 1e9

    def how(key: str) -> str:
        return (
            f"median of {samples} samples of {p[key].passes} (pure) /"
            f" {c[key].passes} (compiled) passes"
        )

    d = p["dag"]
    note = (
        f"pure / compiled time of one full pass over a {LAYERS}x{WIDTH} layered DAG"
        f" ({dag.n_edges:,} edges, {d.units:,} steps with the bypass waves); {how('dag')}"
    )
    out.add(
        "evolution_speedup",
        ratio("dag"),
        "x",
        note if compiled is not None else missing,
        GOAL_SPEEDUP,
    )
    out.add(
        "evolution_ns_per_edge",
        ns(c["dag"]),
        "ns",
        f"{build}: one DAG pass / the {d.units:,} steps (edges visited) it returns",
    )
    out.add("evolution_ns_per_edge_pure", ns(p["dag"]), "ns", "the same, pure build")
    out.add(
        "evolution_speedup_chain",
        ratio("chain"),
        "x",
        f"pure / compiled, {CHAIN_N:,}-node chain: one propagate() call per edge; {how('chain')}"
        if compiled is not None
        else missing,
    )
    out.add(
        "evolution_ns_per_call_chain",
        ns(c["chain"]),
        "ns",
        f"{build}: one chain pass / {line.n_edges + 1:,} propagate() calls",
    )
    out.add("evolution_ns_per_call_chain_pure", ns(p["chain"]), "ns", "the same, pure build")
    out.add(
        "evolution_eq61_speedup",
        ratio("eq61"),
        "x",
        f"pure / compiled default_evolution(rows, {EQ61_ROWS:,}), rows an array('b') one-hot"
        f" matrix; {how('eq61')}"
        if compiled is not None
        else missing,
    )
    out.add(
        "evolution_eq61_ns_per_row",
        ns(c["eq61"]),
        "ns",
        f"{build}: default_evolution over {EQ61_ROWS:,} rows / {EQ61_ROWS:,}",
    )
    out.add("evolution_eq61_ns_per_row_pure", ns(p["eq61"]), "ns", "the same, pure build")
    return out
