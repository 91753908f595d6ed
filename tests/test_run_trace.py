"""The trace contract of ``temoto run --trace`` (docs/design.md §8), on every upstream graph.

A run's trace has exactly one result line, its last, equal to the result the command prints and
to its exit status (0 iff ``on_true``, else 1; 130 after SIGINT). A graph refused before its
start (exit 2) has no run and so no result line. Every graph file of the upstream conformance
folder is run with the result its README documents for a run without external commands; time
runs ten times faster (``--time-scale 10``), which changes no result.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from temoto.cli import main

ROOT = Path(__file__).resolve().parents[1]
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
CONFORMANCE = ROOT / "examples" / "actions" / "conformance"
LEGACY = ROOT / "examples" / "actions" / "legacy"

pytestmark = [
    pytest.mark.skipif(not UPSTREAM.is_dir(), reason=f"no conformance data at {UPSTREAM}"),
    pytest.mark.timeout(60),
]

#: Extra options and expected result of every graph file of the upstream folder; None: the
#: command refuses it with exit 2 (not runnable here: unparseable, actions nobody wrote, or a
#: shared graph without --actor). Results are the README's for a run without external commands.
EXPECTED: dict[str, tuple[tuple[str, ...], str | None]] = {
    "actionengine_test_semantics_test_1.graph.json": ((), "on_true"),
    "actionengine_test_semantics_test_2.graph.json": ((), "on_true"),
    "actionengine_test_semantics_test_3.graph.json": ((), "on_true"),
    "actionengine_test_semantics_test_4.graph.json": ((), "on_true"),
    "actionengine_test_semantics_test_5.graph.json": ((), "on_stopped"),
    "actionengine_test_semantics_test_6.graph.json": ((), "on_true"),
    "actionengine_test_semantics_test_7.graph.json": ((), "on_true"),
    "actionengine_test_semantics_test_8.graph.json": ((), "on_true"),
    "actionengine_test_semantics_test_9.graph.json": ((), "on_stopped"),
    # endless: only a stop ends it
    "actionengine_test_semantics_test_9_infinite_loop.graph.json": (
        ("--timeout", "0.3"),
        "on_stopped",
    ),
    "actionengine_test_ta_generate_string.graph.json": (("--param", "str_a=A"), "on_true"),
    "actionengine_test_external_changes_test_0.graph.json": ((), "on_true"),
    "actionengine_test_external_changes_test_1.graph.json": ((), "on_false"),
    "actionengine_test_external_changes_test_2_a.graph.json": ((), "on_false"),
    "actionengine_test_external_changes_test_2_b.graph.json": ((), "on_true"),
    "actionengine_test_external_changes_test_3_a.graph.json": ((), "on_halted"),
    "actionengine_test_external_changes_test_3_b.graph.json": ((), "on_true"),
    "actionengine_test_external_changes_test_3_c.graph.json": ((), "on_halted"),
    "actionengine_test_external_changes_test_4_a.graph.json": ((), "on_halted"),
    "actionengine_test_external_changes_test_4_b.graph.json": ((), "on_true"),
    "actionengine_test_format_test.graph.json": ((), None),  # actions that do not exist
    "actionengine_test_example_a_unparseable.json": ((), None),
    # shared by three actors: run one of them with --actor (test_multi_actor_traces below)
    "actionengine_test_engine_test_multi_actor.graph.json": ((), None),
    "actionengine_ros2_example_sequential_nav.umrf.graph.json": ((), None),  # no ExampleNavigate
    # counts up forever
    "legacy_actionengine_example_1_loop.umrfg.json": (("--timeout", "0.3"), "on_stopped"),
    "legacy_gptparser_prompt_example_go_wait_return.umrfg.json": ((), "on_true"),
    # these need the Robot Manager's, the demos' or several actors' actions
    "legacy_architecturedemos_demo3_transportation_mission.umrfg.json": ((), None),
    "legacy_gptparser_prompt_example_move_1.json": ((), None),
    "legacy_sharedgraphdemo_shared_graph_test_1_multi_actor.umrfg.json": ((), None),
    "legacy_tutorials_robotont_sim_1_initialize.umrfg.json": ((), None),
    "legacy_umrfdemos_cargo_delivery.umrfg.json": ((), None),
    "legacy_umrfdemos_navigation_demo_concurrent.umrfg.json": ((), None),
    "legacy_umrfdemos_navigation_demo_cycle.umrfg.json": ((), None),
    "legacy_umrfdemos_navigation_demo_sequence.umrfg.json": ((), None),
}


def graph_files() -> list[str]:
    """Every file of the upstream folder but the action descriptions."""
    if not UPSTREAM.is_dir():
        return []
    return sorted(
        p.name
        for p in UPSTREAM.glob("*.json")
        if not (p.name.endswith(".umrf.json") and "_action_" in p.name)
    )


def read_trace(path: Path) -> list[dict[str, object]]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def check_contract(records: list[dict[str, object]], graph: str, result: str, code: int) -> None:
    """The trace has one result line, its last, equal to ``result``; the code agrees with it."""
    results = [r for r in records if "result" in r]
    assert results == [{"graph": graph, "result": result}], records
    assert records[-1] == results[0]
    assert all("node" in r and "state" in r for r in records[:-1])
    if code < 128:  # a signal's code stands for the signal, not for the result
        assert code == (0 if result == "on_true" else 1)


def test_the_table_covers_every_upstream_graph_file() -> None:
    assert sorted(EXPECTED) == graph_files()


@pytest.mark.parametrize("name", graph_files())
def test_the_trace_ends_with_the_one_result_the_command_prints(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    extra, expected = EXPECTED[name]
    trace = tmp_path / "trace.jsonl"
    actions = LEGACY if name.startswith("legacy_") else CONFORMANCE
    argv = ["run", str(UPSTREAM / name), "--actions", str(actions), "--graphs", str(UPSTREAM)]
    code = main([*argv, "--time-scale", "10", "--trace", str(trace), *extra])
    out = capsys.readouterr().out
    records = read_trace(trace)
    if expected is None:
        assert code == 2
        assert [r for r in records if "result" in r] == []
        return
    printed = out.splitlines()[0]
    graph, _, result = printed.partition(": ")
    assert result == expected, out
    check_contract(records, graph, result, code)


def test_a_halted_graph_is_not_stopped_again_in_the_trace(tmp_path: Path) -> None:
    # The engine's shutdown at exit stops the halted run; that stop must not reach the trace.
    trace = tmp_path / "trace.jsonl"
    graph = UPSTREAM / "actionengine_test_external_changes_test_3_c.graph.json"
    code = main(["run", str(graph), "--actions", str(CONFORMANCE), "--trace", str(trace)])
    records = read_trace(trace)
    assert code == 1
    assert [r.get("result") for r in records if "result" in r] == ["on_halted"]
    assert records[-1] == {"graph": "external_changes_test_3_c", "result": "on_halted"}


# --- interrupted runs ---------------------------------------------------------------------------

#: An action that ignores its stop request: only a second signal ends the command.
STUBBORN_ACTION = """
import time

from temoto import Action


class TaStubborn(Action):
    def on_run(self) -> bool:
        while True:
            time.sleep(0.02)
"""


def wait_for_running(trace: Path, proc: subprocess.Popen[str], timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"the command ended early: {proc.communicate()}")
        if trace.exists() and '"RUNNING"' in trace.read_text(encoding="utf-8"):
            return
        time.sleep(0.01)
    raise AssertionError(f"no RUNNING line in {trace} within {timeout} s")


def run_and_interrupt(
    graph: Path, actions: Path, trace: Path, signals: int, signum: int = signal.SIGINT
) -> tuple[int, str, str]:
    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "temoto", "run", str(graph)),
            *("--actions", str(actions), "--trace", str(trace)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        wait_for_running(trace, proc)
        for i in range(signals):
            if i:
                time.sleep(0.05)
            proc.send_signal(signum)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, out, err


@pytest.mark.parametrize(
    ("signum", "expected"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["INT", "TERM"]
)
def test_an_interrupted_run_keeps_its_code_and_its_trace_ends_with_one_result(
    tmp_path: Path, signum: int, expected: int
) -> None:
    trace = tmp_path / "trace.jsonl"
    graph = UPSTREAM / "actionengine_test_semantics_test_9_infinite_loop.graph.json"
    code, out, err = run_and_interrupt(graph, CONFORMANCE, trace, signals=1, signum=signum)
    assert code == expected, err
    assert "Traceback" not in err
    assert out.splitlines()[0] == "semantics_test_9_infinite_loop: on_stopped"
    check_contract(read_trace(trace), "semantics_test_9_infinite_loop", "on_stopped", code)


def test_a_run_abandoned_by_a_second_sigint_still_ends_its_trace(tmp_path: Path) -> None:
    actions = tmp_path / "actions"
    actions.mkdir()
    (actions / "ta_stubborn.py").write_text(STUBBORN_ACTION)
    desc = {"name": "TaStubborn", "type": "sync", "input_parameters": {}, "output_parameters": {}}
    (actions / "ta_stubborn.umrf.json").write_text(json.dumps(desc))
    graph = tmp_path / "stubborn.graph.json"
    node = {"name": "TaStubborn", "instance_id": 0}
    doc = {
        "graph_name": "stubborn",
        "graph_entry": [node],
        "graph_exit": [node],
        "actions": [{**node, "type": "sync"}],
    }
    graph.write_text(json.dumps(doc))
    trace = tmp_path / "trace.jsonl"
    code, out, err = run_and_interrupt(graph, actions, trace, signals=2)
    assert code == 130, err
    assert "Traceback" not in err
    assert out.splitlines()[0] == "stubborn: on_stopped"
    check_contract(read_trace(trace), "stubborn", "on_stopped", code)


def test_progress_reports_the_one_end_of_a_halted_graph(
    capsys: pytest.CaptureFixture[str],
) -> None:
    graph = UPSTREAM / "actionengine_test_external_changes_test_3_c.graph.json"
    assert main(["run", str(graph), "--actions", str(CONFORMANCE), "--progress"]) == 1
    err = capsys.readouterr().err
    ends = [line for line in err.splitlines() if "ended with" in line]
    assert len(ends) == 1, err
    assert ends[0].endswith("external_changes_test_3_c: ended with on_halted")
