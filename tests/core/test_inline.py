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
from test_engine import WAIT, act, cond, describe, engine_with, eventually, graph, n, s

from temoto import Action, ActionCatalog, GraphState, Result
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


@describe("Quick")
class Quick(Action):
    """Inline: records its thread, returns True."""

    blocking = False

    def on_run(self) -> bool:
        _record(self.name)
        return True


@describe("QuickRet", inputs={"result": s()})
class QuickRet(Action):
    """Inline: returns what ``result`` says ("true" / "false"), raises otherwise."""

    blocking = False

    def on_run(self) -> bool:
        result = self.inputs.get_string("result")
        if result in ("true", "false"):
            return result == "true"
        raise RuntimeError(f"asked to fail ({result})")


@describe("Count", inputs={"count": n()}, outputs={"count": n()})
class Count(Action):
    """Inline: count + 1 (a loop's body)."""

    blocking = False

    def on_run(self) -> bool:
        _record(self.name)
        self.outputs["count"] = self.inputs.get_number("count") + 1
        return True


@describe("Meet", inputs={"parties": n()})
class Meet(Action):
    """Blocking: waits at a barrier with the other Meet runs (only concurrent runs pass)."""

    barrier: threading.Barrier | None = None

    def on_run(self) -> bool:
        assert Meet.barrier is not None
        Meet.barrier.wait(WAIT)
        return True


@describe("NapInline", inputs={"seconds": n()})
class NapInline(Action):
    """Declares itself inline but sleeps (a broken promise): still stoppable."""

    blocking = False

    def on_run(self) -> bool:
        self.sleep(self.inputs.get_number("seconds"))
        return True


CLASSES = (Quick, QuickRet, Count, Meet, NapInline)


def chain(name: str, cls: str, length: int) -> Any:
    nodes = [f"{cls}_{i}" for i in range(length)]
    return graph(
        name,
        [
            act(
                node,
                parents=nodes[i - 1 : i] if i else (),
                children=nodes[i + 1 : i + 2],
            )
            for i, node in enumerate(nodes)
        ],
        [nodes[0]],
        [nodes[-1]],
    )


def fan(name: str, cls: str, width: int, inputs: dict[str, Any] | None = None) -> Any:
    """``width`` parallel ``cls`` nodes joined by Quick_999."""
    nodes = [f"{cls}_{i}" for i in range(width)]
    return graph(
        name,
        [
            *(act(node, inputs=inputs, children=["Quick_999"]) for node in nodes),
            act("Quick_999", parents=nodes),
        ],
        nodes,
        ["Quick_999"],
    )


def endless_loop() -> Any:
    """Count_0 <-> Count_1 forever (nothing reaches the exit)."""
    return graph(
        "endless",
        [
            act(
                "Count_0",
                inputs={"count": n()},
                outputs={"count": n()},
                parents=[cond("Count_1", required=False)],
                children=["Count_1"],
            ),
            act(
                "Count_1",
                inputs={"count": n()},
                outputs={"count": n()},
                parents=["Count_0"],
                children=["Count_0"],
            ),
        ],
        ["Count_0"],
        [cond("Count_1", "on_true -> ignore", "on_false -> ignore")],
    )


# ================================================================ where inline actions run


def test_an_inline_chain_runs_on_one_worker_thread_not_the_callers() -> None:
    with engine_with(*CLASSES) as (engine, rec):
        run = engine.start(chain("c", "Quick", 50))
        assert engine.wait(run, WAIT) is Result.TRUE
    assert [name for name, _ in RUNS] == [f"Quick_{i}" for i in range(50)]
    threads = {ident for _, ident in RUNS}
    assert len(threads) == 1
    assert threading.get_ident() not in threads
    assert rec.started(run) == [f"Quick_{i}" for i in range(50)]


def test_a_fan_out_of_inline_actions_runs_as_one_batch_on_one_thread() -> None:
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(fan("f", "Quick", 200))
        assert engine.wait(run, WAIT) is Result.TRUE
        # one worker did all 201 runs: the batch was not split across the pool
        assert len(RUNS) == 201
        assert len({ident for _, ident in RUNS}) == 1
        assert engine._pool.size == 1


def test_blocking_actions_of_a_fan_out_still_get_a_worker_each() -> None:
    width = 4
    Meet.barrier = threading.Barrier(width)
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(fan("meet", "Meet", width, inputs={"parties": n(width)}))
        # only if all four run at once do they pass the barrier
        assert engine.wait(run, WAIT) is Result.TRUE
        assert engine._pool.size >= width


def test_an_inline_child_of_a_blocking_action_runs_on_its_parents_worker() -> None:
    threads: list[int] = []

    @describe("Slow")
    class Slow(Action):
        def on_run(self) -> bool:
            threads.append(threading.get_ident())
            return True

    g = graph(
        "mixed",
        [act("Slow_0", children=["Quick_1"]), act("Quick_1", parents=["Slow_0"])],
        ["Slow_0"],
        ["Quick_1"],
    )
    with engine_with(Slow, *CLASSES) as (engine, _):
        assert engine.wait(engine.start(g), WAIT) is Result.TRUE
    assert threads == [RUNS[0][1]]


def test_a_wave_with_inline_and_blocking_children_splits_them_between_threads() -> None:
    event = threading.Event()
    waiter_thread: list[int] = []

    @describe("Waiter")
    class Waiter(Action):
        """Blocking: true once the inline sibling has run (which it must, meanwhile)."""

        def on_run(self) -> bool:
            waiter_thread.append(threading.get_ident())
            return event.wait(WAIT)

    @describe("Setter")
    class Setter(Action):
        blocking = False

        def on_run(self) -> bool:
            _record(self.name)
            event.set()
            return True

    g = graph(
        "split",
        [
            act("Quick_0", children=["Waiter_1", "Setter_2"]),
            act("Waiter_1", parents=["Quick_0"]),
            act("Setter_2", parents=["Quick_0"]),
        ],
        ["Quick_0"],
        ["Waiter_1", "Setter_2"],
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
    g = graph(
        "results",
        [
            act("QuickRet_0", inputs={"result": s("false")}, children=["QuickRet_1"]),
            act(
                "QuickRet_1",
                inputs={"result": s("boom")},
                parents=[cond("QuickRet_0", "on_false -> run")],
                children=["Quick_2"],
            ),
            act("Quick_2", parents=["QuickRet_1"]),
        ],
        ["QuickRet_0"],
        ["Quick_2"],
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


def test_an_endless_inline_loop_can_be_paused_resumed_and_stopped() -> None:
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(endless_loop(), {"count": 0})
        eventually(lambda: len(RUNS) >= 100, what="the loop turning")
        engine.pause(run)
        assert engine.outcome(run).state is GraphState.PAUSED
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
    g = graph("nap", [act("NapInline_0", inputs={"seconds": n(3600)})], ["NapInline_0"], [])
    with engine_with(*CLASSES) as (engine, rec):
        run = engine.start(g)
        eventually(lambda: rec.started(run) == ["NapInline_0"], what="the nap to start")
        assert engine.stop(run, WAIT) is Result.STOPPED


def test_an_inline_action_ignoring_its_stop_goes_to_error_after_stop_timeout() -> None:
    release = threading.Event()
    entered = threading.Event()

    @describe("Stubborn")
    class Stubborn(Action):
        blocking = False

        def on_run(self) -> bool:
            entered.set()
            release.wait(WAIT)  # does not look at stops
            return True

    g = graph("stubborn", [act("Stubborn_0")], ["Stubborn_0"], [])
    with engine_with(Stubborn, *CLASSES, stop_timeout=0.05) as (engine, _):
        run = engine.start(g)
        assert entered.wait(WAIT)
        assert engine.stop(run, WAIT) is Result.ERROR
        assert "did not stop within" in str(engine.outcome(run).errors[-1])
        release.set()


def test_modify_extends_a_halted_inline_graph() -> None:
    g = chain("grow", "Quick", 2)
    with engine_with(*CLASSES) as (engine, _):
        run = engine.start(
            graph(
                "grow",
                [act("Quick_0", children=["Quick_1"]), act("Quick_1", parents=["Quick_0"])],
                ["Quick_0"],
                [],
            )
        )
        assert engine.wait(run, WAIT) is Result.HALTED
        engine.modify(run, g, continue_from="Quick_1")
        assert engine.wait(run, WAIT) is Result.TRUE
    assert [name for name, _ in RUNS] == ["Quick_0", "Quick_1", "Quick_1"]


@pytest.mark.parametrize("returned", [None, 1, "yes"])
def test_an_inline_on_run_returning_a_non_bool_is_an_error(returned: Any) -> None:
    @describe("Odd")
    class Odd(Action):
        blocking = False

        def on_run(self) -> bool:
            return returned  # type: ignore[no-any-return]

    with engine_with(Odd) as (engine, _):
        run = engine.start(graph("odd", [act("Odd_0")], ["Odd_0"], ["Odd_0"]))
        assert engine.wait(run, WAIT) is Result.ERROR
        assert "must return True or False" in str(engine.outcome(run).errors[0])


def test_an_inline_instance_lives_across_the_runs_of_a_loop() -> None:
    instances: list[tuple[str, int]] = []

    @describe("Same", inputs={"count": n()}, outputs={"count": n()})
    class Same(Action):
        blocking = False

        def on_run(self) -> bool:
            instances.append((self.name, id(self)))
            count = self.inputs.get_number("count") + 1
            self.outputs["count"] = count
            return count < 10

    g = graph(
        "same",
        [
            act(
                "Same_0",
                inputs={"count": n()},
                outputs={"count": n()},
                parents=[cond("Same_1", "on_false -> ignore", required=False)],
                children=["Same_1"],
            ),
            act(
                "Same_1",
                inputs={"count": n()},
                outputs={"count": n()},
                parents=["Same_0"],
                children=["Same_0"],
            ),
        ],
        ["Same_0"],
        [cond("Same_1", "on_true -> ignore")],
    )
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
    @describe("Plain")
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
