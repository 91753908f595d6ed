from __future__ import annotations

import copy
import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from temoto.core import legacy
from temoto.core.documents import graph_to_dict, load_graph, load_umrf
from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.states import GraphState, NodeState, Response, Result
from temoto.core.umrf import parse_umrf
from temoto.errors import GraphDefinitionError, UmrfError

UPSTREAM = Path(
    os.path.normpath(
        Path(__file__).resolve().parents[2] / ".." / "shared" / "conformance" / "umrf" / "upstream"
    )
)
if not UPSTREAM.is_dir():
    pytest.skip(f"upstream conformance data not found at {UPSTREAM}", allow_module_level=True)

INTRO = "converted from the legacy (pre-2023)"
RUN = {
    Result.TRUE: Response.RUN,
    Result.FALSE: Response.RUN,
    Result.STOPPED: Response.IGNORE,
    Result.ERROR: Response.IGNORE,
}
STOP = {
    Result.TRUE: Response.STOP,
    Result.FALSE: Response.STOP,
    Result.STOPPED: Response.IGNORE,
    Result.ERROR: Response.IGNORE,
}

LEGACY_FILES = sorted(p.name for p in UPSTREAM.glob("legacy_*"))
DESCRIPTOR_FILES = [n for n in LEGACY_FILES if n.endswith("umrf.json")]
GRAPH_FILES = [n for n in LEGACY_FILES if n not in DESCRIPTOR_FILES]


def graph(name: str) -> UmrfGraph:
    return load_graph(UPSTREAM / f"legacy_{name}")


def names(relations: Any) -> list[str]:
    return [r.full_name for r in relations]


def parent_of(g: UmrfGraph, child: str, parent: str) -> Any:
    (rel,) = [p for p in g.action(child).parents if p.full_name == parent]
    return rel


def minimal(**changes: Any) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "graph_name": "g",
        "umrf_actions": [
            {
                "name": "TaA",
                "id": 0,
                "effect": "synchronous",
                "children": [{"name": "TaB", "id": 0}],
            },
            {
                "name": "TaB",
                "id": 0,
                "effect": "synchronous",
                "parents": [{"name": "TaA", "id": 0, "required": True}],
            },
        ],
    }
    doc.update(changes)
    return doc


# --- every upstream legacy file ---------------------------------------------------------------


def test_the_upstream_folder_holds_fourteen_legacy_files() -> None:
    assert len(LEGACY_FILES) == 14
    assert len(GRAPH_FILES) == 10
    assert "legacy_gptparser_prompt_example_move_1.json" in GRAPH_FILES


@pytest.mark.parametrize("name", GRAPH_FILES)
def test_every_legacy_graph_file_converts_with_one_summary_warning_first(name: str) -> None:
    raw = json.loads((UPSTREAM / name).read_text(encoding="utf-8"))
    assert legacy.is_legacy_graph(raw)
    assert not legacy.is_legacy_umrf(raw)
    g = load_graph(UPSTREAM / name)
    assert g.warnings[0].startswith(INTRO)
    assert sum(w.startswith(INTRO) for w in g.warnings) == 1
    assert len(g.actions) == len(raw["umrf_actions"])
    assert g.entry
    assert all(a.type in ("sync", "async") for a in g.actions)


@pytest.mark.parametrize("name", DESCRIPTOR_FILES)
def test_every_legacy_descriptor_file_converts_with_one_summary_warning_first(name: str) -> None:
    raw = json.loads((UPSTREAM / name).read_text(encoding="utf-8"))
    assert legacy.is_legacy_umrf(raw)
    assert not legacy.is_legacy_graph(raw)
    warnings: list[str] = []
    action = load_umrf(UPSTREAM / name, warnings=warnings)
    assert action.name == raw["name"]
    assert action.type == {"synchronous": "sync", "asynchronous": "async"}[raw["effect"]]
    assert warnings[0].startswith(INTRO)
    assert sum(w.startswith(INTRO) for w in warnings) == 1
    assert "package_name" in warnings[0]


@pytest.mark.parametrize("name", GRAPH_FILES)
def test_a_converted_graph_survives_a_round_trip_through_graph_to_dict(name: str) -> None:
    g = load_graph(UPSTREAM / name)
    again = parse_graph(graph_to_dict(g))
    assert normalised(again) == normalised(g)
    assert graph_to_dict(again) == graph_to_dict(g)


def normalised(g: UmrfGraph) -> UmrfGraph:
    # graph_to_dict sorts actions and writes a missing state as UNINITIALIZED (upstream's form)
    actions = tuple(
        dataclasses.replace(a, state=a.state or NodeState.UNINITIALIZED)
        for a in sorted(g.actions, key=lambda a: a.full_name)
    )
    state = None if g.state is GraphState.UNINITIALIZED else g.state
    return dataclasses.replace(g, actions=actions, state=state, source=None, warnings=())


# --- specific graphs --------------------------------------------------------------------------


def test_the_sequence_demo_enters_at_the_first_and_exits_at_the_last_waypoint() -> None:
    g = graph("umrfdemos_navigation_demo_sequence.umrfg.json")
    assert names(g.entry) == ["TaNavigateRobot_0"]
    assert names(g.exit) == ["TaNavigateRobot_2"]
    assert g.exit[0].required
    assert dict(g.exit[0].conditions) == RUN
    assert g.state is GraphState.UNINITIALIZED
    summary = g.warnings[0]
    assert "execute_first -> graph_entry (TaNavigateRobot_0)" in summary
    assert "graph_exit = synchronous actions without children (TaNavigateRobot_2)" in summary
    assert "synchronous -> sync \u00d73" in summary
    assert "graph_state 0 -> UNINITIALIZED" in summary
    assert "dropped keys: package_name" in summary
    assert "stop_when_received" not in summary


def test_the_cycle_demo_has_no_exit_and_enters_at_the_execute_first_action() -> None:
    g = graph("umrfdemos_navigation_demo_cycle.umrfg.json")
    assert g.exit == ()
    assert "TaNavigateRobot_0" in names(g.entry)
    assert "runs until stopped" in g.warnings[0]
    assert not parent_of(g, "TaNavigateRobot_0", "TaNavigateRobot_2").required


def test_the_concurrent_demo_stops_the_navigation_when_the_timer_ends() -> None:
    g = graph("umrfdemos_navigation_demo_concurrent.umrfg.json")
    assert names(g.entry) == ["TaCountdownTimer_0", "TaNavigateRobot_0"]
    for i in range(3):
        rel = parent_of(g, f"TaNavigateRobot_{i}", "TaCountdownTimer_0")
        assert rel.response(Result.TRUE) is Response.STOP
        assert rel.response(Result.FALSE) is Response.STOP
        assert dict(rel.conditions) == STOP
        assert not rel.required
    assert dict(parent_of(g, "TaNavigateRobot_1", "TaNavigateRobot_0").conditions) == RUN
    assert (
        "stop_when_received -> 'on_true -> stop', 'on_false -> stop' (3 relations"
        in (g.warnings[0])
    )


def test_the_cargo_demo_routes_by_one_element_allowed_values() -> None:
    g = graph("umrfdemos_cargo_delivery.umrfg.json")
    expected = {
        "TaStateCharge_0": "state_charge",
        "TaStateNavigate_0": "state_navigate",
        "TaStatePickup_0": "state_pickup",
        "TaStateDropoff_0": "state_dropoff",
    }
    for node, value in expected.items():
        action = g.action(node)
        assert action.input_parameters["state"].allowed_values == (value,)
        assert action.type == "sync"
    assert g.action("TaStateDispatcher_0").type == "async"
    assert g.action("TaStateInitialize_0").type == "async"
    assert names(g.entry) == ["TaStateInitialize_0"]
    assert g.exit == ()
    assert "single pvf_allowed_values -> one-element array (4 parameters)" in g.warnings[0]


def test_the_loop_example_joins_two_non_required_parents() -> None:
    g = graph("actionengine_example_1_loop.umrfg.json")
    parents = g.action("TaExample1_1").parents
    assert names(parents) == ["TaExample1_0", "TaExample1_2"]
    assert not any(p.required for p in parents)
    assert names(g.entry) == ["TaExample1_0"]
    assert g.state is GraphState.INITIALIZED
    assert "distance::amount" in g.action("TaExample1_0").input_parameters


def test_the_gpt_shallow_example_starts_at_root_and_becomes_sync() -> None:
    g = graph("gptparser_prompt_example_go_wait_return.umrfg.json")
    assert names(g.entry) == ["Root_0"]
    assert names(g.exit) == ["Navigate_1"]
    assert all(a.type == "sync" for a in g.actions)
    assert all(p.required for a in g.actions for p in a.parents)
    assert "no effect -> type sync" in g.warnings[0]
    assert "missing required -> true (3 relations)" in g.warnings[0]


def test_the_gpt_single_action_example_is_entry_and_exit() -> None:
    g = graph("gptparser_prompt_example_move_1.json")
    assert names(g.entry) == names(g.exit) == ["navigate_0"]
    assert "missing id -> instance_id 0 (1 action)" in g.warnings[0]
    assert "single action" in g.warnings[0]


def test_the_shared_graph_demo_keeps_its_actors() -> None:
    g = graph("sharedgraphdemo_shared_graph_test_1_multi_actor.umrfg.json")
    assert [a.actor for a in g.actions] == ["actor_1", "actor_2", "actor_1"]
    assert g.actors == {"actor_1", "actor_2"}
    assert "stop_when_received (false)" in g.warnings[0]


def test_the_transportation_demo_waits_for_two_required_parents() -> None:
    g = graph("architecturedemos_demo3_transportation_mission.umrfg.json")
    parents = g.action("TaXarmDropObject_0").parents
    assert names(parents) == ["TaInitializeRobot_0", "TaNavigationGoal_0"]
    assert all(p.required for p in parents)
    assert names(g.entry) == ["TaInitializeRobot_0", "TaNavigationGoal_0"]
    assert names(g.exit) == ["TaNavigationGoal_1"]


def test_the_robotont_tutorial_keeps_numeric_node_state_zero_as_uninitialized() -> None:
    g = graph("tutorials_robotont_sim_1_initialize.umrfg.json")
    assert all(a.state is NodeState.UNINITIALIZED for a in g.actions)
    assert all(a.type == "async" for a in g.actions)
    assert g.exit == ()


# --- conversion rules on small documents ------------------------------------------------------


def test_the_summary_mentions_only_what_occurred() -> None:
    g = legacy.convert_graph(minimal())
    (summary,) = g.warnings
    assert summary == (
        "converted from the legacy (pre-2023) UMRF format: umrf_actions -> actions; "
        "id -> instance_id (2 actions, 2 relations); effect -> type (synchronous -> sync \u00d72); "
        "parent relations -> 'on_true -> run', 'on_false -> run', 'on_stopped -> ignore', "
        "'on_error -> ignore' (1 relation; legacy children started only on a normal return); "
        "graph_entry = actions without parents (TaA_0); "
        "graph_exit = synchronous actions without children (TaB_0)"
    )


def test_a_child_declared_on_the_parent_only_gets_a_required_parent_relation() -> None:
    doc = minimal()
    del doc["umrf_actions"][1]["parents"]
    g = legacy.convert_graph(doc)
    rel = parent_of(g, "TaB_0", "TaA_0")
    assert rel.required
    assert dict(rel.conditions) == RUN
    assert "added missing parent relations, required (TaA_0 -> TaB_0)" in g.warnings[0]
    assert names(g.entry) == ["TaA_0"]


def test_a_parent_declared_on_the_child_only_gets_a_child_relation() -> None:
    doc = minimal()
    del doc["umrf_actions"][0]["children"]
    g = legacy.convert_graph(doc)
    assert names(g.action("TaA_0").children) == ["TaB_0"]
    assert "added missing child relations (TaA_0 -> TaB_0)" in g.warnings[0]
    assert names(g.exit) == ["TaB_0"]


def test_numeric_graph_states_follow_the_legacy_enum() -> None:
    expected = [
        "UNINITIALIZED",
        "INITIALIZED",
        "RUNNING",
        "STOPPING",
        "STOPPED",
        "FINISHED",
        "ERROR",
    ]
    for number, name in enumerate(expected):
        g = legacy.convert_graph(minimal(graph_state=number))
        assert g.state is GraphState(name)
        assert f"graph_state {number} -> {name}" in g.warnings[0]


def test_unknown_numeric_states_are_dropped_with_a_note() -> None:
    doc = minimal(graph_state=42)
    doc["umrf_actions"][0]["state"] = 3
    g = legacy.convert_graph(doc)
    assert g.state is GraphState.UNINITIALIZED
    assert g.action("TaA_0").state is NodeState.UNINITIALIZED
    assert "graph_state 42 dropped" in g.warnings[0]
    assert "state 3 dropped" in g.warnings[0]


def test_string_states_of_a_half_converted_document_are_kept() -> None:
    doc = minimal(graph_state="RUNNING")
    doc["umrf_actions"][0]["state"] = "FINISHED"
    g = legacy.convert_graph(doc)
    assert g.state is GraphState.RUNNING
    assert g.action("TaA_0").state is NodeState.FINISHED


def test_legacy_parameter_leaves_are_rewritten() -> None:
    doc = minimal()
    doc["umrf_actions"][0]["input_parameters"] = {
        "pose": {
            "x": {
                "pvf_type": "number",
                "pvf_value": 1,
                "pvf_example": "2.0",
                "pvf_required": "false",
                "pvf_allowed_values": 1,
            }
        },
    }
    g = legacy.convert_graph(doc)
    param = g.action("TaA_0").input_parameters["pose::x"]
    assert param.allowed_values == (1.0,)
    assert param.required is False
    assert "pvf_example dropped (1 parameter)" in g.warnings[0]
    assert "'true'/'false' strings -> booleans" in g.warnings[0]


def test_an_all_asynchronous_graph_has_an_empty_exit() -> None:
    doc = minimal()
    for action in doc["umrf_actions"]:
        action["effect"] = "asynchronous"
    g = legacy.convert_graph(doc)
    assert g.exit == ()
    assert "graph_exit = []" in g.warnings[0]


def test_an_execute_first_action_with_required_parents_is_pointed_out() -> None:
    doc = minimal()
    doc["umrf_actions"][1]["execute_first"] = True
    g = legacy.convert_graph(doc)
    assert names(g.entry) == ["TaA_0", "TaB_0"]
    assert (
        "execute_first actions with required parents start only after those parents (TaB_0)"
        in (g.warnings[0])
    )


def test_unknown_keys_are_warned_with_legacy_paths() -> None:
    doc = minimal()
    doc["umrf_actions"][1]["condition"] = "always->run"
    g = legacy.convert_graph(doc)
    assert g.warnings[1:] == ("umrf_actions[1].condition: unknown key ignored",)


def test_an_unknown_effect_string_is_kept_as_the_type() -> None:
    doc = minimal()
    doc["umrf_actions"][1]["effect"] = "spontaneous"
    g = legacy.convert_graph(doc)
    assert g.action("TaB_0").spontaneous
    assert "unknown effect kept as type (TaB_0: 'spontaneous')" in g.warnings[0]


def test_the_converter_does_not_modify_its_input() -> None:
    doc = minimal()
    doc["umrf_actions"][1]["input_parameters"] = {
        "s": {"pvf_type": "string", "pvf_allowed_values": "a"}
    }
    del doc["umrf_actions"][1]["parents"]
    before = copy.deepcopy(doc)
    legacy.convert_graph(doc)
    assert doc == before


def test_a_legacy_descriptor_converts_to_a_current_format_dict() -> None:
    warnings: list[str] = []
    raw = {
        "name": "TaX",
        "package_name": "ta_x",
        "notation": "x",
        "effect": "asynchronous",
        "input_parameters": {"a": {"pvf_type": "string", "pvf_example": "hi"}},
    }
    converted = legacy.convert_umrf(raw, file="umrf.json", warnings=warnings)
    assert converted == {
        "name": "TaX",
        "instance_id": 0,
        "type": "async",
        "input_parameters": {"a": {"pvf_type": "string"}},
    }
    assert parse_umrf(converted).type == "async"
    (summary,) = warnings
    assert summary.startswith(INTRO)
    assert "asynchronous -> async" in summary
    assert "dropped keys: package_name, notation" in summary
    assert "instance_id" not in summary


def test_a_descriptor_without_effect_becomes_sync() -> None:
    warnings: list[str] = []
    converted = legacy.convert_umrf({"name": "TaX", "package_name": "ta_x"}, warnings=warnings)
    assert converted["type"] == "sync"
    assert "no effect -> type sync (TaX_0)" in warnings[0]


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        ({"umrf_actions": []}, True),
        ({"umrf_actions": [], "actions": []}, False),
        ({"actions": []}, False),
        ([], False),
        ("umrf_actions", False),
    ],
)
def test_is_legacy_graph_wants_umrf_actions_without_actions(raw: object, expected: bool) -> None:
    assert legacy.is_legacy_graph(raw) is expected


@pytest.mark.parametrize(
    ("raw", "expected"),
    [
        ({"name": "A", "effect": "synchronous"}, True),
        ({"name": "A", "package_name": "a"}, True),
        ({"name": "A", "type": "sync", "effect": "synchronous"}, False),
        ({"name": "A"}, False),
        ({"umrf_actions": [], "effect": "synchronous"}, False),
        ({"actions": [], "package_name": "a"}, False),
        (None, False),
    ],
)
def test_is_legacy_umrf_recognises_descriptors(raw: object, expected: bool) -> None:
    assert legacy.is_legacy_umrf(raw) is expected


# --- malformed input --------------------------------------------------------------------------


def action_change(index: int, **changes: Any) -> dict[str, Any]:
    doc = minimal()
    doc["umrf_actions"][index].update(changes)
    return doc


def relation_change(**changes: Any) -> dict[str, Any]:
    doc = minimal()
    doc["umrf_actions"][1]["parents"][0].update(changes)
    return doc


MALFORMED = [
    pytest.param({"graph_name": "g", "umrf_actions": 5}, "umrf_actions", id="actions-not-array"),
    pytest.param({"graph_name": "g", "umrf_actions": []}, "umrf_actions", id="no-actions"),
    pytest.param({"graph_name": "g", "umrf_actions": [3]}, "umrf_actions[0]", id="action-number"),
    pytest.param(action_change(1, name=7), "umrf_actions[1].name", id="name-number"),
    pytest.param(action_change(1, name=""), "umrf_actions[1].name", id="name-empty"),
    pytest.param(action_change(0, id="x"), "umrf_actions[0].id", id="id-string"),
    pytest.param(action_change(0, id=-1), "umrf_actions[0].id", id="id-negative"),
    pytest.param(action_change(0, id=1.5), "umrf_actions[0].id", id="id-fraction"),
    pytest.param(action_change(0, id=True), "umrf_actions[0].id", id="id-bool"),
    pytest.param(action_change(0, effect=5), "umrf_actions[0].effect", id="effect-number"),
    pytest.param(action_change(0, effect=""), "umrf_actions[0].effect", id="effect-empty"),
    pytest.param(
        action_change(0, execute_first="yes"),
        "umrf_actions[0].execute_first",
        id="execute-first-string",
    ),
    pytest.param(action_change(1, parents="x"), "umrf_actions[1].parents", id="parents-string"),
    pytest.param(action_change(0, children={}), "umrf_actions[0].children", id="children-object"),
    pytest.param(action_change(1, parents=[4]), "umrf_actions[1].parents[0]", id="relation-number"),
    pytest.param(
        action_change(1, parents=[{"id": 0}]),
        "umrf_actions[1].parents[0]",
        id="relation-without-name",
    ),
    pytest.param(relation_change(id="0"), "umrf_actions[1].parents[0].id", id="relation-id"),
    pytest.param(
        relation_change(stop_when_received="yes"),
        "umrf_actions[1].parents[0].stop_when_received",
        id="stop-when-received",
    ),
    pytest.param(
        relation_change(required="true"),
        "umrf_actions[1].parents[0].required",
        id="required-string",
    ),
    pytest.param(
        relation_change(name="TaMissing"), "umrf_actions[1].parents[0]", id="unknown-parent"
    ),
    pytest.param(
        action_change(0, children=[{"name": "TaB", "id": 9}]),
        "umrf_actions[0].children[0]",
        id="unknown-child",
    ),
    pytest.param(action_change(1, name="TaA"), "umrf_actions[1]", id="duplicate-action"),
    pytest.param(action_change(0, id=0, instance_id=1), "umrf_actions[0]", id="id-conflict"),
    pytest.param(action_change(0, type="sync"), "umrf_actions[0]", id="effect-and-type"),
    pytest.param(
        action_change(0, parents=[{"name": "TaB", "id": 0}]), "umrf_actions", id="no-root"
    ),
    pytest.param(
        action_change(0, input_parameters={"n": {"pvf_type": "number", "pvf_value": "one"}}),
        "umrf_actions[0].input_parameters.n.pvf_value",
        id="parameter-value",
    ),
    pytest.param(
        action_change(0, input_parameters=[]),
        "umrf_actions[0].input_parameters",
        id="parameters-array",
    ),
    pytest.param(
        action_change(
            0, input_parameters={"s": {"pvf_type": "string", "pvf_allowed_values": None}}
        ),
        "umrf_actions[0].input_parameters.s.pvf_allowed_values",
        id="allowed-null",
    ),
    pytest.param(action_change(0, state="BORED"), "umrf_actions[0].state", id="state-string"),
    pytest.param(action_change(0, state=None), "umrf_actions[0].state", id="state-null"),
    pytest.param(action_change(0, actor=3), "umrf_actions[0].actor", id="actor-number"),
    pytest.param(minimal(graph_state=True), "graph_state", id="graph-state-bool"),
    pytest.param(minimal(graph_name=None), "graph_name", id="graph-name-null"),
    pytest.param({"umrf_actions": [{"name": "A"}]}, "graph_name", id="graph-name-missing"),
]


@pytest.mark.parametrize(("raw", "path"), MALFORMED)
def test_malformed_legacy_graphs_fail_with_the_legacy_key_path(raw: Any, path: str) -> None:
    with pytest.raises(GraphDefinitionError) as info:
        legacy.convert_graph(raw, file="old.umrfg.json")
    err = info.value
    assert err.file == "old.umrfg.json"
    assert path in str(err)
    assert str(err).startswith("old.umrfg.json: ")


def test_a_malformed_legacy_file_names_the_file_and_path(tmp_path: Path) -> None:
    file = tmp_path / "broken.umrfg.json"
    file.write_text(json.dumps(action_change(0, id="zero")), encoding="utf-8")
    with pytest.raises(GraphDefinitionError, match=r"broken\.umrfg\.json: umrf_actions\[0\]\.id"):
        load_graph(file)


@pytest.mark.parametrize(
    "raw",
    [
        5,
        None,
        "text",
        [],
        {"graph_name": "g"},
        {"graph_name": "g", "umrf_actions": [], "actions": []},
    ],
)
def test_convert_graph_rejects_documents_that_are_not_legacy_graphs(raw: object) -> None:
    with pytest.raises(GraphDefinitionError):
        legacy.convert_graph(raw)


@pytest.mark.parametrize(
    ("raw", "path"),
    [
        pytest.param(5, "", id="not-object"),
        pytest.param({"name": "A", "effect": 1}, "effect", id="effect-number"),
        pytest.param({"effect": "synchronous"}, "name", id="no-name"),
        pytest.param(
            {"name": "A", "effect": "synchronous", "parents": [{"name": "B", "required": 1}]},
            "parents[0].required",
            id="relation-required",
        ),
        pytest.param(
            {"name": "A", "package_name": "a", "execute_first": "no"},
            "execute_first",
            id="execute-first",
        ),
    ],
)
def test_malformed_legacy_descriptors_fail_with_umrf_error(raw: object, path: str) -> None:
    with pytest.raises(UmrfError) as info:
        legacy.convert_umrf(raw, file="umrf.json")
    assert path in str(info.value)
    assert info.value.file == "umrf.json"


def test_a_legacy_descriptor_with_a_bad_value_fails_in_load_umrf(tmp_path: Path) -> None:
    file = tmp_path / "umrf.json"
    file.write_text(
        json.dumps(
            {
                "name": "TaX",
                "package_name": "ta_x",
                "effect": "synchronous",
                "input_parameters": {"n": {"pvf_type": "number", "pvf_value": "x"}},
            }
        ),
        encoding="utf-8",
    )
    with pytest.raises(UmrfError, match=r"input_parameters\.n\.pvf_value"):
        load_umrf(file)


# --- nothing but GraphDefinitionError, whatever the input -------------------------------------

JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-3, 3)
    | st.floats(allow_nan=False)
    | st.sampled_from(["", "x", "TaA", "synchronous", "asynchronous", "true", "RUNNING"]),
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.dictionaries(
            st.sampled_from(
                [
                    "name",
                    "id",
                    "effect",
                    "parents",
                    "children",
                    "required",
                    "stop_when_received",
                    "execute_first",
                    "input_parameters",
                    "pvf_type",
                    "pvf_value",
                    "pvf_allowed_values",
                    "state",
                    "x",
                ]
            ),
            inner,
            max_size=5,
        )
    ),
    max_leaves=20,
)


@st.composite
def mutated_documents(draw: st.DrawFn) -> dict[str, Any]:
    doc = minimal()
    target: Any = doc
    path = draw(st.lists(st.integers(0, 6), max_size=4))
    for step in path:
        if isinstance(target, dict) and target:
            key = sorted(target)[step % len(target)]
            if not isinstance(target[key], dict | list):
                break
            target = target[key]
        elif isinstance(target, list) and target:
            target = target[step % len(target)]
        else:
            break
    if isinstance(target, dict):
        target[
            draw(
                st.sampled_from(
                    [
                        "name",
                        "id",
                        "effect",
                        "parents",
                        "children",
                        "required",
                        "stop_when_received",
                        "execute_first",
                        "state",
                        "input_parameters",
                        "graph_state",
                        "umrf_actions",
                    ]
                )
            )
        ] = draw(JSON)
    elif isinstance(target, list):
        target.append(draw(JSON))
    return doc


def convert_or_error(doc: Any) -> UmrfGraph | GraphDefinitionError:
    try:
        return legacy.convert_graph(doc, file="f.json")
    except GraphDefinitionError as err:
        return err


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated_documents())
def test_mutated_legacy_graphs_convert_or_fail_with_graph_definition_error(doc: Any) -> None:
    result = convert_or_error(doc)
    if isinstance(result, GraphDefinitionError):
        assert result.file == "f.json"
    else:
        assert result.warnings[0].startswith(INTRO)


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from(["graph_name", "umrf_actions", "graph_state", "x"]), JSON))
def test_random_documents_never_crash_the_converter(doc: dict[str, Any]) -> None:
    doc.setdefault("umrf_actions", [])
    assert isinstance(convert_or_error(doc), UmrfGraph | GraphDefinitionError)
