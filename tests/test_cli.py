import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from temoto.cli import main

ROOT = Path(__file__).resolve().parents[1]
UPSTREAM = ROOT.parent / "shared" / "conformance" / "umrf" / "upstream"
ACTIONS = ROOT / "examples" / "actions" / "conformance"

pytestmark = pytest.mark.skipif(not UPSTREAM.is_dir(), reason=f"no conformance data at {UPSTREAM}")


def upstream(name: str) -> str:
    return str(UPSTREAM / f"actionengine_test_{name}.graph.json")


def test_run_exits_0_on_true_and_prints_outputs(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", upstream("semantics_test_1"), "--actions", str(ACTIONS)]) == 0
    out = capsys.readouterr().out
    assert "semantics_test_1: on_true" in out
    assert 'result = "Input A and Input B"' in out


def test_run_exits_1_on_any_other_result(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", upstream("external_changes_test_3_c"), "--actions", str(ACTIONS)]) == 1
    assert "on_halted" in capsys.readouterr().out


def test_run_exits_2_with_a_clear_message_on_invalid_input(
    capsys: pytest.CaptureFixture[str],
) -> None:
    bad = str(UPSTREAM / "actionengine_test_example_a_unparseable.json")
    assert main(["run", bad, "--actions", str(ACTIONS)]) == 2
    err = capsys.readouterr().err
    assert "actions[0].state" in err
    assert "Traceback" not in err


def test_run_exits_2_when_an_action_is_unknown(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", upstream("semantics_test_1")]) == 2
    assert "TaAddString" in capsys.readouterr().err


def test_run_exits_2_for_a_missing_graph_input(capsys: pytest.CaptureFixture[str]) -> None:
    graph = upstream("ta_generate_string")
    assert main(["run", graph, "--actions", str(ACTIONS)]) == 2
    assert "str_a" in capsys.readouterr().err


def test_param_fills_a_graph_input(capsys: pytest.CaptureFixture[str]) -> None:
    graph = upstream("ta_generate_string")
    assert main(["run", graph, "--actions", str(ACTIONS), "--param", "str_a=A"]) == 0
    assert 'result = "A and B and C"' in capsys.readouterr().out


def test_malformed_param_is_invalid_input(capsys: pytest.CaptureFixture[str]) -> None:
    graph = upstream("ta_generate_string")
    assert main(["run", graph, "--actions", str(ACTIONS), "--param", "novalue"]) == 2
    assert "NAME=VALUE" in capsys.readouterr().err


def test_trace_writes_one_json_line_per_state_change_and_the_result(tmp_path: Path) -> None:
    trace = tmp_path / "trace.jsonl"
    code = main(
        ["run", upstream("semantics_test_2"), "--actions", str(ACTIONS), "--trace", str(trace)]
    )
    assert code == 0
    lines = [json.loads(line) for line in trace.read_text().splitlines()]
    states = [(r["node"], r["state"]) for r in lines[:-1]]
    assert states == [
        ("TaAddString_0", "RUNNING"),
        ("TaAddString_0", "FINISHED"),
        ("TaCompareString_0", "RUNNING"),
        ("TaCompareString_0", "FINISHED"),
    ]
    assert all(r["graph"] == "semantics_test_2" and r["t"] >= 0 for r in lines[:-1])
    assert lines[-1] == {"graph": "semantics_test_2", "result": "on_true"}


def test_timeout_stops_the_graph(capsys: pytest.CaptureFixture[str]) -> None:
    graph = upstream("semantics_test_9_infinite_loop")
    code = main(["run", graph, "--actions", str(ACTIONS), "--timeout", "0.3"])
    assert code == 1
    assert "on_stopped" in capsys.readouterr().out


def test_validate_accepts_good_files_and_rejects_bad_ones(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["validate", upstream("semantics_test_3"), upstream("semantics_test_4")]) == 0
    assert capsys.readouterr().out.count(": ok") == 2
    assert main(["validate", upstream("format_test")]) == 2
    assert "does not list" in capsys.readouterr().err


def test_validate_with_actions_resolves_every_action(capsys: pytest.CaptureFixture[str]) -> None:
    nav = str(UPSTREAM / "actionengine_ros2_example_sequential_nav.umrf.graph.json")
    assert main(["validate", nav]) == 0
    capsys.readouterr()
    assert main(["validate", nav, "--actions", str(ACTIONS)]) == 2
    assert "ExampleNavigate" in capsys.readouterr().err


def test_graph_dot_prints_graphviz(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["graph", "dot", upstream("semantics_test_4")]) == 0
    out = capsys.readouterr().out
    assert out.startswith("digraph")
    assert '"TaTriggerResult_0" -> "TaRelayString_1"' in out


def test_actions_lists_the_conformance_actions(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["actions", "--no-builtin", "--actions", str(ACTIONS)]) == 0
    out = capsys.readouterr().out
    assert out.count("\n") == 9
    assert "TaTriggerResultMulti (spontaneous)" in out


def test_python_dash_m_temoto_is_the_same_program() -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "temoto",
            "run",
            upstream("semantics_test_3"),
            "--actions",
            str(ACTIONS),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "on_true" in done.stdout


def test_processes_acquired_by_actions_are_stopped_when_the_graph_ends(tmp_path: Path) -> None:
    actions = tmp_path / "actions"
    actions.mkdir()
    (actions / "launch.umrf.json").write_text(
        json.dumps(
            {
                "name": "Launch",
                "type": "sync",
                "input_parameters": {"pidfile": {"pvf_type": "string"}},
            }
        )
    )
    (actions / "launch.py").write_text(
        "import os\n"
        "from temoto import Action\n"
        "from temoto.managers import ProcessRequest\n"
        "from temoto.testing import child_command\n\n"
        "class Launch(Action):\n"
        "    def on_run(self) -> bool:\n"
        "        argv = child_command(touch=self.inputs.get_string('pidfile'))\n"
        "        ref = self.acquire('process', ProcessRequest(argv[0], tuple(argv[1:])))\n"
        "        self.log(f'started {ref.response.pid}')\n"
        "        while not os.path.exists(self.inputs.get_string('pidfile')):\n"
        "            self.sleep(0.01)  # the child writes its pid file once it runs\n"
        "        return True\n"
    )
    pidfile = tmp_path / "child.pid"
    graph = tmp_path / "g.graph.json"
    graph.write_text(
        json.dumps(
            {
                "graph_name": "launch",
                "actions": [
                    {
                        "name": "Launch",
                        "type": "sync",
                        "input_parameters": {
                            "pidfile": {"pvf_type": "string", "pvf_value": str(pidfile)}
                        },
                    }
                ],
            }
        )
    )
    assert main(["run", str(graph), "--actions", str(actions)]) == 0
    pid = int(pidfile.read_text())
    stat = Path(f"/proc/{pid}/stat")
    assert not stat.exists() or stat.read_text().rsplit(")", 1)[1].split()[0] in "ZX"


def test_version_names_the_build(capsys: pytest.CaptureFixture[str]) -> None:
    from temoto.core import _fast

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("temoto ")
    assert f"({_fast.BUILD} build," in out
    assert ("compiled" if _fast.COMPILED else "pure") == _fast.BUILD


# --- the newcomer's path: one-line errors, checked options, tracebacks on demand -------------

GUIDE = ROOT / "examples" / "umrf-guide"
CLI_ACTIONS = ROOT / "tests" / "data" / "cli_actions"


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "soon"])
def test_timeout_must_be_a_positive_number_of_seconds(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["run", upstream("semantics_test_1"), "--actions", str(ACTIONS), "--timeout", value])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "--timeout" in err
    assert "Traceback" not in err


def test_stop_timeout_may_be_0_but_not_negative(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["run", upstream("semantics_test_1"), "--stop-timeout", "-1"])
    assert stop.value.code == 2
    assert "--stop-timeout" in capsys.readouterr().err
    graph, actions = upstream("semantics_test_1"), str(ACTIONS)
    assert main(["run", graph, "--actions", actions, "--stop-timeout", "0"]) == 0


def test_a_bad_live_view_port_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["serve", "--actor", "a", "--insecure", "--live-view", "99999"]) == 2
    err = capsys.readouterr().err
    assert "temoto: error: live view: cannot listen on 127.0.0.1:99999" in err
    assert "Traceback" not in err


def test_a_busy_live_view_port_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["serve", "--actor", "a", "--insecure", "--live-view", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"cannot listen on 127.0.0.1:{port}: Address already in use" in err
    assert "Traceback" not in err


def test_actions_lists_the_builtin_actions_without_arguments(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["actions"]) == 0
    names = {line.split()[0] for line in capsys.readouterr().out.splitlines()}
    assert {"NavigateTo", "MoveJoints", "TakeOff", "RequestComponent", "AddItem"} <= names
    assert main(["actions", "--no-builtin", "--actions", str(ACTIONS)]) == 0
    names = {line.split()[0] for line in capsys.readouterr().out.splitlines()}
    assert "TaAddString" in names
    assert "NavigateTo" not in names


def test_verbose_shows_where_an_action_failed(capsys: pytest.CaptureFixture[str]) -> None:
    graph = str(GUIDE / "graphs" / "07_recover.graph.json")
    actions = str(GUIDE / "actions")
    assert main(["run", graph, "--actions", actions]) == 0  # the graph recovers
    err = capsys.readouterr().err
    assert "error: Divide_0 failed: float division by zero" in err
    assert "Traceback" not in err
    assert main(["-v", "run", graph, "--actions", actions]) == 0
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err
    assert 'divide.py", line 8, in _divide' in err  # the plugin's failing line
    assert "ZeroDivisionError: float division by zero" in err


def test_the_exit_waits_no_longer_than_stop_timeout_for_a_stuck_action() -> None:
    # Stubborn_0 blocks for 60 s and ignores its stop. The run is stopped after 0.3 s, the
    # action is given up on 0.3 s later, and the exit must not wait more for it: before, the
    # engine's shutdown waited 10 s more whatever --stop-timeout said.
    cmd = [sys.executable, "-m", "temoto", "run", str(CLI_ACTIONS / "stubborn.graph.json")]
    cmd += ["--actions", str(CLI_ACTIONS), "--timeout", "0.3", "--stop-timeout", "0.3"]
    began = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60, cwd=ROOT)
    took = time.monotonic() - began
    assert proc.returncode == 1, proc.stderr
    assert "stubborn: on_error" in proc.stdout
    assert "did not stop within 0.3 s" in proc.stderr
    assert took < 8.0, f"the exit took {took:.1f} s"  # 10.6 s or more when it waited 10 s


@pytest.mark.parametrize(
    ("value", "ran", "skipped"), [("12", "Say_0", "Say_1"), ("3", "Say_1", "Say_0")]
)
def test_progress_and_trace_show_each_nodes_result(
    value: str, ran: str, skipped: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph = str(GUIDE / "graphs" / "03_branch.graph.json")
    trace = tmp_path / "trace.jsonl"
    argv = ["run", graph, "--actions", str(GUIDE / "actions"), "--param", f"value={value}"]
    assert main([*argv, "--progress", "--trace", str(trace)]) == 0
    err = capsys.readouterr().err
    decided = "on_true" if value == "12" else "on_false"
    assert f"branch: AtLeast_0 FINISHED {decided}" in err  # which branch ran
    assert f"branch: AtLeast_0: {value} {'>=' if value == '12' else '<'} 10" in err  # its log
    assert f"branch: {ran} FINISHED on_true" in err
    assert skipped not in err
    records = [json.loads(line) for line in trace.read_text().splitlines()]
    ends = {r["node"]: r["node_result"] for r in records if "node_result" in r}
    assert ends == {"AtLeast_0": decided, ran: "on_true"}
    assert [r for r in records if "result" in r] == [{"graph": "branch", "result": "on_true"}]


def test_progress_shows_an_action_error_as_its_result(capsys: pytest.CaptureFixture[str]) -> None:
    graph = str(GUIDE / "graphs" / "07_recover.graph.json")
    assert main(["run", graph, "--actions", str(GUIDE / "actions"), "--progress"]) == 0
    err = capsys.readouterr().err
    assert "recover: Divide_0 ERROR on_error" in err
    assert "recover: Say_0: no quotient: carrying on" in err


@pytest.mark.parametrize("tool", ["trace", "dot"])
def test_an_output_file_that_cannot_be_written_is_one_line(
    tool: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    graph = str(GUIDE / "graphs" / "02_remap.graph.json")
    nowhere = tmp_path / "no-such-folder" / "out"
    if tool == "trace":
        argv = ["run", graph, "--actions", str(GUIDE / "actions"), "--trace", f"{nowhere}.jsonl"]
    else:
        argv = ["graph", "dot", graph, "-o", f"{nowhere}.dot"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"temoto: error: {nowhere}.")
    assert "cannot write: No such file or directory" in err
    assert "Traceback" not in err
