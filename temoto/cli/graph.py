"""``temoto graph TOOL``: draw a graph, or command the fleet's instances and watch their runs.

``dot`` draws a graph; ``start|stop|pause|resume|modify|watch`` command the instances of
``temoto serve`` and of the robot command, and watch their runs.

The fleet stack is imported when a fleet tool runs, not for ``dot``. Like every module of
:mod:`temoto.cli`, it prints.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import IO, Any

from temoto.cli.common import EXIT_FAILED, EXIT_INVALID, EXIT_OK, error, open_output
from temoto.cli.fleet import add_fleet_options, fleet_link
from temoto.cli.signals import stop_on_signals
from temoto.core.documents import load_graph
from temoto.core.dot import graph_to_dot, render
from temoto.errors import GraphInputError

__all__ = ["add_parser", "feedback_json", "main"]


def add_parser(sub: Any) -> None:
    """Add ``temoto graph dot|start|stop|pause|resume|modify|watch``."""
    graph = sub.add_parser("graph", help="graph tools")
    gsub = graph.add_subparsers(dest="graph_command", required=True, metavar="TOOL")
    dot = gsub.add_parser("dot", help="Graphviz DOT of a graph (or an image with -o)")
    dot.add_argument("file", metavar="FILE")
    dot.add_argument("-o", "--output", metavar="OUT", help="render to this file with Graphviz")
    dot.add_argument(
        "--format", choices=("svg", "png", "pdf"), help="image format (default: from OUT)"
    )
    add_graph_commands(gsub)


def main(args: argparse.Namespace) -> int:
    """Run ``temoto graph TOOL``."""
    if args.graph_command == "dot":
        return _dot(args)
    if args.graph_command == "watch":
        return watch(args)
    return graph_command(args)


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


def add_graph_commands(gsub: Any) -> None:
    """``temoto graph start|stop|pause|resume|modify|watch``."""
    helps = {
        "start": "start a graph (a file, or an indexed graph's name) on target instances",
        "stop": "stop a run on target instances",
        "pause": "pause a run on target instances",
        "resume": "resume a paused run on target instances",
        "modify": "replace a running graph's structure (from a file) on target instances",
    }
    for name, text in helps.items():
        p = gsub.add_parser(name, help=text, description=text)
        what = "FILE-or-NAME" if name == "start" else ("FILE" if name == "modify" else "NAME")
        p.add_argument("graph", metavar=what, help="a UMRF graph file, or a graph/run name")
        _targets(p)
        p.add_argument("--session", default="", help="the run's name (default: the graph's)")
        if name == "start":
            p.add_argument(
                "--param",
                action="append",
                default=[],
                metavar="NAME=VALUE",
                help="a graph input (repeatable)",
            )
        if name in ("resume", "modify"):
            p.add_argument("--continue-from", default="", metavar="ACTION", help="e.g. Move_1")
        p.add_argument(
            "--timeout",
            type=float,
            default=15.0,
            metavar="SECONDS",
            help="how long to wait for every target's answer (default 15)",
        )
        add_fleet_options(p, "the fleet of the target instances")
    watch = gsub.add_parser(
        "watch",
        help="show the node states of running graphs, live",
        description="Print the state of every run the instances publish, and every change.",
    )
    _targets(watch, required=False)
    watch.add_argument("--graph", action="append", default=[], help="only this run (repeatable)")
    watch.add_argument(
        "--once", action="store_true", help="print what is heard within --duration, then exit"
    )
    watch.add_argument(
        "--json", action="store_true", help="a JSON line per change of a run (for scripts)"
    )
    watch.add_argument(
        "--duration",
        type=float,
        metavar="SECONDS",
        help="stop after this long (default: until Ctrl-C; 2 with --once)",
    )
    add_fleet_options(watch, "the fleet to watch")


def _targets(p: argparse.ArgumentParser, *, required: bool = True) -> None:
    p.add_argument(
        "--target",
        action="append",
        default=[],
        required=required,
        metavar="ACTOR",
        help="an instance's actor name (repeatable)",
    )


def _sender() -> str:
    import socket

    return f"cli-{socket.gethostname()}-{os.getpid()}"


def graph_command(args: argparse.Namespace) -> int:
    """``temoto graph start|stop|pause|resume|modify``: send, print each target's answer."""
    from temoto.fleet.control import GraphCommander

    command = args.graph_command
    graph_json, name = _graph_arg(args.graph, file_only=command == "modify")
    params: dict[str, str] = {}
    for text in getattr(args, "param", []):
        key, eq, raw = text.partition("=")
        if not eq or not key:
            raise GraphInputError(f"--param {text!r}: expected NAME=VALUE")
        params[key] = raw
    why = f"graph {command} on {', '.join(args.target)}"
    with fleet_link(args, _sender(), why) as link, GraphCommander(link) as commander:
        outcome = commander.command(
            command,
            args.target,
            graph=name,
            session=args.session,
            graph_json=graph_json,
            params=params,
            continue_from=getattr(args, "continue_from", ""),
            timeout=args.timeout,
        )
    for actor, reply in sorted(outcome.replies.items()):
        if reply.ok:
            result = f" ({reply.result})" if reply.result else ""
            sys.stdout.write(f"{actor}: {reply.message}{result}\n")
        else:
            sys.stdout.write(f"{actor}: failed: {reply.message}\n")
    for actor in outcome.missing:
        sys.stdout.write(f"{actor}: no answer within {args.timeout:g} s\n")
    return EXIT_OK if outcome.ok else EXIT_FAILED


def _graph_arg(text: str, *, file_only: bool) -> tuple[dict[str, Any] | None, str]:
    """A graph file's document (and name), or a name."""
    path = Path(text)
    if path.is_file():
        from temoto.core.documents import graph_to_dict, load_graph

        graph = load_graph(path)  # checked here: a bad file fails before anything is sent
        return graph_to_dict(graph), graph.name
    if file_only or text.endswith(".json"):
        raise GraphInputError(f"{text}: no such graph file")
    return None, text


def watch(args: argparse.Namespace) -> int:
    """``temoto graph watch``: print runs' states as instances publish them."""
    from temoto.fleet.control import GraphCommander, GraphFeedback

    duration = args.duration if args.duration is not None else (2.0 if args.once else None)
    view = _WatchView(
        sys.stdout, set(args.target), set(args.graph), live=not args.once, as_json=args.json
    )
    stop = threading.Event()
    with (
        stop_on_signals(stop, (signal.SIGINT,)),
        fleet_link(args, _sender(), "graph watch") as link,
        GraphCommander(link) as cmd,
    ):

        def on_feedback(feedback: GraphFeedback) -> None:
            view.update(feedback)

        cmd.watch(on_feedback)
        stop.wait(duration)
    if args.once:
        view.print_table()
    return EXIT_OK if view.heard else EXIT_FAILED


class _WatchView:
    """What ``temoto graph watch`` prints: a line per change, or a table at the end."""

    def __init__(
        self, out: IO[str], targets: set[str], graphs: set[str], *, live: bool, as_json: bool
    ) -> None:
        self.out = out
        self.as_json = as_json
        self.targets = targets
        self.graphs = graphs
        self.live = live
        self.heard = False
        self.t0 = time.monotonic()
        self._lock = threading.Lock()
        self._last: dict[tuple[str, str], Any] = {}

    def update(self, feedback: Any) -> None:
        if self.targets and feedback.actor not in self.targets:
            return
        if self.graphs and feedback.graph not in self.graphs:
            return
        key = (feedback.actor, feedback.graph)
        with self._lock:
            self.heard = True
            old = self._last.get(key)
            self._last[key] = feedback
            if not self.live:
                return
            if self.as_json:
                if old is None or (old.state, old.result, old.nodes) != (
                    feedback.state,
                    feedback.result,
                    feedback.nodes,
                ):
                    self.out.write(feedback_json(feedback) + "\n")
                    self.out.flush()
                return
            t = time.monotonic() - self.t0
            head = f"[{t:8.3f}s] {feedback.actor} | {feedback.graph}"
            if old is None or (old.state, old.result) != (feedback.state, feedback.result):
                result = f" ({feedback.result})" if feedback.result else ""
                self.out.write(f"{head}: {feedback.state}{result}\n")
            before = dict(old.nodes) if old is not None else {}
            for node, state in feedback.nodes:
                if before.get(node) != state:
                    self.out.write(f"{head}: {node} {state}\n")
            self.out.flush()

    def print_table(self) -> None:
        with self._lock:
            if self.as_json:
                for _, fb in sorted(self._last.items()):
                    self.out.write(feedback_json(fb) + "\n")
                self.out.flush()
                return
            if not self._last:
                self.out.write("no running graphs heard\n")
            for (actor, graph), fb in sorted(self._last.items()):
                result = f" ({fb.result})" if fb.result else ""
                self.out.write(f"{actor} | {graph}: {fb.state}{result}\n")
                width = max((len(n) for n, _ in fb.nodes), default=0)
                for node, state in fb.nodes:
                    self.out.write(f"    {node:<{width}}  {state}\n")
            self.out.flush()


def feedback_json(feedback: Any) -> str:
    """One feedback as a JSON line (for scripts)."""
    return json.dumps(
        {
            "actor": feedback.actor,
            "graph": feedback.graph,
            "state": feedback.state,
            "result": feedback.result,
            "nodes": dict(feedback.nodes),
        }
    )


if __name__ == "__main__":  # python -m temoto.cli.graph: temoto graph, on its own
    from temoto.cli import command_main

    sys.exit(command_main("graph"))
