"""The ``temoto`` command line (also ``python -m temoto``).

Commands:

* ``temoto run GRAPH.json [--actions DIR]... [--graphs DIR]... [--actor NAME]
  [--param NAME=VALUE]... [--trace FILE] [--timeout SECONDS] [--stop-timeout SECONDS]
  [--progress]``: runs one graph in this process and prints its result. Exit status 0 iff
  the result is ``on_true``, 1 for any other result, 2 for invalid input (with a message
  naming the file and the key path). Its actions can acquire processes
  (``self.acquire("process", ProcessRequest(...))``); they are stopped when the graph ends.
  ``--progress`` prints every node state change, each node's result (``FINISHED on_false``:
  the branch its children take) and the actions' logs. ``--trace FILE`` writes a JSON line per
  node state change (``"node_result"`` on the line where a node's run ends) and, as the last
  line, exactly one result line ``{"graph": ..., "result": ...}``: the result the
  command prints and its exit status stands for (a halted graph stays ``on_halted``, an
  interrupted one ``on_stopped``). A graph refused before its start (status 2) has none.
  ``--timeout`` (seconds, more than 0; default none) stops the graph after that long;
  ``--stop-timeout`` (seconds, 0 or more; default 5) is how long a stopped action may take to
  return before its node is marked ERROR, and the most the exit then waits for it (an action
  that ignores its stop delays the exit by ``--stop-timeout`` once, not more). ``temoto -v
  run`` also prints the Python traceback of each action that raised (its plugin's lines).
* ``temoto validate FILE... [--actions DIR]... [--graphs DIR]... [--actor NAME]``: checks graphs
  (and, given action or graph folders, that their actions resolve); every file is checked and
  reported (``FILE: ok (...)`` or an error line); exit 2 if any is invalid. A shared graph needs
  no fleet link: without ``--actor`` the actions of every actor are checked where they resolve
  here, those that do not are named as left to their actor (a note, not an error); with
  ``--actor NAME`` the actions of NAME (and those without an actor) must resolve and the other
  actors' are not looked at.
* ``temoto graph dot FILE [-o OUT] [--format svg|png|pdf]``: Graphviz DOT of a graph, or an
  image when ``-o`` is given and Graphviz's ``dot`` is installed.
* ``temoto actions [--actions DIR]... [--no-builtin]``: lists the known actions and where they
  come from: the built-in robot, component and context actions (``--no-builtin`` leaves them
  out) and those of the folders.

Errors are one line, ``temoto: error: ...``, without a traceback: invalid input (status 2),
including a ``--live-view`` port out of range or in use.

Signals (ARCHITECTURE.md §8): SIGINT (Ctrl-C) or SIGTERM during ``temoto run`` stops the graph
cleanly (its actions get their stop request), makes every device of this process safe, stops
the processes it started, prints the result (``on_stopped``) and exits 130 (SIGINT) or 143
(SIGTERM); ``temoto demo`` does the same. ``temoto serve`` stopped by either exits 0. A
second signal skips the waits (action stops, process grace periods) but still cleans up; a
command still not ended 10 s after it (stuck in a blocking call) exits anyway, devices made safe
first, and a third signal exits at once. No
traceback in any case. A closed standard output (``temoto actions | head``) ends the command
quietly with status 141 (128 + SIGPIPE, as a program killed by SIGPIPE reports).

Each sub-command is one line of :data:`COMMANDS`: its name, the function that adds its parser
and the function that runs it. Most live in their own ``temoto/_cli_*.py`` module, which prints
like this one. This is the only module that configures logging.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from temoto import __version__
from temoto._cli_common import (
    EXIT_BROKEN_PIPE,
    EXIT_INVALID,
    EXIT_OTHER_RESULT,
    EXIT_TRUE,
    add_paths,
    error,
    factor,
    open_output,
    signal_name,
)
from temoto._cli_drivers import add_drivers, drivers_command
from temoto._cli_fleet import (
    Interrupted,
    SignalExit,
    add_graph_commands,
    add_serve,
    graph_command,
    make_devices_safe,
    serve,
    watch,
)
from temoto._cli_keys import add_keys, keys_command
from temoto._cli_router import add_router, router_command
from temoto._cli_run import add_run, run_command
from temoto._cli_signals import FORCE_EXIT_S
from temoto._cli_sim import add_sim, sim_command
from temoto.core import _fast
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.documents import load_graph
from temoto.core.dot import graph_to_dot, render
from temoto.core.graph import UmrfGraph
from temoto.core.planning import Planner
from temoto.core.umrf import Umrf
from temoto.core.validation import validate_graph
from temoto.errors import (
    ActionNotFoundError,
    ConfigError,
    DriverUnavailableError,
    GraphDefinitionError,
    PluginError,
    TransportError,
)
from temoto.managers.visualization.live import add_foxglove_option
from temoto.web.replay import add_view, view_command

__all__ = ["COMMANDS", "Command", "main"]


class Command(NamedTuple):
    """One sub-command of ``temoto``.

    Attributes:
        name: What follows ``temoto`` on the command line.
        add: Adds its parser to the top-level subparsers (``add(sub)``).
        run: Runs it with the parsed arguments; returns the exit status.
    """

    name: str
    add: Callable[[Any], None]
    run: Callable[[argparse.Namespace], int]


def _add_serve(sub: Any) -> None:
    add_serve(sub, add_paths)


def _add_validate(sub: Any) -> None:
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


def _add_graph(sub: Any) -> None:
    graph = sub.add_parser("graph", help="graph tools")
    gsub = graph.add_subparsers(dest="graph_command", required=True, metavar="TOOL")
    dot = gsub.add_parser("dot", help="Graphviz DOT of a graph (or an image with -o)")
    dot.add_argument("file", metavar="FILE")
    dot.add_argument("-o", "--output", metavar="OUT", help="render to this file with Graphviz")
    dot.add_argument(
        "--format", choices=("svg", "png", "pdf"), help="image format (default: from OUT)"
    )
    add_graph_commands(gsub)


def _graph(args: argparse.Namespace) -> int:
    if args.graph_command == "dot":
        return _dot(args)
    if args.graph_command == "watch":
        return watch(args)
    return graph_command(args)


def _add_demo(sub: Any) -> None:
    demo = sub.add_parser(
        "demo",
        help="run one of the thesis' five demonstrations on the simulators",
        description="Run a demonstration headless and print its timeline (docs/demos.md).",
    )
    demo.add_argument("number", type=int, choices=range(1, 6), metavar="N", help="1 to 5")
    demo.add_argument(
        "--speed",
        type=factor,
        default=1.0,
        metavar="F",
        help="run the robots' clocks F times faster than real time (default 1)",
    )
    add_foxglove_option(demo)  # demonstration 1's displays, live (docs/visualization.md)


def _add_actions(sub: Any) -> None:
    act = sub.add_parser(
        "actions",
        help="list known actions",
        description="List the built-in actions (robot, component and context verbs, which need"
        " the managers of `temoto serve` or of the robot command) and those of --actions.",
    )
    add_paths(act)
    act.add_argument("--no-builtin", action="store_true", help="leave out the built-in actions")


def _parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(
        prog="temoto", description="TeMoto for Python: run and check UMRF task graphs."
    )
    top.add_argument(
        "--version",
        action="version",
        version=f"temoto {__version__} ({_fast.BUILD} build, Python {sys.version.split()[0]})",
    )
    top.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv: debug)"
    )
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add(sub)
        if command.name not in sub.choices:
            raise RuntimeError(f"{command.add.__qualname__} did not add 'temoto {command.name}'")
    return top


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line.

    Args:
        argv: Arguments without the program name (default ``sys.argv[1:]``).

    Returns:
        The exit status.

    Raises:
        SystemExit: On ``--help``/``--version`` and argument errors (status 2).
    """
    args: argparse.Namespace | None = None
    try:
        args = _parser().parse_args(argv)
        level = logging.WARNING - 10 * min(args.verbose, 2)
        if getattr(args, "progress", False):
            level = min(level, logging.INFO)
        logging.basicConfig(
            level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr
        )
        code = _command(args)
        sys.stdout.flush()  # here, where a closed pipe is caught, not at interpreter exit
        return code
    except BrokenPipeError:
        # The reader of our output is gone (``temoto actions | head``). Point standard output
        # at /dev/null so that the interpreter's last flush does not fail again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return EXIT_BROKEN_PIPE
    except KeyboardInterrupt:
        # a command without a signal handler of its own (watch, detect, validate, ...): Ctrl-C
        # ends it quietly, devices made safe like everywhere else
        make_devices_safe("SIGINT")
        if args is not None and args.command == "serve":
            return EXIT_TRUE  # a service stopped as asked, even while it was starting
        return 128 + signal.SIGINT


def _command(args: argparse.Namespace) -> int:
    run = next(c.run for c in COMMANDS if c.name == args.command)
    try:
        return run(args)
    except (ConfigError, PluginError) as err:
        error(err)
        return EXIT_INVALID
    except TransportError as err:  # the fleet: no route, no handshake, a lost actor
        error(err)
        return EXIT_OTHER_RESULT
    except Exception as err:
        missing = _missing_extra(err)
        if missing is None:
            raise
        error(missing)
        return EXIT_INVALID


#: The optional modules of ``pyproject.toml``'s extras: top-level module -> extra.
EXTRA_OF_MODULE = {
    "can": "can",
    "msgpack": "can",
    "dynamixel_sdk": "dynamixel",
    "serial": "robot",  # pyserial: both dynamixel and mavlink
    "pymavlink": "mavlink",
    "zenoh": "zenoh",
}


def _missing_extra(err: BaseException) -> str | None:
    """One line naming the extra to install, if ``err`` comes from one that is missing.

    Args:
        err: What a command raised.

    Returns:
        The line, or None if ``err`` is no missing optional dependency.
    """
    seen: set[int] = set()
    cause: BaseException | None = err
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        if isinstance(cause, DriverUnavailableError):
            return str(cause)  # names the extra, or the missing port or simulator
        if isinstance(cause, ModuleNotFoundError):
            top = (cause.name or "").split(".")[0]
            extra = EXTRA_OF_MODULE.get(top)
            if extra is not None:
                return (
                    f"this needs the Python module '{top}', which is not installed:"
                    f" pip install 'temoto[{extra}]'"
                )
        cause = cause.__cause__ or cause.__context__
    return None


def _validate(args: argparse.Namespace) -> int:
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


def _dot(args: argparse.Namespace) -> int:
    graph = load_graph(args.file)
    text = graph_to_dot(graph)
    if not args.output:
        sys.stdout.write(text)
        return 0
    out = Path(args.output)
    fmt = args.format or out.suffix.lstrip(".") or "svg"
    if fmt == "dot":
        with open_output(out) as file:
            file.write(text)
        return 0
    try:
        render(text, out, fmt)
    except (FileNotFoundError, RuntimeError) as err:
        error(err)
        return EXIT_INVALID
    sys.stdout.write(f"wrote {out}\n")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from temoto.demos import DEMOS, run_demo

    # The first signal raises KeyboardInterrupt (Interrupted) inside the demonstration, which
    # cleans up on its way out as it does for Ctrl-C; its processes are stopped by then.
    try:
        with SignalExit(raise_first=True, force_exit=FORCE_EXIT_S) as signals:
            try:
                report = run_demo(args.number, sys.stdout, speed=args.speed, foxglove=_fg(args))
            finally:
                signals.raising = False
                if signals.signum is not None:
                    make_devices_safe(f"temoto demo stopped by {signal_name(signals.signum)}")
    except Interrupted as stop:
        sys.stderr.write(f"temoto: demonstration {args.number} stopped\n")
        return 128 + stop.signum
    except ModuleNotFoundError as err:
        if not (err.name or "").startswith("temoto.demos"):
            raise
        error(f"demonstration {args.number} ({DEMOS[args.number][0]}) is not built yet")
        return EXIT_INVALID
    except ValueError as err:
        error(err)
        return EXIT_INVALID
    if signals.exit_code is not None:  # the signal came after the demonstration had ended
        return signals.exit_code
    return EXIT_TRUE if report.ok else EXIT_OTHER_RESULT


def _add_examples(sub: Any) -> None:
    ex = sub.add_parser(
        "examples",
        help="copy the examples and hardware profiles the docs use into a folder",
        description="Copy examples/ and hw_profiles/ (as in the repository) into DIR, so that"
        " the commands of the README and docs/ run from DIR with an installed wheel.",
    )
    ex.add_argument("dir", metavar="DIR", help="the folder (made if missing)")


def _examples(args: argparse.Namespace) -> int:
    from temoto.examples import copy_examples

    for folder in copy_examples(args.dir):
        sys.stdout.write(f"wrote {folder}\n")
    return 0


def _fg(args: argparse.Namespace) -> tuple[str, int] | None:
    """``--foxglove [PORT]`` and ``--foxglove-host`` as ``run_demo`` takes them."""
    return None if args.foxglove is None else (args.foxglove_host, args.foxglove)


def _actions(args: argparse.Namespace) -> int:
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


#: The sub-commands, in the order ``temoto --help`` lists them. Adding one is one line here:
#: ``Command("name", add_name, name_command)``.
COMMANDS: tuple[Command, ...] = (
    Command("run", add_run, run_command),
    Command("serve", _add_serve, serve),
    Command("validate", _add_validate, _validate),
    Command("graph", _add_graph, _graph),
    Command("demo", _add_demo, _demo),
    Command("actions", _add_actions, _actions),
    Command("drivers", add_drivers, drivers_command),
    Command("sim", add_sim, sim_command),
    Command("router", add_router, router_command),
    Command("view", add_view, view_command),
    Command("keys", add_keys, keys_command),
    Command("examples", _add_examples, _examples),
)
