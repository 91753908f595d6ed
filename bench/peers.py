"""Peer frameworks measured on the same machine, on equivalent work, for scale.

- py_trees: a ``Sequence`` of 10,000 and a ``Parallel`` of 1,000 trivial behaviours, each ticked
  to completion; one re-tick ("scheduling round") of a 1,000-leaf tree with one leaf RUNNING.
- BehaviorTree.CPP through its Python binding ``behaviortreepy``: the same two shapes, with
  Python leaves (an action registered with ``register_simple_action``).
- ``transitions``: 10,000 state transitions of a ``transitions.Machine``.
- supervisord is measured side by side with the Process Manager in ``bench/process.py``.

The peers are never dependencies of the package. They are the ``bench`` extra of
pyproject.toml, and :func:`ensure_peers` installs whatever of it is missing into the running
interpreter's environment (``pip install --quiet``), once per process, unless
``TEMOTO_BENCH_NO_INSTALL=1`` (``python -m bench --no-install``). If that is disabled or fails,
the affected metrics are skipped with a note saying why.
"""

from __future__ import annotations

import gc
import importlib
import importlib.metadata
import importlib.util
import os
import re
import shlex
import subprocess
import sys
import tomllib
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench.common import Results, median, now, percentile, repeat

PYPROJECT = Path(__file__).resolve().parent.parent / "pyproject.toml"
EXTRA = "bench"
NO_INSTALL_ENV = "TEMOTO_BENCH_NO_INSTALL"
PIP_TIMEOUT_S = 600.0

SEQ_N = 10_000  # Sequence leaves
PAR_N = 1_000  # Parallel leaves
ROUND_N = 1_000  # leaves of the tree re-ticked in the "scheduling round" metrics
FSM_N = 10_000  # transitions per repetition
FSM_STATES = 10  # a ring of states s0 -> s1 -> ... -> s9 -> s0

# None until ensure_peers() ran: then {distribution: why it is not available}.
_unavailable: dict[str, str] | None = None


# ------------------------------------------------------------------------------ installation


def bench_requirements() -> list[str]:
    """The ``bench`` extra of pyproject.toml (the one list of peer requirements)."""
    with PYPROJECT.open("rb") as f:
        data = tomllib.load(f)
    reqs = data["project"]["optional-dependencies"][EXTRA]
    if not isinstance(reqs, list) or not all(isinstance(r, str) for r in reqs):
        raise ValueError(f"[project.optional-dependencies] {EXTRA} is not a list of strings")
    return reqs


def _dist_name(requirement: str) -> str:
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", requirement)
    if not m:
        raise ValueError(f"cannot read a distribution name from {requirement!r}")
    return m.group(1)


def _import_name(dist: str) -> str:
    # True for the bench extra's distributions: py_trees, behaviortreepy, transitions, supervisor.
    return re.sub(r"[-.]", "_", dist).lower()


def _importable(dist: str) -> bool:
    try:
        return importlib.util.find_spec(_import_name(dist)) is not None
    except (ImportError, ValueError):
        return False


def _version(dist: str) -> str:
    try:
        return importlib.metadata.version(dist)
    except importlib.metadata.PackageNotFoundError:
        return "?"


def ensure_peers(quiet: bool = False) -> dict[str, str]:
    """Make the ``bench`` extra importable; return ``{distribution: reason}`` for what is not.

    Checks which of the extra's distributions are importable; if some are missing, runs
    ``python -m pip install --quiet <the extra's requirements>`` once with this interpreter
    (unless ``TEMOTO_BENCH_NO_INSTALL=1``) and checks again. Never raises: a failure (no
    network, no pip, no pyproject.toml) is returned as the reason. The result is cached, so pip
    runs at most once per process.
    """
    global _unavailable
    if _unavailable is not None:
        return dict(_unavailable)
    try:
        reqs = bench_requirements()
        dists = [_dist_name(r) for r in reqs]
    except (OSError, KeyError, ValueError, tomllib.TOMLDecodeError) as e:
        _unavailable = {}
        for dist in ("py_trees", "behaviortreepy", "transitions", "supervisor"):
            if not _importable(dist):
                _unavailable[dist] = (
                    f"not importable, and the {EXTRA!r} extra could not be read from"
                    f" {PYPROJECT}: {type(e).__name__}: {e}"
                )
        return dict(_unavailable)

    missing = [d for d in dists if not _importable(d)]
    if not missing:
        _unavailable = {}
        return {}
    manual = shlex.join(["pip", "install", *reqs])
    if os.environ.get(NO_INSTALL_ENV, "") not in ("", "0"):
        why = f"not importable; not installed because {NO_INSTALL_ENV}=1 (--no-install): {manual}"
        _unavailable = dict.fromkeys(missing, why)
        return dict(_unavailable)

    cmd = [sys.executable, "-m", "pip", "install", "--quiet", *reqs]
    if not quiet:
        print(
            f"      installing bench peers (missing: {', '.join(missing)}): {shlex.join(cmd)}",
            flush=True,
        )
    t0 = now()
    failure = ""
    try:
        proc = subprocess.run(
            cmd, capture_output=True, text=True, timeout=PIP_TIMEOUT_S, check=False
        )
        if proc.returncode != 0:
            lines = [ln.strip() for ln in (proc.stderr + proc.stdout).splitlines() if ln.strip()]
            failure = f"pip exited with status {proc.returncode}" + (
                f": {lines[-1]}" if lines else ""
            )
    except subprocess.TimeoutExpired:
        failure = f"pip did not finish within {PIP_TIMEOUT_S:.0f} s"
    except OSError as e:
        failure = f"cannot run pip: {e}"
    importlib.invalidate_caches()
    _unavailable = {}
    for d in missing:
        if _importable(d):
            continue
        why = failure or "pip succeeded but it is still not importable"
        _unavailable[d] = f"not importable; installing it failed ({why}); by hand: {manual}"
    if not quiet:
        done = [d for d in missing if d not in _unavailable]
        print(
            f"      pip took {now() - t0:.1f} s;"
            f" installed: {', '.join(f'{d} {_version(d)}' for d in done) or 'nothing'}"
            + (
                f"; still missing: {', '.join(_unavailable)} ({failure or 'not importable'})"
                if _unavailable
                else ""
            ),
            flush=True,
        )
    return dict(_unavailable)


# ------------------------------------------------------------------------------------ py_trees


def _counting(fn: Callable[[], Any], counts: list[int]) -> Callable[[], Any]:
    def counted() -> Any:
        counts[0] += 1
        return fn()

    return counted


def _py_trees(out: Results, quick: bool) -> None:
    import py_trees

    ver = _version("py_trees")
    success = py_trees.common.Status.SUCCESS
    running = py_trees.common.Status.RUNNING

    # Sequence of SEQ_N leaves, ticked to completion: a fresh tree per repetition (built and set
    # up outside the timing), so the tick does not include resetting a previous run.
    seq_reps = 5 if quick else 20

    def tick_fresh(root: Any, leaves: list[Any], what: str) -> float:
        """Set a fresh tree up (untimed), then time the one tick that runs it to SUCCESS."""
        root.setup_with_descendants()
        gc.collect()
        t0 = now()
        root.tick_once()
        dt = now() - t0
        if root.status is not success or any(leaf.status is not success for leaf in leaves):
            raise RuntimeError(f"py_trees {what} did not tick every leaf to SUCCESS in one tick")
        return dt

    def seq_once() -> float:
        leaves = [py_trees.behaviours.Success(name=f"leaf_{i}") for i in range(SEQ_N)]
        root = py_trees.composites.Sequence(name="bench_seq", memory=True, children=leaves)
        return tick_fresh(root, leaves, "Sequence")

    times = repeat(seq_once, seq_reps)
    out.add(
        "peer_py_trees_seq_us_per_leaf",
        median(times) / SEQ_N * 1e6,
        "us",
        f"py_trees {ver}: Sequence(memory=True) of {SEQ_N:,} behaviours.Success, fresh tree"
        f" (built + set up untimed); one tick_once() runs all to SUCCESS (checked) / {SEQ_N:,};"
        f" median of {seq_reps}",
    )

    par_reps = 10 if quick else 50

    def par_once() -> float:
        leaves = [py_trees.behaviours.Success(name=f"leaf_{i}") for i in range(PAR_N)]
        root = py_trees.composites.Parallel(
            name="bench_par",
            policy=py_trees.common.ParallelPolicy.SuccessOnAll(synchronise=False),
            children=leaves,
        )
        return tick_fresh(root, leaves, "Parallel")

    times = repeat(par_once, par_reps)
    out.add(
        "peer_py_trees_parallel_1000_ms",
        median(times) * 1e3,
        "ms",
        f"py_trees {ver}: Parallel(SuccessOnAll) of {PAR_N:,} behaviours.Success, fresh tree;"
        f" one tick_once() runs all to SUCCESS (checked); median of {par_reps}",
    )

    # One scheduling round: a 1,000-leaf tree with exactly one leaf RUNNING, re-ticked once.
    ticks = 100 if quick else 1000

    def round_ticks(root: Any, leaves: list[Any], expect_ticked: int) -> list[float]:
        root.setup_with_descendants()
        for _ in range(10):  # warm-up: the first tick starts the tree, the rest are rounds
            root.tick_once()
        if root.status is not running or leaves[-1].status is not running:
            raise RuntimeError("py_trees round tree is not RUNNING on its last leaf")
        # One checked round: count the leaves' update() calls, then remove the counters.
        counts = [0]
        for leaf in leaves:
            leaf.update = _counting(leaf.update, counts)
        root.tick_once()
        for leaf in leaves:
            del leaf.update
        if counts[0] != expect_ticked:
            raise RuntimeError(f"py_trees round ticked {counts[0]} leaves, not {expect_ticked}")
        gc.collect()
        samples = []
        for _ in range(ticks):
            t0 = now()
            root.tick_once()
            samples.append(now() - t0)
        if root.status is not running or leaves[-1].status is not running:
            raise RuntimeError("py_trees round tree left RUNNING")
        return samples

    def round_leaves() -> list[Any]:
        return [py_trees.behaviours.Success(name=f"done_{i}") for i in range(ROUND_N - 1)] + [
            py_trees.behaviours.Running(name="running")
        ]

    # The main round metric: a Parallel whose 999 other children have finished, the closest
    # shape to a TeMoto graph of 1,000 actions with one still running.
    leaves = round_leaves()
    par = py_trees.composites.Parallel(
        name="bench_round_par",
        policy=py_trees.common.ParallelPolicy.SuccessOnAll(synchronise=True),
        children=leaves,
    )
    samples = round_ticks(par, leaves, 1)
    out.add(
        "peer_py_trees_round_1000_us",
        median(samples) * 1e6,
        "us",
        f"py_trees {ver}: one tick_once() of a Parallel(SuccessOnAll(synchronise=True)) of"
        f" {ROUND_N - 1:,} finished Success leaves + 1 Running leaf: the done leaves are skipped,"
        f" the Running one ticked, the status of all {ROUND_N:,} checked; median of {ticks:,}"
        f" consecutive ticks",
    )
    out.add(
        "peer_py_trees_round_1000_us_p99",
        percentile(samples, 99) * 1e6,
        "us",
        f"p99 of the same {ticks:,} ticks",
    )

    leaves = round_leaves()
    seq = py_trees.composites.Sequence(name="bench_round", memory=False, children=leaves)
    samples = round_ticks(seq, leaves, ROUND_N)
    out.add(
        "peer_py_trees_round_1000_us_reactive_seq",
        median(samples) * 1e6,
        "us",
        f"py_trees {ver}: as peer_py_trees_round_1000_us with a Sequence(memory=False) of"
        f" {ROUND_N - 1:,} Success + 1 Running (last) leaf: a reactive sequence re-ticks all"
        f" {ROUND_N:,} leaves each round; median of {ticks:,}",
    )

    leaves = round_leaves()
    seq = py_trees.composites.Sequence(name="bench_round_mem", memory=True, children=leaves)
    samples = round_ticks(seq, leaves, 1)
    out.add(
        "peer_py_trees_round_1000_us_seq_memory",
        median(samples) * 1e6,
        "us",
        f"py_trees {ver}: as peer_py_trees_round_1000_us with Sequence(memory=True): the round"
        f" resumes at the Running leaf (1 leaf ticked; the 999 done ones are not); median of"
        f" {ticks:,}",
    )


# ----------------------------------------------------------------------- BehaviorTree.CPP


def _bt_xml(control: str, tag: str, n: int) -> str:
    return (
        f'<root BTCPP_format="4"><BehaviorTree ID="Bench"><{control}>'
        + "<BenchSuccess/>" * n
        + f"</{tag}></BehaviorTree></root>"
    )


def _bt_cpp(out: Results, quick: bool) -> None:
    import behaviortreepy as bt

    ver = f"behaviortreepy {_version('behaviortreepy')} (BehaviorTree.CPP v4)"
    success = bt.NodeStatus.SUCCESS
    calls = [0]

    def leaf(node: Any) -> Any:
        calls[0] += 1
        return success

    factory = bt.BehaviorTreeFactory()
    factory.register_simple_action("BenchSuccess", leaf)

    def runner(tree: Any, n: int, what: str) -> Callable[[], float]:
        def once() -> float:
            calls[0] = 0
            t0 = now()
            status = tree.tick_exactly_once()
            dt = now() - t0
            if status != success or calls[0] != n:
                raise RuntimeError(
                    f"BehaviorTree.CPP {what}: tick returned {status} after {calls[0]} of {n}"
                    " leaves (expected SUCCESS after all)"
                )
            return dt

        return once

    # The tree is built once: BehaviorTree.CPP resets every node to IDLE when its parent
    # completes, so each tick_exactly_once() is a run from idle to SUCCESS.
    seq_reps = 10 if quick else 50
    tree = factory.create_tree_from_text(_bt_xml("Sequence", "Sequence", SEQ_N))
    times = repeat(runner(tree, SEQ_N, "Sequence"), seq_reps)
    out.add(
        "peer_bt_cpp_seq_us_per_leaf",
        median(times) / SEQ_N * 1e6,
        "us",
        f"{ver}: <Sequence> of {SEQ_N:,} Python leaves (register_simple_action, returns"
        f" SUCCESS); one tick_exactly_once() runs all (counted) to SUCCESS / {SEQ_N:,};"
        f" median of {seq_reps}",
    )
    del tree

    par_reps = 30 if quick else 200
    tree = factory.create_tree_from_text(
        _bt_xml('Parallel success_count="-1" failure_count="1"', "Parallel", PAR_N)
    )
    times = repeat(runner(tree, PAR_N, "Parallel"), par_reps)
    out.add(
        "peer_bt_cpp_parallel_1000_ms",
        median(times) * 1e3,
        "ms",
        f'{ver}: <Parallel success_count="-1"> (all must succeed) of {PAR_N:,} Python leaves;'
        f" one tick_exactly_once() runs all (counted) to SUCCESS; single-threaded; median of"
        f" {par_reps}",
    )


# --------------------------------------------------------------------------------- transitions


def _transitions(out: Results, quick: bool) -> None:
    from transitions import Machine

    ver = _version("transitions")
    reps = 5 if quick else 30

    class Model:
        state: str

    model = Model()
    states = [f"s{i}" for i in range(FSM_STATES)]
    machine = Machine(model=model, states=states, initial=states[0], auto_transitions=False)
    machine.add_ordered_transitions(loop=True)  # trigger next_state(): s_i -> s_(i+1 mod 10)
    step = model.next_state  # type: ignore[attr-defined]
    singles: list[float] = []

    def once() -> float:
        start = states.index(model.state)
        t0 = now()
        for _ in range(FSM_N):
            step()
        dt = now() - t0
        expected = states[(start + FSM_N) % FSM_STATES]
        if model.state != expected:
            raise RuntimeError(f"transitions: ended in {model.state}, not {expected}")
        # Second pass, each transition timed on its own (for the p99; perf_counter() pairs add
        # ≈ 0.15 µs to each sample, with the append).
        for _ in range(FSM_N):
            t1 = now()
            step()
            singles.append(now() - t1)
        return dt

    times = repeat(once, reps)
    del singles[: len(singles) - reps * FSM_N]  # the warm-up repetition's samples
    what = (
        f"transitions {ver}: Machine (auto_transitions=False) with a ring of {FSM_STATES} states"
        f" (add_ordered_transitions(loop=True)), model.next_state() x {FSM_N:,}"
    )
    out.add(
        "peer_transitions_us_per_transition",
        median(times) / FSM_N * 1e6,
        "us",
        f"{what} in a plain loop, time / {FSM_N:,}; median of {reps}",
    )
    out.add(
        "peer_transitions_us_per_transition_p99",
        percentile(singles, 99) * 1e6,
        "us",
        f"p99 of {len(singles):,} transitions timed one by one (same machine)",
    )


# ---------------------------------------------------------------------------------- the group

# (title, distribution, metric name prefix, function)
PEERS: list[tuple[str, str, str, Callable[[Results, bool], None]]] = [
    ("py_trees", "py_trees", "peer_py_trees_", _py_trees),
    ("BehaviorTree.CPP", "behaviortreepy", "peer_bt_cpp_", _bt_cpp),
    ("transitions", "transitions", "peer_transitions_", _transitions),
]


def bench_peers(quick: bool) -> Results:
    out = Results()
    unavailable = ensure_peers(quiet=False)
    for title, dist, prefix, fn in PEERS:
        if dist in unavailable or not _importable(dist):
            why = unavailable.get(dist, "is not importable")
            out.notes.append(f"{title}: {prefix}* skipped: {dist} {why}")
            continue
        t0 = now()
        try:
            fn(out, quick)
        except Exception as e:
            traceback.print_exc()
            out.notes.append(f"{title}: FAILED after {now() - t0:.1f} s ({type(e).__name__}: {e})")
    return out
