from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from temoto.core import dot as dot_module
from temoto.core.documents import load_graph
from temoto.core.dot import STATE_COLORS, graph_to_dot, quote, render
from temoto.core.graph import parse_graph

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
UPSTREAM = SHARED / "conformance" / "umrf" / "upstream"
needs_upstream = pytest.mark.skipif(
    not UPSTREAM.is_dir(), reason=f"upstream conformance data not found at {UPSTREAM}"
)
HAVE_DOT = shutil.which("dot") is not None
# `make test` installs Graphviz (Makefile SYSDEPS): under CI a missing `dot` fails these tests
IN_CI = os.environ.get("CI", "").lower() in ("true", "1")
needs_dot = pytest.mark.skipif(
    not HAVE_DOT and not IN_CI,
    reason="Graphviz 'dot' is not installed (`make sysdeps` installs it as root)",
)

ODD_NAME = 'we"ird \\ name\n[x]; {y} -> z'


def upstream(name: str) -> str:
    return graph_to_dot(load_graph(UPSTREAM / f"actionengine_test_{name}.graph.json"))


def odd_graph() -> Any:
    return parse_graph(
        {
            "graph_name": ODD_NAME,
            "graph_entry": [{"name": 'A"\\b'}],
            "graph_exit": [{"name": "B c", "instance_id": 4}],
            "actions": [
                {
                    "name": 'A"\\b',
                    "type": "sync",
                    "input_parameters": {
                        "s": {"pvf_type": "string", "pvf_value": 'q"\\\n\x01 end'},
                    },
                    "children": [{"name": "B c", "instance_id": 4}],
                },
                {"name": "B c", "instance_id": 4, "type": "sync", "parents": [{"name": 'A"\\b'}]},
            ],
        }
    )


# --- content ---------------------------------------------------------------------------------


@needs_upstream
def test_semantics_test_4_nodes_edges_and_labels() -> None:
    text = upstream("semantics_test_4")
    assert text.startswith('digraph "semantics_test_4" {\n')
    assert text.endswith("}\n")
    assert '"graph_entry" [shape=circle' in text
    assert '"graph_exit" [shape=doublecircle' in text
    for node in ("TaTriggerResult_0", "TaRelayString_0", "TaRelayString_1", "TaCompareString_1"):
        assert re.search(rf'^  "{node}" \[label="{node}(\\n|")', text, re.M), node
    assert 'label="TaTriggerResult_0\\nresult=\\"on_true\\""' in text
    edges = [line.strip() for line in text.splitlines() if " -> " in line]
    assert edges == [
        '"graph_entry" -> "TaTriggerResult_0";',
        '"TaTriggerResult_0" -> "TaRelayString_0" [label="on_false→ignore"];',
        '"TaTriggerResult_0" -> "TaRelayString_1" [label="on_true→ignore"];',
        '"TaRelayString_0" -> "TaCompareString_1"'
        ' [label="on_false→bypass\\nstring_out→str_a", style=dashed];',
        '"TaRelayString_1" -> "TaCompareString_1"'
        ' [label="on_false→bypass\\nstring_out→str_a", style=dashed];',
        '"TaCompareString_1" -> "graph_exit";',
    ]


@needs_upstream
def test_exit_edges_carry_their_non_default_conditions() -> None:
    text = upstream("semantics_test_9_infinite_loop")
    assert '"TaTimer_1" -> "graph_exit" [label="on_true→ignore\\non_false→ignore"];' in text
    # the non-required back edge of the loop is dashed
    assert '"TaTimer_1" -> "TaTimer_0" [style=dashed];' in text


@needs_upstream
def test_non_required_exit_is_dashed_and_actors_are_shown() -> None:
    text = upstream("format_test")
    assert '"action_5_0" -> "graph_exit" [style=dashed];' in text
    assert "actor: Actor A" in text
    assert "test_param_x→test_param_y" in text


@needs_upstream
def test_one_sided_relation_is_drawn_red() -> None:
    text = upstream("format_test")
    assert '"action_0_0" -> "action_3_0" [color=red' in text
    # both sides written: the usual black edge, with the child's conditions
    assert '"action_3_0" -> "action_0_0" [label="on_true→stop\\non_false→stop"];' in text


@needs_upstream
def test_type_other_than_sync_is_shown() -> None:
    text = upstream("semantics_test_7")
    assert "type: spontaneous" in text
    assert "type: sync" not in text


def test_long_literals_are_truncated_and_many_are_summarised() -> None:
    inputs = {f"p{k}": {"pvf_type": "string", "pvf_value": "x" * 100} for k in range(9)}
    g = parse_graph(
        {"graph_name": "g", "actions": [{"name": "A", "type": "sync", "input_parameters": inputs}]}
    )
    text = graph_to_dot(g)
    assert "x" * 30 not in text
    assert "…" in text
    assert "(+3 more)" in text
    assert "p6=" not in text


@needs_upstream
def test_states_colour_nodes() -> None:
    g = load_graph(UPSTREAM / "actionengine_test_semantics_test_2.graph.json")
    text = graph_to_dot(
        g,
        states={
            "TaAddString_0": "FINISHED",
            "TaCompareString_0": "ERROR",
            "graph_entry": "RUNNING",
            "Nope_0": "RUNNING",
        },
    )
    line = next(s for s in text.splitlines() if s.startswith('  "TaAddString_0" ['))
    assert f'fillcolor="{STATE_COLORS["FINISHED"]}"' in line
    assert "[FINISHED]" in line
    line = next(s for s in text.splitlines() if s.startswith('  "TaCompareString_0" ['))
    assert f'fillcolor="{STATE_COLORS["ERROR"]}"' in line
    line = next(s for s in text.splitlines() if s.startswith('  "graph_entry" ['))
    assert "filled" in line
    assert "Nope_0" not in text
    assert "fillcolor" not in graph_to_dot(g)


@needs_upstream
def test_unknown_state_is_shown_without_colour() -> None:
    g = load_graph(UPSTREAM / "actionengine_test_semantics_test_1.graph.json")
    text = graph_to_dot(g, states={"TaAddString_0": "WEIRD"})
    line = next(s for s in text.splitlines() if s.startswith('  "TaAddString_0" ['))
    assert "[WEIRD]" in line
    assert "fillcolor" not in line


# --- quoting and determinism -----------------------------------------------------------------


@pytest.mark.parametrize(
    ("raw", "quoted"),
    [
        ("plain", '"plain"'),
        ('a "b"', '"a \\"b\\""'),
        ("back\\slash\\", '"back\\\\slash\\\\"'),
        ("two\nlines", '"two\\nlines"'),
        ("bell\x07", '"bell\\\\x07"'),
        ("lone\ud800", '"lone\\\\xd800"'),
        ("ünï ✓", '"ünï ✓"'),
    ],
)
def test_quote(raw: str, quoted: str) -> None:
    assert quote(raw) == quoted


@needs_upstream
def test_format_test_graph_name_is_quoted() -> None:
    text = upstream("format_test")
    name = "robot go observe the valve [x=-93.6; y=11.0; yaw=-0.85]"
    assert text.startswith(f'digraph "{name}" {{\n')
    assert f'label="{name}"' in text


def test_odd_names_are_escaped() -> None:
    text = graph_to_dot(odd_graph())
    assert text.startswith('digraph "we\\"ird \\\\ name\\n[x]; {y} -> z" {')
    assert '"A\\"\\\\b_0" -> "B c_4";' in text
    # every double quote in the text is either a delimiter or escaped: strip the quoted
    # strings and no quote may remain
    assert '"' not in re.sub(r'"(?:[^"\\]|\\.)*"', "", text)


@needs_upstream
def test_output_is_deterministic() -> None:
    path = UPSTREAM / "actionengine_test_format_test.graph.json"
    first = graph_to_dot(load_graph(path))
    assert graph_to_dot(load_graph(path)) == first
    assert graph_to_dot(load_graph(path)) == first


# --- rendering -------------------------------------------------------------------------------


@needs_upstream
@needs_dot
@pytest.mark.parametrize(("fmt", "magic"), [("png", b"\x89PNG\r\n\x1a\n"), ("svg", b"<?xml")])
def test_render_writes_image(tmp_path: Path, fmt: str, magic: bytes) -> None:
    out = tmp_path / f"g.{fmt}"
    render(upstream("format_test"), out, fmt)
    assert out.read_bytes().startswith(magic)


@needs_dot
def test_render_svg_of_odd_names_mentions_them(tmp_path: Path) -> None:
    out = tmp_path / "odd.svg"
    render(graph_to_dot(odd_graph()), out, "svg")
    svg = out.read_text(encoding="utf-8")
    assert "<svg" in svg
    assert "B c_4" in svg


@needs_dot
def test_dot_reads_odd_names_as_exactly_the_expected_nodes(tmp_path: Path) -> None:
    out = tmp_path / "odd.json"
    render(graph_to_dot(odd_graph()), out, "json")
    data = json.loads(out.read_text(encoding="utf-8"))
    names = sorted(obj["name"] for obj in data["objects"])
    assert names == sorted(['A"\\\\b_0', "B c_4", "graph_entry", "graph_exit"])
    assert len(data["edges"]) == 3


NAMES = st.text(min_size=1, max_size=12) | st.sampled_from(['"', "\\", '\\"', "a\nb", "->", "{}"])


@needs_dot
@settings(max_examples=30, deadline=None, database=None)
@given(st.text(max_size=20), st.lists(NAMES, min_size=1, max_size=4, unique=True), st.text())
def test_dot_accepts_any_names_and_values(graph_name: str, names: list[str], value: str) -> None:
    if not graph_name:
        graph_name = "g"
    actions = [
        {
            "name": name,
            "type": name,
            "actor": name,
            "input_parameters": {"v": {"pvf_type": "string", "pvf_value": value}},
            "parents": [{"name": names[k - 1], "conditions": ["on_true -> stop"]}] if k else [],
            "children": [{"name": names[k + 1]}] if k + 1 < len(names) else [],
        }
        for k, name in enumerate(names)
    ]
    doc = {
        "graph_name": graph_name,
        "actions": actions,
        "graph_entry": [{"name": names[0]}],
        "graph_exit": [{"name": names[-1], "conditions": ["on_false -> ignore"]}],
    }
    text = graph_to_dot(parse_graph(doc), states={f"{names[0]}_0": "RUNNING"})
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "g.json"
        render(text, out, "json")
        data = json.loads(out.read_text(encoding="utf-8"))
    assert len(data["objects"]) == len(names) + 2
    assert len(data["edges"]) == len(names) + 1


@needs_dot
def test_render_reports_dot_errors(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="syntax error"):
        render("digraph { a -> ", tmp_path / "bad.png", "png")


@needs_upstream
@needs_dot
def test_render_reports_unknown_format(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="nosuchformat"):
        render(upstream("semantics_test_1"), tmp_path / "x.out", "nosuchformat")


def test_render_without_graphviz_says_how_to_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dot_module.shutil, "which", lambda _name: None)
    with pytest.raises(FileNotFoundError, match="apt-get install graphviz"):
        render("digraph {}", tmp_path / "x.png", "png")
    assert not (tmp_path / "x.png").exists()
