"""Action Engine benchmarks: chain, scheduling round, fan-out/fan-in, cyclic graph, start
latency, load, idle memory, import time.

Unless a metric says otherwise, every run uses a fresh :class:`temoto.ActionEngine` (shut down
afterwards) with the engine's default ``max_workers``, one discarded warm-up run, and
``gc.collect()`` between runs (the collector stays enabled while timing). Only the public API
is used; timestamps are ``time.perf_counter()``, taken by an :class:`temoto.Instrument` or
inside the actions' ``on_run``.
"""

from __future__ import annotations

import dataclasses
import gc
import itertools
import json
import logging
import os
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.common import (
    COUNTER,
    NOOP,
    Metric,
    Results,
    chain_graph,
    cyclic_graph,
    fanout_graph,
    median,
    now,
    percentile,
    repeat,
)
from temoto import (
    Action,
    ActionCatalog,
    ActionEngine,
    GraphIndex,
    Instrument,
    NodeState,
    Result,
    UmrfGraph,
    parse_graph,
    parse_graph_text,
    parse_umrf,
)

REPO = Path(__file__).resolve().parent.parent
CHAIN_N = 10_000
ROUND_N = 1_000
FANOUT_N = 1_000
WARMUP_N = 1_000  # the warm-up run of the 10,000-action benchmarks
LOAD_N = 10_000
START_N = 10  # actions in the graph whose start latency is measured
RSS_GRAPHS = 100  # indexed graphs held by the engine whose idle RSS is measured ...
RSS_GRAPH_N = 100  # ... each a chain of this many actions
WAIT_TIMEOUT = 120.0  # seconds; a hang fails the benchmark instead of blocking forever

GOAL_CHAIN_US = ("<=", 20.0)
GOAL_CHAIN_PURE_US = ("<=", 50.0)
GOAL_ROUND_US = ("<=", 20.0)
GOAL_FANOUT_MS = ("<=", 20.0)
GOAL_LOAD_MS = ("<=", 1000.0)
GOAL_RSS_MB = ("<=", 40.0)
GOAL_IMPORT_MS = ("<=", 150.0)


class BenchNoop(Action):
    """The no-op action: returns on_true at once (declared blocking, the default)."""

    def on_run(self) -> bool:
        return True


class BenchInline(Action):
    """The no-op action declared inline (``blocking = False``): runs on the evolving thread."""

    blocking = False

    def on_run(self) -> bool:
        return True


#: perf_counter() at entry and just before return of every BenchStamp.on_run, in order.
STAMPS: list[float] = []

#: Counts the on_run calls of the cyclic graph's actions (next() is atomic in CPython).
_CYCLIC_RUNS = itertools.count()


class BenchStamp(Action):
    """A no-op that appends perf_counter() to STAMPS on entry and just before it returns."""

    def on_run(self) -> bool:
        STAMPS.append(now())
        STAMPS.append(now())
        return True


class CountingNoop(Action):
    """A no-op that counts its runs (for the cyclic graph: how many actions ran)."""

    def on_run(self) -> bool:
        next(_CYCLIC_RUNS)
        return True


class BenchCounter(Action):
    """Returns on_true on every ``limit``-th run of this instance, on_false otherwise."""

    def on_init(self) -> None:
        self.count = 0

    def on_run(self) -> bool:
        next(_CYCLIC_RUNS)
        self.count += 1
        return self.count % int(self.inputs.get_number("limit")) == 0


def make_catalog(noop: type[Action] = BenchNoop) -> ActionCatalog:
    """A catalog with ``noop`` registered as BenchNoop (and BenchCounter)."""
    catalog = ActionCatalog(use_entry_points=False)
    catalog.register(noop, parse_umrf({"name": NOOP, "type": "sync"}))
    catalog.register(
        BenchCounter,
        parse_umrf(
            {
                "name": COUNTER,
                "type": "sync",
                "input_parameters": {"limit": {"pvf_type": "number"}},
            }
        ),
    )
    return catalog


class Stamps(Instrument):
    """Records perf_counter() at graph start and at every RUNNING / FINISHED transition."""

    def __init__(self) -> None:
        self.started: float | None = None
        self.running: list[float] = []
        self.finished: list[tuple[float, str]] = []

    def graph_started(self, graph: str, t: float) -> None:
        if self.started is None:
            self.started = now()

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        if new is NodeState.RUNNING:
            self.running.append(now())
        elif new is NodeState.FINISHED:
            self.finished.append((now(), node))


class StartStamp(Stamps):
    """Records perf_counter() at graph start only: no per-transition hook, so the engine runs
    as it does without observers (an instrument that does not override ``node_transition``
    costs nothing per action)."""

    node_transition = Instrument.node_transition


class FirstRunning(Instrument):
    """Records perf_counter() at the first RUNNING transition only."""

    def __init__(self) -> None:
        self.first: float | None = None

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        if self.first is None and new is NodeState.RUNNING:
            self.first = now()


@dataclass
class Run:
    t_call: float  # just before engine.start()
    t_end: float  # just after engine.wait() returned
    stamps: Stamps | None


def run_once(
    graph: UmrfGraph,
    catalog: ActionCatalog,
    *,
    instrumented: bool = True,
    max_workers: int | None = None,
) -> Run:
    stamps = Stamps() if instrumented else None
    kwargs: dict[str, Any] = {} if max_workers is None else {"max_workers": max_workers}
    engine = ActionEngine(
        "bench", actions=catalog, instruments=[stamps] if stamps else [], **kwargs
    )
    try:
        t_call = now()
        name = engine.start(graph)
        result = engine.wait(name, WAIT_TIMEOUT)
        t_end = now()
    finally:
        engine.shutdown()
    if result is not Result.TRUE:
        raise RuntimeError(f"graph {graph.name} ended with {result.value}, expected on_true")
    return Run(t_call, t_end, stamps)


def warm_runs(
    graph: UmrfGraph,
    catalog: ActionCatalog,
    reps: int,
    *,
    max_workers: int | None = None,
    traced: bool = True,
) -> list[Run]:
    """``reps`` timed runs on one long-lived engine, after one untimed warm-up run.

    A robot's engine lives for hours: its worker threads are started by the first graph and
    reused (idle ones retire after 30 s), so thread creation is not part of a graph's cost.
    Every run has the graph's name, so each start replaces the previous, ended run (as a robot
    that runs the same task again does).

    ``traced``: the instrument also stamps every RUNNING and FINISHED transition (for the gap
    distributions; it costs the engine a hook call per transition). Untraced runs stamp the
    graph's start only, and the engine runs as it does with no observer.
    """
    stamps = Stamps() if traced else StartStamp()
    kwargs: dict[str, Any] = {} if max_workers is None else {"max_workers": max_workers}
    engine = ActionEngine("bench", actions=catalog, instruments=[stamps], **kwargs)
    runs: list[Run] = []
    try:
        for i in range(reps + 1):
            stamps.__init__()  # type: ignore[misc]  # reset the recorded stamps
            t_call = now()
            name = engine.start(graph)
            result = engine.wait(name, WAIT_TIMEOUT)
            t_end = now()
            if result is not Result.TRUE:
                raise RuntimeError(f"graph {graph.name} ended with {result.value}")
            if i:
                copy = Stamps()
                copy.started, copy.running, copy.finished = (
                    stamps.started,
                    list(stamps.running),
                    list(stamps.finished),
                )
                runs.append(Run(t_call, t_end, copy))
    finally:
        engine.shutdown()
    return runs


def gaps_us(times: list[float]) -> list[float]:
    return [(b - a) * 1e6 for a, b in itertools.pairwise(times)]


def _compiled_note() -> str:
    from temoto.core import _fast

    return f"{_fast.BUILD} build"


# ------------------------------------------------------------------------------------ chain


def chain_runs(reps: int, *, traced: bool = False, noop: type[Action] = BenchNoop) -> list[Run]:
    """``reps`` runs of the CHAIN_N chain of ``noop`` actions on one warm engine, checked.

    A run that ends ``on_true`` ran every action: each waits for its parent's ``on_true``.
    Traced runs also check that CHAIN_N actions were stamped RUNNING.
    """
    catalog = make_catalog(noop)
    graph = parse_graph(chain_graph(CHAIN_N))
    runs = warm_runs(graph, catalog, reps, traced=traced)
    for run in runs:
        st = run.stamps
        assert st is not None
        if st.started is None or (traced and len(st.running) != CHAIN_N):
            raise RuntimeError(f"chain: {len(st.running)} actions ran, expected {CHAIN_N}")
    return runs


def _per_action_us(run: Run) -> float:
    assert run.stamps is not None
    assert run.stamps.started is not None
    return (run.t_end - run.stamps.started) / CHAIN_N * 1e6


def bench_chain(quick: bool) -> Results:
    out = Results()
    n = CHAIN_N
    reps = 3 if quick else 11
    runs = chain_runs(reps)
    traced = chain_runs(reps, traced=True)
    per_action = [_per_action_us(run) for run in runs]
    gaps = []
    for run in traced:
        assert run.stamps is not None
        gaps.extend(gaps_us(run.stamps.running))
    value = median(per_action)
    out.add(
        "engine_chain_us_per_action",
        value,
        "us",
        f"median of {reps} runs of a {n:,}-action chain on one warm engine;"
        f" (graph started -> wait() returned) / {n:,}; excludes planning; no per-transition"
        f" observer; {_compiled_note()}",
        GOAL_CHAIN_US,
    )
    out.add(
        "engine_chain_us_per_action_traced",
        median([_per_action_us(run) for run in traced]),
        "us",
        f"as engine_chain_us_per_action with an instrument stamping every RUNNING and FINISHED"
        f" transition (median of {reps} more runs; the gap metrics below come from them)",
    )
    out.add(
        "engine_chain_us_per_action_p99",
        percentile(gaps, 99),
        "us",
        f"p99 gap between consecutive action starts ({len(gaps):,} gaps)",
    )
    out.add(
        "engine_chain_us_per_action_p50",
        percentile(gaps, 50),
        "us",
        "median gap between consecutive action starts",
    )
    out.add(
        "engine_chain_max_gap_ms",
        median([max(gaps_us(r.stamps.running)) / 1e3 for r in traced if r.stamps]),
        "ms",
        "largest gap between consecutive action starts in a traced run (median over runs):"
        " the longest pause, a garbage collection when one lands in the run",
    )
    out.add("engine_chain_actions_per_s", 1e6 / value, "1/s", "1e6 / engine_chain_us_per_action")
    inline = [_per_action_us(run) for run in chain_runs(reps, noop=BenchInline)]
    out.add(
        "engine_chain_inline_us_per_action",
        median(inline),
        "us",
        f"as engine_chain_us_per_action with inline actions (blocking = False: each runs on"
        f" the thread that evolved the graph); median of {reps} more runs; {_compiled_note()}",
    )
    out.add(
        "engine_chain_us_per_action_incl_plan",
        median([(r.t_end - r.t_call) / n * 1e6 for r in runs]),
        "us",
        f"same runs, (start() call -> wait() returned) / {n:,}; includes planning",
    )

    from temoto.core import _fast

    if not _fast.COMPILED:
        out.add(
            "engine_chain_us_per_action_pure",
            value,
            "us",
            "identical to engine_chain_us_per_action: no compiled extension in use"
            " (temoto.core._fast.COMPILED is False)",
            GOAL_CHAIN_PURE_US,
        )
    elif os.environ.get("TEMOTO_NO_EXTENSIONS"):
        out.add(
            "engine_chain_us_per_action_pure",
            value,
            "us",
            "this process runs with TEMOTO_NO_EXTENSIONS set",
            GOAL_CHAIN_PURE_US,
        )
    else:
        pure = _pure_chain(reps)
        out.add(
            "engine_chain_us_per_action_pure",
            pure,
            "us",
            f"as engine_chain_us_per_action (median of {reps}) in a subprocess with"
            " TEMOTO_NO_EXTENSIONS=1",
            GOAL_CHAIN_PURE_US,
        )
        out.add(
            "engine_chain_speedup",
            pure / value,
            "x",
            "engine_chain_us_per_action_pure / engine_chain_us_per_action",
        )
    return out


def _pure_chain(reps: int) -> float:
    """The chain's median µs per action in a subprocess with the compiled extensions off."""
    code = "import sys, bench.engine as e; e.pure_chain_main(int(sys.argv[1]))"
    proc = subprocess.run(
        [sys.executable, "-c", code, str(reps)],
        env=_env(TEMOTO_NO_EXTENSIONS="1"),
        cwd=REPO,
        check=True,
        capture_output=True,
        text=True,
        timeout=600,
    )
    return float(json.loads(proc.stdout.strip().splitlines()[-1])["us_per_action"])


def pure_chain_main(reps: int) -> None:
    """Entry point of :func:`_pure_chain`'s subprocess: print the chain's median as JSON."""
    from temoto.core import _fast

    if _fast.COMPILED:
        raise SystemExit("the compiled extensions are in use despite TEMOTO_NO_EXTENSIONS")
    logging.getLogger("temoto").setLevel(logging.ERROR)
    runs = chain_runs(reps)
    print(json.dumps({"us_per_action": median([_per_action_us(r) for r in runs])}))


# ------------------------------------------------------------------------------------ round


def bench_round(quick: bool) -> Results:
    """One scheduling round: on_run of action i returns -> on_run of action i+1 starts."""
    out = Results()
    n = ROUND_N
    reps = 5 if quick else 20
    catalog = make_catalog(BenchStamp)
    graph = parse_graph(chain_graph(n, "bench_round"))

    def once() -> list[float]:
        STAMPS.clear()
        run_once(graph, catalog, instrumented=False)
        if len(STAMPS) != 2 * n:
            raise RuntimeError(f"round: {len(STAMPS) // 2} actions ran, expected {n}")
        # STAMPS = [entry_0, exit_0, entry_1, exit_1, ...]: gap i = entry_{i+1} - exit_i
        return [(STAMPS[2 * i + 2] - STAMPS[2 * i + 1]) * 1e6 for i in range(n - 1)]

    samples = repeat(once, reps)
    gaps = [g for sample in samples for g in sample]
    out.add(
        "engine_round_1000_us",
        median(gaps),
        "us",
        f"median over {len(gaps):,} gaps ({reps} runs of a {n:,}-action chain): on_run of"
        f" action i returned -> on_run of action i+1 entered; {_compiled_note()}",
        GOAL_ROUND_US,
    )
    out.add(
        "engine_round_1000_us_p99",
        percentile(gaps, 99),
        "us",
        "p99 of the same gaps",
    )
    out.add(
        "engine_round_1000_us_run_median_max",
        max(median(s) for s in samples),
        "us",
        "the largest of the per-run medians (spread between runs)",
    )
    return out


# ----------------------------------------------------------------------------------- fanout


def bench_fanout(quick: bool) -> Results:
    out = Results()
    n = FANOUT_N
    reps = 5 if quick else 30
    catalog = make_catalog()
    graph = parse_graph(fanout_graph(n))
    join = f"{NOOP}_{n}"

    def measure(
        max_workers: int | None, count: int, traced: bool = False, cat: ActionCatalog = catalog
    ) -> tuple[list[float], list[float], list[float]]:
        # an untraced run that ends on_true finished all n: the join needs every parent
        runs = warm_runs(graph, cat, count, max_workers=max_workers, traced=traced)
        wall, incl, gaps = [], [], []
        for run in runs:
            st = run.stamps
            assert st is not None
            assert st.started is not None
            if traced:
                done = sorted(t for t, node in st.finished if node != join)
                if len(done) != n or len(st.running) != n + 1:
                    raise RuntimeError(f"fan-out: {len(done)} actions finished, expected {n}")
                gaps.extend(gaps_us(done))
            wall.append((run.t_end - st.started) * 1e3)
            incl.append((run.t_end - run.t_call) * 1e3)
        return wall, incl, gaps

    wall, incl, _ = measure(None, reps)
    traced_wall, _, gaps = measure(None, reps, traced=True)
    out.add(
        "engine_fanout_1000_ms",
        median(wall),
        "ms",
        f"median of {reps} runs on one warm engine (workers started by an untimed first run);"
        " graph started -> wait() returned; excludes planning; no per-transition observer;"
        f" {_compiled_note()}",
        GOAL_FANOUT_MS,
    )
    inline_wall, _, _ = measure(None, reps, cat=make_catalog(BenchInline))
    out.add(
        "engine_fanout_inline_1000_ms",
        median(inline_wall),
        "ms",
        f"as engine_fanout_1000_ms with inline actions (blocking = False: the 1,000 ready"
        f" actions run as one batch on one worker); median of {reps} more runs;"
        f" {_compiled_note()}",
    )
    out.add(
        "engine_fanout_1000_ms_traced",
        median(traced_wall),
        "ms",
        f"as engine_fanout_1000_ms with an instrument stamping every transition (median of"
        f" {reps} more runs; the gap metrics below come from them)",
    )
    out.add(
        "engine_fanout_1000_ms_incl_plan",
        median(incl),
        "ms",
        "start() call -> wait() returned; includes planning",
    )
    out.add(
        "engine_fanout_us_per_action_p99",
        percentile(gaps, 99),
        "us",
        f"p99 gap between consecutive completions of the {n} parallel actions ({len(gaps)} gaps)",
    )
    out.add(
        "engine_fanout_us_per_action_p50",
        percentile(gaps, 50),
        "us",
        "median gap between consecutive completions",
    )
    if not quick:
        cpus = os.cpu_count() or 2
        wall2, _, _ = measure(cpus, max(reps // 2, 5))
        out.add(
            "engine_fanout_1000_ms_nproc_workers",
            median(wall2),
            "ms",
            f"as engine_fanout_1000_ms with max_workers={cpus}",
        )
    return out


# ----------------------------------------------------------------------------------- cyclic


def bench_cyclic(quick: bool) -> Results:
    """The 100-action graph with nested cycles and a conditional branch, run 100 times."""
    out = Results()
    reps = 100
    doc, expected = cyclic_graph()
    catalog = make_catalog(CountingNoop)
    graph = parse_graph(doc)
    times: list[float] = []
    with ActionEngine("bench", actions=catalog) as engine:
        plan_ms = []
        for _ in range(11 if quick else 31):
            fresh = dataclasses.replace(graph)  # a new object: not in the planner's cache
            t0 = now()
            engine.plan(fresh)
            plan_ms.append((now() - t0) * 1e3)
        gc.collect()
        for i in range(reps + 2):  # two warm-up runs
            before = next(_CYCLIC_RUNS)
            t0 = now()
            name = engine.start(graph)
            result = engine.wait(name, WAIT_TIMEOUT)
            t1 = now()
            ran = next(_CYCLIC_RUNS) - before - 1
            if result is not Result.TRUE or ran != expected:
                raise RuntimeError(
                    f"cyclic: run ended with {result.value} after {ran} action runs,"
                    f" expected on_true after {expected}"
                )
            if i >= 2:
                times.append((t1 - t0) * 1e3)
    value = median(times)
    out.add(
        "engine_cyclic_100_ms",
        value,
        "ms",
        f"median of {reps} runs on one engine: start() call -> wait() returned (the plan is"
        f" remembered after the first run); 100 actions, two nested cycles, a branch: {expected}"
        f" action runs per run; {_compiled_note()}",
    )
    out.add("engine_cyclic_100_ms_p99", percentile(times, 99), "ms", f"p99 of the {reps} runs")
    out.add(
        "engine_cyclic_100_us_per_action_run",
        value / expected * 1e3,
        "us",
        f"engine_cyclic_100_ms / {expected} action runs",
    )
    out.add(
        "engine_cyclic_100_plan_ms",
        median(plan_ms),
        "ms",
        f"a first engine.plan() of the graph (resolve + validate, not cached), median of"
        f" {len(plan_ms)}",
    )
    return out


# ------------------------------------------------------------------------------------ start


def bench_start(quick: bool) -> Results:
    """engine.start(name) of an indexed small graph -> first action's on_run entered."""
    out = Results()
    n = START_N
    reps = 300 if quick else 2000
    warmup = 20
    index = GraphIndex()
    index.add(parse_graph(chain_graph(n, "bench_start")))
    lat: list[float] = []
    with ActionEngine("bench", actions=make_catalog(BenchStamp), graphs=index) as engine:
        gc.collect()
        for i in range(warmup + reps):
            STAMPS.clear()
            t0 = now()
            name = engine.start("bench_start")
            result = engine.wait(name, WAIT_TIMEOUT)
            if result is not Result.TRUE or len(STAMPS) != 2 * n:
                raise RuntimeError(f"start: {result.value} after {len(STAMPS) // 2} actions")
            if i >= warmup:
                lat.append((STAMPS[0] - t0) * 1e6)
        graph = index.get("bench_start")
        plan_us = []
        for _ in range(101):
            fresh = dataclasses.replace(graph)  # a new object: not in the planner's cache
            t0 = now()
            engine.plan(fresh)
            plan_us.append((now() - t0) * 1e6)
    out.add(
        "engine_start_latency_us",
        median(lat),
        "us",
        f"median of {reps} starts on one engine: start('bench_start') called -> first action's"
        f" on_run entered; indexed {n}-action chain, planned at the first start only;"
        f" {_compiled_note()}",
    )
    out.add(
        "engine_start_latency_us_p99",
        percentile(lat, 99),
        "us",
        f"p99 of the same {reps} starts",
    )
    out.add(
        "engine_start_plan_us",
        median(plan_us),
        "us",
        f"a first (uncached) engine.plan() of that graph, which later starts skip; median of"
        f" {len(plan_us)}",
    )
    return out


# ------------------------------------------------------------------------------------- load


def bench_load(quick: bool) -> Results:
    out = Results()
    n = LOAD_N
    reps = 3 if quick else 10
    catalog = make_catalog()
    text = json.dumps(chain_graph(n, "bench_load"))

    def once() -> tuple[float, float, float]:
        first = FirstRunning()
        engine = ActionEngine("bench", actions=catalog, instruments=[first])
        try:
            t0 = now()
            graph = parse_graph_text(text)
            t_parsed = now()
            name = engine.start(graph)
            t_started = now()
            assert first.first is not None, "start() returned before the first action ran"
            engine.stop(name, WAIT_TIMEOUT)
        finally:
            engine.shutdown()
        return (t_started - t0) * 1e3, (t_parsed - t0) * 1e3, (first.first - t0) * 1e3

    engine = ActionEngine("bench", actions=catalog)  # warm-up: the same steps, a smaller chain
    try:
        engine.stop(engine.start(parse_graph_text(json.dumps(chain_graph(WARMUP_N)))))
    finally:
        engine.shutdown()
    samples = repeat(once, reps, warmup=0)
    out.add(
        "engine_load_10000_ms",
        median([s[0] for s in samples]),
        "ms",
        f"median of {reps}; JSON text of a {n:,}-action chain -> start() returned:"
        " parse_graph_text() + start() (resolve, validate, wire, start)",
        GOAL_LOAD_MS,
    )
    out.add(
        "engine_load_10000_parse_ms",
        median([s[1] for s in samples]),
        "ms",
        "of which parse_graph_text()",
    )
    out.add(
        "engine_load_10000_first_running_ms",
        median([s[2] for s in samples]),
        "ms",
        "JSON text -> first action RUNNING (inside start())",
    )
    return out


# -------------------------------------------------------------------------------- idle RSS

# Runs in a fresh interpreter; deliberately self-contained (no bench imports) so the numbers
# are those of a process that holds only TeMoto.
_RSS_CHILD = r"""
def rss_kb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])

bare = rss_kb()
import gc, json, time
from temoto import Action, ActionCatalog, ActionEngine, GraphIndex, parse_graph, parse_umrf
imported = rss_kb()

class BenchNoop(Action):
    def on_run(self):
        return True

def chain(n, name):
    ref = lambda i: {"name": "BenchNoop", "instance_id": i}
    acts = []
    for i in range(n):
        a = {"name": "BenchNoop", "instance_id": i, "type": "sync"}
        if i:
            a["parents"] = [ref(i - 1)]
        if i < n - 1:
            a["children"] = [ref(i + 1)]
        acts.append(a)
    return {"graph_name": name, "graph_entry": [ref(0)], "graph_exit": [ref(n - 1)],
            "actions": acts}

def settle():
    gc.collect(); time.sleep(0.3)
    return rss_kb()

catalog = ActionCatalog(use_entry_points=False)
catalog.register(BenchNoop, parse_umrf({"name": "BenchNoop", "type": "sync"}))
index = GraphIndex()
engine = ActionEngine("bench", actions=catalog, graphs=index)
assert engine.run(parse_graph(chain(10, "small")), timeout=60).result.value == "on_true"
empty = settle()
for g in range(N_GRAPHS):
    index.add(parse_graph(chain(GRAPH_N, f"indexed_{g}")))
assert len(engine.indexed_graphs()) == N_GRAPHS
idle = settle()
big = parse_graph(chain(N_BIG, "big"))
assert engine.run(big, timeout=120).result.value == "on_true"
loaded = settle()
engine.shutdown()
print(json.dumps({"bare": bare, "imported": imported, "empty": empty, "idle": idle,
                  "loaded": loaded}))
"""


def bench_rss(quick: bool) -> Results:
    out = Results()
    reps = 1 if quick else 3
    samples = []
    code = (
        _RSS_CHILD.replace("N_BIG", str(LOAD_N))
        .replace("N_GRAPHS", str(RSS_GRAPHS))
        .replace("GRAPH_N", str(RSS_GRAPH_N))
    )
    for _ in range(reps):
        proc = subprocess.run(
            [sys.executable, "-c", code],
            env=_env(),
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
            timeout=300,
        )
        samples.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    idle = median([s["idle"] for s in samples]) / 1024
    out.add(
        "engine_idle_rss_mb",
        idle,
        "MB",
        f"VmRSS of a fresh process whose engine holds {RSS_GRAPHS} indexed graphs of"
        f" {RSS_GRAPH_N} actions, has run a 10-action chain and is idle; median of {reps}",
        GOAL_RSS_MB,
    )
    out.add(
        "engine_idle_rss_mb_no_graphs",
        median([s["empty"] for s in samples]) / 1024,
        "MB",
        "the same process before the graphs were indexed",
    )
    out.add(
        "engine_index_kb_per_action",
        median([(s["idle"] - s["empty"]) / (RSS_GRAPHS * RSS_GRAPH_N) for s in samples]),
        "KB",
        f"(engine_idle_rss_mb - ..._no_graphs) / {RSS_GRAPHS * RSS_GRAPH_N:,} indexed actions",
    )
    out.add(
        "python_bare_rss_mb",
        median([s["bare"] for s in samples]) / 1024,
        "MB",
        "same interpreter before importing temoto",
    )
    per_action = median([(s["loaded"] - s["idle"]) / LOAD_N for s in samples])
    out.add(
        "engine_mem_kb_per_action",
        per_action,
        "KB",
        f"RSS growth after parsing and running a {LOAD_N:,}-action chain"
        f" (kept as the engine's last run) / {LOAD_N:,}",
    )
    return out


# ----------------------------------------------------------------------------- import time


def bench_import(quick: bool) -> Results:
    out = Results()
    reps = 9 if quick else 31
    with tempfile.TemporaryDirectory() as cache:
        # Measure a normal installation: bytecode cached (written to a private prefix so the
        # source tree is not touched), which this sandbox otherwise disables.
        env = _env(PYTHONPYCACHEPREFIX=cache)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        # -S (no site): site-packages' .pth files may pre-import modules temoto needs (this
        # sandbox's pull in importlib.resources), which hides part of temoto's own cost.
        cmds = {
            "import": [sys.executable, "-c", "import temoto"],
            "pass": [sys.executable, "-c", "pass"],
            "import_S": [sys.executable, "-S", "-c", "import temoto"],
            "pass_S": [sys.executable, "-S", "-c", "pass"],
        }
        times: dict[str, list[float]] = {k: [] for k in cmds}
        for i in range(reps + 1):
            for key, cmd in cmds.items():
                t0 = now()
                subprocess.run(cmd, env=env, cwd=REPO, check=True, timeout=60)
                if i:  # the first round fills the bytecode cache
                    times[key].append((now() - t0) * 1e3)

    # Median of the differences of runs made back to back: robust to load that drifts while
    # the benchmark runs (other processes on this 2-core machine), unlike a difference of medians.
    def diff(a: str, b: str) -> float:
        return median([x - y for x, y in zip(times[a], times[b], strict=True)])

    out.add(
        "import_ms",
        diff("import", "pass"),
        "ms",
        f"median of {reps} pairs: python -c 'import temoto' minus python -c 'pass'"
        " (bytecode cached)",
        GOAL_IMPORT_MS,
    )
    out.add("python_startup_ms", median(times["pass"]), "ms", "python -c 'pass'")
    out.add(
        "import_ms_no_site",
        diff("import_S", "pass_S"),
        "ms",
        "as import_ms, both with python -S (no site-packages .pth pre-imports)",
    )
    return out


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ)
    path = env.get("PYTHONPATH", "")
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + path if path else "")
    env.update(extra)
    return env


# ------------------------------------------------------------------------- ratios to the peers

#: (ratio metric, ours, theirs, goal, what): computed from the same run's metrics.
RATIOS: tuple[tuple[str, str, str, tuple[str, float], str], ...] = (
    (
        "engine_chain_vs_bt_cpp",
        "engine_chain_inline_us_per_action",
        "peer_bt_cpp_seq_us_per_leaf",
        ("<=", 1.0),
        "per action in a 10,000 chain of inline actions / per Python leaf of BehaviorTree.CPP's"
        " Sequence",
    ),
    (
        "engine_chain_vs_py_trees",
        "engine_chain_inline_us_per_action",
        "peer_py_trees_seq_us_per_leaf",
        ("<=", 0.5),
        "per action in a 10,000 chain of inline actions / per leaf of py_trees' Sequence",
    ),
    (
        "engine_fanout_vs_bt_cpp",
        "engine_fanout_inline_1000_ms",
        "peer_bt_cpp_parallel_1000_ms",
        ("<=", 1.0),
        "1,000 concurrent inline actions / BehaviorTree.CPP's Parallel of 1,000 Python leaves",
    ),
    (
        "engine_fanout_vs_py_trees",
        "engine_fanout_inline_1000_ms",
        "peer_py_trees_parallel_1000_ms",
        ("<=", 1.0),
        "1,000 concurrent inline actions / py_trees' Parallel of 1,000 leaves",
    ),
)


def ratios(metrics: Sequence[Metric]) -> Results:
    """Ours / the peer's, for every pair of :data:`RATIOS` measured in this run.

    Args:
        metrics: Every metric of the run so far.

    Returns:
        The ratios (lower is better for us; below 1 we are faster), and a note for each that
        could not be computed because a group did not run or a peer was missing.
    """
    out = Results()
    values = {m.name: m.value for m in metrics}
    for name, ours, theirs, goal, what in RATIOS:
        if ours in values and theirs in values and values[theirs] > 0:
            out.add(
                name,
                values[ours] / values[theirs],
                "x",
                f"{ours} / {theirs} of this run: {what}",
                goal,
            )
        elif ours in values or theirs in values:
            missing = theirs if ours in values else ours
            out.notes.append(f"{name} not computed: {missing} was not measured in this run")
    return out
