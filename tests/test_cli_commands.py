"""The command line's sub-commands are a table: one line registers one, in help order."""

from __future__ import annotations

import argparse
import importlib
from typing import Any

import pytest

from temoto import cli


def test_the_help_lists_the_registered_commands_in_order() -> None:
    sub = next(a for a in cli._parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices) == [c.name for c in cli.COMMANDS]


def test_each_command_is_a_module_of_the_cli_package_with_its_entry() -> None:
    # python-can's layout: `temoto NAME` is temoto/cli/NAME.py, its add_parser and main
    for command in cli.COMMANDS:
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

    monkeypatch.setattr(cli, "COMMANDS", (*cli.COMMANDS, cli.Command("hello", add, hello)))
    assert cli.main(["hello", "--name", "robot"]) == 3
    assert capsys.readouterr().out == "hello robot\n"


def test_an_adder_that_adds_another_name_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    def add(sub: Any) -> None:
        sub.add_parser("other")

    monkeypatch.setattr(cli, "COMMANDS", (cli.Command("hello", add, lambda args: 0),))
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

    monkeypatch.setattr(cli, "COMMANDS", (cli.Command("broken", add, broken),))
    assert cli.main(["broken"]) == 2
    assert capsys.readouterr().err == "temoto: error: no such thing\n"
