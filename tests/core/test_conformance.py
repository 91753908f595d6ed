"""The executable specification: upstream TeMoto's own test graphs, with their documented results.

Every current-format graph in ``shared/conformance/umrf/upstream`` is run the way upstream's
gtest suites run it (actor ``ae_instance_1``, the nine conformance actions, the upstream folder
indexed for sub-graphs), with the expected result **and** execution order from that folder's
README. Time runs ten times faster (``ScaledClock(10)``): upstream's timings are scaled by 0.1,
the semantics are unchanged. ``time.sleep`` is used only to place an external command (stop,
pause, modify) at a point in clock time; real seconds = clock seconds / 10.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from temoto import ActionEngine, GraphState, Result, ScaledClock, load_graph, parse_graph
from temoto.core.documents import graph_to_dict
from temoto.core.instrument import RecordingInstrument
from temoto.errors import ActionNotFoundError, GraphDefinitionError, GraphInputError

ROOT = Path(__file__).resolve().parents[2]
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
if not UPSTREAM.is_dir():  # the executable specification is upstream's data
    pytest.skip(f"upstream conformance data not found at {UPSTREAM}", allow_module_level=True)
ACTIONS = ROOT / "examples" / "actions" / "conformance"

ACTOR = "ae_instance_1"
FACTOR = 10.0  # clock seconds per real second
WAIT = 10.0  # generous real-time bound for a graph to end (these are not performance tests)


def upstream(name: str) -> Path:
    return UPSTREAM / f"actionengine_{name}.graph.json"


def graph_of(name: str):
    return load_graph(upstream(name))


def at_clock(seconds: float) -> None:
    """Let ``seconds`` of clock time pass (real sleep of seconds / FACTOR)."""
    time.sleep(seconds / FACTOR)


class Harness:
    def __init__(self, engine: ActionEngine, rec: RecordingInstrument) -> None:
        self.engine = engine
        self.rec = rec

    def start(self, name: str, params: dict[str, Any] | None = None) -> str:
        return self.engine.start(graph_of(name), params)

    def run(self, name: str, params: dict[str, Any] | None = None) -> tuple[str, Result]:
        run = self.start(name, params)
        return run, self.engine.wait(run, timeout=WAIT)

    def order(self, run: str) -> list[str]:
        return self.rec.started(run)


@pytest.fixture
def h() -> Iterator[Harness]:
    rec = RecordingInstrument()
    with ActionEngine(
        ACTOR, actions=[ACTIONS], graphs=[UPSTREAM], clock=ScaledClock(FACTOR), instruments=[rec]
    ) as engine:
        yield Harness(engine, rec)


def node_json(snapshot: dict[str, Any], full_name: str) -> dict[str, Any]:
    for act in snapshot["actions"]:
        if f"{act['name']}_{act['instance_id']}" == full_name:
            return act
    raise AssertionError(f"{full_name} not in snapshot: {[a['name'] for a in snapshot['actions']]}")


def spy_runs(
    monkeypatch: pytest.MonkeyPatch, engine: ActionEngine, action: str
) -> list[tuple[str, int]]:
    """Record (node name, id(instance)) for every on_run of an action class, for this test only."""
    cls = engine.catalog.load_class(action)
    original = cls.on_run
    calls: list[tuple[str, int]] = []

    def on_run(self: Any) -> bool:
        calls.append((self.name, id(self)))
        return original(self)

    monkeypatch.setattr(cls, "on_run", on_run)
    return calls


# ================ semantics_test_1..9 (test_semantics.cpp)


def test_lifecycle_engine_constructs_and_shuts_down() -> None:
    engine = ActionEngine(ACTOR, actions=[ACTIONS], graphs=[UPSTREAM], clock=ScaledClock(FACTOR))
    engine.shutdown()
    engine.shutdown()  # idempotent


def test_semantics_1_simple_action(h: Harness) -> None:
    run, result = h.run("test_semantics_test_1")
    assert result is Result.TRUE
    assert h.order(run) == ["TaAddString_0"]
    assert h.engine.outcome(run).outputs == {"result": "Input A and Input B"}
    assert h.engine.outcome(run).state is GraphState.FINISHED


def test_semantics_2_simple_sequence(h: Harness) -> None:
    run, result = h.run("test_semantics_test_2")
    assert result is Result.TRUE
    assert h.order(run) == ["TaAddString_0", "TaCompareString_0"]


def test_semantics_3_simple_concurrency_join(h: Harness) -> None:
    run, result = h.run("test_semantics_test_3")
    assert result is Result.TRUE
    order = h.order(run)
    assert sorted(order[:2]) == ["TaAddString_0", "TaAddString_1"]
    assert order[2:] == ["TaAddString_2", "TaCompareString_0"]
    assert order.count("TaAddString_2") == 1


def test_semantics_4_simple_conditionals(h: Harness) -> None:
    run, result = h.run("test_semantics_test_4")
    assert result is Result.TRUE
    order = h.order(run)
    assert order == ["TaTriggerResult_0", "TaRelayString_0", "TaCompareString_1"]
    assert "TaRelayString_1" not in order


def test_semantics_5_invoke_stop(h: Harness) -> None:
    t0 = time.monotonic()
    run, result = h.run("test_semantics_test_5")
    assert result is Result.STOPPED
    assert sorted(h.order(run)) == ["TaTimer_0", "TaTimer_1"]
    # TaTimer_0 counts 3 clock-seconds before it stops TaTimer_1
    assert time.monotonic() - t0 >= 3.0 / FACTOR * 0.9


def test_semantics_6_simple_hierarchy(h: Harness) -> None:
    run, result = h.run("test_semantics_test_6")
    assert result is Result.TRUE
    assert h.order(run) == ["TaRelayString_0", "TaGenerateString_0", "TaCompareString_0"]
    sub = "semantics_test_6__TaGenerateString__0"
    assert sub in h.engine.running_graphs()
    assert h.order(sub) == ["TaAddString_0", "TaAddString_1"]
    assert h.engine.outcome(sub).result is Result.TRUE
    assert h.engine.outcome(sub).outputs == {"result": "A and B and C"}


def test_semantics_7_simple_reactive_behavior(h: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    ingests = spy_runs(monkeypatch, h.engine, "TaIngestResult")
    t0 = time.monotonic()
    run, result = h.run("test_semantics_test_7")
    assert result is Result.TRUE
    # three trigger events, 1 clock-second apart
    assert time.monotonic() - t0 >= 3.0 / FACTOR * 0.9
    order = h.order(run)
    assert order.count("TaIngestResult_0") == 3
    assert order[:2] == ["TaTriggerResultMulti_0", "TaIngestResult_0"]
    # the same instance ran three times (it counts its runs)
    assert len(ingests) == 3
    assert len({ident for _, ident in ingests}) == 1
    log = node_json(h.engine.graph_json(run), "TaIngestResult_0")["runtime"]["messages"]
    assert [m["message"] for m in log] == [
        "ingested result 3",
        "ingested result 2",
        "ingested result 1",
    ]


def test_semantics_8_messages(h: Harness) -> None:
    run, result = h.run("test_semantics_test_8")
    assert result is Result.TRUE
    snapshot = h.engine.graph_json(run)
    json.dumps(snapshot)  # JSON-ready
    messages = node_json(snapshot, "TaLogger_0")["runtime"]["messages"]
    texts = [m["message"] for m in messages]
    for k in (1, 2, 3):
        assert f"some message {k}" in texts
    assert texts == ["some message 3", "some message 2", "some message 1"]  # newest first
    for m in messages:
        assert type(m["timestamp"]) is int
        assert m["timestamp"] > 1_000_000_000_000  # milliseconds since the epoch
    stamps = [m["timestamp"] for m in messages]
    assert stamps == sorted(stamps, reverse=True)


def test_semantics_9_hierarchy_with_stop(h: Harness) -> None:
    run, result = h.run("test_semantics_test_9")
    assert result is Result.STOPPED
    assert sorted(h.order(run)) == ["TaTimer_0", "semantics_test_9_infinite_loop_0"]
    sub = "semantics_test_9__semantics_test_9_infinite_loop__0"
    assert sub in h.engine.running_graphs()
    assert h.engine.outcome(sub).result is Result.STOPPED
    loop = h.order(sub)
    # 3 clock-seconds of 0.5 s timers: several turns of the loop, strictly alternating
    assert len(loop) >= 4
    assert loop == [("TaTimer_0", "TaTimer_1")[i % 2] for i in range(len(loop))]


def test_semantics_9_infinite_loop_runs_until_stopped(h: Harness) -> None:
    run = h.start("test_semantics_test_9_infinite_loop")
    at_clock(2.2)
    assert h.engine.outcome(run).state is GraphState.RUNNING
    assert h.engine.stop(run, timeout=WAIT) is Result.STOPPED
    loop = h.order(run)
    assert len(loop) >= 3
    assert loop == [("TaTimer_0", "TaTimer_1")[i % 2] for i in range(len(loop))]


# ================================================================ ta_generate_string


def test_ta_generate_string_without_input_is_refused(h: Harness) -> None:
    with pytest.raises(GraphInputError, match="str_a"):
        h.start("test_ta_generate_string")
    assert "TaGenerateString" not in h.engine.running_graphs()


def test_ta_generate_string_with_input(h: Harness) -> None:
    run, result = h.run("test_ta_generate_string", {"str_a": "A"})
    assert run == "TaGenerateString"
    assert result is Result.TRUE
    assert h.engine.outcome(run).outputs == {"result": "A and B and C"}
    assert h.order(run) == ["TaAddString_0", "TaAddString_1"]


def test_ta_generate_string_by_indexed_name(h: Harness) -> None:
    run = h.engine.start("TaGenerateString", {"str_a": "x"})
    assert h.engine.wait(run, timeout=WAIT) is Result.TRUE
    assert h.engine.outcome(run).outputs == {"result": "x and B and C"}


# ================ external_changes graphs, unattended


@pytest.mark.parametrize(
    ("name", "expected", "order"),
    [
        ("test_external_changes_test_0", Result.TRUE, ["TaTimer_0"]),
        ("test_external_changes_test_1", Result.FALSE, ["TaTimer_0", "TaCompareNumber_0"]),
        ("test_external_changes_test_2_a", Result.FALSE, ["TaTimer_0", "TaCompareString_0"]),
        (
            "test_external_changes_test_2_b",
            Result.TRUE,
            ["TaTimer_0", "TaRelayString_0", "TaCompareString_0"],
        ),
        ("test_external_changes_test_3_a", Result.HALTED, ["TaRelayString_0", "TaTriggerResult_0"]),
        ("test_external_changes_test_3_b", Result.TRUE, ["TaRelayString_0", "TaTriggerResult_0"]),
        ("test_external_changes_test_3_c", Result.HALTED, ["TaTriggerResult_0"]),
        ("test_external_changes_test_4_a", Result.HALTED, ["TaRelayString_0"]),
        ("test_external_changes_test_4_b", Result.TRUE, ["TaRelayString_0", "TaRelayString_1"]),
    ],
)
def test_external_changes_graph_alone(
    h: Harness, name: str, expected: Result, order: list[str]
) -> None:
    run, result = h.run(name)
    assert result is expected
    assert h.order(run) == order
    state = {Result.HALTED: GraphState.HALTED}.get(expected, GraphState.FINISHED)
    assert h.engine.outcome(run).state is state


def test_external_changes_3_a_error_is_recorded(h: Harness) -> None:
    run, result = h.run("test_external_changes_test_3_a")
    assert result is Result.HALTED
    errors = h.engine.outcome(run).errors
    assert len(errors) == 1
    assert "on_error" in str(errors[0].__cause__)


# ================================================================ negative / non-executable files


def test_sequential_nav_missing_action_fails_at_start(h: Harness) -> None:
    graph = load_graph(UPSTREAM / "actionengine_ros2_example_sequential_nav.umrf.graph.json")
    t0 = time.monotonic()
    with pytest.raises(ActionNotFoundError, match="ExampleNavigate"):
        h.engine.start(graph)
    assert time.monotonic() - t0 < 2.0
    assert graph.name not in h.engine.running_graphs()


def test_multi_actor_graph_rejected_on_single_engine(h: Harness) -> None:
    graph = graph_of("test_engine_test_multi_actor")
    with pytest.raises(GraphDefinitionError) as info:
        h.engine.start(graph)
    message = str(info.value)
    for actor in ("Actor A", "Actor B", "Actor C"):
        assert actor in message
    assert graph.name not in h.engine.running_graphs()


def test_format_test_round_trip() -> None:
    raw = json.loads(upstream("test_format_test").read_text(encoding="utf-8"))
    assert graph_to_dict(parse_graph(raw)) == raw
    # and through the file loader too
    assert graph_to_dict(graph_of("test_format_test")) == raw


def test_unparseable_example_is_rejected() -> None:
    path = UPSTREAM / "actionengine_test_example_a_unparseable.json"
    with pytest.raises(GraphDefinitionError) as info:
        load_graph(path)
    message = str(info.value)
    # the numeric "state": 0 of the first action is the first problem found
    assert "state" in message
    assert "0" in message
    assert "actions[0]" in message


def test_every_current_format_graph_is_covered() -> None:
    """Guard: a new upstream graph file must get an expectation here."""
    covered = {
        "semantics_test_1",
        "semantics_test_2",
        "semantics_test_3",
        "semantics_test_4",
        "semantics_test_5",
        "semantics_test_6",
        "semantics_test_7",
        "semantics_test_8",
        "semantics_test_9",
        "semantics_test_9_infinite_loop",
        "ta_generate_string",
        "external_changes_test_0",
        "external_changes_test_1",
        "external_changes_test_2_a",
        "external_changes_test_2_b",
        "external_changes_test_3_a",
        "external_changes_test_3_b",
        "external_changes_test_3_c",
        "external_changes_test_4_a",
        "external_changes_test_4_b",
        "format_test",
        "engine_test_multi_actor",
    }
    found = {
        p.name.removeprefix("actionengine_test_").removesuffix(".graph.json")
        for p in UPSTREAM.glob("actionengine_test_*.graph.json")
    }
    assert found == covered


# ================================================================ test_external_changes.cpp


def test_external_stop(h: Harness) -> None:
    run = h.start("test_external_changes_test_0")
    at_clock(0.5)
    t0 = time.monotonic()
    result = h.engine.stop(run, timeout=WAIT)
    elapsed = time.monotonic() - t0
    assert result is Result.STOPPED
    assert h.engine.outcome(run).state is GraphState.STOPPED
    # cooperative: far below the 5 clock-second stop timeout (0.5 s real)
    assert elapsed < 0.3
    assert h.order(run) == ["TaTimer_0"]
    assert node_json(h.engine.graph_json(run), "TaTimer_0")["state"] == "FINISHED"


def test_external_pause_resume(h: Harness) -> None:
    run = h.start("test_external_changes_test_1")
    at_clock(0.5)
    h.engine.pause(run)
    # PAUSE_REQUESTED until TaTimer_0's on_pause has returned (on a worker)
    assert h.engine.outcome(run).state in (GraphState.PAUSE_REQUESTED, GraphState.PAUSED)
    at_clock(2.0)
    assert h.engine.outcome(run).state is GraphState.PAUSED
    assert h.order(run) == ["TaTimer_0"]  # nothing started while paused
    h.engine.resume(run)
    assert h.engine.wait(run, timeout=WAIT) is Result.TRUE  # final_count ~2.5 > 1.5
    assert h.order(run) == ["TaTimer_0", "TaCompareNumber_0"]


def test_external_modify_graph(h: Harness) -> None:
    run = h.start("test_external_changes_test_2_a")
    assert run == "external_changes_test_2"
    at_clock(0.5)
    h.engine.modify(run, graph_of("test_external_changes_test_2_b"))
    assert h.engine.wait(run, timeout=WAIT) is Result.TRUE
    assert h.order(run) == ["TaTimer_0", "TaRelayString_0", "TaCompareString_0"]


def test_external_modify_graph_and_set(h: Harness, monkeypatch: pytest.MonkeyPatch) -> None:
    relays = spy_runs(monkeypatch, h.engine, "TaRelayString")
    run = h.start("test_external_changes_test_3_a")
    assert run == "external_changes_test_3"
    assert h.engine.wait(run, timeout=WAIT) is Result.HALTED
    h.engine.modify(
        run, graph_of("test_external_changes_test_3_b"), continue_from="TaRelayString_0"
    )
    assert h.engine.wait(run, timeout=WAIT) is Result.TRUE
    assert h.order(run) == [
        "TaRelayString_0",
        "TaTriggerResult_0",
        "TaRelayString_0",
        "TaTriggerResult_0",
    ]
    # the relay kept its instance across the modification
    assert [name for name, _ in relays] == ["TaRelayString_0", "TaRelayString_0"]
    assert relays[0][1] == relays[1][1]


def test_external_halt_on_true(h: Harness) -> None:
    run, result = h.run("test_external_changes_test_3_c")
    assert result is Result.HALTED
    assert h.engine.outcome(run).state is GraphState.HALTED


def test_external_modify_graph_and_set_after(h: Harness) -> None:
    run = h.start("test_external_changes_test_4_a")
    assert run == "external_changes_test_4"
    assert h.engine.wait(run, timeout=WAIT) is Result.HALTED
    h.engine.modify(
        run, graph_of("test_external_changes_test_4_b"), continue_from="TaRelayString_1"
    )
    assert h.engine.wait(run, timeout=WAIT) is Result.TRUE
    # only the new action ran: TaRelayString_0 did not run again
    assert h.order(run) == ["TaRelayString_0", "TaRelayString_1"]
    assert h.engine.outcome(run).outputs == {"string_out": "Another random string"}
