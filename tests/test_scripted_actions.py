"""temoto.testing.Script: scripted actions do what is planned per node and record what ran."""

from __future__ import annotations

import pytest

from temoto import ActionEngine, ManualClock, Result, catalog, graph, node
from temoto.testing import Outcome, Script

WAIT = 30.0


def test_planned_runs_then_the_default_per_node() -> None:
    script = Script()
    step = script.action("Step", outputs={"out": str}, default=Outcome(outputs={"out": "d"}))
    script.plan("Step_1", Outcome(False, outputs={"out": "planned"}))
    with ActionEngine(actions=catalog(step)) as engine:
        first = engine.run(graph(step, step, name="g"), timeout=WAIT)
        second = engine.run(graph(step, step, name="g"), timeout=WAIT)
    assert first.result is Result.FALSE  # Step_1, the exit, ran as planned
    assert first.outputs == {"out": "planned"}
    assert second.result is Result.TRUE
    assert second.outputs == {"out": "d"}  # the plan was used up
    assert script.started() == ["Step_0", "Step_1", "Step_0", "Step_1"]
    assert script.started("g") == script.started()


def test_outputs_from_inputs_and_the_inputs_recorded() -> None:
    script = Script()
    echo = script.action(
        "Echo",
        inputs={"value": str},
        outputs={"out": str},
        default=Outcome(outputs=lambda inputs: {"out": inputs["value"] * 2}),
    )
    with ActionEngine(actions=catalog(echo)) as engine:
        outcome = engine.run(graph(node(echo, value="ab")), timeout=WAIT)
    assert outcome.outputs == {"out": "abab"}
    assert script.inputs("Echo_0") == {"value": "ab"}
    with pytest.raises(IndexError):
        script.inputs("Echo_0", 1)


def test_a_planned_exception_is_the_node_s_error() -> None:
    script = Script()
    fail = script.action("Fail", default=RuntimeError("boom"))
    with ActionEngine(actions=catalog(fail)) as engine:
        outcome = engine.run(graph(fail), timeout=WAIT)
    assert outcome.result is Result.ERROR
    assert "boom" in str(outcome.errors[0].__cause__)


def test_waits_are_on_the_engine_s_clock() -> None:
    clock = ManualClock()
    script = Script()
    nap = script.action("Nap", default=Outcome(seconds=5.0))
    after = script.action("After")
    with ActionEngine(actions=catalog(nap, after), clock=clock) as engine:
        run = engine.start(graph(nap, after, name="nap"))
        assert script.wait_started("Nap_0")
        clock.advance(4.0)
        with pytest.raises(TimeoutError):
            engine.wait(run, 0.2)  # 4 of its 5 virtual seconds: still napping
        assert script.started() == ["Nap_0"]
        clock.advance(1.0)
        engine.wait(run, WAIT)
        assert engine.outcome(run).result is Result.TRUE
    assert script.started() == ["Nap_0", "After_0"]


def test_until_stopped_waits_for_the_stop_and_records_the_hook() -> None:
    script = Script()
    block = script.action("Block", default=Outcome(until_stopped=True))
    with ActionEngine(actions=catalog(block), stop_timeout=WAIT) as engine:
        run = engine.start(graph(block, name="b"))
        assert script.wait_started("Block_0")
        engine.stop(run, timeout=WAIT)
    assert ("Block_0", "on_stop") in script.calls
    assert not script.wait_started("Block_0", count=2, timeout=0)


def test_bad_plans_are_refused() -> None:
    script = Script()
    with pytest.raises(TypeError, match="a planned run is True, False"):
        script.plan("A_0", "yes")
    with pytest.raises(TypeError, match="a planned run"):
        script.action("A", default=None)
