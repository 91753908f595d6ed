"""temoto.core.shared: the engine's side of shared runs, against a recording link."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import pytest

from temoto import Action, ActionEngine, GraphState, NodeState, Result, build
from temoto.build import action
from temoto.core.catalog import ActionCatalog
from temoto.core.graph import UmrfGraph
from temoto.core.shared import SharedRuns
from temoto.errors import FleetError

WAIT = 5.0


@action
class Step(Action):
    """Returns True."""

    def on_run(self) -> bool:
        return True


def catalog() -> ActionCatalog:
    return build.catalog(Step)


def shared_graph() -> UmrfGraph:
    """Step_0 on A -> Step_1 on B."""
    return build.graph(build.node(Step, actor="A"), build.node(Step, actor="B"), name="shared")


class RecordingLink:
    """An ActorLink that records the calls; notify fails when told to."""

    def __init__(self, actor: str, *, fail_notify: bool = False) -> None:
        self._actor = actor
        self.fail_notify = fail_notify
        self.calls: list[tuple[Any, ...]] = []
        self.on_end: Callable[[str, Result], None] | None = None
        self.on_abort: Callable[[str, str], None] | None = None
        self.on_lost: Callable[[str, str], None] | None = None
        self.expected: list[Callable[[Result, Mapping[str, Any]], None]] = []

    @property
    def actor(self) -> str:
        return self._actor

    def handshake(self, graph: str, session: str, actors: Sequence[str], timeout: float) -> str:
        self.calls.append(("handshake", graph, session, tuple(actors), timeout))
        return f"{session}@id"

    def notify(
        self,
        graph: str,
        session: str,
        action: str,
        result: Result,
        outputs: Mapping[str, Any],
        actors: Sequence[str],
        timeout: float,
    ) -> None:
        self.calls.append(("notify", graph, session, action, result, tuple(actors), timeout))
        if self.fail_notify:
            raise FleetError("'B' did not acknowledge")

    def expect(
        self,
        graph: str,
        session: str,
        action: str,
        actor: str,
        on_result: Callable[[Result, Mapping[str, Any]], None],
    ) -> Callable[[], None]:
        self.calls.append(("expect", graph, session, action, actor))
        self.expected.append(on_result)
        return lambda: None

    def watch(
        self,
        actors: Sequence[str],
        on_lost: Callable[[str, str], None],
        *,
        graph: str = "",
        session: str = "",
        on_end: Callable[[str, Result], None] | None = None,
        on_abort: Callable[[str, str], None] | None = None,
    ) -> Callable[[], None]:
        self.calls.append(("watch", tuple(actors), graph, session))
        self.on_lost, self.on_end, self.on_abort = on_lost, on_end, on_abort
        return lambda: None

    def end(
        self,
        graph: str,
        session: str,
        *,
        gave_up: bool = False,
        result: Result | None = None,
        reason: str = "",
    ) -> None:
        self.calls.append(("end", graph, session, gave_up, result, reason))


def started(link: RecordingLink, engine: ActionEngine, name: str) -> None:
    """Start the shared graph and wait until the engine expects the remote node."""
    engine.start(shared_graph(), name=name)
    for _ in range(500):
        if link.expected:
            return
        threading.Event().wait(0.01)
    raise AssertionError("the remote node was never expected")


def test_peers_are_the_other_actors_of_the_graph() -> None:
    with ActionEngine("A", actions=catalog(), link=RecordingLink("A")) as engine:
        plan = engine.plan(shared_graph())
    assert SharedRuns.peers("A", plan) == ("B",)
    assert SharedRuns.peers("C", plan) == ("A", "B")


def test_a_shared_run_shakes_hands_watches_notifies_and_expects() -> None:
    link = RecordingLink("A")
    with ActionEngine(
        "A", actions=catalog(), link=link, handshake_timeout=2.0, settle_timeout=0.1
    ) as engine:
        name = engine.start(shared_graph(), name="run-1")
        # A's Step_0 ran and was notified; B's Step_1 is now awaited through the link
        for _ in range(500):
            if any(c[0] == "expect" for c in link.calls):
                break
            threading.Event().wait(0.01)
        assert engine.stop(name, timeout=WAIT) is Result.STOPPED
    assert link.calls[0] == ("handshake", "shared", "run-1", ("A", "B"), 2.0)
    # every later call names the run by the run id the handshake agreed on
    assert ("watch", ("B",), "shared", "run-1@id") in link.calls
    assert ("notify", "shared", "run-1@id", "Step_0", Result.TRUE, ("B",), 5.0) in link.calls
    assert ("expect", "shared", "run-1@id", "Step_1", "B") in link.calls
    assert link.calls[-1] == ("end", "shared", "run-1@id", True, None, "actor 'A' stopped the run")


def test_a_finished_shared_run_ends_without_giving_up() -> None:
    link = RecordingLink("B")
    with ActionEngine("B", actions=catalog(), link=link) as engine:
        name = engine.start(shared_graph(), name="run-2")
        # B waits for A's Step_0: deliver it as the link would
        expect = next(c for c in link.calls if c[0] == "expect")
        assert expect[3:] == ("Step_0", "A")
        assert engine._shared is not None
        run = engine._runs[name]
        engine._shared._remote_finished(
            run.nodes["Step_0"], run.nodes["Step_0"].gen, Result.TRUE, {}
        )
        assert engine.wait(name, WAIT) is Result.TRUE
    assert link.calls[-1] == ("end", "shared", "run-2@id", False, Result.TRUE, "")


def test_a_peer_that_ended_the_run_ends_it_here_with_its_result() -> None:
    link = RecordingLink("A")
    with ActionEngine("A", actions=catalog(), link=link, settle_timeout=0.1) as engine:
        started(link, engine, "run-3")  # A waits for B's Step_1
        assert link.on_end is not None
        link.on_end("B", Result.FALSE)
        assert engine.wait("run-3", WAIT) is Result.FALSE
        outcome = engine.outcome("run-3")
    assert outcome.state is GraphState.FINISHED
    assert outcome.aborted is None
    assert link.calls[-1] == ("end", "shared", "run-3@id", False, Result.FALSE, "")


def test_a_peer_that_aborted_the_run_aborts_it_here_with_its_reason() -> None:
    link = RecordingLink("A")
    with ActionEngine("A", actions=catalog(), link=link, settle_timeout=0.1) as engine:
        started(link, engine, "run-4")
        assert link.on_abort is not None
        link.on_abort("B", "actor 'C' was lost (left)")
        assert engine.wait("run-4", WAIT) is Result.ERROR
        outcome = engine.outcome("run-4")
    assert outcome.aborted == "actor 'C' was lost (left)"
    # passed on word for word
    assert link.calls[-1] == ("end", "shared", "run-4@id", True, None, "actor 'C' was lost (left)")


def test_a_lost_peer_aborts_the_run() -> None:
    link = RecordingLink("A")
    with ActionEngine("A", actions=catalog(), link=link, settle_timeout=0.1) as engine:
        started(link, engine, "run-5")
        assert link.on_lost is not None
        link.on_lost("B", "not heard for 3 s")
        assert engine.wait("run-5", WAIT) is Result.ERROR
        assert engine.outcome("run-5").aborted == "an actor was lost (not heard for 3 s)"


def test_an_unacknowledged_notification_aborts_the_run_with_the_links_words() -> None:
    link = RecordingLink("A", fail_notify=True)
    with ActionEngine("A", actions=catalog(), link=link, settle_timeout=0.1) as engine:
        engine.start(shared_graph(), name="run-6")
        assert engine.wait("run-6", WAIT) is Result.ERROR
        outcome = engine.outcome("run-6")
        states = engine.node_states("run-6")
    assert outcome.state is GraphState.ERROR
    assert outcome.aborted == "'B' did not acknowledge"
    assert states["Step_0"] is NodeState.FINISHED  # stopped by the abort, not failed
    assert not link.expected  # B's node was never waited for
    assert link.calls[-1] == ("end", "shared", "run-6@id", True, None, "'B' did not acknowledge")


def test_a_peer_result_heard_while_an_abort_settles_is_taken() -> None:
    link = RecordingLink("A")
    with ActionEngine("A", actions=catalog(), link=link, settle_timeout=WAIT) as engine:
        started(link, engine, "run-7")
        assert link.on_lost is not None
        assert link.on_end is not None
        link.on_lost("B", "not heard for 3 s")  # aborted here ...
        with pytest.raises(TimeoutError):
            engine.wait("run-7", 0.05)  # ... but not done while it settles
        link.on_end("C", Result.TRUE)  # ... and C had reached the end: its result stands
        assert engine.wait("run-7", WAIT) is Result.TRUE
        outcome = engine.outcome("run-7")
    assert outcome.state is GraphState.FINISHED
    assert outcome.aborted is None
    assert link.calls[-1] == ("end", "shared", "run-7@id", False, Result.TRUE, "")


def test_concurrent_aborts_settle_on_the_smallest_reason() -> None:
    link = RecordingLink("A")
    with ActionEngine("A", actions=catalog(), link=link, settle_timeout=0.3) as engine:
        started(link, engine, "run-8")
        assert link.on_abort is not None
        link.on_abort("B", "reason 2")
        link.on_abort("C", "reason 3")  # larger: ignored
        link.on_abort("C", "reason 1")  # smaller: taken, and passed on
        assert engine.wait("run-8", WAIT) is Result.ERROR
        assert engine.outcome("run-8").aborted == "reason 1"
    ends = [c for c in link.calls if c[0] == "end"]
    assert ends == [
        ("end", "shared", "run-8@id", True, None, "reason 2"),
        ("end", "shared", "run-8@id", True, None, "reason 1"),
    ]
