"""``temoto validate FILE...``: check graphs, and that their actions resolve.

Every file is checked and reported (``FILE: ok (...)`` or an error line); exit 2 if any is
invalid. Like every module of :mod:`temoto.cli`, it prints.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

from temoto.cli.common import EXIT_INVALID, EXIT_TRUE, add_paths, error
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.documents import load_graph
from temoto.core.graph import UmrfGraph
from temoto.core.planning import Planner
from temoto.core.umrf import Umrf
from temoto.core.validation import validate_graph
from temoto.errors import (
    ActionNotFoundError,
    ConfigError,
    GraphDefinitionError,
    PluginError,
)

__all__ = ["add_parser", "main"]


def add_parser(sub: Any) -> None:
    """Add ``temoto validate`` to the top-level subparsers."""
    val = sub.add_parser(
        "validate",
        help="check graph files",
        description="Check graphs: their structure and, given action or graph folders, that"
        " their actions resolve. A shared graph needs no fleet: without --actor, the actions"
        " of every actor are checked where they resolve here and the others are named as left"
        " to their actors; with --actor, that actor's actions must all resolve.",
    )
    val.add_argument("files", nargs="+", metavar="FILE")
    add_paths(val)
    val.add_argument(
        "--actor",
        default="",
        metavar="NAME",
        help="check a shared graph as this actor: its actions must resolve, the other actors'"
        " are not checked",
    )


def main(args: argparse.Namespace) -> int:
    """``temoto validate``: every file is checked and reported (an error line or ``ok``)."""
    planning = bool(args.actions or args.graphs)
    catalog = ActionCatalog(args.actions) if planning else None
    graphs = GraphIndex(args.graphs) if planning else None
    code = EXIT_TRUE
    for file in args.files:
        try:
            if not _validate_file(args, file, catalog, graphs):
                code = EXIT_INVALID
        except (ConfigError, PluginError) as err:
            error(err)
            code = EXIT_INVALID
    return code


def _validate_file(
    args: argparse.Namespace, file: str, catalog: ActionCatalog | None, graphs: GraphIndex | None
) -> bool:
    """Check one file for ``temoto validate``; False if it is invalid (its error printed)."""
    planning = catalog is not None
    graph = load_graph(file)
    report = validate_graph(graph)
    report.raise_for_errors(file)
    actors = sorted({a.actor for a in graph.actions if a.actor})
    if args.actor and actors and args.actor not in actors:
        raise GraphDefinitionError(
            f"graph '{graph.name}' has no actions for actor '{args.actor}' (its actors:"
            f" {', '.join(repr(a) for a in actors)})",
            file=file,
        )
    elsewhere: list[tuple[Umrf, str]] = []
    if catalog is not None and graphs is not None:
        # without --actor, every actor's actions are checked where they resolve here
        planner = Planner(
            args.actor,
            catalog,
            graphs,
            remote=True,
            elsewhere=None if args.actor else _collect(elsewhere),
        )
        try:
            planner.plan(graph)
        except ActionNotFoundError as err:  # its message names the graph, not the file
            error(f"{file}: {err}")
            return False
    for issue in report.warnings:
        sys.stdout.write(f"{file}: warning: {issue}\n")
    for umrf, why in elsewhere:
        sys.stdout.write(
            f"{file}: note: '{umrf.full_name}' is left to actor '{umrf.actor}': {why} here\n"
        )
    checked = _validated(graph, actors, args.actor, len(elsewhere) if planning else None)
    sys.stdout.write(f"{file}: ok ({checked})\n")
    return True


def _collect(into: list[tuple[Umrf, str]]) -> Callable[[Umrf, str], None]:
    """A planner's ``elsewhere`` callback that appends to ``into``."""

    def elsewhere(umrf: Umrf, why: str) -> None:
        into.append((umrf, why))

    return elsewhere


def _validated(graph: UmrfGraph, actors: list[str], actor: str, elsewhere: int | None) -> str:
    """What ``temoto validate`` checked in a graph, for its ``ok`` line.

    Args:
        graph: The graph.
        actors: The actors it names (empty for a local graph).
        actor: ``--actor`` (empty when not given).
        elsewhere: How many actions were left to other actors, or None if actions were not
            resolved (no ``--actions``/``--graphs``).
    """
    count = len(graph.actions)
    text = f"{count} action{'s' if count != 1 else ''}"
    if not actors:
        return text
    text += f"; shared by {', '.join(repr(a) for a in actors)}"
    if actor:
        mine = sum(1 for a in graph.actions if not a.actor or a.actor == actor)
        what = "to run" if elsewhere is None else "resolved"
        text += f"; actor '{actor}' has {mine} {what}, the other actors' were not checked"
    elif elsewhere is not None:
        text += f"; {count - elsewhere} resolved here, {elsewhere} left to their actors"
    return text


if __name__ == "__main__":  # python -m temoto.cli.validate: temoto validate, on its own
    from temoto.cli import command_main

    sys.exit(command_main("validate"))
