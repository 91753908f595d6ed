"""The command line's sub-commands are a table: one line registers one, in help order; each
also runs on its own as ``python -m temoto.cli.<name>``."""

from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from temoto import cli

ROOT = Path(__file__).resolve().parents[1]


def test_the_help_lists_the_registered_commands_in_order() -> None:
    sub = next(a for a in cli._parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == list(cli.COMMAND_NAMES)


def test_each_command_is_a_module_of_the_cli_package_with_its_entry() -> None:
    # python-can's layout: `temoto NAME` is temoto/cli/NAME.py, its add_parser and main
    for command in cli.commands():
        module = importlib.import_module(f"temoto.cli.{command.name}")
        assert (command.add, command.run) == (module.add_parser, module.main), command.name


def test_one_line_registers_a_command(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def add(sub: Any) -> None:
        sub.add_parser("hello", help="say hello").add_argument("--name", default="world")

    def hello(args: argparse.Namespace) -> int:
        print(f"hello {args.name}")
        return 3

    known = cli.commands()
    monkeypatch.setattr(cli, "commands", lambda: (*known, cli.Command("hello", add, hello)))
    assert cli.main(["hello", "--name", "robot"]) == 3
    assert capsys.readouterr().out == "hello robot\n"


def test_an_adder_that_adds_another_name_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def add(sub: Any) -> None:
        sub.add_parser("other")

    monkeypatch.setattr(cli, "commands", lambda: (cli.Command("hello", add, lambda args: 0),))
    with pytest.raises(RuntimeError, match="did not add 'temoto hello'"):
        cli.main(["hello"])


def test_errors_of_a_command_are_one_line_with_status_2(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from temoto.errors import ConfigError

    def add(sub: Any) -> None:
        sub.add_parser("broken")

    def broken(args: argparse.Namespace) -> int:
        raise ConfigError("no such thing")

    monkeypatch.setattr(cli, "commands", lambda: (cli.Command("broken", add, broken),))
    assert cli.main(["broken"]) == 2
    assert capsys.readouterr().err == "temoto: error: no such thing\n"


# --- python -m temoto.cli.<name> --------------------------------------------------------------


def _python_m(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONWARNINGS": "default"},
    )


def test_every_command_runs_on_its_own_with_python_m() -> None:
    # all at once: each is an interpreter importing the command line (seconds when loaded)
    started = {name: _python_m(f"temoto.cli.{name}", "--help") for name in cli.COMMAND_NAMES}
    for name, proc in started.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, (name, err)
        assert out.startswith(f"usage: python -m temoto.cli.{name} "), (name, out[:200])
        assert err == "", (name, err)  # no runpy warning: the package did not import it first
    assert set(cli.COMMAND_NAMES) == {
        p.stem
        for p in (ROOT / "temoto" / "cli").glob("*.py")
        if 'if __name__ == "__main__":' in p.read_text(encoding="utf-8")
    } - {"robot"}  # robot: its own main (python -m temoto.managers.robot)


def test_python_m_temoto_cli_run_is_temoto_run(capsys: pytest.CaptureFixture[str]) -> None:
    graph = "examples/umrf-guide/graphs/03_branch.graph.json"
    args = [graph, "--actions", "examples/umrf-guide/actions", "--param", "value=3"]
    proc = _python_m("temoto.cli.run", "-v", *args)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == cli.main(["-v", "run", *args]), err
    assert out == capsys.readouterr().out
    assert out.startswith("branch: on_true\n"), out
    # invalid input: the same one-line error and exit status 2
    proc = _python_m("temoto.cli.run", "no-such.graph.json")
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 2, err
    assert err.startswith("temoto: error: "), err
    assert err.count("\n") == 1, err
    assert "no-such.graph.json" in err
