"""Every example of docs/umrf-guide.md runs and does what the guide says it does."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from temoto.cli import main

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "examples" / "umrf-guide"
DOC = ROOT / "docs" / "umrf-guide.md"
ACTIONS = str(GUIDE / "actions")
SUBGRAPHS = str(GUIDE / "subgraphs")

# graph -> (extra arguments, exit status, printed result and outputs)
EXPECTED: dict[str, tuple[list[str], int, list[str]]] = {
    "01_hello": (["--param", "text=hi"], 0, ["hello: on_true", '  said = "hi"']),
    "02_remap": ([], 0, ["remap: on_true", "  sum = 15.0"]),
    "03_branch": (["--param", "value=3"], 0, ["branch: on_true", '  said = "small"']),
    "04_join": ([], 0, ["join: on_true", "  sum = 10.0"]),
    "05_reactive": ([], 0, ["reactive: on_true"]),
    "06_subgraph": ([], 0, ["subgraph: on_true", "  sum = 103.5"]),
    "07_recover": ([], 0, ["recover: on_true", '  said = "no quotient: carrying on"']),
}


def test_every_example_graph_is_in_the_table_and_in_the_guide() -> None:
    files = sorted(p.name.removesuffix(".graph.json") for p in (GUIDE / "graphs").glob("*.json"))
    assert files == sorted(EXPECTED)
    text = DOC.read_text(encoding="utf-8")
    for name in files:
        assert f"`{name}`" in text, f"{name} is not explained in {DOC.name}"


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_the_example_runs_as_the_guide_says(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    extra, status, printed = EXPECTED[name]
    graph = str(GUIDE / "graphs" / f"{name}.graph.json")
    trace = tmp_path / "trace.jsonl"
    argv = ["run", graph, "--actions", ACTIONS, "--graphs", SUBGRAPHS, "--timeout", "20"]
    assert main([*argv, "--trace", str(trace), *extra]) == status
    assert capsys.readouterr().out.splitlines() == printed
    last = json.loads(trace.read_text().splitlines()[-1])
    assert last["result"] == printed[0].split(": ")[1]


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_the_example_validates(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    graph = str(GUIDE / "graphs" / f"{name}.graph.json")
    assert main(["validate", graph, "--actions", ACTIONS, "--graphs", SUBGRAPHS]) == 0
    assert "warning" not in capsys.readouterr().out


def test_the_branch_takes_the_other_way_for_a_big_value(capsys: pytest.CaptureFixture[str]) -> None:
    graph = str(GUIDE / "graphs" / "03_branch.graph.json")
    assert main(["run", graph, "--actions", ACTIONS, "--param", "value=12"]) == 0
    assert '  said = "big"' in capsys.readouterr().out


def test_the_reactive_graph_ends_at_the_third_tick(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph = str(GUIDE / "graphs" / "05_reactive.graph.json")
    trace = tmp_path / "trace.jsonl"
    assert main(["run", graph, "--actions", ACTIONS, "--trace", str(trace)]) == 0
    records = [json.loads(line) for line in trace.read_text().splitlines()]
    checks = [
        r["node_result"] for r in records if r.get("node") == "AtLeast_0" and "node_result" in r
    ]
    # ticks 1 and 2 are below the limit, tick 3 ends the graph (a check that a newer tick
    # pre-empted, on a loaded machine, would be on_stopped)
    assert checks[-1] == "on_true"
    assert checks.count("on_true") == 1
    assert checks.count("on_false") >= 1


def test_hello_without_its_input_is_refused_naming_it(capsys: pytest.CaptureFixture[str]) -> None:
    graph = str(GUIDE / "graphs" / "01_hello.graph.json")
    assert main(["run", graph, "--actions", ACTIONS]) == 2
    assert "text" in capsys.readouterr().err


def test_the_commands_in_the_guide_name_existing_files() -> None:
    text = DOC.read_text(encoding="utf-8")
    for path in re.findall(r"\$E/(\S+\.graph\.json)", text):
        assert (GUIDE / path).is_file(), path
