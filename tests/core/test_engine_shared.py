"""temoto.core.shared: the engine's side of shared runs, against a recording link."""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from temoto import Action, ActionEngine, Result
from temoto.core.catalog import ActionCatalog
from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.shared import SharedRuns
from temoto.core.umrf import parse_umrf
from temoto.errors import FleetError

WAIT = 5.0
DESCRIPTION = {"name": "Step", "type": "sync", "input_parameters": {}, "output_parameters": {}}


class Step(Action):
    """Returns True."""

    def on_run(self) -> bool:
        return True


def catalog() -> ActionCatalog:
    c = ActionCatalog(use_entry_points=False)
    c.register(Step, parse_umrf(DESCRIPTION))
    return c


def shared_graph() -> UmrfGraph:
    """Step_0 on A -> Step_1 on B."""
    return parse_graph(
        {
            "graph_name": "shared",
            "graph_entry": [{"name": "Step", "instance_id": 0}],
            "graph_exit": [{"name": "Step", "instance_id": 1}],
            "actions": [
                {
                    "name": "Step",
                    "instance_id": 0,
                    "type": "sync",
                    "actor": "A",
                    "children": [{"name": "Step", "instance_id": 1}],
                },
                {
                    "name": "Step",
                    "instance_id": 1,
                    "type": "sync",
                    "actor": "B",
                    "parents": [{"name": "Step", "instance_id": 0, "required": True}],
                },
            ],
        }
    )


class RecordingLink:
    """An ActorLink that records the calls; notify fails when told to."""

    def __init__(self, actor: str, *, fail_notify: bool = False) -> None:
        self._actor = actor
        self.fail_notify = fail_notify
        self.calls: list[tuple[Any, ...]] = []

    @property
    def actor(self) -> str:
        return self._actor

    def handshake(self, graph: str, session: str, actors: Sequence[str], timeout: float) -> None:
        self.calls.append(("handshake", graph, session, tuple(actors), timeout))

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
        return lambda: None

    def watch(
        self,
        actors: Sequence[str],
        on_lost: Callable[[str, str], None],
        *,
        graph: str = "",
        session: str = "",
    ) -> Callable[[], None]:
        self.calls.append(("watch", tuple(actors), graph, session))
        return lambda: None

    def end(self, graph: str, session: str, *, gave_up: bool = False) -> None:
        self.calls.append(("end", graph, session, gave_up))


def test_peers_are_the_other_actors_of_the_graph() -> None:
    with ActionEngine("A", actions=catalog(), link=RecordingLink("A")) as engine:
        plan = engine.plan(shared_graph())
    assert SharedRuns.peers("A", plan) == ("B",)
    assert SharedRuns.peers("C", plan) == ("A", "B")


def test_a_shared_run_shakes_hands_watches_notifies_and_expects() -> None:
    link = RecordingLink("A")
    with ActionEngine("A", actions=catalog(), link=link, handshake_timeout=2.0) as engine:
        name = engine.start(shared_graph(), name="run-1")
        # A's Step_0 ran and was notified; B's Step_1 is now awaited through the link
        for _ in range(500):
            if any(c[0] == "expect" for c in link.calls):
                break
            threading.Event().wait(0.01)
        assert engine.stop(name, timeout=WAIT) is Result.STOPPED
    assert link.calls[0] == ("handshake", "shared", "run-1", ("A", "B"), 2.0)
    assert ("watch", ("B",), "shared", "run-1") in link.calls
    assert ("notify", "shared", "run-1", "Step_0", Result.TRUE, ("B",), 5.0) in link.calls
    assert ("expect", "shared", "run-1", "Step_1", "B") in link.calls
    assert link.calls[-1] == ("end", "shared", "run-1", True)


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
    assert link.calls[-1] == ("end", "shared", "run-2", False)
