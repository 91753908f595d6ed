"""Action Engine benchmarks: chain, fan-out/fan-in, load, idle memory, import time.

Every run uses a fresh :class:`temoto.ActionEngine` (shut down afterwards) with the engine's
default ``max_workers`` unless stated, one discarded warm-up run, and ``gc.collect()`` between
runs (the collector stays enabled while timing). Only the public API is used; timestamps come
from an :class:`temoto.Instrument` that records ``time.perf_counter()``.
"""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from bench.common import NOOP, Results, chain_graph, fanout_graph, median, now, percentile, repeat
from temoto import (
    Action,
    ActionCatalog,
    ActionEngine,
    Instrument,
    NodeState,
    Result,
    UmrfGraph,
    parse_graph,
    parse_graph_text,
    parse_umrf,
)

REPO = Path(__file__).resolve().parent.parent
CHAIN_N = 1000
FANOUT_N = 1000
LOAD_N = 10_000
WAIT_TIMEOUT = 120.0  # seconds; a hang fails the benchmark instead of blocking forever

GOAL_CHAIN_US = ("<=", 50.0)
GOAL_FANOUT_MS = ("<", 250.0)


class BenchNoop(Action):
    """The no-op action: returns on_true at once."""

    def on_run(self) -> bool:
        return True


def make_catalog() -> ActionCatalog:
    catalog = ActionCatalog(use_entry_points=False)
    catalog.register(BenchNoop, parse_umrf({"name": NOOP, "type": "sync"}))
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
    kwargs = {} if max_workers is None else {"max_workers": max_workers}
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


def gaps_us(times: list[float]) -> list[float]:
    return [(b - a) * 1e6 for a, b in itertools.pairwise(times)]


# ------------------------------------------------------------------------------------ chain


def bench_chain(quick: bool) -> Results:
    out = Results()
    n = CHAIN_N
    reps = 5 if quick else 30
    catalog = make_catalog()
    graph = parse_graph(chain_graph(n))
    runs = repeat(lambda: run_once(graph, catalog), reps)
    per_action, gaps = [], []
    for run in runs:
        st = run.stamps
        assert st is not None
        assert st.started is not None
        if len(st.running) != n:
            raise RuntimeError(f"chain: {len(st.running)} actions ran, expected {n}")
        per_action.append((run.t_end - st.started) / n * 1e6)
        gaps.extend(gaps_us(st.running))
    value = median(per_action)
    out.add(
        "engine_chain_us_per_action",
        value,
        "us",
        f"median of {reps} runs; (graph started -> wait() returned) / {n}; excludes planning",
        GOAL_CHAIN_US,
    )
    out.add(
        "engine_chain_us_per_action_p99",
        percentile(gaps, 99),
        "us",
        f"p99 gap between consecutive action starts ({len(gaps)} gaps)",
    )
    out.add(
        "engine_chain_us_per_action_p50",
        percentile(gaps, 50),
        "us",
        "median gap between consecutive action starts",
    )
    out.add("engine_chain_actions_per_s", 1e6 / value, "1/s", "1e6 / engine_chain_us_per_action")

    # The same chain without any instrument, timed start() call -> wait() return: includes
    # planning (resolve + validate) and shows what the instrument costs.
    plain_reps = 3 if quick else 10
    plain = repeat(lambda: run_once(graph, catalog, instrumented=False), plain_reps)
    out.add(
        "engine_chain_us_per_action_incl_plan",
        median([(r.t_end - r.t_call) / n * 1e6 for r in plain]),
        "us",
        f"no instrument; (start() call -> wait() returned) / {n}; includes planning",
    )

    from temoto.core import _fast

    if not _fast.COMPILED:
        out.add(
            "engine_chain_us_per_action_pure",
            value,
            "us",
            "identical to engine_chain_us_per_action: no compiled extension in use"
            " (temoto.core._fast.COMPILED is False)",
        )
    elif os.environ.get("TEMOTO_NO_EXTENSIONS"):
        out.add(
            "engine_chain_us_per_action_pure",
            value,
            "us",
            "this process runs with TEMOTO_NO_EXTENSIONS set",
        )
    else:
        out.add(
            "engine_chain_us_per_action_pure",
            _pure_chain(quick),
            "us",
            "subprocess with TEMOTO_NO_EXTENSIONS=1",
        )
    return out


def _pure_chain(quick: bool) -> float:
    """Re-run the chain benchmark in a subprocess with the compiled extensions disabled."""
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(tmp) / "pure.json"
        cmd = [sys.executable, "-m", "bench", "--only", "chain", "--json", str(target)]
        if quick:
            cmd.append("--quick")
        env = _env(TEMOTO_NO_EXTENSIONS="1")
        subprocess.run(cmd, env=env, cwd=REPO, check=True, stdout=subprocess.DEVNULL, timeout=600)
        return float(json.loads(target.read_text())["engine_chain_us_per_action"]["value"])


# ----------------------------------------------------------------------------------- fanout


def bench_fanout(quick: bool) -> Results:
    out = Results()
    n = FANOUT_N
    reps = 5 if quick else 30
    catalog = make_catalog()
    graph = parse_graph(fanout_graph(n))
    join = f"{NOOP}_{n}"

    def measure(
        max_workers: int | None, count: int
    ) -> tuple[list[float], list[float], list[float]]:
        runs = repeat(lambda: run_once(graph, catalog, max_workers=max_workers), count)
        wall, incl, gaps = [], [], []
        for run in runs:
            st = run.stamps
            assert st is not None
            assert st.started is not None
            done = sorted(t for t, node in st.finished if node != join)
            if len(done) != n or len(st.running) != n + 1:
                raise RuntimeError(f"fan-out: {len(done)} parallel actions finished, expected {n}")
            wall.append((run.t_end - st.started) * 1e3)
            incl.append((run.t_end - run.t_call) * 1e3)
            gaps.extend(gaps_us(done))
        return wall, incl, gaps

    wall, incl, gaps = measure(None, reps)
    out.add(
        "engine_fanout_1000_ms",
        median(wall),
        "ms",
        f"median of {reps} runs; graph started -> wait() returned; excludes planning",
        GOAL_FANOUT_MS,
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


# ------------------------------------------------------------------------------------- load


def bench_load(quick: bool) -> Results:
    out = Results()
    n = LOAD_N
    reps = 3 if quick else 10
    catalog = make_catalog()
    text = json.dumps(chain_graph(n, "bench_load"))

    def once() -> tuple[float, float]:
        first = FirstRunning()
        engine = ActionEngine("bench", actions=catalog, instruments=[first])
        try:
            t0 = now()
            graph = parse_graph_text(text)
            t_parsed = now()
            name = engine.start(graph)
            assert first.first is not None, "start() returned before the first action ran"
            engine.stop(name, WAIT_TIMEOUT)
        finally:
            engine.shutdown()
        return (first.first - t0) * 1e3, (t_parsed - t0) * 1e3

    samples = repeat(once, reps)
    out.add(
        "engine_load_10000_ms",
        median([s[0] for s in samples]),
        "ms",
        f"median of {reps}; JSON text of a {n}-action chain -> first action RUNNING"
        " (parse + plan + start)",
    )
    out.add(
        "engine_load_10000_parse_ms",
        median([s[1] for s in samples]),
        "ms",
        "of which parse_graph_text()",
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
from temoto import Action, ActionCatalog, ActionEngine, parse_graph, parse_umrf
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

catalog = ActionCatalog(use_entry_points=False)
catalog.register(BenchNoop, parse_umrf({"name": "BenchNoop", "type": "sync"}))
engine = ActionEngine("bench", actions=catalog)
assert engine.run(parse_graph(chain(10, "small")), timeout=60).result.value == "on_true"
gc.collect(); time.sleep(0.3)
idle = rss_kb()
big = parse_graph(chain(N_BIG, "big"))
assert engine.run(big, timeout=120).result.value == "on_true"
gc.collect(); time.sleep(0.3)
loaded = rss_kb()
engine.shutdown()
print(json.dumps({"bare": bare, "imported": imported, "idle": idle, "loaded": loaded}))
"""


def bench_rss(quick: bool) -> Results:
    out = Results()
    reps = 1 if quick else 3
    samples = []
    for _ in range(reps):
        code = _RSS_CHILD.replace("N_BIG", str(LOAD_N))
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
        "VmRSS of a process whose engine ran a 10-action chain and is idle",
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
        f"RSS growth after parsing and running a {LOAD_N}-action chain"
        f" (kept as the engine's last run) / {LOAD_N}",
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
