from __future__ import annotations

import copy
import dataclasses
import pickle
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.core.documents import load_graph
from temoto.core.graph import UmrfGraph, parse_graph
from temoto.core.params import Parameter
from temoto.core.validation import Issue, ValidationReport, validate_graph
from temoto.errors import GraphDefinitionError

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
UPSTREAM = SHARED / "conformance" / "umrf" / "upstream"
needs_upstream = pytest.mark.skipif(
    not UPSTREAM.is_dir(), reason=f"upstream conformance data not found at {UPSTREAM}"
)
CURRENT_GRAPHS = sorted(UPSTREAM.glob("actionengine_*graph.json"))
FORMAT_TEST = "actionengine_test_format_test.graph.json"


# --- helpers ---------------------------------------------------------------------------------


def string(value: str | None = None, **extra: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"pvf_type": "string", **extra}
    if value is not None:
        out["pvf_value"] = value
    return out


def action(
    name: str,
    instance: int = 0,
    *,
    parents: Sequence[str | dict[str, Any]] = (),
    children: Sequence[str | dict[str, Any]] = (),
    inputs: dict[str, Any] | None = None,
    outputs: dict[str, Any] | None = None,
    type_: str = "sync",
) -> dict[str, Any]:
    """An action; parents/children given as "Name_i" strings or relation dicts."""
    out: dict[str, Any] = {"name": name, "instance_id": instance, "type": type_}
    if parents:
        out["parents"] = [rel(p) for p in parents]
    if children:
        out["children"] = [rel(c) for c in children]
    if inputs is not None:
        out["input_parameters"] = inputs
    if outputs is not None:
        out["output_parameters"] = outputs
    return out


def rel(spec: str | dict[str, Any]) -> dict[str, Any]:
    if isinstance(spec, dict):
        return spec
    name, _, inst = spec.rpartition("_")
    return {"name": name, "instance_id": int(inst)}


def graph(
    actions: list[dict[str, Any]],
    entry: list[Any] | None = None,
    exit_: list[Any] | None = None,
    **extra: Any,
) -> UmrfGraph:
    doc: dict[str, Any] = {
        "graph_name": "g",
        "actions": actions,
        "graph_entry": [rel(e) for e in (entry if entry is not None else ["A_0"])],
        "graph_exit": [rel(e) for e in (exit_ if exit_ is not None else ["B_0"])],
        **extra,
    }
    return parse_graph(doc)


def chain(**over: Any) -> list[dict[str, Any]]:
    """A_0 -> B_0, A outputs `out` (string), B takes `inp` via a remap."""
    a = action(
        "A",
        children=[{"name": "B", "remap": [{"from": "out", "to": "inp"}]}],
        outputs={"out": string()},
    )
    b = action("B", parents=["A_0"], inputs={"inp": string()})
    for act, changes in ((a, over.get("a", {})), (b, over.get("b", {}))):
        for key, value in changes.items():
            act[key] = [rel(r) for r in value] if key in ("parents", "children") else value
    return [a, b]


def errors(g: UmrfGraph, **kw: Any) -> list[Issue]:
    return list(validate_graph(g, **kw).errors)


def warnings(g: UmrfGraph, **kw: Any) -> list[Issue]:
    return list(validate_graph(g, **kw).warnings)


def only(issues: list[Issue]) -> Issue:
    assert len(issues) == 1, issues
    return issues[0]


def find(issues: list[Issue], phrase: str) -> Issue:
    hits = [i for i in issues if phrase in i.message]
    assert len(hits) == 1, (phrase, issues)
    return hits[0]


# --- report object ---------------------------------------------------------------------------


def test_issue_str_includes_path_only_when_present() -> None:
    assert str(Issue("actions[2].parents[0]", "bad")) == "actions[2].parents[0]: bad"
    assert str(Issue("", "bad")) == "bad"


def test_report_ok_and_raise_for_errors_without_errors_returns_none() -> None:
    report = ValidationReport("g", (), (Issue("", "w"),))
    assert report.ok
    report.raise_for_errors("f.json")  # does not raise


def test_raise_for_errors_lists_every_error_and_carries_first_path() -> None:
    report = ValidationReport("my graph", (Issue("actions[1]", "one"), Issue("", "two")), ())
    assert not report.ok
    with pytest.raises(GraphDefinitionError) as info:
        report.raise_for_errors("dir/g.graph.json")
    err = info.value
    lines = str(err).splitlines()
    assert lines[0] == "dir/g.graph.json: graph 'my graph' cannot run (2 errors):"
    assert lines[1].strip() == "actions[1]: one"
    assert lines[2].strip() == "two"
    assert err.path == "actions[1]"
    assert err.file == "dir/g.graph.json"
    clone = pickle.loads(pickle.dumps(err))
    assert str(clone) == str(err)
    assert clone.path == "actions[1]"


def test_raise_for_errors_singular_and_without_file() -> None:
    with pytest.raises(GraphDefinitionError) as info:
        ValidationReport("g", (Issue("", "x"),), ()).raise_for_errors()
    assert str(info.value).splitlines()[0] == "graph 'g' cannot run (1 error):"
    assert info.value.file is None


# --- conformance data ------------------------------------------------------------------------


@needs_upstream
def test_conformance_folder_holds_the_current_format_graphs() -> None:
    assert len(CURRENT_GRAPHS) == 23


@pytest.mark.parametrize("path", CURRENT_GRAPHS, ids=lambda p: p.name)
def test_upstream_graphs_validate(path: Path) -> None:
    report = validate_graph(load_graph(path))
    if path.name == FORMAT_TEST:
        return  # checked precisely below
    assert report.errors == (), report.errors
    assert report.graph == load_graph(path).name


@needs_upstream
def test_format_test_reports_its_one_sided_relation_exactly() -> None:
    report = validate_graph(load_graph(UPSTREAM / FORMAT_TEST))
    assert [i.path for i in report.errors] == ["actions[0].children[0]"]
    msg = report.errors[0].message
    assert "'action_0_0' lists 'action_3_0' as a child" in msg
    assert "does not list 'action_0_0' among its parents" in msg
    assert '{"name": "action_0", "instance_id": 0}' in msg
    with pytest.raises(GraphDefinitionError) as info:
        report.raise_for_errors(FORMAT_TEST)
    assert info.value.path == "actions[0].children[0]"


LEGACY_GRAPHS = [
    *sorted(UPSTREAM.glob("legacy_*.umrfg.json")),
    UPSTREAM / "legacy_gptparser_prompt_example_move_1.json",
]


@needs_upstream
@pytest.mark.parametrize("path", LEGACY_GRAPHS, ids=lambda p: p.name)
def test_converted_legacy_graphs_validate(path: Path) -> None:
    report = validate_graph(load_graph(path))
    assert report.errors == ()
    # the conversion note has no path; it is kept as a whole
    assert any(w.path == "" and "legacy" in w.message for w in report.warnings)


@needs_upstream
def test_generate_string_requires_its_external_input() -> None:
    g = load_graph(UPSTREAM / "actionengine_test_ta_generate_string.graph.json")
    issue = only(errors(g, supplied=set()))
    assert "'str_a'" in issue.message
    assert "was not supplied" in issue.message
    assert issue.path == "actions[0].input_parameters.str_a"
    assert validate_graph(g, supplied={"str_a"}).ok
    assert validate_graph(g).ok  # None: inputs not checked


@needs_upstream
def test_unknown_supplied_input_is_an_error_listing_the_real_ones() -> None:
    g = load_graph(UPSTREAM / "actionengine_test_ta_generate_string.graph.json")
    issue = only(errors(g, supplied={"str_a", "nope"}))
    assert issue.path == ""
    assert "unknown graph input 'nope'" in issue.message
    assert "'str_a'" in issue.message


@needs_upstream
def test_supplied_may_be_a_single_string() -> None:
    g = load_graph(UPSTREAM / "actionengine_test_ta_generate_string.graph.json")
    assert validate_graph(g, supplied="str_a").ok


def test_optional_graph_input_need_not_be_supplied() -> None:
    g = graph([action("A", inputs={"x": string(pvf_required=False)})], ["A_0"], ["A_0"])
    assert validate_graph(g, supplied=()).ok
    issue = only(errors(g, supplied=["y"]))
    assert "unknown graph input 'y'" in issue.message


def test_graph_without_inputs_names_none_in_unknown_input_message() -> None:
    g = graph([action("A")], ["A_0"], ["A_0"])
    assert "(the graph's inputs are: none)" in only(errors(g, supplied={"z"})).message


# --- relations -------------------------------------------------------------------------------


def test_valid_chain_has_no_issues() -> None:
    report = validate_graph(graph(chain()))
    assert report.errors == ()
    assert report.warnings == ()


def test_parent_naming_a_missing_action() -> None:
    acts = chain(b={"parents": [{"name": "A"}, {"name": "Nope", "instance_id": 3}]})
    issue = only(errors(graph(acts)))
    assert issue.path == "actions[1].parents[1]"
    assert "parent 'Nope_3' is not an action of this graph" in issue.message


def test_child_naming_a_missing_instance_suggests_existing_ones() -> None:
    acts = chain()
    acts[0]["children"].append({"name": "B", "instance_id": 7})
    issue = only(errors(graph(acts)))
    assert issue.path == "actions[0].children[1]"
    assert "child 'B_7' is not an action" in issue.message
    assert "'B' exists with instance_id 0" in issue.message


def test_graph_entry_written_as_a_parent_explains_it_is_implicit() -> None:
    acts = chain(a={"parents": [{"name": "graph_entry"}]})
    issue = only(errors(graph(acts)))
    assert issue.path == "actions[0].parents[0]"
    assert "implicit" in issue.message


def test_self_loop_as_parent_and_as_child() -> None:
    acts = chain(b={"parents": ["A_0", "B_0"], "children": [{"name": "B"}]})
    errs = errors(graph(acts))
    assert {i.path for i in errs} == {"actions[1].parents[1]", "actions[1].children[0]"}
    assert all("self-loop" in i.message for i in errs)


def test_child_without_back_reference_is_an_error_on_the_parent_side() -> None:
    acts = chain(b={"parents": []})
    issue = find(errors(graph(acts)), "does not list 'A_0' among its parents")
    assert issue.path == "actions[0].children[0]"
    assert "upstream crashes" in issue.message
    assert 'add {"name": "A", "instance_id": 0} to the parents of \'B_0\'' in issue.message


def test_parent_without_forward_reference_is_an_error_on_the_child_side() -> None:
    acts = [
        action("A", outputs={"inp": string()}),
        action("B", parents=["A_0"], inputs={"inp": string()}),
    ]
    issue = only(errors(graph(acts)))
    assert issue.path == "actions[1].parents[0]"
    assert "does not list 'B_0' among its children" in issue.message
    assert "never reach" in issue.message
    assert 'add {"name": "B", "instance_id": 0} to the children of \'A_0\'' in issue.message


def test_relation_listed_twice() -> None:
    acts = chain(b={"parents": ["A_0", {"name": "A", "required": False}]})
    acts[0]["children"].append({"name": "B"})
    errs = errors(graph(acts))
    assert {i.path for i in errs} == {"actions[1].parents[1]", "actions[0].children[1]"}
    assert all("listed twice" in i.message for i in errs)


# --- remaps and parameter transfer -----------------------------------------------------------


def test_remap_from_unknown_output() -> None:
    acts = chain()
    acts[0]["children"][0]["remap"] = [{"from": "outt", "to": "inp"}]
    errs = errors(graph(acts))
    issue = find(errs, "remap from 'outt'")
    assert issue.path == "actions[0].children[0].remap[0]"
    assert "'out'" in issue.message  # lists the real outputs
    # ... and therefore B's input can never be filled
    assert find(errs, "required input 'inp'").path == "actions[1].input_parameters.inp"


def test_remap_to_unknown_input() -> None:
    acts = chain()
    acts[0]["children"][0]["remap"] = [{"from": "out", "to": "in"}]
    errs = errors(graph(acts))
    issue = find(errs, "remap to 'in'")
    assert issue.path == "actions[0].children[0].remap[0]"
    assert "its inputs: 'inp'" in issue.message


def test_remap_between_different_types() -> None:
    acts = chain(b={"input_parameters": {"inp": {"pvf_type": "number"}}})
    errs = errors(graph(acts))
    issue = find(errs, "types that differ")
    assert issue.path == "actions[0].children[0].remap[0]"
    assert "'string'" in issue.message
    assert "'number'" in issue.message
    find(errs, "required input 'inp'")


def test_remap_into_non_updatable_literal_is_a_warning() -> None:
    acts = chain(b={"input_parameters": {"inp": string("x", pvf_updatable=False)}})
    report = validate_graph(graph(acts))
    assert report.ok
    issue = only(list(report.warnings))
    assert issue.path == "actions[0].children[0].remap[0]"
    assert "not updatable" in issue.message
    assert "never arrive" in issue.message


def test_required_non_updatable_input_without_literal_is_unfillable() -> None:
    acts = chain(b={"input_parameters": {"inp": string(pvf_updatable=False)}})
    issue = find(errors(graph(acts)), "required input 'inp'")
    assert issue.path == "actions[1].input_parameters.inp"
    assert "not updatable" in issue.message


def test_two_remaps_to_one_input_warn() -> None:
    acts = chain()
    acts[0]["output_parameters"]["out2"] = string()
    acts[0]["children"][0]["remap"].append({"from": "out2", "to": "inp"})
    issue = find(warnings(graph(acts)), "already maps")
    assert issue.path == "actions[0].children[0].remap[1]"


def test_required_input_nobody_fills_names_input_and_parents() -> None:
    acts = chain()
    acts[1]["input_parameters"]["other"] = string()
    issue = only(errors(graph(acts)))
    assert issue.path == "actions[1].input_parameters.other"
    assert "required input 'other' of 'B_0'" in issue.message
    assert "parents considered: 'A_0'" in issue.message


def test_nested_input_path_uses_dots() -> None:
    acts = chain()
    acts[1]["input_parameters"]["pose"] = {"x": {"pvf_type": "number"}}
    issue = only(errors(graph(acts)))
    assert issue.path == "actions[1].input_parameters.pose.x"
    assert "'pose::x'" in issue.message


def test_inputs_filled_by_literal_name_or_optional_are_fine() -> None:
    acts = chain()
    acts[0]["output_parameters"]["same"] = {"pvf_type": "number"}
    acts[1]["input_parameters"].update(
        {"lit": string("v"), "same": {"pvf_type": "number"}, "opt": string(pvf_required=False)}
    )
    assert validate_graph(graph(acts)).ok


def test_input_filled_by_any_of_several_parents() -> None:
    acts = [
        action("A", children=["C_0"], outputs={"x": string()}),
        action("B", children=["C_0"]),
        action("C", parents=["A_0", "B_0"], inputs={"x": string()}),
    ]
    assert validate_graph(graph(acts, ["A_0", "B_0"], ["C_0"])).ok


def test_same_name_with_other_type_warns_and_explains_unfilled_input() -> None:
    acts = chain()
    acts[0]["output_parameters"]["x"] = {"pvf_type": "number"}
    acts[1]["input_parameters"]["x"] = string()
    g = graph(acts)
    issue = find(warnings(g), "silently")
    assert issue.path == "actions[0].children[0]"
    assert "output 'x' of 'A_0' is 'number'" in issue.message
    err = only(errors(g))
    assert "a parent offers 'x' as 'number', not 'string'" in err.message


def test_entry_actions_inputs_are_graph_inputs_not_errors() -> None:
    g = graph([action("A", inputs={"x": string()})], ["A_0"], ["A_0"])
    assert validate_graph(g).ok


def test_allowed_values_on_plural_type_warns() -> None:
    acts = chain()
    acts[1]["input_parameters"]["v"] = {
        "pvf_type": "numbers",
        "pvf_value": [1],
        "pvf_allowed_values": [1, 2],
    }
    issue = only(warnings(graph(acts)))
    assert issue.path == "actions[1].input_parameters.v.pvf_allowed_values"
    assert "rejects every incoming value" in issue.message


def test_allowed_values_on_non_native_type_warns() -> None:
    # The parser refuses values for non-JSON types, so build such a graph in code.
    g = graph(chain())
    b = g.actions[1]
    handle = Parameter("h", "cir_pointer", required=False, allowed_values=("x",))
    b = dataclasses.replace(b, input_parameters={**b.input_parameters, "h": handle})
    g = dataclasses.replace(g, actions=(g.actions[0], b))
    issue = only(warnings(g))
    assert issue.path == "actions[1].input_parameters.h.pvf_allowed_values"
    assert "'cir_pointer'" in issue.message


# --- entry, exit, reachability, types, conditions --------------------------------------------


def test_empty_graph_entry_is_an_error() -> None:
    errs = errors(graph(chain(), entry=[]))
    assert find(errs, "no entry").path == "graph_entry"


def test_empty_graph_exit_is_only_a_warning() -> None:
    report = validate_graph(graph(chain(), exit_=[]))
    assert report.ok
    assert find(list(report.warnings), "runs until stopped").path == "graph_exit"


def test_entry_and_exit_naming_missing_actions_in_graphs_built_in_code() -> None:
    from temoto.core.umrf import ChildRelation, ParentRelation

    g = dataclasses.replace(
        graph(chain()), entry=(ChildRelation("Zed"),), exit=(ParentRelation("Zed", 2),)
    )
    errs = errors(g)
    assert find(errs, "entry action 'Zed_0'").path == "graph_entry[0]"
    assert find(errs, "exit action 'Zed_2'").path == "graph_exit[0]"


def test_unreachable_action_and_exit_warn() -> None:
    acts = chain()
    acts.append(action("C", inputs={"x": string()}))
    report = validate_graph(graph(acts, exit_=["B_0", "C_0"]))
    assert report.ok  # no "unfillable input" error for an action without parents
    issue = find(list(report.warnings), "'C_0' cannot be reached from graph_entry along")
    assert issue.path == "actions[2]"
    assert find(list(report.warnings), "exit action 'C_0'").path == "graph_exit[1]"


def test_one_sided_parent_does_not_make_an_action_reachable() -> None:
    acts = [action("A"), action("B", parents=["A_0"])]
    report = validate_graph(graph(acts))
    issue = find(list(report.warnings), "'B_0' cannot be reached from graph_entry along")
    assert issue.path == "actions[1]"


@pytest.mark.parametrize(
    ("type_", "phrase"), [("async", "behaves exactly like 'sync'"), ("fast", "unknown type")]
)
def test_action_type_warnings(type_: str, phrase: str) -> None:
    acts = chain(a={"type": type_})
    issue = only(warnings(graph(acts)))
    assert issue.path == "actions[0].type"
    assert phrase in issue.message


def test_spontaneous_is_fine() -> None:
    assert validate_graph(graph(chain(a={"type": "spontaneous"}))).warnings == ()


@pytest.mark.parametrize(
    ("condition", "phrase"),
    [
        ("on_true -> restart", "meaningless"),
        ("on_false -> stop", "cannot be stopped"),
        ("on_error -> pause", "cannot be paused"),
    ],
)
def test_exit_conditions_that_cannot_act_warn(condition: str, phrase: str) -> None:
    g = graph(chain(), exit_=[{"name": "B", "conditions": [condition]}])
    issue = only(warnings(g))
    assert issue.path == "graph_exit[0]"
    assert phrase in issue.message


def test_exit_conditions_run_ignore_bypass_are_fine() -> None:
    conds = ["on_true -> ignore", "on_false -> bypass", "on_stopped -> run"]
    assert warnings(graph(chain(), exit_=[{"name": "B", "conditions": conds}])) == []


def test_parser_warnings_become_issues_with_split_paths() -> None:
    acts = chain(a={"colour": "red"})
    g = graph(acts, frobnicate=1)
    ws = warnings(g)
    assert Issue("actions[0].colour", "unknown key ignored") in ws
    assert Issue("frobnicate", "unknown key ignored") in ws


def test_parser_warning_without_path_keeps_whole_text() -> None:
    g = dataclasses.replace(graph(chain()), warnings=("converted from the legacy format",))
    assert only(warnings(g)) == Issue("", "converted from the legacy format")


# --- cycles ----------------------------------------------------------------------------------


def loop(required_back: bool) -> UmrfGraph:
    """A_0 -> B_0 -> A_0, like semantics_test_9_infinite_loop."""
    acts = [
        action("A", parents=[{"name": "B", "required": required_back}], children=["B_0"]),
        action("B", parents=["A_0"], children=["A_0"]),
    ]
    return graph(acts)


def test_cycle_entered_through_a_non_required_relation_is_fine() -> None:
    assert validate_graph(loop(required_back=False)).ok


def test_cycle_of_required_relations_can_never_start() -> None:
    issue = only(errors(loop(required_back=True)))
    assert issue.path == "actions[0]"
    assert "'A_0', 'B_0' wait for each other" in issue.message
    assert '"required": false' in issue.message


def test_entry_action_inside_a_required_cycle_still_waits() -> None:
    acts = [
        action("A", parents=["B_0"], children=["B_0"]),
        action("B", parents=["A_0"], children=["A_0"]),
    ]
    issue = only(errors(graph(acts)))
    assert "wait for each other" in issue.message


def test_duplicate_actions_in_graphs_built_in_code() -> None:
    g = graph(chain())
    g = dataclasses.replace(g, actions=(*g.actions, g.actions[1]))
    issue = find(errors(g), "duplicate action 'B_0'")
    assert issue.path == "actions[2]"
    assert "also actions[1]" in issue.message


def test_required_cycle_outside_the_entry_is_found() -> None:
    acts = [
        action("A", children=["B_0"]),
        action("B", parents=["A_0", "C_0"], children=["C_0"]),
        action("C", parents=["B_0"], children=["B_0"]),
    ]
    issue = only(errors(graph(acts, exit_=["C_0"])))
    assert issue.path == "actions[1]"
    assert "'B_0', 'C_0'" in issue.message


def test_cycle_with_one_member_lacking_a_required_parent_inside_is_fine() -> None:
    acts = [
        action("A", children=["B_0"]),
        action("B", parents=["A_0", {"name": "D", "required": False}], children=["C_0"]),
        action("C", parents=["B_0"], children=["D_0"]),
        action("D", parents=["C_0"], children=["B_0"]),
    ]
    assert validate_graph(graph(acts, exit_=["D_0"])).ok


def test_many_disjoint_required_cycles_each_reported_once() -> None:
    acts = [action("E", children=[f"X_{k}" for k in range(0, 6, 2)])]
    for k in range(0, 6, 2):
        acts.append(action("X", k, parents=["E_0", f"X_{k + 1}"], children=[f"X_{k + 1}"]))
        acts.append(action("X", k + 1, parents=[f"X_{k}"], children=[f"X_{k}"]))
    errs = errors(graph(acts, ["E_0"], ["E_0"]))
    assert sorted(i.path for i in errs) == ["actions[1]", "actions[3]", "actions[5]"]


def test_action_started_only_by_the_action_it_waits_for_can_never_start() -> None:
    # No cycle of required relations: A requires B, but B's only (non-required) parent is A.
    acts = [
        action("A", parents=["B_0"], children=["B_0"]),
        action("B", parents=[{"name": "A", "required": False}], children=["A_0", "C_0"]),
        action("C", parents=["B_0"]),
    ]
    report = validate_graph(graph(acts, ["A_0"], ["C_0"]))
    issue = only(list(report.errors))  # C_0, stuck behind them, is not reported again
    assert issue.path == "actions[0]"
    assert "'A_0', 'B_0' can never start" in issue.message


def test_input_only_filled_by_a_later_action_can_never_start() -> None:
    # B's input x comes only from C, and C only runs after B: no relation cycle is required.
    acts = [
        action("A", children=["B_0"]),
        action(
            "B",
            parents=["A_0", {"name": "C", "required": False}],
            children=["C_0"],
            inputs={"x": string()},
        ),
        action("C", parents=["B_0"], children=["B_0"], outputs={"x": string()}),
    ]
    issue = only(errors(graph(acts, ["A_0"], ["C_0"])))
    assert issue.path == "actions[1]"
    assert "'B_0', 'C_0' can never start" in issue.message


def test_actions_behind_a_required_cycle_are_not_reported_again() -> None:
    acts = [
        action("A", parents=["B_0"], children=["B_0", "C_0"]),
        action("B", parents=["A_0"], children=["A_0"]),
        action("C", parents=["A_0"], children=["D_0"]),
        action("D", parents=["C_0"]),
    ]
    issue = only(errors(graph(acts, ["A_0"], ["D_0"])))
    assert "wait for each other" in issue.message


def test_waiting_for_an_unreachable_required_parent_warns() -> None:
    acts = chain()
    acts.append(action("U", children=["B_0"]))
    acts[1]["parents"].append(rel("U_0"))
    report = validate_graph(graph(acts))
    assert report.ok
    issue = find(list(report.warnings), "never runs: it waits for 'U_0'")
    assert issue.path == "actions[1]"
    assert "cannot be reached" in issue.message
    assert find(list(report.warnings), "'U_0' cannot be reached").path == "actions[2]"


def test_a_non_required_unreachable_parent_is_harmless() -> None:
    acts = chain()
    acts.append(action("U", children=["B_0"]))
    acts[1]["parents"].append({"name": "U", "required": False})
    ws = warnings(graph(acts))
    assert [w.path for w in ws] == ["actions[2]"]


# --- agreement with a simulated run -----------------------------------------------------------

PARAM_NAMES = ["a", "b", "c"]
TYPES = ["string", "number"]


@st.composite
def random_graphs(draw: st.DrawFn) -> dict[str, Any]:
    """Small graphs of actions N_0..N_n-1 with random two-sided relations and parameters."""
    n = draw(st.integers(1, 7))
    acts: list[dict[str, Any]] = []
    for k in range(n):
        outputs = {
            name: {"pvf_type": draw(st.sampled_from(TYPES))}
            for name in draw(st.lists(st.sampled_from(PARAM_NAMES), unique=True, max_size=2))
        }
        inputs: dict[str, Any] = {}
        for name in draw(st.lists(st.sampled_from(PARAM_NAMES), unique=True, max_size=2)):
            kind = draw(st.sampled_from(TYPES))
            leaf: dict[str, Any] = {"pvf_type": kind}
            if draw(st.integers(0, 3)) == 0:
                leaf["pvf_value"] = "v" if kind == "string" else 1
            if draw(st.integers(0, 4)) == 0:
                leaf["pvf_required"] = False
            if draw(st.integers(0, 5)) == 0:
                leaf["pvf_updatable"] = False
            inputs[name] = leaf
        acts.append(
            action("N", k, inputs=inputs, outputs=outputs) | {"parents": [], "children": []}
        )
    pairs = draw(
        st.lists(
            st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), unique=True, max_size=2 * n
        )
    )
    for p, c in pairs:
        if p == c:
            continue
        child: dict[str, Any] = {"name": "N", "instance_id": c}
        outs, ins = list(acts[p]["output_parameters"]), list(acts[c]["input_parameters"])
        if outs and ins and draw(st.booleans()):
            child["remap"] = [
                {"from": draw(st.sampled_from(outs)), "to": draw(st.sampled_from(ins))}
            ]
        acts[p]["children"].append(child)
        acts[c]["parents"].append({"name": "N", "instance_id": p, "required": draw(st.booleans())})
    entry = draw(st.lists(st.integers(0, n - 1), unique=True, min_size=1, max_size=n))
    exit_ = draw(st.lists(st.integers(0, n - 1), unique=True, max_size=2))
    return {
        "graph_name": "random",
        "actions": acts,
        "graph_entry": [{"name": "N", "instance_id": k} for k in entry],
        "graph_exit": [{"name": "N", "instance_id": k} for k in exit_],
    }


def simulate(g: UmrfGraph) -> set[int]:
    """Upstream propagation with every action returning true (default conditions), all graph
    inputs supplied; each action runs at most once. Returns the positions of actions that ran."""
    pos = {a.full_name: k for k, a in enumerate(g.actions)}
    acts = g.actions
    graph_inputs = g.signature().inputs
    entry = {pos[r.full_name] for r in g.entry}
    data = [{n for n, p in a.input_parameters.items() if p.has_value} for a in acts]
    received: list[set[str]] = [set() for _ in acts]
    ran: set[int] = set()
    queue: list[int] = []

    def ready(k: int) -> bool:
        a = acts[k]
        if any(p.required and n not in data[k] for n, p in a.input_parameters.items()):
            return False
        needed = {p.full_name for p in a.parents if p.required}
        if k in entry:
            needed.add("graph_entry")
        return needed <= received[k]

    for k in sorted(entry):
        received[k].add("graph_entry")
        data[k] |= {n for n in acts[k].input_parameters if n in graph_inputs}
        if ready(k):
            ran.add(k)
            queue.append(k)
    while queue:
        p = queue.pop(0)
        for rel_ in acts[p].children:
            c = pos[rel_.full_name]
            received[c].add(acts[p].full_name)
            renames = {r.from_: r.to for r in rel_.remap}
            for name, out in acts[p].output_parameters.items():
                inp = acts[c].input_parameters.get(renames.get(name, name))
                if inp is not None and inp.type == out.type and inp.updatable:
                    data[c].add(inp.name)
            if c not in ran and ready(c):
                ran.add(c)
                queue.append(c)
    return ran


@settings(max_examples=400, deadline=None, database=None)
@given(random_graphs())
def test_validator_agrees_with_a_simulated_run(doc: dict[str, Any]) -> None:
    g = parse_graph(doc)
    report = validate_graph(g)
    ran = simulate(g)
    never: set[int] = set()
    for issue in report.errors + report.warnings:
        whole = re.fullmatch(r"actions\[(\d+)\]", issue.path)
        if whole:
            never.add(int(whole.group(1)))
        elif issue.path.startswith("actions[") and "required input" in issue.message:
            never.add(int(issue.path[8 : issue.path.index("]")]))
    # What the validator says never runs does not run ...
    assert not (never & ran), (report, ran)
    # ... and when it has no complaint about an action, every action runs.
    if not report.errors and not never:
        assert ran == set(range(len(g.actions))), (report, ran)


# --- size ------------------------------------------------------------------------------------

N = 10_000


def big_chain(n: int, *, cycle: bool) -> dict[str, Any]:
    acts = []
    for k in range(n):
        parents: list[dict[str, Any]] = [{"name": "T", "instance_id": k - 1}] if k else []
        children = [{"name": "T", "instance_id": k + 1}] if k + 1 < n else []
        if cycle and k == 0:
            parents.append({"name": "T", "instance_id": n - 1, "required": False})
        if cycle and k == n - 1:
            children.append({"name": "T", "instance_id": 0})
        acts.append(
            {
                "name": "T",
                "instance_id": k,
                "type": "sync",
                "parents": parents,
                "children": children,
                "input_parameters": {"v": {"pvf_type": "number", "pvf_value": 1}},
                "output_parameters": {"v": {"pvf_type": "number"}},
            }
        )
    return {
        "graph_name": "big",
        "actions": acts,
        "graph_entry": [{"name": "T", "instance_id": 0}],
        "graph_exit": [{"name": "T", "instance_id": n - 1}],
    }


def test_ten_thousand_action_chain_validates() -> None:
    assert validate_graph(parse_graph(big_chain(N, cycle=False))).ok


def test_ten_thousand_action_cycle_validates() -> None:
    assert validate_graph(parse_graph(big_chain(N, cycle=True))).ok


def test_ten_thousand_action_required_cycle_is_one_error() -> None:
    doc = big_chain(N, cycle=True)
    doc["actions"][0]["parents"][-1]["required"] = True
    issue = only(errors(parse_graph(doc)))
    assert "and 9992 more" in issue.message


def test_validate_does_not_mutate_or_depend_on_document() -> None:
    doc = big_chain(5, cycle=True)
    before = copy.deepcopy(doc)
    g = parse_graph(doc)
    first = validate_graph(g)
    assert validate_graph(g) == first
    assert doc == before
