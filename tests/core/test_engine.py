"""Action Engine features beyond upstream's own tests.

Graphs are built in the tests with :mod:`temoto.build` (compositions, or ``GraphBuilder`` node by
node); actions are tiny classes declared with ``@action`` and registered in code. Real time is
used unless a test says otherwise; waits are bounded by generous timeouts (correctness, not
performance).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import pytest

from temoto import (
    Action,
    ActionEngine,
    GraphIndex,
    GraphState,
    Instrument,
    Result,
    ScaledClock,
    build,
)
from temoto.build import Param, action, description_of
from temoto.core.graph import UmrfGraph
from temoto.core.instrument import RecordingInstrument
from temoto.errors import ActionError, GraphInputError, StateError
from temoto.testing import Outcome, Run, Script

WAIT = 10.0  # real seconds a graph may take before a test gives up


# ================================================================ actions


@action
class Noop(Action):
    def on_run(self) -> bool:
        return True


@action(inputs={"value": str}, outputs={"out": str})
class Emit(Action):
    """out = value."""

    def on_run(self) -> bool:
        self.outputs["out"] = self.inputs.get_string("value")
        return True


@action(inputs={"result": str})
class Ret(Action):
    """Returns what ``result`` says: "true", "false", anything else raises."""

    def on_run(self) -> bool:
        result = self.inputs.get_string("result")
        if result == "true":
            return True
        if result == "false":
            return False
        raise RuntimeError(f"asked to fail ({result})")


@action
class Fail(Action):
    def on_run(self) -> bool:
        raise RuntimeError("boom")


@action
class Blocker(Action):
    """Runs until stopped; returns True."""

    def on_run(self) -> bool:
        self.wait_until_stopped()
        return True


@action(inputs={"seconds": float})
class Nap(Action):
    """Pause-aware sleep of ``seconds`` clock seconds."""

    def on_run(self) -> bool:
        self.sleep(self.inputs.get_number("seconds"))
        return True


COMMON: tuple[type[Action], ...] = (Noop, Emit, Ret, Fail, Blocker, Nap)


def answering(
    name: str,
    target: type[Action],
    response: str,
    *exit_conditions: str,
    trigger: type[Action] = Nap,
    **trigger_values: Any,
) -> UmrfGraph:
    """``target`` and ``trigger`` start together; ``trigger``'s on_true makes ``target``
    ``response`` (restart, stop, pause); ``target`` is the exit."""
    b = build.GraphBuilder(name)
    node, cause = b.add(target), b.add(trigger, trigger_values)
    b.link(cause, node, f"on_true -> {response}", required=False)
    b.entry(node)
    b.entry(cause)
    b.exit(node, *exit_conditions)
    return b.build()


def halting(name: str) -> UmrfGraph:
    """One Noop whose exit ignores its on_true: the graph halts."""
    b = build.GraphBuilder(name)
    only = b.add(Noop)
    b.entry(only)
    b.exit(only, "on_true -> ignore")
    return b.build()


@contextmanager
def engine_with(
    *classes: type[Action], graphs: Sequence[UmrfGraph] = (), **kwargs: Any
) -> Iterator[tuple[ActionEngine, RecordingInstrument]]:
    """An engine knowing COMMON + ``classes`` (and in-memory ``graphs``), recording events."""
    rec = RecordingInstrument()
    index = GraphIndex()
    for g in graphs:
        index.add(g)
    kwargs.setdefault("stop_timeout", 2.0)
    instruments = [rec, *kwargs.pop("instruments", ())]
    with ActionEngine(
        "me",
        actions=build.catalog(*COMMON, *classes),
        graphs=index,
        instruments=instruments,
        **kwargs,
    ) as engine:
        yield engine, rec


def node_state(engine: ActionEngine, run: str, node: str) -> str:
    for a in engine.graph_json(run)["actions"]:
        if f"{a['name']}_{a['instance_id']}" == node:
            return a["state"]
    raise AssertionError(f"no node {node}")


def eventually(predicate: Any, timeout: float = WAIT, what: str = "condition") -> None:
    # pytest.fail, not AssertionError: a strict xfail(raises=AssertionError) test must not
    # "fail as expected" because its set-up timed out
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.002)


def require(condition: bool, what: str) -> None:
    """A precondition of a test (reported as a plain failure, never as an expected one)."""
    if not condition:
        pytest.fail(f"precondition failed: {what}")


# ================ structure: sequence, concurrency, join


def test_sequence_runs_in_order_and_passes_data() -> None:
    g = build.graph(
        build.node(Emit, value="x", remap={"out": "value"}),
        build.node(Emit, remap={"out": "value"}),
        Emit,
        name="seq",
    )
    with engine_with() as (engine, rec):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert outcome.state is GraphState.FINISHED
        assert outcome.outputs == {"out": "x"}
        assert rec.started("seq") == ["Emit_0", "Emit_1", "Emit_2"]


def test_concurrent_branches_run_at_the_same_time_and_join_once() -> None:
    barrier = threading.Barrier(3, timeout=5)
    joined: list[int] = []

    @action
    class Meet(Action):
        def on_run(self) -> bool:
            barrier.wait()  # raises BrokenBarrierError unless all three run concurrently
            return True

    @action
    class Join(Action):
        def on_run(self) -> bool:
            joined.append(1)
            return True

    branches = ["Meet_0", "Meet_1", "Meet_2"]
    g = build.graph(Noop, build.parallel(Meet, Meet, Meet), Join, name="fan")
    with engine_with(Meet, Join) as (engine, rec):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        order = rec.started("fan")
        assert order[0] == "Noop_0"
        assert sorted(order[1:4]) == branches
        assert order[4:] == ["Join_0"]
        assert joined == [1]


def test_non_required_parents_start_child_on_first_parent() -> None:
    b = build.GraphBuilder("any")
    first, nap, last = b.add(Noop), b.add(Nap, seconds=0.3), b.add(Noop, instance=2)
    for parent in (first, nap):
        b.entry(parent)
        b.link(parent, last, required=False)
    b.exit(last)
    g = b.build()
    with engine_with() as (engine, rec):
        t0 = time.monotonic()
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert time.monotonic() - t0 < 0.25  # did not wait for Nap_0
        assert rec.started("any").count("Noop_2") == 1


# ================================================================ default conditions


def test_error_propagates_to_graph_result_through_bypass() -> None:
    g = build.graph(Fail, Noop, Noop, name="err")
    with engine_with() as (engine, rec):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.ERROR
        assert rec.started("err") == ["Fail_0"]  # descendants were bypassed, not run
        assert len(outcome.errors) == 1
        error = outcome.errors[0]
        assert isinstance(error, ActionError)
        assert isinstance(error.__cause__, RuntimeError)
        assert "boom" in str(error)
        assert "Fail_0" in str(error)
        assert [node for _, node, _ in rec.failures] == ["Fail_0"]
        assert node_state(engine, "err", "Fail_0") == "ERROR"


def test_on_false_runs_children_by_default() -> None:
    g = build.graph(build.node(Ret, result="false"), Noop, name="false")
    with engine_with() as (engine, rec):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert rec.started("false") == ["Ret_0", "Noop_0"]


def test_on_false_reaches_graph_exit_as_graph_result() -> None:
    g = build.graph(build.node(Ret, result="false"), name="f1")
    with engine_with() as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.FALSE


def test_on_false_bypass_branching() -> None:
    g = build.graph(
        build.branch(build.node(Ret, result="false"), on_true=Noop, on_false=Noop),
        Noop,
        name="branch",
    )
    with engine_with() as (engine, rec):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert rec.started("branch") == ["Ret_0", "Noop_1", "Noop_2"]


# ================================================================ responses: restart, pause, stop


def test_restart_response_restarts_a_running_child_on_the_same_instance() -> None:
    runs: list[tuple[int, str]] = []

    @action
    class Worker(Action):
        def __init__(self) -> None:
            super().__init__()
            self.count = 0

        def on_run(self) -> bool:
            self.count += 1
            if self.count == 1:
                stopped = self.wait_until_stopped(5.0)
                runs.append((id(self), "stopped" if stopped else "timeout"))
                return True
            runs.append((id(self), "second"))
            return True

    # Worker_0 starts at once; Nap_0 finishes a moment later and restarts it.
    # An on_stopped reaching graph_exit would end the graph with on_stopped.
    g = answering("restart", Worker, "restart", "on_stopped -> run", seconds=0.1)
    with engine_with(Worker) as (engine, rec):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert [what for _, what in runs] == ["stopped", "second"]
        assert runs[0][0] == runs[1][0]  # same instance
        assert rec.started("restart").count("Worker_0") == 2


def test_pause_response_pauses_a_running_child() -> None:
    # Nap_0 runs 0.3 s; Noop_1 finishes after 0.05 s and pauses it (on_true -> pause)
    b = build.GraphBuilder("pausing")
    long, short = b.add(Nap, seconds=0.3), b.add(Nap, seconds=0.05)
    pauser = b.add(Noop, instance=1)
    b.link(short, pauser)
    b.link(pauser, long, "on_true -> pause", required=False)
    b.entry(long)
    b.entry(short)
    b.exit(long)
    g = b.build()
    with engine_with() as (engine, _):
        run = engine.start(g)
        eventually(lambda: node_state(engine, run, "Nap_0") == "PAUSED", 5, "Nap_0 paused")
        time.sleep(0.5)  # longer than Nap_0's 0.3 s: it is held by the pause
        assert node_state(engine, run, "Nap_0") == "PAUSED"
        assert engine.outcome(run).state is GraphState.RUNNING
        engine.pause(run)
        engine.resume(run)
        assert engine.wait(run, timeout=WAIT) is Result.TRUE


def test_stop_response_stops_a_running_child_and_calls_on_stop() -> None:
    hooks: list[str] = []

    @action
    class Stoppable(Action):
        def on_run(self) -> bool:
            stopped = self.wait_until_stopped(5.0)
            hooks.append(f"run returned stopped={stopped}")
            return True

        def on_stop(self) -> None:
            hooks.append("on_stop")

    g = answering("stopping", Stoppable, "stop", "on_stopped -> run", seconds=0.05)
    with engine_with(Stoppable) as (engine, rec):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.STOPPED
        assert "run returned stopped=True" in hooks
        # on_stop runs on a worker, concurrently with on_run: it may land a moment later
        eventually(lambda: "on_stop" in hooks, 5, "on_stop")
        states = [new.value for gname, node, _, new in rec.transitions if node == "Stoppable_0"]
        assert states == ["RUNNING", "STOPPING", "FINISHED"]


def test_stopped_result_is_ignored_by_default() -> None:
    # same as above, default exit conditions: on_stopped -> ignore; Nap_0 has no other child →
    # nothing runs any more → halted
    g = answering("stop_ignored", Blocker, "stop", seconds=0.05)
    with engine_with() as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.HALTED


# ================================================================ pause / resume of the graph


def test_non_pause_aware_action_finishing_while_paused_is_held_until_resume() -> None:
    started = threading.Event()
    returned = threading.Event()

    @action
    class Busy(Action):
        def on_run(self) -> bool:
            started.set()
            threading.Event().wait(0.2)  # ignores pause
            returned.set()
            return True

    g = build.graph(Busy, Noop, name="held")
    with engine_with(Busy) as (engine, rec):
        run = engine.start(g)
        assert started.wait(5)
        t0 = time.monotonic()
        engine.pause(run)
        assert time.monotonic() - t0 < 0.1  # pause does not wait for the action
        # PAUSE_REQUESTED until Busy_0's on_pause has returned (on a worker)
        assert engine.outcome(run).state in (GraphState.PAUSE_REQUESTED, GraphState.PAUSED)
        eventually(lambda: engine.outcome(run).state is GraphState.PAUSED, 5, "paused run")
        assert returned.wait(5)
        time.sleep(0.1)
        assert rec.started(run) == ["Busy_0"]  # the child did not start
        assert engine.outcome(run).state is GraphState.PAUSED
        assert engine.outcome(run).result is None
        engine.resume(run)
        assert engine.wait(run, timeout=WAIT) is Result.TRUE
        assert rec.started(run) == ["Busy_0", "Noop_0"]


def test_pause_blocks_sleep_and_resume_continues() -> None:
    g = build.graph(build.node(Nap, seconds=0.2), name="napping")
    with engine_with() as (engine, _):
        t0 = time.monotonic()
        run = engine.start(g)
        time.sleep(0.05)
        engine.pause(run)
        eventually(lambda: node_state(engine, run, "Nap_0") == "PAUSED", 5, "paused node")
        time.sleep(0.3)
        assert engine.outcome(run).state is GraphState.PAUSED
        assert engine.outcome(run).result is None  # Nap_0's 0.2 s passed, but it is held
        engine.resume(run)
        assert engine.wait(run, timeout=WAIT) is Result.TRUE
        assert time.monotonic() - t0 >= 0.35


def test_pause_and_resume_in_wrong_states_raise() -> None:
    g = build.graph(Noop, name="once")
    with engine_with() as (engine, _):
        run = engine.start(g)
        engine.wait(run, timeout=WAIT)
        with pytest.raises(StateError):
            engine.pause(run)
        with pytest.raises(StateError):
            engine.resume(run)


# ================================================================ stop timeout


def test_action_ignoring_stop_goes_to_error_after_stop_timeout() -> None:
    started = threading.Event()
    done = threading.Event()

    @action
    class Stubborn(Action):
        def on_run(self) -> bool:
            started.set()
            for _ in range(20):  # ~0.6 s, never looks at stop_requested
                threading.Event().wait(0.03)
            done.set()
            return True

    g = build.graph(Stubborn, name="stubborn")
    with engine_with(Stubborn, stop_timeout=0.15) as (engine, _):
        run = engine.start(g)
        assert started.wait(5)
        t0 = time.monotonic()
        result = engine.stop(run, timeout=WAIT)
        elapsed = time.monotonic() - t0
        assert result is Result.ERROR
        assert 0.14 <= elapsed < 0.5
        assert not done.is_set()  # the engine gave up before the action returned
        assert engine.outcome(run).state is GraphState.ERROR
        assert node_state(engine, run, "Stubborn_0") == "ERROR"
        errors = engine.outcome(run).errors
        assert len(errors) == 1
        assert "did not stop" in str(errors[0])
        assert done.wait(5)  # it ends eventually; its late result is ignored
        time.sleep(0.05)
        assert engine.outcome(run).result is Result.ERROR
        assert node_state(engine, run, "Stubborn_0") == "ERROR"


def test_stop_timeout_is_in_clock_seconds() -> None:
    started = threading.Event()

    @action
    class Stubborn2(Action):
        def on_run(self) -> bool:
            started.set()
            for _ in range(10):
                threading.Event().wait(0.03)
            return True

    g = build.graph(Stubborn2, name="stubborn2")
    # 1 clock-second at factor 10 = 0.1 s real
    with engine_with(Stubborn2, stop_timeout=1.0, clock=ScaledClock(10)) as (engine, _):
        run = engine.start(g)
        assert started.wait(5)
        t0 = time.monotonic()
        assert engine.stop(run, timeout=WAIT) is Result.ERROR
        assert time.monotonic() - t0 < 0.25


# ================================================================ cycles and parameter lifetime


def test_counter_loop_parameter_lifetime() -> None:
    script = Script()
    inc_action = script.action(
        "Inc",
        inputs={"count": float, "step": float, "extra": Param(str, required=False)},
        outputs={"count": float},
        default=Outcome(outputs=lambda values: {"count": values["count"] + values["step"]}),
    )

    @action(inputs={"count": float, "limit": float}, outputs={"count": float})
    class AtLeast(Action):
        def on_run(self) -> bool:
            count = self.inputs.get_number("count")
            self.outputs["count"] = count
            return count >= self.inputs.get_number("limit")

    b = build.GraphBuilder("loop")
    inc, check = b.add(inc_action, step=1), b.add(AtLeast, limit=3)
    b.link(inc, check)
    b.link(check, inc, "on_true -> ignore", required=False)
    b.entry(inc)
    b.exit(check, "on_false -> ignore")
    g = b.build()
    with engine_with(inc_action, AtLeast) as (engine, rec):
        run = engine.start(g, {"count": 0, "extra": "first run only"})
        assert engine.wait(run, timeout=WAIT) is Result.TRUE
        assert rec.started(run) == ["Inc_0", "AtLeast_0"] * 3
        assert engine.outcome(run).outputs == {"count": 3.0}
        # received data is consumed by each run; literals stay
        assert [run.inputs for run in script.runs] == [
            {"count": 0.0, "step": 1.0, "extra": "first run only"},
            {"count": 1.0, "step": 1.0},
            {"count": 2.0, "step": 1.0},
        ]
        # after the run only literals remain in the snapshot
        inputs = next(a for a in engine.graph_json(run)["actions"] if a["name"] == "Inc")[
            "input_parameters"
        ]
        assert inputs["step"]["pvf_value"] == 1.0
        assert "pvf_value" not in inputs["count"]


def test_parent_value_replacing_a_literal_is_consumed() -> None:
    seen: list[dict[str, Any]] = []

    @action(inputs={"value": str}, outputs={"value": str})
    class Show(Action):
        def on_run(self) -> bool:
            seen.append(dict(self.inputs))
            return len(seen) >= 3

    # Show_0 (literal "lit") <-> Emit_0 (sends "sent"): the loop runs Show_0 three times
    b = build.GraphBuilder("lit")
    show, emit = b.add(Show, value="lit"), b.add(Emit, value="sent")
    b.link(show, emit, "on_true -> ignore")
    b.link(emit, show, required=False, remap={"out": "value"})
    b.entry(show)
    b.exit(show, "on_false -> ignore")
    g = b.build()
    with engine_with(Show) as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert seen == [{"value": "lit"}, {"value": "sent"}, {"value": "sent"}]


# ================ data flow: allowed values, updatable, remap


@pytest.mark.parametrize("state", ["charge", "navigate", "pickup"])
def test_allowed_values_route_to_exactly_one_child(state: str) -> None:
    script = Script()
    handle = script.action("Handle", inputs={"state": str})

    @action(inputs={"choice": str}, outputs={"state": str})
    class Dispatch(Action):
        def on_run(self) -> bool:
            self.outputs["state"] = self.inputs.get_string("choice")
            return True

    targets = {"charge": "Handle_0", "navigate": "Handle_1", "pickup": "Handle_2"}
    b = build.GraphBuilder("route")
    dispatch = b.add(Dispatch, choice=state)
    b.entry(dispatch)
    for value in targets:
        handler = b.add(handle, state=Param(str, allowed=[value]))
        b.link(dispatch, handler)
        b.exit(handler, required=False)
    g = b.build()
    with engine_with(Dispatch, handle) as (engine, rec):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert script.runs == [Run(targets[state], "route", {"state": state})]
        assert rec.started("route") == ["Dispatch_0", targets[state]]


def test_value_outside_allowed_values_halts_instead_of_hanging() -> None:
    g = build.graph(
        build.node(Emit, value="z", remap={"out": "value"}),
        build.node(Emit, value=Param(str, allowed=["a", "b"])),
        name="nowhere",
    )
    with engine_with() as (engine, rec):
        assert engine.run(g, timeout=WAIT).result is Result.HALTED
        assert rec.started("nowhere") == ["Emit_0"]


@pytest.mark.parametrize(("updatable", "expected"), [(False, "literal"), (True, "from parent")])
def test_updatable_flag_decides_whether_parent_overwrites_literal(
    updatable: bool, expected: str
) -> None:
    # pvf_updatable is a property of the action's description (the graph supplies literals and
    # allowed values; docs/design.md §4.1)
    @action(inputs={"value": Param(str, updatable=updatable)}, outputs={"out": str})
    class Keep(Action):
        def on_run(self) -> bool:
            self.outputs["out"] = self.inputs.get_string("value")
            return True

    g = build.graph(
        build.node(Emit, value="from parent", remap={"out": "value"}),
        build.node(Keep, value="literal"),
        name="upd",
    )
    with engine_with(Keep) as (engine, _):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert outcome.outputs == {"out": expected}


def test_remap_renames_parent_output() -> None:
    g = build.graph(build.node(Emit, value="hello", remap={"out": "result"}), Ret, name="remap")
    with engine_with() as (engine, _):
        # "hello" reaches Ret_0.result → it raises "asked to fail (hello)"
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.ERROR
        assert "hello" in str(outcome.errors[0])


def test_same_name_output_flows_without_remap() -> None:
    script = Script()
    take = script.action("Take", inputs={"out": str})
    g = build.graph(build.node(Emit, value="v"), take, name="same")
    with engine_with(take) as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert script.inputs("Take_0") == {"out": "v"}


# ================================================================ spontaneous actions


def test_spontaneous_source_reruns_and_preempts_downstream() -> None:
    work: list[tuple[float, str]] = []
    source_runs: list[int] = []

    @action(outputs={"n": float}, type="spontaneous")
    class Events(Action):
        def __init__(self) -> None:
            super().__init__()
            self.k = 0

        def on_run(self) -> bool:
            source_runs.append(id(self))
            if self.k >= 3:
                self.wait_until_stopped()
                return True
            self.sleep(0.05)
            self.k += 1
            self.outputs["n"] = self.k
            return True

    @action(inputs={"n": float})
    class Work(Action):
        def on_run(self) -> bool:
            k = self.inputs.get_number("n")
            if k < 3:
                stopped = self.wait_until_stopped(5.0)
                work.append((k, "preempted" if stopped else "timeout"))
                return True
            work.append((k, "done"))
            return True

    g = build.graph(Events, Work, name="spont")
    with engine_with(Events, Work) as (engine, rec):
        t0 = time.monotonic()
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert time.monotonic() - t0 < 2.0  # pre-empted, not timed out
        assert work == [(1.0, "preempted"), (2.0, "preempted"), (3.0, "done")]
        order = rec.started("spont")
        assert order[:6] == ["Events_0", "Work_0"] * 3
        assert len(set(source_runs)) == 1  # same instance every run


# ================================================================ hierarchy


def _upper_graphs() -> tuple[UmrfGraph, UmrfGraph, UmrfGraph]:
    leaf = build.graph(Upper, name="Leaf")
    mid = build.graph(leaf, name="Mid")
    top = build.graph(build.node(mid, text="hi", remap={"text_out": "value"}), Emit, name="Top")
    return leaf, mid, top


@action(inputs={"text": str}, outputs={"text_out": str})
class Upper(Action):
    def on_run(self) -> bool:
        self.outputs["text_out"] = self.inputs.get_string("text").upper()
        return True


def test_nested_subgraphs_two_levels_deep() -> None:
    leaf, mid, top = _upper_graphs()
    with engine_with(Upper, graphs=[leaf, mid]) as (engine, rec):
        outcome = engine.run(top, timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert outcome.outputs == {"out": "HI"}
        runs = engine.running_graphs()
        assert runs["Top__Mid__0"] is GraphState.FINISHED
        assert runs["Top__Mid__0__Leaf__0"] is GraphState.FINISHED
        assert rec.started("Top") == ["Mid_0", "Emit_0"]
        assert rec.started("Top__Mid__0") == ["Leaf_0"]
        assert rec.started("Top__Mid__0__Leaf__0") == ["Upper_0"]


def test_subgraph_error_propagates_to_parent_graph() -> None:
    leaf = build.graph(Fail, name="Boom")
    top = build.graph(leaf, Noop, name="TopB")
    with engine_with(graphs=[leaf]) as (engine, rec):
        outcome = engine.run(top, timeout=WAIT)
        assert outcome.result is Result.ERROR
        assert rec.started("TopB") == ["Boom_0"]
        assert any("boom" in str(e) for e in outcome.errors)


def test_subgraph_is_paused_with_its_parent() -> None:
    inner = build.graph(build.node(Nap, seconds=0.2), name="Sleepy")
    top = build.graph(inner, name="TopP")
    with engine_with(graphs=[inner]) as (engine, _):
        t0 = time.monotonic()
        run = engine.start(top)
        sub = "TopP__Sleepy__0"
        eventually(lambda: sub in engine.running_graphs(), 5, "sub-graph run")
        time.sleep(0.05)
        engine.pause(run)
        eventually(lambda: engine.running_graphs()[sub] is GraphState.PAUSED, 5, "sub-graph paused")
        eventually(lambda: node_state(engine, sub, "Nap_0") == "PAUSED", 5, "sub-graph node paused")
        time.sleep(0.3)
        assert engine.running_graphs()[sub] is GraphState.PAUSED
        assert engine.outcome(run).result is None
        engine.resume(run)
        assert engine.wait(run, timeout=WAIT) is Result.TRUE
        assert engine.running_graphs()[sub] is GraphState.FINISHED
        assert time.monotonic() - t0 >= 0.35  # Nap_0 (0.2 s) did not end during the pause


def test_subgraph_is_stopped_with_its_parent() -> None:
    inner = build.graph(Blocker, name="Forever")
    top = build.graph(inner, name="TopS")
    with engine_with(graphs=[inner]) as (engine, _):
        run = engine.start(top)
        sub = "TopS__Forever__0"
        eventually(lambda: sub in engine.running_graphs(), 5, "sub-graph run")
        eventually(lambda: node_state(engine, sub, "Blocker_0") == "RUNNING", 5, "blocker running")
        assert engine.stop(run, timeout=WAIT) is Result.STOPPED
        assert engine.running_graphs()[sub] is GraphState.STOPPED


# ================================================================ modify


def test_modify_refuses_to_delete_a_running_node() -> None:
    g = build.graph(Blocker, Noop, name="mod")
    smaller = build.graph(Noop, name="mod")
    with engine_with() as (engine, _):
        run = engine.start(g)
        eventually(lambda: node_state(engine, run, "Blocker_0") == "RUNNING", 5, "blocker running")
        before = engine.graph_json(run)
        with pytest.raises(StateError, match="Blocker_0"):
            engine.modify(run, smaller)
        assert engine.graph_json(run) == before
        assert engine.outcome(run).state is GraphState.RUNNING
        assert engine.stop(run, timeout=WAIT) is Result.STOPPED


def test_modify_of_ended_graph_is_refused() -> None:
    g = build.graph(Noop, name="ended")
    with engine_with() as (engine, _):
        engine.run(g, timeout=WAIT)
        with pytest.raises(StateError):
            engine.modify("ended", g)


def test_modify_unknown_continue_from_raises_key_error() -> None:
    g = halting("halts")
    with engine_with() as (engine, _):
        run = engine.start(g)
        assert engine.wait(run, timeout=WAIT) is Result.HALTED
        with pytest.raises(KeyError):
            engine.modify(run, g, continue_from="Nope_0")
        assert engine.outcome(run).state is GraphState.HALTED


# ================================================================ start / restart / inputs


def test_starting_an_active_graph_raises_state_error() -> None:
    g = build.graph(Blocker, name="busy")
    with engine_with() as (engine, _):
        run = engine.start(g)
        with pytest.raises(StateError, match="already active"):
            engine.start(g)
        assert engine.stop(run, timeout=WAIT) is Result.STOPPED


def test_run_under_another_name_is_independent() -> None:
    g = build.graph(Blocker, name="twice")
    with engine_with() as (engine, _):
        a = engine.start(g)
        b = engine.start(g, name="twice-b")
        assert (a, b) == ("twice", "twice-b")
        assert engine.stop(b, timeout=WAIT) is Result.STOPPED
        assert engine.outcome(a).state is GraphState.RUNNING
        assert engine.stop(a, timeout=WAIT) is Result.STOPPED


def test_restarting_a_finished_graph_gives_fresh_instances() -> None:
    instances: list[tuple[Action, int]] = []  # the objects, not id()s: a freed one's is reused

    @action
    class Counted(Action):
        def __init__(self) -> None:
            super().__init__()
            self.runs = 0

        def on_run(self) -> bool:
            self.runs += 1
            instances.append((self, self.runs))
            return True

    g = build.graph(Counted, name="again")
    with engine_with(Counted) as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert [runs for _, runs in instances] == [1, 1]
        assert instances[0][0] is not instances[1][0]


def _input_graph() -> UmrfGraph:
    return build.graph(Emit, name="inputs")


def test_graph_input_is_passed() -> None:
    with engine_with() as (engine, _):
        run = engine.start(_input_graph(), {"value": "given"})
        assert engine.wait(run, timeout=WAIT) is Result.TRUE
        assert engine.outcome(run).outputs == {"out": "given"}


def test_graph_input_of_wrong_type_is_refused() -> None:
    with engine_with() as (engine, _):
        with pytest.raises(GraphInputError, match="value"):
            engine.start(_input_graph(), {"value": 5})
        assert "inputs" not in engine.running_graphs()


def test_unknown_graph_input_is_refused() -> None:
    with engine_with() as (engine, _), pytest.raises(GraphInputError, match="bogus"):
        engine.start(_input_graph(), {"value": "ok", "bogus": 1})


def test_missing_graph_input_is_refused() -> None:
    with engine_with() as (engine, _), pytest.raises(GraphInputError, match="value"):
        engine.start(_input_graph())


# ================================================================ action failures


@pytest.mark.parametrize("returned", [None, 1, "yes"])
def test_on_run_returning_non_bool_is_an_error(returned: Any) -> None:
    @action
    class Sloppy(Action):
        def on_run(self) -> bool:
            return returned  # type: ignore[no-any-return]

    g = build.graph(Sloppy, name="sloppy")
    with engine_with(Sloppy) as (engine, _):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.ERROR
        chain = []
        err: BaseException | None = outcome.errors[0]
        while err is not None:
            chain.append(err)
            err = err.__cause__
        assert any(isinstance(e, TypeError) for e in chain)


def test_raising_on_init_is_an_error() -> None:
    ran: list[int] = []

    @action
    class BadInit(Action):
        def on_init(self) -> None:
            raise ValueError("no hardware")

        def on_run(self) -> bool:
            ran.append(1)
            return True

    g = build.graph(BadInit, Noop, name="badinit")
    with engine_with(BadInit) as (engine, rec):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.ERROR
        assert ran == []
        assert isinstance(outcome.errors[0].__cause__, ValueError)
        assert "no hardware" in str(outcome.errors[0])
        assert rec.started("badinit") == ["BadInit_0"]


def test_waiting_for_a_parent_that_never_runs_halts_quickly() -> None:
    # Noop_2 needs both Noop_0 and Noop_1; Noop_1 ignores Noop_0's on_true so it never runs.
    # Upstream would leave the graph RUNNING forever.
    b = build.GraphBuilder("stuck")
    first, second, last = b.add(Noop), b.add(Noop), b.add(Noop)
    b.link(first, second, "on_true -> ignore")
    b.link(first, last)
    b.link(second, last)
    b.entry(first)
    b.exit(last)
    g = b.build()
    with engine_with() as (engine, rec):
        t0 = time.monotonic()
        run = engine.start(g)
        assert engine.wait(run, timeout=WAIT) is Result.HALTED
        assert time.monotonic() - t0 < 0.5
        assert rec.started(run) == ["Noop_0"]
        assert engine.outcome(run).state is GraphState.HALTED


def test_halted_graph_can_be_resumed_from_a_node() -> None:
    g = halting("resumable")
    with engine_with() as (engine, rec):
        run = engine.start(g)
        assert engine.wait(run, timeout=WAIT) is Result.HALTED
        engine.resume(run, continue_from="Noop_0")
        assert engine.wait(run, timeout=WAIT) is Result.HALTED
        assert rec.started(run) == ["Noop_0", "Noop_0"]


# ================================================================ feedback and instruments


def test_feedback_snapshots_show_changing_node_states() -> None:
    g = build.graph(Noop, Noop, name="fb")
    with engine_with(feedback_size=100) as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        snapshots = engine.read_feedback()
        assert snapshots
        assert all(snap["graph_name"] == "fb" for snap in snapshots)

        def states(node: str) -> list[str]:
            out = []
            for snap in snapshots:
                for a in snap["actions"]:
                    if f"{a['name']}_{a['instance_id']}" == node and (
                        not out or out[-1] != a["state"]
                    ):
                        out.append(a["state"])
            return out

        assert states("Noop_0") == ["RUNNING", "FINISHED"]
        assert states("Noop_1") == ["UNINITIALIZED", "RUNNING", "FINISHED"]
        assert engine.read_feedback() == []  # read clears


def test_feedback_is_a_ring_buffer() -> None:
    g = build.graph(*[Noop] * 5, name="ring")
    with engine_with(feedback_size=3) as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        snapshots = engine.read_feedback()
        assert len(snapshots) == 3
        last = {f"{a['name']}_{a['instance_id']}": a["state"] for a in snapshots[-1]["actions"]}
        assert last["Noop_4"] == "FINISHED"


def test_feedback_off_by_default() -> None:
    g = build.graph(Noop, name="nofb")
    with engine_with() as (engine, _):
        engine.run(g, timeout=WAIT)
        assert engine.read_feedback() == []


def test_raising_instrument_is_removed_and_graph_finishes() -> None:
    class Broken(Instrument):
        calls = 0

        def node_transition(self, *args: Any) -> None:
            Broken.calls += 1
            raise RuntimeError("instrument bug")

    class BrokenStart(Instrument):
        calls = 0

        def graph_started(self, *args: Any) -> None:
            BrokenStart.calls += 1
            raise RuntimeError("instrument bug")

    g = build.graph(Noop, Noop, name="instr")
    with engine_with(instruments=[Broken(), BrokenStart()]) as (engine, rec):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert Broken.calls == 1
        assert BrokenStart.calls == 1
        assert rec.started() == ["Noop_0", "Noop_1", "Noop_0", "Noop_1"]  # others keep working


# ================================================================ threads


def test_fan_out_of_200_respects_max_workers() -> None:
    peak = [0]
    lock = threading.Lock()

    @action
    class Tick(Action):
        def on_run(self) -> bool:
            workers = len([t for t in threading.enumerate() if t.name.startswith("temoto-worker")])
            with lock:
                peak[0] = max(peak[0], workers)
            threading.Event().wait(0.001)
            return True

    width = 200
    leaves = [f"Tick_{i}" for i in range(width)]
    g = build.graph(Noop, build.parallel(*[Tick] * width), name="wide")
    with engine_with(Tick, max_workers=4) as (engine, rec):
        assert engine.run(g, timeout=30).result is Result.TRUE
        assert sorted(rec.started("wide")) == sorted(["Noop_0", *leaves])
        assert 1 <= peak[0] <= 4


def test_shutdown_stops_an_infinite_graph_and_joins_threads() -> None:
    b = build.GraphBuilder("forever")
    one, two = b.add(Nap, seconds=0.01), b.add(Nap, seconds=0.01)
    b.link(one, two)
    b.link(two, one, required=False)
    b.entry(one)
    b.exit(two, "on_true -> ignore", "on_false -> ignore")
    loop = b.build()
    before = set(threading.enumerate())
    with engine_with() as (engine, rec):
        run = engine.start(loop)
        eventually(lambda: len(rec.started(run)) >= 6, 5, "a few turns of the loop")
        engine.shutdown()
        assert engine.outcome(run).state is GraphState.STOPPED
        assert engine.outcome(run).result is Result.STOPPED
        alive = [
            t.name for t in set(threading.enumerate()) - before if t.name.startswith("temoto-")
        ]
        assert alive == []
        with pytest.raises(StateError):
            engine.start(loop, name="after-shutdown")


# ================================================================ more engine behaviour


def test_all_required_exits_must_finish() -> None:
    g = build.graph(build.parallel(Noop, build.node(Nap, seconds=0.15)), name="exits")
    with engine_with() as (engine, _):
        t0 = time.monotonic()
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert time.monotonic() - t0 >= 0.15


def test_non_required_exit_finishes_on_first_and_stops_the_rest() -> None:
    b = build.GraphBuilder("first_exit")
    for node in (b.add(Noop), b.add(Blocker)):
        b.entry(node)
        b.exit(node, required=False)
    g = b.build()
    with engine_with() as (engine, rec):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.TRUE
        # the graph is done: the still running Blocker_0 is stopped, its result ignored
        eventually(
            lambda: node_state(engine, "first_exit", "Blocker_0") == "FINISHED",
            5,
            "blocker stopped",
        )
        blocker = [new.value for _, node, _, new in rec.transitions if node == "Blocker_0"]
        assert blocker == ["RUNNING", "STOPPING", "FINISHED"]
        assert engine.outcome("first_exit").result is Result.TRUE


@pytest.mark.parametrize(
    ("given", "expected", "ran"),
    [
        (Result.FALSE, Result.TRUE, ["Noop_0"]),
        (Result.ERROR, Result.ERROR, []),
        (Result.STOPPED, Result.HALTED, []),
    ],
)
def test_start_result_is_handed_to_the_entry_actions(
    given: Result, expected: Result, ran: list[str]
) -> None:
    g = build.graph(Noop, name="entry_result")
    with engine_with() as (engine, rec):
        run = engine.start(g, result=given)
        assert engine.wait(run, timeout=WAIT) is expected
        assert rec.started(run) == ran


def test_halting_subgraph_fails_its_parent_node() -> None:
    inner = halting("Halter")
    top = build.graph(inner, Noop, name="TopH")
    with engine_with(graphs=[inner]) as (engine, rec):
        outcome = engine.run(top, timeout=WAIT)
        assert outcome.result is Result.ERROR
        assert "halted" in str(outcome.errors[-1])
        assert engine.running_graphs()["TopH__Halter__0"] is GraphState.HALTED
        assert rec.started("TopH") == ["Halter_0"]


def test_stop_paused_graph_with_held_result() -> None:
    started = threading.Event()

    @action
    class Quick(Action):
        def on_run(self) -> bool:
            started.set()
            threading.Event().wait(0.05)
            return True

    g = build.graph(Quick, Noop, name="held_stop")
    with engine_with(Quick) as (engine, rec):
        run = engine.start(g)
        assert started.wait(5)
        engine.pause(run)
        time.sleep(0.15)  # Quick_0 has returned; its result is held
        assert engine.stop(run, timeout=WAIT) is Result.STOPPED
        assert rec.started(run) == ["Quick_0"]
        assert node_state(engine, run, "Quick_0") == "FINISHED"


def test_stop_halted_graph() -> None:
    g = halting("halt_stop")
    with engine_with() as (engine, _):
        run = engine.start(g)
        assert engine.wait(run, timeout=WAIT) is Result.HALTED
        assert engine.stop(run, timeout=WAIT) is Result.STOPPED
        assert engine.outcome(run).state is GraphState.STOPPED
        # stopping an ended graph again returns its result at once
        assert engine.stop(run, timeout=WAIT) is Result.STOPPED


def test_preempted_action_ignoring_stop_is_abandoned_and_next_event_gets_fresh_instance() -> None:
    runs: list[tuple[int, float]] = []

    @action(outputs={"n": float}, type="spontaneous")
    class Src(Action):
        def __init__(self) -> None:
            super().__init__()
            self.k = 0

        def on_run(self) -> bool:
            if self.k >= 2:
                self.wait_until_stopped()
                return True
            self.sleep(0.05)
            self.k += 1
            self.outputs["n"] = self.k
            return True

    @action(inputs={"n": float})
    class Deaf(Action):
        def on_run(self) -> bool:
            k = self.inputs.get_number("n")
            runs.append((id(self), k))
            if k < 2:
                for _ in range(15):  # ~0.45 s, never looks at stop_requested
                    threading.Event().wait(0.03)
            return True

    g = build.graph(Src, Deaf, name="deaf")
    with engine_with(Src, Deaf, stop_timeout=0.1) as (engine, _):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert [k for _, k in runs] == [1.0, 2.0]
        assert runs[0][0] != runs[1][0]  # the abandoned instance is still busy: a fresh one runs
        assert any("did not stop" in str(e) for e in outcome.errors)


def test_restart_of_an_action_ignoring_stop_runs_a_fresh_instance() -> None:
    runs: list[int] = []

    @action
    class Deaf2(Action):
        def on_run(self) -> bool:
            runs.append(id(self))
            if len(runs) == 1:
                for _ in range(15):
                    threading.Event().wait(0.03)
            return True

    g = answering("restart_deaf", Deaf2, "restart", "on_error -> ignore", trigger=Noop)
    with engine_with(Deaf2, stop_timeout=0.1) as (engine, _):
        outcome = engine.run(g, timeout=WAIT)
        assert outcome.result is Result.TRUE
        assert len(runs) == 2
        assert runs[0] != runs[1]


def test_on_stop_is_not_delivered_to_the_restarted_run() -> None:
    events: list[str] = []

    @action
    class Restartee(Action):
        def __init__(self) -> None:
            super().__init__()
            self.k = 0

        def on_run(self) -> bool:
            self.k += 1
            events.append(f"run{self.k} start")
            if self.k == 1:
                self.wait_until_stopped(5.0)
            else:
                threading.Event().wait(0.05)
            events.append(f"run{self.k} end")
            return True

        def on_stop(self) -> None:
            events.append(f"on_stop during run{self.k}")

    g = answering("restart_hook", Restartee, "restart", seconds=0.02)
    for _ in range(5):
        events.clear()
        with engine_with(Restartee) as (engine, _):
            require(engine.run(g, timeout=WAIT).result is Result.TRUE, "graph result")
        # actual: [..., 'run2 start', 'on_stop during run2', 'run2 end']
        assert "on_stop during run2" not in events, events


def test_shutdown_right_after_finish_leaves_no_node_active() -> None:
    second_run = threading.Event()

    @action(outputs={"n": float}, type="spontaneous")
    class Source(Action):
        def __init__(self) -> None:
            super().__init__()
            self.k = 0

        def on_run(self) -> bool:
            if self.k >= 1:
                second_run.set()
                self.wait_until_stopped()
                threading.Event().wait(0.3)  # a short clean-up, well within stop_timeout
                return True
            self.k += 1
            self.outputs["n"] = self.k
            return True

    @action
    class Gate(Action):
        def on_run(self) -> bool:
            # finish the graph only once the source is inside its next (blocking) run
            return second_run.wait(5)

    g = build.graph(Source, Gate, name="spont_end")
    with engine_with(Source, Gate) as (engine, _):
        require(engine.run(g, timeout=WAIT).result is Result.TRUE, "graph result")
        require(node_state(engine, "spont_end", "Source_0") == "STOPPING", "source stopping")
        engine.shutdown()  # closes the pool while the source is still cleaning up
        # actual: STOPPING (its result was dropped with the closed pool)
        assert node_state(engine, "spont_end", "Source_0") == "FINISHED"


def test_modify_removing_a_literal_does_not_keep_the_old_value() -> None:
    b = build.GraphBuilder("lit_mod")
    emit = b.add(Emit, value="old")
    b.entry(emit)
    b.exit(emit, "on_true -> ignore")
    v1 = b.build()
    v2 = build.graph(Emit, name="lit_mod")
    with engine_with() as (engine, _):
        run = engine.start(v1)
        require(engine.wait(run, timeout=WAIT) is Result.HALTED, "v1 halts")
        engine.modify(run, v2)
        inputs = engine.graph_json(run)["actions"][0]["input_parameters"]
        assert "pvf_value" not in inputs["value"]  # actual: {"pvf_value": "old"}
        engine.resume(run, continue_from="Emit_0")
        engine.wait(run, timeout=WAIT)
        assert engine.outcome(run).outputs.get("out") != "old"


def test_a_replaced_run_lets_go_of_its_nodes_and_the_new_one_runs() -> None:
    g = build.graph(build.node(Emit, value="x"), build.node(Emit, value="y"), name="again")
    with engine_with() as (engine, _):
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        old = engine._runs["again"]
        assert len(old.nodes) == 2
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        new = engine._runs["again"]
        assert new is not old
        assert old.nodes == {}  # the cycles between the run and its nodes are broken
        assert old.edge_child == old.edge_parent == []
        assert old.order == []
        assert len(new.nodes) == 2
        assert engine.outcome("again").outputs == {"out": "y"}


def test_a_graph_started_again_is_planned_once_until_the_catalog_changes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from temoto.core import planning

    validated: list[str] = []
    real = planning.validate_graph

    def counting(g: UmrfGraph) -> Any:
        validated.append(g.name)
        return real(g)

    monkeypatch.setattr(planning, "validate_graph", counting)
    g = build.graph(build.node(Emit, value="x"), name="cached")
    with engine_with() as (engine, _):
        for _ in range(3):
            assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert validated == ["cached"]  # the same graph object: one plan
        same_text = build.graph(build.node(Emit, value="x"), name="cached")
        assert engine.run(same_text, timeout=WAIT).result is Result.TRUE
        assert validated == ["cached", "cached"]  # another object is planned afresh

        @action
        class Later(Action):
            def on_run(self) -> bool:
                return True

        engine.catalog.register(Later, description_of(Later))
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert validated == ["cached", "cached", "cached"]  # the catalog changed: planned again
        engine.graphs.add(build.graph(Emit, name="other"))
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
        assert len(validated) == 4  # so did the index
