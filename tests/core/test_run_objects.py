"""What a graph run costs the garbage collector, and the reuse of an ended run's nodes.

A node is one tracked object (it carries its action's stop and pause signals itself; the
numbering of nodes and relations is made once per plan), and a run that replaces an ended run
of the same plan takes over its nodes (``GraphRun(reuse=...)``), renewed: a robot that runs
the same task again makes no object per node. The renewal must look like a new run in every
way an action or a caller can see, and must not happen while an action of the old run may
still be running (a failed stop).
"""

from __future__ import annotations

import gc
import threading
import weakref
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from test_engine import WAIT, Emit, Upper, _upper_graphs, engine_with, eventually

from temoto import Action, ActionEngine, GraphState, NodeState, Result, build
from temoto.build import Param, action
from temoto.core._runtime import GraphRun, Node

N = 300


@contextmanager
def _collector_off() -> Iterator[None]:
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


@action
class Tick(Action):
    """Inline no-op."""

    blocking = False

    def on_run(self) -> bool:
        return True


#: (node, number of runs of that instance, the literal it read) per run of Stateful
SEEN: list[tuple[str, int, str]] = []


@action(inputs={"text": str})
class Stateful(Action):
    """Counts its own runs (state kept in the instance), logs, and reads a literal input."""

    def on_init(self) -> None:
        self.runs = 0

    def on_run(self) -> bool:
        self.runs += 1
        SEEN.append((self.name, self.runs, self.inputs.get_string("text")))
        self.log(f"run {self.runs}")
        return True


def test_a_run_makes_one_tracked_object_per_node() -> None:
    g = build.graph(*[Tick] * N, name="objects")
    with engine_with(Tick) as (engine, _):
        plan = engine.plan(g)
        GraphRun("first", plan)  # makes the plan's wiring, kept with the plan
        with _collector_off():
            gc.collect()
            before = len(gc.get_objects())
            run = GraphRun("second", plan)
            made = len(gc.get_objects()) - before
        assert len(run.nodes) == N
        # the nodes, plus a few per run (lists, the kernel): not two or three per node
        assert made < N + 50, made


def test_a_new_run_of_the_same_graph_takes_over_the_ended_runs_nodes() -> None:
    g = build.graph(*[Tick] * 20, name="again")
    with engine_with(Tick) as (engine, _):
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        old = engine._runs["again"]
        old_nodes = list(old.nodes.values())
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        new = engine._runs["again"]
        assert new is not old
        assert list(new.nodes.values()) == old_nodes
        assert all(a is b for a, b in zip(new.nodes.values(), old_nodes, strict=True))
        assert all(node.run is new for node in new.all_nodes())
        assert old.nodes == {}  # the old run forgot them


def test_a_repeated_run_leaves_the_young_collector_idle() -> None:
    """A run that took over an ended run's nodes makes a new instance per node, but frees the
    previous run's instance of that node right after (``Node.spent``): the collector's count
    sees replacements, not growth, so no young collection falls inside the run. Nor is there
    a scan of the young generations at the start of such a run (that is for new nodes)."""
    if not gc.isenabled():
        pytest.skip("the collector is disabled in this process")
    n = 2000
    g = build.graph(build.parallel(*[Tick] * n), name="replaced_instances")
    collections: list[int] = []

    def count(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            collections.append(info["generation"])

    # no instrument: a recorder keeps objects per transition (the collector's count grows)
    with ActionEngine("me", actions=build.catalog(Tick)) as engine:
        for _ in range(2):  # the plan, its wiring, the nodes: made once
            assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        gc.callbacks.append(count)
        try:
            for _ in range(4):
                assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        finally:
            gc.callbacks.remove(count)
    # before (the old instances freed at each start): 12, a scan at each start and two young
    # collections in each run; one is allowed for what other threads of the process allocate
    assert len(collections) <= 1, collections


def test_the_ended_runs_instances_are_freed_as_the_new_run_makes_its_own() -> None:
    g = build.graph(*[Tick] * 20, name="spent")
    with engine_with(Tick) as (engine, _), _collector_off():
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        nodes = list(engine._runs["spent"].nodes.values())
        first = [weakref.ref(node.instance) for node in nodes]
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        # by reference counting (the collector is off): the node dropped its old instance
        assert [ref() for ref in first] == [None] * len(first)
        second = [weakref.ref(node.instance) for node in nodes]
        assert all(ref() is not None for ref in second)
        g2 = build.graph(*[Tick] * 20, name="spent")  # a new plan: the old run is disposed
        assert engine.wait(engine.start(g2), WAIT) is Result.TRUE
        assert [ref() for ref in second] == [None] * len(second)
        assert all(node.spent is None and node.instance is None for node in nodes)


def test_a_renewed_node_starts_like_a_new_one() -> None:
    SEEN.clear()
    g = build.graph(
        build.node(Stateful, {"text": "a"}),
        build.node(Stateful, {"text": "b"}, instance=1),
        name="fresh",
    )
    with engine_with(Stateful) as (engine, rec):
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        first_instance = engine._runs["fresh"].nodes["Stateful_0"].instance
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        run = engine._runs["fresh"]
        # a new instance per node and run (on_init again), the literals as written
        assert run.nodes["Stateful_0"].instance is not first_instance
        assert SEEN == [
            ("Stateful_0", 1, "a"),
            ("Stateful_1", 1, "b"),
            ("Stateful_0", 1, "a"),
            ("Stateful_1", 1, "b"),
        ]
        assert engine.node_states("fresh") == {
            "Stateful_0": NodeState.FINISHED,
            "Stateful_1": NodeState.FINISHED,
        }
        # the log is the new run's only
        snapshot = str(engine.graph_json("fresh"))
        assert snapshot.count("run 1") == 2, snapshot  # one message per node
        assert engine.outcome("fresh").state is GraphState.FINISHED
        # every node went UNINITIALIZED -> RUNNING -> FINISHED in the second run too
        second = [t for t in rec.transitions if t[0] == "fresh"][-4:]
        assert sorted((node, old.name, new.name) for _, node, old, new in second) == sorted(
            [
                ("Stateful_0", "UNINITIALIZED", "RUNNING"),
                ("Stateful_0", "RUNNING", "FINISHED"),
                ("Stateful_1", "UNINITIALIZED", "RUNNING"),
                ("Stateful_1", "RUNNING", "FINISHED"),
            ]
        )


@action(inputs={"value": Param(str, updatable=True)}, outputs={"out": str})
class Keep(Action):
    """out = value (a parent may overwrite its literal: updatable)."""

    def on_run(self) -> bool:
        self.outputs["out"] = self.inputs.get_string("value")
        return True


def test_a_renewed_node_is_a_new_node_in_every_field() -> None:
    """The reuse path (renewal, no wiring again) leaves each node and the run as a new run of
    the plan has them, also after a run in which a parent overwrote a literal input."""
    g = build.graph(
        build.node(Emit, value="from parent", remap={"out": "value"}),
        build.node(Keep, value="literal"),
        build.parallel(Tick, build.node(Keep, value="other", instance=1)),
        name="renewed",
    )
    fields = [f for f in Node.__slots__ if f not in ("run", "gen", "spent", "instance")]
    fields += ["stop", "paused", "broken", "logged", "acquired", "condition"]
    with engine_with(Keep, Tick) as (engine, _):
        plan = engine.plan(g)
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        old = engine._runs["renewed"]
        assert old.nodes["Keep_0"].data == {}  # the parent's value, dropped after the run
        assert old.nodes["Keep_0"].native == frozenset()
        renewed = GraphRun("renewed", plan, reuse=old)
        new = GraphRun("new", plan)
        for mine, theirs in zip(renewed.order, new.order, strict=True):
            for field in fields:
                assert getattr(mine, field) == getattr(theirs, field), (mine.name, field)
            assert mine.run is renewed
        assert renewed.nodes["Keep_0"].data == {"value": "literal"}
        assert renewed.nodes["Keep_0"].native == {"value"}
        assert [n.name for n in renewed.edge_parent] == [n.name for n in new.edge_parent]
        assert [n.name for n in renewed.edge_child] == [n.name for n in new.edge_child]
        assert renewed.edge_start == new.edge_start
        assert renewed.edge_remap == new.edge_remap
        assert renewed.evolution.received_flags() == new.evolution.received_flags()
        assert all(
            renewed.evolution.missing_parents(n.idx) == new.evolution.missing_parents(n.idx)
            for n in new.order
        )
        assert old.nodes == {}
        assert old.order == []
        assert old.edge_child == []


def test_a_run_whose_stop_failed_lends_no_node() -> None:
    """An action the engine gave up on still runs: its node keeps saying "stop" to it."""
    started = threading.Semaphore(0)
    release = threading.Event()
    stop_seen: list[bool] = []

    @action
    class Stubborn(Action):
        def on_run(self) -> bool:
            started.release()
            release.wait(WAIT)  # ignores the stop
            stop_seen.append(self.stop_requested)
            return True

    g = build.graph(Stubborn, name="stubborn")
    with engine_with(Stubborn, stop_timeout=0.1) as (engine, _):
        engine.start(g)
        assert started.acquire(timeout=WAIT)
        assert engine.stop("stubborn", timeout=WAIT) is Result.ERROR
        old_node = engine._runs["stubborn"].nodes["Stubborn_0"]
        engine.start(g)
        assert started.acquire(timeout=WAIT)
        assert engine._runs["stubborn"].nodes["Stubborn_0"] is not old_node
        assert old_node.stop  # still stopped: the old action sees it
        release.set()
        assert engine.wait("stubborn", WAIT) is Result.TRUE
        eventually(lambda: len(stop_seen) == 2, what="both actions to return")
        assert sorted(stop_seen) == [False, True]  # the old run's action saw its stop
        assert isinstance(old_node, Node)


def test_a_replaced_run_is_freed_without_the_cyclic_collector() -> None:
    """A node and its action refer to each other (the action's RunControl is the node):
    disposing of a replaced run must break that, or every node waits for a full collection."""
    with engine_with(Tick) as (engine, _):
        for _ in range(2):  # a new graph object each time: a new plan, so no reuse
            g = build.graph(*[Tick] * N, name="replaced")
            assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        with _collector_off():
            gc.collect()
            g = build.graph(*[Tick] * N, name="replaced")
            assert engine.wait(engine.start(g), WAIT) is Result.TRUE  # disposes of the last one
            garbage = gc.collect()
        assert garbage < N // 10, garbage


def test_a_graph_with_sub_graphs_runs_again_on_its_renewed_nodes() -> None:
    leaf, mid, top = _upper_graphs()
    with engine_with(Upper, graphs=[leaf, mid]) as (engine, rec):
        for _ in range(3):
            outcome = engine.run(top, timeout=WAIT)
            assert outcome.result is Result.TRUE
            assert outcome.outputs == {"out": "HI"}
        assert rec.started("Top") == ["Mid_0", "Emit_0"] * 3
        assert rec.started("Top__Mid__0__Leaf__0") == ["Upper_0"] * 3
        assert engine.running_graphs()["Top__Mid__0"] is GraphState.FINISHED


def test_a_run_whose_action_acquired_a_resource_lends_no_node() -> None:
    """The registrar may still report on the old run's resource through its action, whose
    RunControl is its node: that node must not become a node of the next run."""
    from test_registrar import Req, chain

    rr, _, _ = chain()

    @action
    class Holder(Action):
        def on_run(self) -> bool:
            self.acquire("m2", Req("camera"))
            return True

    g = build.graph(Holder, Tick, name="holder")
    with engine_with(Holder, Tick, registrar=rr) as (engine, _):
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        old = engine._runs["holder"]
        old_nodes = dict(old.nodes)
        assert old_nodes["Holder_0"].acquired
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
        new = engine._runs["holder"]
        assert all(new.nodes[name] is not node for name, node in old_nodes.items())
        assert old_nodes["Holder_0"].run is old
