"""temoto.build: graphs built in Python are the graphs their JSON is, and run as such."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from temoto import (
    Action,
    ActionEngine,
    GraphBuilder,
    Param,
    Result,
    action,
    branch,
    catalog,
    graph,
    load_graph,
    node,
    parallel,
    parse_graph,
    sequence,
)
from temoto.build import description_of, graph_document
from temoto.core.catalog import ActionCatalog
from temoto.errors import ActionNotFoundError, GraphDefinitionError, UmrfError
from temoto.testing import Outcome, Script

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "examples" / "umrf-guide"
WAIT = 30.0


@pytest.fixture(scope="module")
def guide() -> ActionCatalog:
    return ActionCatalog([GUIDE / "actions"], use_entry_points=False)


def same_as_file(built: Any, file: str) -> None:
    expected = load_graph(GUIDE / "graphs" / file)
    assert built == expected


# ================================================================ the same graphs as the JSON


def test_sequence_with_a_remap_is_the_guide_s_remap_graph(guide: ActionCatalog) -> None:
    desc = load_graph(GUIDE / "graphs" / "02_remap.graph.json").description
    built = graph(
        node("Add", a=2, b=3, remap={"sum": "a"}),
        node("Add", b=10),
        name="remap",
        description=desc,
        catalog=guide,
    )
    same_as_file(built, "02_remap.graph.json")
    # the document it is parsed from, through JSON text, is that graph too
    document = graph_document(
        node("Add", a=2, b=3, remap={"sum": "a"}),
        node("Add", b=10),
        name="remap",
        description=desc,
        catalog=guide,
    )
    assert parse_graph(json.loads(json.dumps(document))) == built


def test_branch_is_the_guide_s_branch_graph(guide: ActionCatalog) -> None:
    desc = load_graph(GUIDE / "graphs" / "03_branch.graph.json").description
    built = graph(
        branch(
            node("AtLeast", limit=10),
            on_true=node("Say", text="big"),
            on_false=node("Say", text="small"),
        ),
        name="branch",
        description=desc,
        catalog=guide,
    )
    same_as_file(built, "03_branch.graph.json")


def test_parallel_then_join_is_the_guide_s_join_graph(guide: ActionCatalog) -> None:
    desc = load_graph(GUIDE / "graphs" / "04_join.graph.json").description
    built = graph(
        parallel(
            node("Add", a=1, b=2, remap={"sum": "a"}), node("Add", a=3, b=4, remap={"sum": "b"})
        ),
        "Add",
        name="join",
        description=desc,
        catalog=guide,
    )
    same_as_file(built, "04_join.graph.json")


def test_graph_builder_writes_the_guide_s_recover_graph(guide: ActionCatalog) -> None:
    desc = load_graph(GUIDE / "graphs" / "07_recover.graph.json").description
    g = GraphBuilder("recover", description=desc, catalog=guide)
    divide = g.add("Divide", a=1, b=0)
    say = g.add("Say", {"text": "no quotient: carrying on"})
    g.link(divide, say, "on_error -> run", "on_true -> ignore", "on_false -> ignore")
    g.entry(divide)
    g.exit(say)
    same_as_file(g.build(), "07_recover.graph.json")


@action(inputs={"a": float, "b": float}, outputs={"sum": float})
def add(a: float, b: float) -> dict[str, float]:
    return {"sum": a + b}


def test_decorated_actions_give_the_graph_their_description_files_give() -> None:
    desc = load_graph(GUIDE / "graphs" / "02_remap.graph.json").description
    assert description_of(add).name == "Add"  # the function's name, in CamelCase
    built = graph(node(add, a=2, b=3, remap={"sum": "a"}), node(add, b=10), name="remap")
    with pytest.raises(AssertionError):  # the description differs: the comparison can fail
        same_as_file(built, "02_remap.graph.json")
    same_as_file(
        graph(
            node(add, a=2, b=3, remap={"sum": "a"}),
            node(add, b=10),
            name="remap",
            description=desc,
        ),
        "02_remap.graph.json",
    )


# ================================================================ running what was built


def test_the_example_prints_the_result() -> None:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "python_api.py")],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "{'text': 'HELLO!'}\n"
    text = (ROOT / "examples" / "python_api.py").read_text()
    assert sum(1 for line in text.splitlines() if line.strip()) <= 12
    # the README's quick start and docs/python-api.md show this very file
    for doc in ("README.md", "docs/python-api.md"):
        assert f"```python\n{text}```" in (ROOT / doc).read_text(), doc


def test_join_runs_with_function_actions() -> None:
    g = graph(
        parallel(node(add, a=1, b=2, remap={"sum": "a"}), node(add, a=3, b=4, remap={"sum": "b"})),
        add,
        name="join",
    )
    with ActionEngine(actions=catalog(add)) as engine:
        outcome = engine.run(g, timeout=WAIT)
    assert outcome.result is Result.TRUE
    assert outcome.outputs == {"sum": 10.0}


@pytest.mark.parametrize(
    ("decides", "arms", "result", "ran"),
    [
        (True, ("on_true", "on_false"), Result.TRUE, ["Check_0", "Yes_0", "After_0"]),
        (False, ("on_true", "on_false"), Result.TRUE, ["Check_0", "No_0", "After_0"]),
        (False, ("on_true",), Result.TRUE, ["Check_0", "After_0"]),
        (True, ("on_false",), Result.TRUE, ["Check_0", "After_0"]),
        (RuntimeError("x"), ("on_true", "on_false", "on_error"), Result.TRUE, None),
        (RuntimeError("x"), ("on_true", "on_false"), Result.ERROR, ["Check_0"]),
    ],
)
def test_branch_runs_the_arm_its_result_names(
    decides: Any, arms: tuple[str, ...], result: Result, ran: list[str] | None
) -> None:
    script = Script()
    check = script.action("Check", default=decides)
    yes, no, oops, after = (script.action(n) for n in ("Yes", "No", "Oops", "After"))
    given = {"on_true": yes, "on_false": no, "on_error": oops}
    g = graph(branch(check, **{a: given[a] for a in arms}), after, name="b")
    with ActionEngine(actions=catalog(check, yes, no, oops, after)) as engine:
        outcome = engine.run(g, timeout=WAIT)
    assert outcome.result is result
    expected = ["Check_0", "Oops_0", "After_0"] if ran is None else ran
    assert script.started() == expected


def test_nested_compositions_run_in_order() -> None:
    script = Script()
    a, b, c, d = (script.action(n, outputs={"seen": str}) for n in "ABCD")
    script.plan("A_0", Outcome(outputs={"seen": "a"}))
    g = graph(a, parallel(sequence(b, c), d), a, name="nest")
    assert [n.full_name for n in g.actions] == ["A_0", "B_0", "C_0", "D_0", "A_1"]
    assert {p.full_name for p in g.action("A_1").parents} == {"C_0", "D_0"}
    with ActionEngine(actions=catalog(a, b, c, d)) as engine:
        assert engine.run(g, timeout=WAIT).result is Result.TRUE
    order = script.started()
    assert order[0] == "A_0"
    assert order[-1] == "A_1"
    assert order.index("B_0") < order.index("C_0")
    assert script.inputs("B_0") == {}


# ================================================================ declarations and errors


def test_action_on_a_class_declares_its_parameters() -> None:
    @action(
        inputs={
            "pose::x": float,
            "mode": Param(str, default="fast", allowed=["fast", "slow"]),
            "note": Param("string", required=False),
            "ids": list[float],
        },
        outputs={"done": bool},
        type="spontaneous",
    )
    class Move(Action):
        """Moves somewhere.

        More text that is not part of the description.
        """

        def on_run(self) -> bool:
            return True

    desc = description_of(Move)
    assert (desc.name, desc.type, desc.description) == ("Move", "spontaneous", "Moves somewhere.")
    assert {n: p.type for n, p in desc.input_parameters.items()} == {
        "pose::x": "number",
        "mode": "string",
        "note": "string",
        "ids": "numbers",
    }
    assert desc.input_parameters["mode"].value == "fast"
    assert desc.input_parameters["mode"].allowed_values == ("fast", "slow")
    assert not desc.input_parameters["note"].required

    class Sub(Move):
        pass

    with pytest.raises(TypeError, match="Sub has no description"):
        description_of(Sub)


def test_bad_declarations_are_refused_clearly() -> None:
    def fine() -> bool:
        return True

    with pytest.raises(TypeError, match="is not a parameter type"):
        action(inputs={"x": dict})(fine)
    with pytest.raises(TypeError, match="not a valid action name"):
        action(lambda: True)
    with pytest.raises(TypeError, match=r"not a subclass of temoto\.Action"):
        action(int)
    with pytest.raises(UmrfError, match="pvf_value"):

        @action(inputs={"x": Param(float, default="one")})
        def bad(x: float) -> bool:
            return True


def test_node_values_are_checked_where_they_are_given(guide: ActionCatalog) -> None:
    with pytest.raises(ValueError, match=r"Add_0: no input 'c' \(its inputs: a, b\)"):
        graph(node("Add", c=1), catalog=guide)
    with pytest.raises(TypeError, match=r"Add_0: input 'a' \(number\): expected a number"):
        graph(node("Add", a="one"), catalog=guide)
    with pytest.raises(ActionNotFoundError, match="no action named 'Nope'"):
        graph("Nope", catalog=guide)
    with pytest.raises(ActionNotFoundError, match="no catalog"):
        graph("Add")
    g = GraphBuilder("dup", catalog=guide)
    g.add("Add", instance=3)
    with pytest.raises(ValueError, match="already has a node Add_3"):
        g.add("Add", instance=3)
    assert g.add("Add").full_name == "Add_0"


def test_compositions_umrf_cannot_express_are_refused() -> None:
    script = Script()
    a, b, c = (script.action(n) for n in "ABC")
    with pytest.raises(ValueError, match="cannot end a parallel"):
        graph(parallel(branch(a, on_true=b), c), a)
    with pytest.raises(ValueError, match="ends in several nodes"):
        graph(branch(a, on_true=parallel(b, c)))
    with pytest.raises(ValueError, match="at least one of on_true"):
        branch(a)
    with pytest.raises(TypeError, match="is not a step"):
        graph(42)  # type: ignore[arg-type]


def test_a_graph_the_json_path_refuses_is_refused_the_same_way() -> None:
    script = Script()
    a = script.action("A")
    g = GraphBuilder("g")
    first = g.add(a)
    g.entry(first)
    g.entry(first)
    g.exit(first)
    with pytest.raises(GraphDefinitionError, match=r"graph_entry\[1\]: 'A_0' is listed twice"):
        g.build()


def test_function_action_returning_anything_else_is_an_error() -> None:
    @action
    def maybe() -> Any:
        return "yes"

    with ActionEngine(actions=catalog(maybe)) as engine:
        outcome = engine.run(graph(maybe), timeout=WAIT)
    assert outcome.result is Result.ERROR
    assert "return True or False, or a dict" in str(outcome.errors[0].__cause__)
