"""Every bad input is one line, exit status 2, with the right words.

One table: the arguments (``{tmp}`` is a folder made by :func:`inputs`), the exit status, the
words the error must hold. Each row runs ``temoto`` in a child process (bounded in time) and
also checks that no traceback is printed. Below it: Ctrl-C during the imports, and ``serve``
interrupted while it starts.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from temoto.core.planning import MAX_SUBGRAPH_DEPTH

ROOT = Path(__file__).resolve().parents[1]
GUIDE = ROOT / "examples" / "umrf-guide"
HELLO = GUIDE / "graphs" / "01_hello.graph.json"
BOUND = 60.0  # seconds one command may take on a loaded machine


def _hello(**changes: Any) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(HELLO.read_text(encoding="utf-8"))
    doc.update(changes)
    return doc


def _nested(folder: Path, depth: int) -> None:
    """top.graph.json using G1 using ... G<depth> (graphs/), the last using the guide's Say."""
    (folder / "graphs").mkdir()
    for i in range(depth + 1):
        inner = "Say" if i == depth else f"G{i + 1}"
        text: dict[str, Any] = {"pvf_type": "string"}
        if i == 0:
            text["pvf_value"] = "hi"
        doc = {
            "graph_name": f"G{i}",
            "actions": [
                {
                    "name": inner,
                    "instance_id": 0,
                    "type": "sync",
                    "input_parameters": {"text": text},
                    "output_parameters": {"said": {"pvf_type": "string"}},
                }
            ],
        }
        path = folder / "top.graph.json" if i == 0 else folder / "graphs" / f"g{i}.graph.json"
        path.write_text(json.dumps(doc), encoding="utf-8")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("inputs")
    # json.dumps writes the lone surrogate as the escape "\udc80", which JSON allows
    (tmp / "surrogate.json").write_text(json.dumps(_hello(graph_name="bad\udc80name")))
    array = _hello()
    array["actions"][0]["input_parameters"]["text"] = {
        "pvf_type": "numbers",
        "pvf_value": [1, "two"],
    }
    (tmp / "array.json").write_text(json.dumps(array))
    (tmp / "ok.json").write_text(json.dumps(_hello()))
    (tmp / "broken.json").write_text("{")
    quad = (ROOT / "hw_profiles" / "sim_quad.yaml").read_text(encoding="utf-8")
    start, end = quad.index("  quad:\n"), quad.index("features:")
    (tmp / "twice.yaml").write_text(quad[:end] + quad[start:end] + quad[end:])
    bomb = "robot: r\ndescription:\n  - &a0 [x, x, x, x, x, x, x, x, x, x]\n"
    for k in range(1, 7):  # 10^7 leaves
        bomb += f"  - &a{k} [" + ", ".join([f"*a{k - 1}"] * 10) + "]\n"
    (tmp / "bomb.yaml").write_text(bomb + "devices: {}\n")
    nested = tmp / "nested"
    nested.mkdir()
    _nested(nested, 2 * MAX_SUBGRAPH_DEPTH)
    return tmp


ACTIONS = str(GUIDE / "actions")

#: (arguments, exit status, words the error output must hold)
BAD_INPUTS = [
    pytest.param(
        ["validate", "{tmp}/surrogate.json"],
        2,
        ["surrogate.json: graph_name:", "lone UTF-16 surrogate"],
        id="surrogate-graph-name-validate",
    ),
    pytest.param(
        ["run", "{tmp}/surrogate.json", "--actions", ACTIONS, "--param", "text=x"],
        2,
        ["graph_name:", "lone UTF-16 surrogate"],
        id="surrogate-graph-name-run",
    ),
    pytest.param(
        ["serve", "--actor", "", "--insecure"],
        2,
        ["--actor", "must not be empty"],
        id="actor-empty",
    ),
    *(
        pytest.param(
            ["demo", "3", "--speed", speed],
            2,
            ["--speed", f"'{speed}'", "finite number more than 0"],
            id=f"demo-speed-{speed}",
        )
        for speed in ("inf", "nan", "0", "-2")
    ),
    pytest.param(
        ["sim", "--profile", "{tmp}/twice.yaml"],
        2,
        ["twice.yaml:", "the key 'quad' is given twice"],
        id="device-named-twice",
    ),
    pytest.param(
        ["sim", "--profile", "{tmp}/bomb.yaml"],
        2,
        ["bomb.yaml:", "expand to more than"],
        id="yaml-alias-bomb",
    ),
    pytest.param(
        ["validate", "{tmp}/array.json"],
        2,
        ["pvf_value[1]: expected a number for type 'numbers', got string 'two'"],
        id="array-element-of-the-wrong-type",
    ),
    pytest.param(
        ["validate", "{tmp}/broken.json", "{tmp}/ok.json", "{tmp}/array.json"],
        2,
        ["broken.json: invalid JSON", "ok.json: ok (1 action)", "array.json:", "pvf_value[1]"],
        id="validate-reports-every-file",
    ),
    pytest.param(
        [
            "run",
            "{tmp}/nested/top.graph.json",
            "--actions",
            ACTIONS,
            "--graphs",
            "{tmp}/nested/graphs",
            "--timeout",
            "20",
        ],
        2,
        [f"sub-graphs nested more than {MAX_SUBGRAPH_DEPTH} deep (the limit)"],
        id="sub-graphs-nested-too-deep",
    ),
]


@pytest.mark.parametrize(("args", "status", "words"), BAD_INPUTS)
def test_a_bad_input_is_one_clean_line(
    inputs: Path, args: list[str], status: int, words: list[str]
) -> None:
    argv = [a.replace("{tmp}", str(inputs)) for a in args]
    done = subprocess.run(
        [sys.executable, "-m", "temoto", *argv],
        capture_output=True,
        text=True,
        timeout=BOUND,
        cwd=ROOT,
        check=False,
    )
    both = done.stdout + done.stderr
    assert done.returncode == status, both
    assert "Traceback" not in both
    for word in words:
        assert word in both
    # one error line (argparse's usage line before it aside), none of them long
    errors = [line for line in done.stderr.splitlines() if "error" in line]
    assert errors, both
    assert all(len(line) < 500 for line in done.stderr.splitlines()), done.stderr[:2000]
    if args[0] != "validate":
        assert len(errors) == 1, errors


IMPORT_INTERRUPTED = r"""
import builtins, os, signal, sys
import _temoto_entry

real_import = builtins.__import__

def interrupting(name, *args, **kwargs):
    if name == "temoto.cli":  # Ctrl-C while the command line is being imported
        os.kill(os.getpid(), signal.SIGINT)
    return real_import(name, *args, **kwargs)

builtins.__import__ = interrupting
sys.exit(_temoto_entry.main())
"""


@pytest.mark.parametrize(("command", "status"), [("actions", 130), ("serve", 0)])
def test_ctrl_c_during_the_imports_prints_no_traceback(command: str, status: int) -> None:
    done = subprocess.run(
        [sys.executable, "-c", IMPORT_INTERRUPTED, command, "--help"],
        capture_output=True,
        text=True,
        timeout=BOUND,
        cwd=ROOT,
        check=False,
    )
    assert done.returncode == status, done.stderr
    assert "Traceback" not in done.stderr


MODULE_INTERRUPTED = r"""
import builtins, os, runpy, signal, sys

real_import = builtins.__import__
sent = []

def interrupting(name, *args, **kwargs):
    if name.startswith("temoto.core") and not sent:  # Ctrl-C while the framework loads
        sent.append(name)
        os.kill(os.getpid(), signal.SIGINT)
    return real_import(name, *args, **kwargs)

builtins.__import__ = interrupting
runpy.run_module("temoto", run_name="__main__", alter_sys=True)
"""


@pytest.mark.parametrize(("command", "status"), [("actions", 130), ("serve", 0)])
def test_python_m_temoto_interrupted_while_it_loads_prints_no_traceback(
    command: str, status: int
) -> None:
    """``python -m temoto``: the package's import loads nothing, so the Ctrl-C lands in the try."""
    done = subprocess.run(
        [sys.executable, "-c", MODULE_INTERRUPTED, command, "--help"],
        capture_output=True,
        text=True,
        timeout=BOUND,
        cwd=ROOT,
        check=False,
    )
    assert done.returncode == status, done.stderr
    assert "Traceback" not in done.stderr


def test_importing_the_package_imports_none_of_the_framework() -> None:
    code = "import sys, temoto; print(sorted(m for m in sys.modules if m.startswith('temoto')))"
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=BOUND, check=True
    )
    assert done.stdout.strip() == "['temoto']"


ENTRY = "import sys, _temoto_entry; sys.exit(_temoto_entry.main())"


@pytest.mark.parametrize("delay", [0.5, 1.5, 3.0])
def test_serve_interrupted_while_it_starts_exits_0(delay: float) -> None:
    proc = subprocess.Popen(
        # the console script's entry
        [sys.executable, "-c", ENTRY, "serve", "--actor", "a", "--insecure"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    try:
        time.sleep(delay)  # somewhere in its start-up (imports, fleet, instance), or serving
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=BOUND)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
