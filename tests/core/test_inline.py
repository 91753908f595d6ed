"""Inline actions (``Action.blocking = False``) and batched dispatch.

An inline action runs on the thread that evolves its graph (a worker: never the caller of
``start``), the inline actions that become ready together run back to back on one thread,
and blocking actions keep a worker each. Stop, pause, resume, modify and errors behave as for
blocking actions; the upstream conformance graphs (whose never-waiting actions are inline)
are in ``test_conformance.py``.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
from test_engine import WAIT, engine_with, eventually

from temoto import Action, ActionCatalog, GraphState, NodeState, Result, build
from temoto.build import action
from temoto.core.executor import WorkerPool
from temoto.errors import ActionError

CONFORMANCE = Path(__file__).resolve().parents[2] / "examples" / "actions" / "conformance"

#: (node name, thread id) of every inline run, in order
RUNS: list[tuple[str, int]] = []
_RUNS_LOCK = threading.Lock()


def _record(name: str) -> None:
    with _RUNS_LOCK:
        RUNS.append((name, threading.get_ident()))


@pytest.fixture(autouse=True)
def _clear_runs() -> None:
    RUNS.clear()


@action
class Quick(Action):
    """Inline: records its thread, returns True."""

    blocking = False

    def on_run(self) -> bool:
        _record(self.name)
        return True


@action(inputs={"result": str})
class QuickRet(Action):
    """Inline: returns what ``result`` says ("true" / "false"), raises otherwise."""

    blocking = False

    def on_run(self) -> bool:
        result = self.inputs.get_string("result")
        if result in ("true", "false"):
            return result == "true"
        raise RuntimeError(f"asked to fail ({result})")


@action(inputs={"count": float}, outputs={"count": float})
class Count(Action):
    """Inline: count + 1 (a loop's body)."""

    blocking = False

    def on_run(self) -> bool:
        _record(self.name)
        self.outputs["count"] = self.inputs.get_number("count") + 1
        return True


@action(inputs={"parties": float})
class Meet(Action):
    """Blocking: waits at a barrier with the other Meet runs (only concurrent runs pass)."""

    barrier: threading.Barrier | None = None

    def on_run(self) -> bool:
        assert Meet.barrier is not None
        Meet.barrier.wait(WAIT)
        return True


@action(inputs={"seconds": float})
class NapInline(Action):
    """Declares itself inline but sleeps (a broken promise): still stoppable."""

    blocking = False

    def on_run(self) -> bool:
        self.sleep(self.inputs.get_number("seconds"))
        return True


@action(inputs={"text": str}, outputs={"out": str})
class Relay(Action):
    """Inline: out = text + "!"."""

    blocking = False

    def on_run(self) -> bool:
        _record(self.name)
        self.outputs["out"] = self.inputs.get_string("text") + "!"
        return True


@action(outputs={"out": str})
class Silent(Action):
    """Inline: declares an output and never writes it."""

    blocking = False

    def on_run(self) -> bool:
        _record(self.name)
        return True


@action
class BadInit(Action):
    """Inline, but its on_init raises."""

    blocking = False

    def on_init(self) -> None:
        raise RuntimeError("no init today")

    def on_run(self) -> bool:
        _record(self.name)
        return True


CLASSES = (Quick, QuickRet, Count, Meet, NapInline, Relay, Silent, BadInit)


def chain(name: str, cls: type[Action], length: int) -> Any:
    return build.graph(*[cls] * length, name=name)


def fan(name: str, cls: type[Action], width: int, **inputs: Any) -> Any:
    """``width`` parallel ``cls`` nodes joined by Quick_999."""
    nodes = [build.node(cls, inputs) for _ in range(width)]
    return build.graph(build.parallel(*nodes), build.node(Quick, instance=999), name=name)


def endless_loop() -> Any:
    """Count_0 <-> Count_1 forever (nothing reaches the exit)."""
    b = build.GraphBuilder("endless")
    first, second = b.add(Count), b.add(Count)
    b.link(first, second)
    b.link(second, first, required=False)
    b.entry(first)
    b.exit(second, "on_true -> ignore", "on_false -> ignore")
    return b.build()


def no_exit(name: str, cls: type[Action], **values: Any) -> Any:
    """One ``cls`` node and no exit: the graph ends only when stopped (or halts)."""
    b = build.GraphBuilder(name)
    b.entry(b.add(cls, values))
    return b.build()


# ================================================================ where inline actions run


def test_an_inline_chain_runs_on_one_worker_thread_not_the_callers() -> None:
    with engine_with(*CLASSES) as (engine, rec):
        run = engine.start(chain("c", Quick, 50))
        assert engine.wait(run, WAIT) is Result.TRUE
    assert [name for name, _ in RUNS] == [f"Quick_{i}" for i in range(50)]
    threads = {ident for _, ident in RUNS}
    assert len(threads) == 1
    assert threading.get_ident() not in threads
    assert rec.started(run) == [f"Quick_{i}" for i in range(50)]


def test_a_fan_out_of_inline_actions_runs_as_one_batch_on_one_thread() -> None:
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(fan("f", Quick, 200))
        assert engine.wait(run, WAIT) is Result.TRUE
        # one worker did all 201 runs: the batch was not split across the pool
        assert len(RUNS) == 201
        assert len({ident for _, ident in RUNS}) == 1
        assert engine._pool.size == 1


def test_blocking_actions_of_a_fan_out_still_get_a_worker_each() -> None:
    width = 4
    Meet.barrier = threading.Barrier(width)
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(fan("meet", Meet, width, parties=width))
        # only if all four run at once do they pass the barrier
        assert engine.wait(run, WAIT) is Result.TRUE
        assert engine._pool.size >= width


def test_an_inline_child_of_a_blocking_action_runs_on_its_parents_worker() -> None:
    threads: list[int] = []

    @action
    class Slow(Action):
        def on_run(self) -> bool:
            threads.append(threading.get_ident())
            return True

    g = build.graph(Slow, build.node(Quick, instance=1), name="mixed")
    with engine_with(Slow, *CLASSES) as (engine, _):
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
    assert threads == [RUNS[0][1]]


def test_a_wave_with_inline_and_blocking_children_splits_them_between_threads() -> None:
    event = threading.Event()
    waiter_thread: list[int] = []

    @action
    class Waiter(Action):
        """Blocking: true once the inline sibling has run (which it must, meanwhile)."""

        def on_run(self) -> bool:
            waiter_thread.append(threading.get_ident())
            return event.wait(WAIT)

    @action
    class Setter(Action):
        blocking = False

        def on_run(self) -> bool:
            _record(self.name)
            event.set()
            return True

    g = build.graph(
        Quick,
        build.parallel(build.node(Waiter, instance=1), build.node(Setter, instance=2)),
        name="split",
    )
    with engine_with(Waiter, Setter, *CLASSES) as (engine, _):
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
    # the inline child continued on its parent's worker; the blocking one went to the pool
    # (had the worker run it first, it would have waited for the inline one in vain)
    assert [name for name, _ in RUNS] == ["Quick_0", "Setter_2"]
    assert RUNS[0][1] == RUNS[1][1]
    assert len(waiter_thread) == 1


# ================================================================ same semantics as blocking


def test_inline_results_and_errors_propagate_like_blocking_ones() -> None:
    g = build.graph(
        build.node(QuickRet, result="false"),  # on_false runs the child (the default)
        build.node(QuickRet, result="boom"),
        build.node(Quick, instance=2),
        name="results",
    )
    with engine_with(*CLASSES) as (engine, rec):
        run = engine.start(g)
        assert engine.wait(run, WAIT) is Result.ERROR
        outcome = engine.outcome(run)
    assert len(outcome.errors) == 1
    assert isinstance(outcome.errors[0], ActionError)
    assert "asked to fail (boom)" in str(outcome.errors[0])
    assert [name for _, name, _ in rec.failures] == ["QuickRet_1"]
    assert RUNS == []  # Quick_2 was bypassed by the error


def test_an_inline_chain_hands_outputs_down_with_remaps() -> None:
    b = build.GraphBuilder("relay")
    first = b.add(Relay, text="a")
    second, third = b.add(Relay), b.add(Relay)
    b.link(first, second, remap={"out": "text"})
    b.link(second, third, remap={"out": "text"})
    b.entry(first)
    b.exit(third)
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(b.build())
        assert engine.wait(run, WAIT) is Result.TRUE
        assert engine.outcome(run).outputs == {"out": "a!!!"}
    assert [name for name, _ in RUNS] == ["Relay_0", "Relay_1", "Relay_2"]
    assert len({thread for _, thread in RUNS}) == 1


def test_an_inline_action_whose_on_init_raises_fails_in_a_chain() -> None:
    g = build.graph(Quick, BadInit, build.node(Quick, instance=1), name="bad_init")
    with engine_with(*CLASSES) as (engine, rec):
        run = engine.start(g)
        assert engine.wait(run, WAIT) is Result.ERROR
        outcome = engine.outcome(run)
        states = engine.node_states(run)
    assert [name for name, _ in RUNS] == ["Quick_0"]  # Quick_1 was bypassed by the error
    assert len(outcome.errors) == 1
    assert "BadInit_0 could not be initialised: no init today" in str(outcome.errors[0])
    assert [name for _, name, _ in rec.failures] == ["BadInit_0"]
    assert states["BadInit_0"] is NodeState.ERROR


def test_an_inline_child_missing_a_required_input_waits_and_the_graph_halts() -> None:
    b = build.GraphBuilder("missing")
    first, second = b.add(Silent), b.add(Relay)  # Silent leaves "out" unset
    b.link(first, second, remap={"out": "text"})
    b.entry(first)
    b.exit(second)
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(b.build())
        assert engine.wait(run, WAIT) is Result.HALTED
        states = engine.node_states(run)
    assert [name for name, _ in RUNS] == ["Silent_0"]
    assert states == {"Silent_0": NodeState.FINISHED, "Relay_0": NodeState.UNINITIALIZED}


def test_an_endless_inline_loop_can_be_paused_resumed_and_stopped() -> None:
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(endless_loop(), {"count": 0})
        eventually(lambda: len(RUNS) >= 100, what="the loop turning")
        engine.pause(run)
        assert engine.outcome(run).state in (GraphState.PAUSE_REQUESTED, GraphState.PAUSED)
        # at most the run in flight when the pause landed may still complete
        eventually(lambda: all(not a for a in _active(engine, run)), what="the loop to settle")
        paused_at = len(RUNS)
        assert engine.outcome(run).state is GraphState.PAUSED
        assert len(RUNS) == paused_at
        engine.resume(run)
        eventually(lambda: len(RUNS) >= paused_at + 100, what="the loop turning again")
        assert engine.stop(run, WAIT) is Result.STOPPED
        assert engine.outcome(run).state is GraphState.STOPPED
        stopped_at = len(RUNS)
        assert all(not a for a in _active(engine, run))
    assert len(RUNS) == stopped_at


def _active(engine: Any, run: str) -> list[bool]:
    busy = ("RUNNING", "PAUSE_REQUESTED", "STOPPING")
    return [a["state"] in busy for a in engine.graph_json(run)["actions"]]


def test_an_inline_action_that_sleeps_is_still_stopped() -> None:
    g = no_exit("nap", NapInline, seconds=3600)
    with engine_with(*CLASSES) as (engine, rec):
        run = engine.start(g)
        eventually(lambda: rec.started(run) == ["NapInline_0"], what="the nap to start")
        assert engine.stop(run, WAIT) is Result.STOPPED


def test_an_inline_action_ignoring_its_stop_goes_to_error_after_stop_timeout() -> None:
    release = threading.Event()
    entered = threading.Event()

    @action
    class Stubborn(Action):
        blocking = False

        def on_run(self) -> bool:
            entered.set()
            release.wait(WAIT)  # does not look at stops
            return True

    g = no_exit("stubborn", Stubborn)
    with engine_with(Stubborn, *CLASSES, stop_timeout=0.05) as (engine, _):
        run = engine.start(g)
        assert entered.wait(WAIT)
        assert engine.stop(run, WAIT) is Result.ERROR
        assert "did not stop within" in str(engine.outcome(run).errors[-1])
        release.set()


def test_modify_extends_a_halted_inline_graph() -> None:
    g = chain("grow", Quick, 2)
    halting = build.GraphBuilder("grow")
    first, second = halting.add(Quick), halting.add(Quick)
    halting.link(first, second)
    halting.entry(first)
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(halting.build())
        assert engine.wait(run, WAIT) is Result.HALTED
        engine.modify(run, g, continue_from="Quick_1")
        assert engine.wait(run, WAIT) is Result.TRUE
    assert [name for name, _ in RUNS] == ["Quick_0", "Quick_1", "Quick_1"]


@pytest.mark.parametrize("returned", [None, 1, "yes"])
def test_an_inline_on_run_returning_a_non_bool_is_an_error(returned: Any) -> None:
    @action
    class Odd(Action):
        blocking = False

        def on_run(self) -> bool:
            return returned  # type: ignore[no-any-return]

    with engine_with(Odd) as (engine, _):
        run = engine.start(build.graph(Odd, name="odd"))
        assert engine.wait(run, WAIT) is Result.ERROR
        assert "must return True or False" in str(engine.outcome(run).errors[0])


def test_an_inline_instance_lives_across_the_runs_of_a_loop() -> None:
    instances: list[tuple[str, int]] = []

    @action(inputs={"count": float}, outputs={"count": float})
    class Same(Action):
        blocking = False

        def on_run(self) -> bool:
            instances.append((self.name, id(self)))
            count = self.inputs.get_number("count") + 1
            self.outputs["count"] = count
            return count < 10

    b = build.GraphBuilder("same")
    first, second = b.add(Same), b.add(Same)
    b.link(first, second)
    b.link(second, first, "on_false -> ignore", required=False)
    b.entry(first)
    b.exit(second, "on_true -> ignore")
    g = b.build()
    with engine_with(Same) as (engine, _):
        run = engine.start(g, {"count": 0})
        assert engine.wait(run, WAIT) is Result.FALSE
        assert engine.outcome(run).outputs == {"count": 10.0}
    assert [name for name, _ in instances] == ["Same_0", "Same_1"] * 5
    assert len({ident for name, ident in instances if name == "Same_0"}) == 1
    assert len({ident for name, ident in instances if name == "Same_1"}) == 1


# ================================================================ declarations


def test_conformance_actions_that_never_wait_are_inline_and_the_others_are_not() -> None:
    catalog = ActionCatalog([CONFORMANCE], use_entry_points=False)
    inline = {name for name in catalog.names() if not catalog.load_class(name).blocking}
    assert inline == {
        "TaAddString",
        "TaCompareNumber",
        "TaCompareString",
        "TaLogger",
        "TaRelayString",
        "TaTriggerResult",
    }


def test_blocking_is_the_default() -> None:
    @action
    class Plain(Action):
        def on_run(self) -> bool:
            return True

    assert Plain.blocking is True
    assert Quick.blocking is False


# ================================================================ the pool's batch submission


def test_submit_many_runs_every_job_within_max_workers() -> None:
    pool = WorkerPool(max_workers=3, name="temoto-test")
    done: list[int] = []
    lock = threading.Lock()
    finished = threading.Event()

    def job(i: int) -> None:
        with lock:
            done.append(i)
            if len(done) == 50:
                finished.set()

    try:
        pool.submit_many(job, [(i,) for i in range(50)])
        assert finished.wait(WAIT)
        assert sorted(done) == list(range(50))
        assert pool.size <= 3
    finally:
        assert pool.shutdown(WAIT) == []


def test_submit_many_after_shutdown_raises_and_queues_nothing() -> None:
    pool = WorkerPool(max_workers=2, name="temoto-test")
    pool.shutdown(WAIT)
    ran: list[int] = []
    with pytest.raises(RuntimeError, match="shut down"):
        pool.submit_many(ran.append, [(1,), (2,)])
    assert pool.size == 0
    assert ran == []
