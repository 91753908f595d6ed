"""``temoto run``: one graph in this process, its result printed (see :mod:`temoto.cli`).

Kept apart from :mod:`temoto.cli` (which owns the parser, logging and exit codes) so that the
command line reads as a list of commands. Like :mod:`temoto.cli`, this module prints.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
import textwrap
import threading
import time
import traceback
from collections.abc import Sequence
from typing import IO, Any

from temoto.actions.builtin import ROS2_ACTIONS
from temoto.cli.common import (
    EXIT_OTHER_RESULT,
    EXIT_TRUE,
    add_paths,
    not_negative,
    open_output,
    positive,
    signal_name,
)
from temoto.cli.fleet import (
    add_fleet_options,
    add_record_option,
    close_recorder,
    fleet_key,
    open_recorder,
)
from temoto.cli.progress import ActionLogHandler, Progress
from temoto.cli.signals import FORCE_EXIT_S, SignalExit, make_devices_safe
from temoto.clock import MonotonicClock, ScaledClock
from temoto.core.catalog import ActionCatalog, GraphIndex
from temoto.core.documents import load_graph
from temoto.core.engine import ActionEngine
from temoto.core.graph import UmrfGraph
from temoto.core.instrument import Instrument, TraceInstrument
from temoto.core.planning import graph_inputs_from_text
from temoto.core.registrar import Registrar
from temoto.core.states import NodeState, Result
from temoto.errors import GraphInputError
from temoto.managers.process import ProcessManager
from temoto.ros2.lifecycle import Ros2LifecycleManager
from temoto.ros2.manager import Ros2Manager

__all__ = ["add_parser", "main"]

logger = logging.getLogger(__name__)


class _RunTrace(TraceInstrument):
    """The ``--trace`` file of one ``temoto run``: exactly one result line, its last.

    Node lines are written as they happen. The engine's own end-of-graph events are not
    written: a halted graph is still stopped when the engine shuts down at exit, which would
    end the trace with a second result. Instead :meth:`finish` writes the result the command
    prints (docs/design.md §8) and closes the trace to everything after it.

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


def add_parser(sub: Any) -> None:
    """Add ``temoto run`` to the top-level subparsers.

    Args:
        sub: The ``add_subparsers()`` object of the top-level parser.
    """
    run = sub.add_parser("run", help="run one graph and print its result")
    run.add_argument("graph", metavar="GRAPH.json", help="the graph file")
    add_paths(run)
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
        type=positive,
        metavar="SECONDS",
        help="stop the graph after this long (seconds > 0)",
    )
    run.add_argument("--progress", action="store_true", help="print state changes and action logs")
    run.add_argument("--time-scale", type=float, default=1.0, metavar="F", help=argparse.SUPPRESS)
    run.add_argument(
        "--stop-timeout",
        type=not_negative,
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
        type=positive,
        default=5.0,
        metavar="SECONDS",
        help="how long to wait for the other actors before the start (default 5)",
    )
    fleet.add_argument(
        "--notify-timeout",
        type=positive,
        default=5.0,
        metavar="SECONDS",
        help="how long every other actor has to acknowledge a finished action before the run"
        " aborts (default 5); raise it with --fleet-silence on lossy links over TCP (Zenoh),"
        " where a lost packet arrives late rather than never (docs/zenoh.md)",
    )


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


def main(args: argparse.Namespace) -> int:
    """``temoto run``: run one graph, print its result; the exit status stands for it.

    Args:
        args: The parsed command line.

    Returns:
        The exit status (docs/design.md §8).
    """
    with SignalExit(force_exit=FORCE_EXIT_S) as signals:
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
    trace_file = open_output(args.trace) if args.trace else None
    trace = None
    try:
        if trace_file is not None:
            trace = _RunTrace(trace_file, graph.name, t0)
            instruments.append(trace)
        # Actions get resources (processes) from a registrar that lives as long as the run;
        # the graph's end releases them, so nothing outlives the command.
        registrar = Registrar("temoto-run")
        processes = ProcessManager(registrar)
        # ROS 2 bridges (docs/ros2.md): started only when a ROS 2 action asks for one
        ros2 = Ros2Manager(registrar)
        Ros2LifecycleManager(registrar)
        engine = ActionEngine(
            args.actor,
            actions=ActionCatalog([ROS2_ACTIONS, *args.actions]),
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
                        logger.warning(
                            "graph %s did not end within %s s; stopping it", name, args.timeout
                        )
                    else:
                        sys.stderr.write("temoto: stopping the graph\n")
                    stop_sent = time.monotonic()
                    with contextlib.suppress(TimeoutError):
                        engine.stop(name, timeout=0)
                    # the engine cannot end the run (a fault of its own): give up on it, so
                    # that --timeout always ends the command
                    ended = _wait_run(engine, name, args.stop_timeout + 5.0, signals.hurried)
                    if not ended and not signals.hurried.is_set():
                        sys.stderr.write(
                            f"temoto: the graph did not stop within"
                            f" {args.stop_timeout + 5.0:g} s; giving up on it\n"
                        )
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
                    make_devices_safe(f"temoto run stopped by {signal_name(signals.signum)}")
                # Actions still winding down get what is left of --stop-timeout (not the
                # engine's default of 10 s); one that ignored its stop is given up on.
                engine.shutdown(timeout=0.1 if signals.hurried.is_set() else grace)
        finally:
            # Whatever the actions did not release (a run that did not stop) is stopped here:
            # nothing started by this command outlives it.
            processes.shutdown(stop_processes=True)
            ros2.shutdown()  # segments a crashed bridge's peers re-created
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


if __name__ == "__main__":  # python -m temoto.cli.run: temoto run, on its own
    from temoto.cli import command_main

    sys.exit(command_main("run"))
