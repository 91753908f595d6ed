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
  (and, given action or graph folders, that their actions resolve); exit 2 on the first invalid
  file. A shared graph needs no fleet link: without ``--actor`` the actions of every actor are
  checked where they resolve here, those that do not are named as left to their actor (a note,
  not an error); with ``--actor NAME`` the actions of NAME (and those without an actor) must
  resolve and the other actors' are not looked at.
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
second signal skips the waits (action stops, process grace periods) but still cleans up. No
traceback in any case. A closed standard output (``temoto actions | head``) ends the command
quietly with status 141 (128 + SIGPIPE, as a program killed by SIGPIPE reports).

This is the only module that configures logging or prints.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import sys
import textwrap
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

from temoto import __version__
from temoto._cli_drivers import add_drivers, drivers_command
from temoto._cli_fleet import (
    Interrupted,
    SignalExit,
    add_fleet_options,
    add_graph_commands,
    add_record_option,
    add_serve,
    close_recorder,
    fleet_key,
    graph_command,
    make_devices_safe,
    open_recorder,
    serve,
    watch,
)
from temoto._cli_keys import add_keys, keys_command
from temoto._cli_router import add_router, router_command
from temoto._cli_sim import add_sim, sim_command
from temoto._progress import ActionLogHandler, Progress
from temoto.clock import MonotonicClock, ScaledClock
from temoto.core import _fast
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.dot import graph_to_dot, render
from temoto.core.engine import ActionEngine
from temoto.core.graph import UmrfGraph, load_graph
from temoto.core.instrument import Instrument, TraceInstrument
from temoto.core.planning import Planner, graph_inputs_from_text
from temoto.core.registrar import Registrar
from temoto.core.states import NodeState, Result
from temoto.core.umrf import Umrf
from temoto.core.validation import validate_graph
from temoto.errors import (
    ActionNotFoundError,
    ConfigError,
    GraphDefinitionError,
    GraphInputError,
    PluginError,
    TransportError,
)
from temoto.managers.process import ProcessManager
from temoto.web.replay import add_view, view_command

__all__ = ["main"]

EXIT_TRUE = 0
EXIT_OTHER_RESULT = 1
EXIT_INVALID = 2
EXIT_BROKEN_PIPE = 128 + 13  # SIGPIPE


class _RunTrace(TraceInstrument):
    """The ``--trace`` file of one ``temoto run``: exactly one result line, its last.

    Node lines are written as they happen. The engine's own end-of-graph events are not
    written: a halted graph is still stopped when the engine shuts down at exit, which would
    end the trace with a second result. Instead :meth:`finish` writes the result the command
    prints (ARCHITECTURE.md §8) and closes the trace to everything after it.

    Args:
        stream: The trace file.
        graph: The top-level graph's name.
        t0: Clock reading that ``t`` is measured from.
    """

    def __init__(self, stream: IO[str], graph: str, t0: float) -> None:
        super().__init__(stream, graph, t0)
        self._lock = threading.Lock()  # node lines come from the engine's threads
        self._finished = False

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Write a state line, unless the run's result is written already."""
        with self._lock:
            if not self._finished:
                super().node_transition(graph, node, old, new, t)

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Write nothing: the command writes the one result line (:meth:`finish`)."""

    def finish(self, result: str) -> None:
        """Write the result line and nothing after it.

        Args:
            result: The result the command prints (``on_true``, ...).
        """
        with self._lock:
            if not self._finished:
                self._finished = True
                self._write({"graph": self.graph, "result": result})


def _seconds(text: str, *, zero: bool) -> float:
    """A duration option's value: a finite number of seconds, above 0 (or at least 0)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not math.isfinite(value) or value < 0 or (value == 0 and not zero):
        bound = "at least 0" if zero else "more than 0"
        raise argparse.ArgumentTypeError(f"{text!r}: must be {bound} seconds")
    return value


def _positive(text: str) -> float:
    """``--timeout`` and the like: seconds, more than 0."""
    return _seconds(text, zero=False)


def _not_negative(text: str) -> float:
    """``--stop-timeout``: seconds, 0 or more (0: give up at once on an action asked to stop)."""
    return _seconds(text, zero=True)


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

    def paths(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--actions",
            action="append",
            default=[],
            metavar="DIR",
            help="folder of actions (repeatable)",
        )
        p.add_argument(
            "--graphs",
            action="append",
            default=[],
            metavar="DIR",
            help="folder of graphs (repeatable)",
        )

    run = sub.add_parser("run", help="run one graph and print its result")
    run.add_argument("graph", metavar="GRAPH.json", help="the graph file")
    paths(run)
    run.add_argument("--actor", default="", help="this engine's actor name")
    run.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a graph input (repeatable)",
    )
    run.add_argument("--trace", metavar="FILE", help="write a JSON line per node state change")
    add_record_option(run)
    run.add_argument(
        "--timeout",
        type=_positive,
        metavar="SECONDS",
        help="stop the graph after this long (seconds > 0)",
    )
    run.add_argument("--progress", action="store_true", help="print state changes and action logs")
    run.add_argument("--time-scale", type=float, default=1.0, metavar="F", help=argparse.SUPPRESS)
    run.add_argument(
        "--stop-timeout",
        type=_not_negative,
        default=5.0,
        metavar="SECONDS",
        help="how long an action may take to stop; also the most the exit waits for actions"
        " still winding down (default 5)",
    )
    add_fleet_options(
        run, "for a graph shared with other actors (docs/fleet.md); not used otherwise"
    )
    fleet = run.add_argument_group("shared graphs")
    fleet.add_argument(
        "--handshake-timeout",
        type=_positive,
        default=5.0,
        metavar="SECONDS",
        help="how long to wait for the other actors before the start (default 5)",
    )
    fleet.add_argument(
        "--notify-timeout",
        type=_positive,
        default=5.0,
        metavar="SECONDS",
        help="how long every other actor has to acknowledge a finished action before the run"
        " aborts (default 5); raise it with --fleet-silence on lossy links over TCP (Zenoh),"
        " where a lost packet arrives late rather than never (docs/zenoh.md)",
    )

    add_serve(sub, paths)

    val = sub.add_parser(
        "validate",
        help="check graph files",
        description="Check graphs: their structure and, given action or graph folders, that"
        " their actions resolve. A shared graph needs no fleet: without --actor, the actions"
        " of every actor are checked where they resolve here and the others are named as left"
        " to their actors; with --actor, that actor's actions must all resolve.",
    )
    val.add_argument("files", nargs="+", metavar="FILE")
    paths(val)
    val.add_argument(
        "--actor",
        default="",
        metavar="NAME",
        help="check a shared graph as this actor: its actions must resolve, the other actors'"
        " are not checked",
    )

    graph = sub.add_parser("graph", help="graph tools")
    gsub = graph.add_subparsers(dest="graph_command", required=True, metavar="TOOL")
    dot = gsub.add_parser("dot", help="Graphviz DOT of a graph (or an image with -o)")
    dot.add_argument("file", metavar="FILE")
    dot.add_argument("-o", "--output", metavar="OUT", help="render to this file with Graphviz")
    dot.add_argument(
        "--format", choices=("svg", "png", "pdf"), help="image format (default: from OUT)"
    )

    add_graph_commands(gsub)

    demo = sub.add_parser(
        "demo",
        help="run one of the thesis' five demonstrations on the simulators",
        description="Run a demonstration headless and print its timeline (docs/demos.md).",
    )
    demo.add_argument("number", type=int, choices=range(1, 6), metavar="N", help="1 to 5")
    demo.add_argument(
        "--speed",
        type=float,
        default=1.0,
        metavar="F",
        help="run the robots' clocks F times faster than real time (default 1)",
    )

    act = sub.add_parser(
        "actions",
        help="list known actions",
        description="List the built-in actions (robot, component and context verbs, which need"
        " the managers of `temoto serve` or of the robot command) and those of --actions.",
    )
    paths(act)
    act.add_argument("--no-builtin", action="store_true", help="leave out the built-in actions")

    add_drivers(sub)
    add_sim(sub)
    add_router(sub)
    add_view(sub)
    add_keys(sub)
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
    args = _parser().parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    if getattr(args, "progress", False):
        level = min(level, logging.INFO)
    logging.basicConfig(
        level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )
    try:
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
        return 128 + signal.SIGINT


def _command(args: argparse.Namespace) -> int:
    try:
        if args.command == "run":
            return _run(args)
        if args.command == "validate":
            return _validate(args)
        if args.command == "serve":
            return serve(args)
        if args.command == "demo":
            return _demo(args)
        if args.command == "graph" and args.graph_command == "dot":
            return _dot(args)
        if args.command == "graph" and args.graph_command == "watch":
            return watch(args)
        if args.command == "graph":
            return graph_command(args)
        if args.command == "drivers":
            return drivers_command(args)
        if args.command == "sim":
            return sim_command(args)
        if args.command == "router":
            return router_command(args)
        if args.command == "view":
            return view_command(args)
        if args.command == "keys":
            return keys_command(args)
        return _actions(args)
    except (ConfigError, PluginError) as err:
        _error(err)
        return EXIT_INVALID
    except TransportError as err:  # the fleet: no route, no handshake, a lost actor
        _error(err)
        return EXIT_OTHER_RESULT


def _error(err: BaseException | str) -> None:
    sys.stderr.write(f"temoto: error: {err}\n")


def _open_output(path: str | Path) -> IO[str]:
    """A file the command writes (``--trace``, ``-o``), opened for writing.

    Raises:
        ConfigError: It cannot be written (no such folder, no permission), in one line.
    """
    try:
        return open(path, "w", encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{path}: cannot write: {err.strerror or err}") from None


def _params(graph: UmrfGraph, texts: Sequence[str]) -> dict[str, Any]:
    """``--param NAME=VALUE`` options as graph input values."""
    pairs: dict[str, str] = {}
    for text in texts:
        name, eq, raw = text.partition("=")
        if not eq or not name:
            raise GraphInputError(f"--param {text!r}: expected NAME=VALUE")
        pairs[name] = raw
    return graph_inputs_from_text(graph, pairs)


def _open_fleet(args: argparse.Namespace, graph: UmrfGraph) -> Any:
    """The fleet link, transport and authentication for a shared graph; None for a local one."""
    others = sorted({a.actor for a in graph.actions if a.actor and a.actor != args.actor})
    if not others:
        return None
    if not args.actor:
        raise GraphInputError(
            f"graph '{graph.name}' is shared by actors {', '.join(others)}: say which one this"
            " is with --actor"
        )
    from temoto.fleet import FleetActorLink  # the fleet stack is imported only when needed
    from temoto.transport import FleetAuth, FleetLink, open_transport

    key = fleet_key(args, f"graph '{graph.name}' is shared with {', '.join(others)}")
    transport = open_transport(args.fleet_url)
    try:
        auth = FleetAuth(args.fleet, args.actor, key, insecure=key is None)
        link = FleetActorLink(
            FleetLink(transport, auth),
            args.actor,
            silence_s=args.fleet_silence,
            resend_s=args.fleet_resend,
        )
        return link, transport, auth
    except BaseException:
        transport.close()
        raise


def _run(args: argparse.Namespace) -> int:
    with SignalExit() as signals:
        graph = load_graph(args.graph)
        opened = _open_fleet(args, graph)
        link, transport, auth = opened if opened is not None else (None, None, None)
        recorder = None
        try:
            recorder = open_recorder(args, "temoto run", args.actor, transport)
            code = _run_graph(args, graph, link, signals, recorder)
        finally:
            close_recorder(recorder)
            if link is not None:
                link.close()
            if transport is not None:
                transport.close()
            if auth is not None:
                auth.log_drop_summary()  # the drops of the last seconds, not summarised yet
    return signals.exit_code or code


def _wait_run(engine: ActionEngine, name: str, timeout: float | None, interrupt: Any) -> bool:
    """Wait for a run to end, at most ``timeout`` seconds or until ``interrupt`` is set.

    The wait is in steps of 50 ms so that a signal (whose handler sets ``interrupt``) is
    noticed soon: the handler runs in this thread, but does not end the step it interrupts.

    Returns:
        True if the run ended.
    """
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        step = 0.05 if deadline is None else min(0.05, max(0.0, deadline - time.monotonic()))
        try:
            engine.wait(name, step)
            return True
        except TimeoutError:
            pass
        if interrupt.is_set() or (deadline is not None and time.monotonic() >= deadline):
            return False


def _run_graph(
    args: argparse.Namespace, graph: UmrfGraph, link: Any, signals: SignalExit, recorder: Any
) -> int:
    params = _params(graph, args.param)
    clock = ScaledClock(args.time_scale) if args.time_scale != 1.0 else MonotonicClock()
    t0 = clock.monotonic()
    instruments: list[Instrument] = [] if recorder is None else [recorder]
    progress = Progress(sys.stderr, clock, t0) if args.progress else None
    action_logs = ActionLogHandler(progress) if progress is not None else None
    if progress is not None and action_logs is not None:
        instruments.append(progress)
        action_logs.install()
    trace_file = _open_output(args.trace) if args.trace else None
    trace = None
    try:
        if trace_file is not None:
            trace = _RunTrace(trace_file, graph.name, t0)
            instruments.append(trace)
        # Actions get resources (processes) from a registrar that lives as long as the run;
        # the graph's end releases them, so nothing outlives the command.
        registrar = Registrar("temoto-run")
        processes = ProcessManager(registrar)
        engine = ActionEngine(
            args.actor,
            actions=ActionCatalog(args.actions),
            graphs=GraphIndex(args.graphs),
            clock=clock,
            instruments=instruments,
            stop_timeout=args.stop_timeout,
            registrar=registrar,
            link=link,
            handshake_timeout=args.handshake_timeout,
            notify_timeout=args.notify_timeout,
        )
        try:
            with engine:
                name = engine.start(graph, params)
                grace = args.stop_timeout  # what the exit waits for actions still stopping
                if not _wait_run(engine, name, args.timeout, signals.stop):
                    if signals.signum is None:
                        logging.getLogger("temoto.cli").warning(
                            "graph %s did not end within %s s; stopping it", name, args.timeout
                        )
                    else:
                        sys.stderr.write("temoto: stopping the graph\n")
                    stop_sent = time.monotonic()
                    with contextlib.suppress(TimeoutError):
                        engine.stop(name, timeout=0)
                    _wait_run(engine, name, None, signals.hurried)
                    # the run's actions had their --stop-timeout from here on: not twice
                    grace = max(0.1, args.stop_timeout - (time.monotonic() - stop_sent))
                outcome = engine.outcome(name)
                result = _printed_result(outcome.result, interrupted=signals.signum is not None)
                # before the engine's shutdown, which stops a halted run once more
                if trace is not None:
                    trace.finish(result)
                if progress is not None:
                    progress.finish()
                if signals.signum is not None:
                    make_devices_safe(f"temoto run stopped by {_signal_name(signals.signum)}")
                # Actions still winding down get what is left of --stop-timeout (not the
                # engine's default of 10 s); one that ignored its stop is given up on.
                engine.shutdown(timeout=0.1 if signals.hurried.is_set() else grace)
        finally:
            # Whatever the actions did not release (a run that did not stop) is stopped here:
            # nothing started by this command outlives it.
            processes.shutdown(stop_processes=True)
            registrar.close()
    finally:
        if trace_file is not None:
            trace_file.close()
        if action_logs is not None:
            action_logs.remove()
    sys.stdout.write(f"{graph.name}: {result}\n")
    for name, value in sorted(outcome.outputs.items()):
        sys.stdout.write(f"  {name} = {json.dumps(value, ensure_ascii=False, default=repr)}\n")
    for error in outcome.errors:
        sys.stderr.write(f"  error: {error}\n")
        if args.verbose:
            _write_traceback(error)
    return EXIT_TRUE if outcome.result is Result.TRUE else EXIT_OTHER_RESULT


def _write_traceback(error: BaseException) -> None:
    """``-v``: where an action failed, as Python prints it (the plugin's own lines included).

    The engine wraps what ``on_run`` raised in an :class:`~temoto.errors.ActionError`; the
    traceback shown is that of the original exception.
    """
    cause = error.__cause__ if error.__cause__ is not None else error
    if cause.__traceback__ is None:
        return
    for line in traceback.format_exception(cause):
        sys.stderr.write(textwrap.indent(line, "    "))


def _printed_result(result: Result | None, *, interrupted: bool) -> str:
    """The result a run reports: printed, in the trace's last line, and behind the exit code.

    A run that a second signal abandoned while it was still stopping has no result of its own;
    it reports ``on_stopped``, as every interrupted run does (and exits 130 or 143).
    """
    if result is None:
        return Result.STOPPED.value if interrupted else "none"
    return result.value


def _validate(args: argparse.Namespace) -> int:
    planning = bool(args.actions or args.graphs)
    catalog = ActionCatalog(args.actions) if planning else None
    graphs = GraphIndex(args.graphs) if planning else None
    for file in args.files:
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
                _error(f"{file}: {err}")
                return EXIT_INVALID
        for issue in report.warnings:
            sys.stdout.write(f"{file}: warning: {issue}\n")
        for umrf, why in elsewhere:
            sys.stdout.write(
                f"{file}: note: '{umrf.full_name}' is left to actor '{umrf.actor}': {why} here\n"
            )
        checked = _validated(graph, actors, args.actor, len(elsewhere) if planning else None)
        sys.stdout.write(f"{file}: ok ({checked})\n")
    return 0


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
        with _open_output(out) as file:
            file.write(text)
        return 0
    try:
        render(text, out, fmt)
    except (FileNotFoundError, RuntimeError) as err:
        _error(err)
        return EXIT_INVALID
    sys.stdout.write(f"wrote {out}\n")
    return 0


def _signal_name(signum: int) -> str:
    return signal.Signals(signum).name


def _demo(args: argparse.Namespace) -> int:
    from temoto.demos import DEMOS, run_demo

    # The first signal raises KeyboardInterrupt (Interrupted) inside the demonstration, which
    # cleans up on its way out as it does for Ctrl-C; its processes are stopped by then.
    try:
        with SignalExit(raise_first=True) as signals:
            try:
                report = run_demo(args.number, sys.stdout, speed=args.speed)
            finally:
                signals.raising = False
                if signals.signum is not None:
                    make_devices_safe(f"temoto demo stopped by {_signal_name(signals.signum)}")
    except Interrupted as stop:
        sys.stderr.write(f"temoto: demonstration {args.number} stopped\n")
        return 128 + stop.signum
    except ModuleNotFoundError as err:
        if not (err.name or "").startswith("temoto.demos"):
            raise
        _error(f"demonstration {args.number} ({DEMOS[args.number][0]}) is not built yet")
        return EXIT_INVALID
    except ValueError as err:
        _error(err)
        return EXIT_INVALID
    if signals.exit_code is not None:  # the signal came after the demonstration had ended
        return signals.exit_code
    return EXIT_TRUE if report.ok else EXIT_OTHER_RESULT


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
