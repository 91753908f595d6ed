"""``temoto actions``: the known actions and where they come from.

The built-in robot, component and context actions (``--no-builtin`` leaves them out) and those
of the ``--actions`` folders. Like every module of :mod:`temoto.cli`, it prints.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from temoto.cli.common import add_paths
from temoto.core.catalog import ActionCatalog
from temoto.errors import PluginError

__all__ = ["add_parser", "main"]


def add_parser(sub: Any) -> None:
    """Add ``temoto actions``."""
    act = sub.add_parser(
        "actions",
        help="list known actions",
        description="List the built-in actions (robot, component and context verbs, which need"
        " the managers of `temoto serve` or of the robot command) and those of --actions.",
    )
    add_paths(act)
    act.add_argument("--no-builtin", action="store_true", help="leave out the built-in actions")


def main(args: argparse.Namespace) -> int:
    """Run ``temoto actions``: one line per known action, then the folders' problems."""
    from temoto.actions.builtin import BUILTIN_ACTIONS

    folders = [*args.actions] if args.no_builtin else [*BUILTIN_ACTIONS, *args.actions]
    catalog = ActionCatalog(folders)
    for name in catalog.names():
        try:
            entry = catalog.entry(name)
        except PluginError as err:
            sys.stdout.write(f"{name}: {err}\n")
            continue
        desc = entry.description
        ins = ", ".join(f"{n}:{p.type}" for n, p in desc.input_parameters.items())
        outs = ", ".join(f"{n}:{p.type}" for n, p in desc.output_parameters.items())
        sys.stdout.write(f"{name} ({desc.type}) in [{ins}] out [{outs}]  {entry.origin}\n")
    for file, problem in catalog.problems:
        sys.stdout.write(f"problem: {file}: {problem}\n")
    return 0


if __name__ == "__main__":  # python -m temoto.cli.actions: temoto actions, on its own
    from temoto.cli import command_main

    sys.exit(command_main("actions"))
