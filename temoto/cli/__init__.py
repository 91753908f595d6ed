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

Signals (docs/design.md §8): SIGINT (Ctrl-C) or SIGTERM during ``temoto run`` stops the graph
cleanly (its actions get their stop request), makes every device of this process safe, stops
the processes it started, prints the result (``on_stopped``) and exits 130 (SIGINT) or 143
(SIGTERM); ``temoto demo`` does the same. ``temoto serve`` stopped by either exits 0. A
second signal skips the waits (action stops, process grace periods) but still cleans up; a
command still not ended 10 s after it (stuck in a blocking call) exits anyway, devices made safe
first, and a third signal exits at once. No
traceback in any case. A closed standard output (``temoto actions | head``) ends the command
quietly with status 141 (128 + SIGPIPE, as a program killed by SIGPIPE reports).

Each sub-command is a module of this package (python-can's layout), with ``add_parser(sub)``
and ``main(args)``, and one line of :data:`COMMAND_NAMES`: ``run``, ``serve``, ``validate``,
``graph``, ``demo``, ``actions``, ``drivers``, ``sim``, ``router``, ``view``, ``keys``,
``examples``. Each also runs on its own, ``python -m temoto.cli.<name> ARGS``, the same as
``temoto <name> ARGS`` (:func:`command_main`: the same parser, named after the module, errors,
exit statuses and signal handling). This package imports them only when the command line runs.
The robot command (``python -m temoto.managers.robot``, or ``python -m temoto.cli.robot``) is
:mod:`temoto.cli.robot`. What they share is written once: exit statuses and error lines in
:mod:`temoto.cli.common`, signals in :mod:`temoto.cli.signals`, the fleet's options in
:mod:`temoto.cli.fleet`. These modules print; nothing else in the package does. This one
configures logging.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from temoto import __version__
from temoto.cli.common import (
    EXIT_BROKEN_PIPE,
    EXIT_INVALID,
    EXIT_OTHER_RESULT,
    EXIT_TRUE,
    error,
)
from temoto.cli.signals import make_devices_safe
from temoto.core import _fast
from temoto.errors import (
    ConfigError,
    DriverUnavailableError,
    PluginError,
    TransportError,
)

__all__ = ["COMMAND_NAMES", "Command", "command_main", "commands", "main"]


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


#: The sub-commands, in the order ``temoto --help`` lists them: each is the module
#: ``temoto.cli.<name>``, with ``add_parser(sub)`` and ``main(args)``. Adding one is one line here.
COMMAND_NAMES: tuple[str, ...] = (
    "run",
    "serve",
    "validate",
    "graph",
    "demo",
    "actions",
    "drivers",
    "sim",
    "router",
    "view",
    "keys",
    "examples",
)


def commands() -> tuple[Command, ...]:
    """The sub-commands of :data:`COMMAND_NAMES`, their modules imported.

    Imported here, when the command line runs, not with this package:
    ``python -m temoto.cli.<name>`` runs the module as ``__main__``, and Python imports this
    package first (a module it had imported already would run twice, with a warning).

    Returns:
        One :class:`Command` per name, in order.
    """
    found = []
    for name in COMMAND_NAMES:
        module = importlib.import_module(f"temoto.cli.{name}")
        found.append(Command(name, module.add_parser, module.main))
    return tuple(found)


#: The help of ``-v``, on ``temoto`` and on each ``python -m temoto.cli.<name>``.
_VERBOSE = "more log output (-vv: debug)"


class _Alone:
    """The sub-parsers of ``python -m temoto.cli.<name>``: the command's parser alone.

    The command's ``add_parser`` gets this instead of the top-level sub-parsers: its parser is
    named ``python -m temoto.cli.<name>`` (its usage line), and takes the top level's ``-v``
    too (the command's own ``-v``, if it has one, replaces it).

    Args:
        sub: The top-level parser's sub-parsers.
    """

    def __init__(self, sub: Any) -> None:
        self.sub = sub

    def add_parser(self, name: str, **kwargs: Any) -> argparse.ArgumentParser:
        """Add the command's parser (``argparse``'s ``add_parser``, named after the module).

        Args:
            name: The command's name.
            **kwargs: ``argparse``'s.

        Returns:
            The parser.
        """
        kwargs.setdefault("prog", f"python -m temoto.cli.{name}")
        parser: argparse.ArgumentParser = self.sub.add_parser(
            name, conflict_handler="resolve", **kwargs
        )
        parser.add_argument(  # SUPPRESS: the top level's default (0) stays when it is not given
            "-v", "--verbose", action="count", default=argparse.SUPPRESS, help=_VERBOSE
        )
        return parser


def _parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``temoto``, or with ``only``, of ``python -m temoto.cli.<only>``."""
    top = argparse.ArgumentParser(
        prog="temoto", description="TeMoto for Python: run and check UMRF task graphs."
    )
    top.add_argument(
        "--version",
        action="version",
        version=f"temoto {__version__} ({_fast.BUILD} build, Python {sys.version.split()[0]})",
    )
    top.add_argument("-v", "--verbose", action="count", default=0, help=_VERBOSE)
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in commands():
        if only is not None and command.name != only:
            continue
        command.add(sub if only is None else _Alone(sub))
        if command.name not in sub.choices:
            raise RuntimeError(f"{command.add.__qualname__} did not add 'temoto {command.name}'")
    if only is not None and only not in sub.choices:
        raise ValueError(f"no command '{only}' (commands: {', '.join(COMMAND_NAMES)})")
    return top


def command_main(name: str, argv: Sequence[str] | None = None) -> int:
    """``python -m temoto.cli.<name>``: one command, as ``temoto <name>`` runs it.

    The same parser (named after the module), logging, error lines, exit statuses and signal
    handling as :func:`main`, which it calls.

    Args:
        name: The command (one of :data:`COMMAND_NAMES`).
        argv: Its arguments, without the program name (default ``sys.argv[1:]``).

    Returns:
        The exit status.

    Raises:
        SystemExit: On ``--help`` and argument errors (status 2).
    """
    return main([name, *(sys.argv[1:] if argv is None else argv)], only=name)


def main(argv: Sequence[str] | None = None, *, only: str | None = None) -> int:
    """Run the command line.

    Args:
        argv: Arguments without the program name (default ``sys.argv[1:]``).
        only: The command, when this is ``python -m temoto.cli.<only>``
            (:func:`command_main`): its parser alone.

    Returns:
        The exit status.

    Raises:
        SystemExit: On ``--help``/``--version`` and argument errors (status 2).
    """
    args: argparse.Namespace | None = None
    try:
        args = _parser(only).parse_args(argv)
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
        if args is not None:
            command = args.command
        else:  # while the command's modules were imported
            words = sys.argv[1:] if argv is None else argv
            command = next((a for a in words if not a.startswith("-")), "")
        if command == "serve":
            return EXIT_TRUE  # a service stopped as asked, even while it was starting
        return 128 + signal.SIGINT


def _command(args: argparse.Namespace) -> int:
    run = next(c.run for c in commands() if c.name == args.command)
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
