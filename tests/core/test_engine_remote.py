"""Shared graphs: several engines (actors) run one graph through an ActorLink (in memory)."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto import Action, ActionEngine, GraphState, NodeState, Result, build, load_graph
from temoto.build import action
from temoto.core.catalog import ActionCatalog
from temoto.core.graph import UmrfGraph
from temoto.errors import FleetError, GraphDefinitionError
from temoto.testing.actors import MemoryFleet

ROOT = Path(__file__).resolve().parents[2]
ACTIONS = ROOT / "examples" / "actions" / "conformance"
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
MULTI = UPSTREAM / "actionengine_test_engine_test_multi_actor.graph.json"
WAIT = 10.0


@pytest.fixture
def fleet() -> Iterator[MemoryFleet]:
    f = MemoryFleet()
    yield f
    f.close()


def run_all(engines: list[ActionEngine], graph: UmrfGraph) -> dict[str, Any]:
    """Run ``graph`` on every engine at once; each engine's outcome (or exception)."""
    out: dict[str, Any] = {}

    def one(engine: ActionEngine) -> None:
        try:
            out[engine.actor] = engine.run(graph, timeout=WAIT)
        except Exception as err:
            out[engine.actor] = err

    threads = [threading.Thread(target=one, args=(e,)) for e in engines]
    for t in threads:
        t.start()
    for t in threads:
        t.join(WAIT + 5)
    return out


@pytest.mark.skipif(not MULTI.is_file(), reason=f"upstream data not found at {MULTI}")
def test_upstream_three_actor_graph_ends_on_true_on_every_actor(fleet: MemoryFleet) -> None:
    graph = load_graph(MULTI)
    names = ["Actor A", "Actor B", "Actor C"]
    links = {n: fleet.link(n) for n in names}
    engines = [ActionEngine(n, actions=[ACTIONS], link=links[n]) for n in names]
    try:
        outcomes = run_all(engines, graph)
    finally:
        for e in engines:
            e.shutdown()
    for name in names:
        outcome = outcomes[name]
        assert not isinstance(outcome, BaseException), f"{name}: {outcome!r}"
        assert outcome.result is Result.TRUE, (name, outcome)
    # each actor notified exactly its own action, once
    assert links["Actor A"].notified == [("TaRelayString_0", Result.TRUE)]
    assert links["Actor B"].notified == [("TaAddString_0", Result.TRUE)]
    assert links["Actor C"].notified == [("TaCompareString_0", Result.TRUE)]


# ----------------------------------------------------------------------------- small graphs


@action
class Step(Action):
    """Returns True; ``Step_1`` first sets :attr:`entered` and waits for :attr:`block` when one
    is set."""

    block: threading.Event | None = None
    entered = threading.Event()

    def on_run(self) -> bool:
        if Step.block is not None and self.name == "Step_1":
            Step.entered.set()
            Step.block.wait(WAIT)
        return True


def catalog() -> ActionCatalog:
    return build.catalog(Step)


def two_actor_graph() -> UmrfGraph:
    """Step_0 on A -> Step_1 on B -> Step_2 (no actor: runs on both)."""
    return build.graph(
        build.node(Step, actor="A"), build.node(Step, actor="B"), Step, name="shared"
    )


def test_a_graph_naming_another_actor_needs_a_link() -> None:
    with (
        ActionEngine("A", actions=catalog()) as engine,
        pytest.raises(GraphDefinitionError, match="no fleet link"),
    ):
        engine.start(two_actor_graph())


def test_the_link_must_speak_for_the_engine(fleet: MemoryFleet) -> None:
    with pytest.raises(ValueError, match="speaks for actor 'B'"):
        ActionEngine("A", actions=catalog(), link=fleet.link("B"))


def test_a_missing_actor_fails_the_handshake(fleet: MemoryFleet) -> None:
    with ActionEngine("A", actions=catalog(), link=fleet.link("A"), handshake_timeout=0.2) as e:
        with pytest.raises(FleetError, match="no answer from B"):
            e.start(two_actor_graph())
        assert e.running_graphs() == {}


def test_an_actor_that_does_not_acknowledge_aborts_the_run_everywhere(
    fleet: MemoryFleet,
) -> None:
    engines = [ActionEngine(n, actions=catalog(), link=fleet.link(n)) for n in ("A", "B")]
    fleet.silence("B")
    try:
        started = threading.Thread(target=lambda: engines[1].start(two_actor_graph()))
        started.start()  # B waits for A's Step_0, which never reaches it
        a = engines[0].run(two_actor_graph(), timeout=WAIT)
        started.join(WAIT)
        # B does not wait for A's node: A's abort reaches it, with A's reason
        assert engines[1].wait("shared", WAIT) is Result.ERROR
        b = engines[1].outcome("shared")
    finally:
        for e in engines:
            e.shutdown(timeout=2.0)
    assert a.result is Result.ERROR
    assert a.aborted == "Step_0: no acknowledgement from B"
    assert b.aborted == a.aborted
    assert engines[0].node_states("shared")["Step_0"] is NodeState.FINISHED  # stopped, not ERROR


def test_a_lost_actor_fails_the_graph_on_the_others(fleet: MemoryFleet) -> None:
    Step.block = threading.Event()
    Step.entered.clear()  # B's Step_1 blocks until released
    engines = [ActionEngine(n, actions=catalog(), link=fleet.link(n)) for n in ("A", "B")]
    try:
        # both must shake hands: B starts in a thread (start blocks in the handshake)
        started = threading.Thread(target=lambda: engines[1].start(two_actor_graph()))
        started.start()
        name = engines[0].start(two_actor_graph())
        started.join(WAIT)
        assert Step.entered.wait(WAIT)  # A's Step_0 reached B, whose Step_1 now runs
        fleet.lose("B", "silent for 3 s")
        assert engines[0].wait(name, WAIT) is Result.ERROR
        outcome = engines[0].outcome(name)
        assert outcome.state is GraphState.ERROR
        assert outcome.aborted == "an actor was lost (silent for 3 s)"
        assert any(outcome.aborted in str(e) for e in outcome.errors)
    finally:
        Step.block.set()
        Step.block = None
        for e in engines:
            e.shutdown(timeout=2.0)


def test_stopping_a_shared_graph_stops_waiting_for_remote_actions(fleet: MemoryFleet) -> None:
    Step.block = threading.Event()
    engines = [ActionEngine(n, actions=catalog(), link=fleet.link(n)) for n in ("A", "B")]
    try:
        t = threading.Thread(target=lambda: engines[1].start(two_actor_graph()))
        t.start()
        name = engines[0].start(two_actor_graph())
        t.join(WAIT)
        # A waits for B's Step_1 (remote here); stopping A ends its run at once
        assert engines[0].stop(name, timeout=WAIT) is Result.STOPPED
        # ... and A gave the run up: B is told, and its run fails instead of waiting for A
        Step.block.set()
        assert engines[1].wait(name, WAIT) is Result.ERROR
        outcome = engines[1].outcome(name)
        assert outcome.aborted == "actor 'A' stopped the run"
        assert engines[0].outcome(name).aborted == outcome.aborted
    finally:
        Step.block.set()
        Step.block = None
        for e in engines:
            e.shutdown(timeout=2.0)
