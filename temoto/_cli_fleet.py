"""The fleet side of the command line: ``temoto serve`` and ``temoto graph start|...|watch``.

Kept apart from :mod:`temoto.cli` (which owns the parser, logging and exit codes) so that a
local ``temoto run`` imports none of the fleet stack. Like :mod:`temoto.cli`, this module
prints; nothing else in the package does. The handling of signals lives in
:mod:`temoto._cli_signals`; its names are re-exported here for the commands that import them
from this module.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, NamedTuple

from temoto._cli_common import non_empty, not_negative, positive
from temoto._cli_signals import (
    FORCE_EXIT_S,
    Interrupted,
    SignalExit,
    make_devices_safe,
    stop_on_signals,
)
from temoto._files import read_regular_text
from temoto.errors import ConfigError, GraphInputError
from temoto.managers.visualization.live import add_foxglove_option, close_foxglove, open_foxglove

if TYPE_CHECKING:
    from temoto.transport.identity import Credentials

__all__ = [
    "Interrupted",
    "SignalExit",
    "StateFiles",
    "add_components_option",
    "add_fleet_options",
    "add_graph_commands",
    "add_live_view_option",
    "add_record_option",
    "add_serve",
    "add_state_options",
    "graph_command",
    "make_devices_safe",
    "open_recorder",
    "serve",
    "state_files",
]

#: The fleet's LCM URL unless --fleet-url says otherwise (ttl=1: the robots' own network).
DEFAULT_FLEET_URL = "udpm://239.255.76.67:7667?ttl=1"

EXIT_OK = 0
EXIT_FAILED = 1


def add_fleet_options(parser: argparse.ArgumentParser, description: str) -> None:
    """The options that join a fleet: URL, name, key (or ``--insecure``)."""
    fleet = parser.add_argument_group("fleet", description)
    fleet.add_argument(
        "--fleet-url",
        default=DEFAULT_FLEET_URL,
        metavar="URL",
        help=f"the fleet's transport: an LCM URL (default {DEFAULT_FLEET_URL}) or"
        " zenoh:tcp/ROUTER:7447 for a Zenoh client of a router (docs/zenoh.md)",
    )
    fleet.add_argument("--fleet", default="temoto", metavar="NAME", help="fleet name")
    fleet.add_argument(
        "--fleet-key-file",
        metavar="FILE",
        help="file holding the fleet key (hex or base64); default: $TEMOTO_FLEET_KEY",
    )
    fleet.add_argument(
        "--insecure",
        action="store_true",
        help="run without a fleet key: any host on the network could take part",
    )
    fleet.add_argument(
        "--fleet-identity",
        metavar="FILE",
        help="this member's identity file (temoto keys new), instead of a shared fleet key;"
        " default: $TEMOTO_FLEET_IDENTITY (docs/security.md)",
    )
    fleet.add_argument(
        "--fleet-roster",
        metavar="FILE",
        help="the fleet's roster file, with --fleet-identity; default: $TEMOTO_FLEET_ROSTER",
    )
    fleet.add_argument(
        "--fleet-silence",
        type=float,
        default=3.0,
        metavar="SECONDS",
        help="another actor not heard for this long is lost (default 3)",
    )
    fleet.add_argument(
        "--fleet-resend",
        type=float,
        default=0.1,
        metavar="SECONDS",
        help="handshakes and notifications are resent this often until answered (default 0.1)",
    )


def add_components_option(parser: argparse.ArgumentParser) -> None:
    """``--components FILE``: component descriptions for the instance's Component Manager."""
    parser.add_argument(
        "--components",
        action="append",
        default=[],
        metavar="FILE",
        help="component descriptions and pipeline templates (YAML/JSON, repeatable;"
        " docs/component-manager.md)",
    )


def add_state_options(parser: argparse.ArgumentParser) -> None:
    """``--state-dir DIR`` (or ``--catalog``, ``--world``, ``--reliability``): what survives."""
    parser.add_argument(
        "--state-dir",
        metavar="DIR",
        help="keep the instance's state here across restarts and crashes: the registrar's"
        " journal (registrar.journal), the world model (world.journal) and the components'"
        " reliabilities (reliability.json); created if missing",
    )
    parser.add_argument(
        "--catalog", metavar="FILE", help="the registrar's journal (default: in --state-dir)"
    )
    parser.add_argument(
        "--world", metavar="FILE", help="the world model's journal (default: in --state-dir)"
    )
    parser.add_argument(
        "--reliability",
        metavar="FILE",
        help="the components' reliabilities (default: in --state-dir)",
    )


class StateFiles(NamedTuple):
    """Where an instance keeps what survives a restart (None: in memory only)."""

    catalog: Path | None  #: the registrar's journal
    world: Path | None  #: the world model's journal
    reliability: Path | None  #: the components' reliabilities


def state_files(args: argparse.Namespace) -> StateFiles:
    """The state files ``add_state_options`` asked for.

    Raises:
        ConfigError: ``--state-dir`` is not a directory and cannot be made one.
    """
    directory = Path(args.state_dir) if args.state_dir else None
    if directory is not None:
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise ConfigError(f"--state-dir {directory}: {err}") from err

    def pick(given: str | None, default: str) -> Path | None:
        if given:
            return Path(given)
        return directory / default if directory is not None else None

    return StateFiles(
        pick(args.catalog, "registrar.journal"),
        pick(args.world, "world.journal"),
        pick(args.reliability, "reliability.json"),
    )


def add_live_view_option(parser: argparse.ArgumentParser) -> None:
    """``--live-view [PORT]``: serve the live view of running graphs on localhost."""
    parser.add_argument(
        "--live-view",
        nargs="?",
        type=int,
        const=8765,
        metavar="PORT",
        help="serve a live view of the running graphs on http://127.0.0.1:PORT (default 8765)",
    )


def add_record_option(parser: argparse.ArgumentParser) -> None:
    """``--record FILE.mcap``: record the command's runs, logs, telemetry and fleet traffic."""
    parser.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="record graph runs, node transitions, action logs, robot telemetry and fleet"
        " messages to this MCAP file (opens in Foxglove; docs/recording.md)",
    )


def open_recorder(
    args: argparse.Namespace, command: str, actor: str = "", transport: Any = None
) -> Any:
    """The :class:`~temoto.record.Recorder` that ``--record`` asks for, or None.

    It already takes the action logs, and the fleet's envelopes when ``transport`` is given;
    the caller adds it to its engine (and has it sample its robot), and closes it last.

    Args:
        args: The parsed arguments (``args.record``).
        command: What runs (kept in the recording's metadata).
        actor: The instance's actor, if any (likewise).
        transport: The fleet transport to listen to (None: no fleet messages).

    Raises:
        ConfigError: The file cannot be written.
    """
    if not getattr(args, "record", None):
        return None
    from temoto.record import Recorder

    recorder = Recorder(args.record, metadata={"command": command, "actor": actor})
    recorder.capture_logs()
    if transport is not None:
        try:
            recorder.listen(transport, [actor] if actor else [])
        except BaseException:
            recorder.close()
            raise
    return recorder


def close_recorder(recorder: Any) -> None:
    """Finish a recording made by :func:`open_recorder` (None: nothing) and say where it is."""
    if recorder is None:
        return
    recorder.close()
    count = sum(recorder.counts.values())
    sys.stderr.write(f"temoto: recorded {count} message(s) to {recorder.path}\n")


def fleet_key(args: argparse.Namespace, why: str) -> bytes | Credentials | None:
    """The fleet key, or the member's credentials; None only with --insecure.

    The key comes from ``--fleet-key-file`` or ``$TEMOTO_FLEET_KEY``; the credentials from
    ``--fleet-identity`` and ``--fleet-roster`` (or their environment variables), which win.

    Raises:
        GraphInputError: No key and no ``--insecure`` (``why`` says what needs it).
        ConfigError: The key file cannot be read or holds no valid key; an identity without a
            roster; an unusable identity or roster.
    """
    from temoto.transport import identity as ids
    from temoto.transport import key_from_env, key_from_text

    identity = getattr(args, "fleet_identity", None) or os.environ.get(ids.IDENTITY_ENV)
    roster = getattr(args, "fleet_roster", None) or os.environ.get(ids.ROSTER_ENV)
    if identity or roster:
        if not (identity and roster):
            raise ConfigError(
                "a fleet identity needs a roster and a roster an identity: give both"
                " --fleet-identity and --fleet-roster"
                f" (or ${ids.IDENTITY_ENV} and ${ids.ROSTER_ENV})"
            )
        try:
            return ids.Credentials.load(identity, roster)
        except ValueError as err:
            raise ConfigError(str(err)) from None
    try:
        if args.fleet_key_file:
            text = read_regular_text(args.fleet_key_file).strip()
            key: bytes | None = key_from_text(text)
        else:
            key = key_from_env()
    except OSError as err:
        raise ConfigError(f"--fleet-key-file: {err}") from None
    except ValueError as err:
        raise ConfigError(f"fleet key: {err}") from None
    if key is None and not args.insecure:
        raise GraphInputError(
            f"{why}: a fleet key is needed (--fleet-key-file or $TEMOTO_FLEET_KEY),"
            " or --insecure to run without one"
        )
    return key


@contextmanager
def fleet_link(args: argparse.Namespace, sender: str, why: str) -> Iterator[Any]:
    """An authenticated link on the fleet transport, closed (with its transport) at the end."""
    from temoto.transport import FleetAuth, FleetLink, open_transport

    key = fleet_key(args, why)
    if key is not None and not isinstance(key, bytes):
        sender = key.identity.name  # a commander speaks as its identity
    transport = open_transport(args.fleet_url)
    try:
        yield FleetLink(transport, FleetAuth(args.fleet, sender, key, insecure=key is None))
    finally:
        transport.close()


# ===================================================================================== serve


def add_serve(sub: Any, paths: Any) -> None:
    """``temoto serve``."""
    serve_p = sub.add_parser(
        "serve",
        help="run an instance that takes graph commands from the fleet",
        description="Run a TeMoto instance (engine, registrar, process manager, fleet link)"
        " until SIGINT or SIGTERM; `temoto graph start|stop|... --target ACTOR` command it.",
    )
    serve_p.add_argument(
        "--actor", required=True, type=non_empty, help="this instance's actor (robot) name"
    )
    serve_p.add_argument(  # also after the command (SUPPRESS: `temoto -v serve` is kept)
        "-v",
        "--verbose",
        action="count",
        default=argparse.SUPPRESS,
        help="more log output (-vv: debug); -v also prints each failed action's traceback",
    )
    paths(serve_p)
    add_state_options(serve_p)
    serve_p.add_argument(
        "--handshake-timeout",
        type=float,
        default=5.0,
        metavar="SECONDS",
        help="how long to wait for the other actors of a shared graph (default 5)",
    )
    serve_p.add_argument(
        "--stop-timeout",
        type=not_negative,
        default=5.0,
        metavar="SECONDS",
        help="how long an action may take to stop (default 5)",
    )
    serve_p.add_argument(
        "--feedback-period",
        type=positive,
        default=1.0,
        metavar="SECONDS",
        help="publish every run's state this often (default 1)",
    )
    add_components_option(serve_p)
    add_live_view_option(serve_p)
    add_record_option(serve_p)
    add_foxglove_option(serve_p)
    add_fleet_options(serve_p, "the fleet this instance joins")


def serve(args: argparse.Namespace) -> int:
    """Run an instance until SIGINT/SIGTERM; then exit 0 (a service stopped as asked).

    The first signal makes every device safe and closes the instance (its runs stopped, its
    processes stopped); a second one skips the grace periods of the process stops. A
    ``--record`` file is finished after the instance closed, on every way out.
    """
    from temoto.transport import open_transport

    key = fleet_key(args, f"instance '{args.actor}'")
    state = state_files(args)
    with SignalExit(force_exit=FORCE_EXIT_S, force_exit_code=EXIT_OK) as signals:
        transport = open_transport(args.fleet_url)
        try:
            recorder = open_recorder(args, "temoto serve", args.actor, transport)
        except BaseException:
            transport.close()
            raise
        try:
            return _serve(args, key, state, transport, recorder, signals)
        finally:
            close_recorder(recorder)  # after the instance: its runs' last transitions are in


def _serve(
    args: argparse.Namespace,
    key: bytes | Credentials | None,
    state: StateFiles,
    transport: Any,
    recorder: Any,
    signals: SignalExit,
) -> int:
    from temoto.instance import Instance

    instance = Instance(
        args.actor,
        transport=transport,
        key=key,
        fleet=args.fleet,
        insecure=key is None,
        actions=args.actions,
        graphs=args.graphs,
        catalog=state.catalog,
        world=state.world,
        reliability_file=state.reliability,
        handshake_timeout=args.handshake_timeout,
        stop_timeout=args.stop_timeout,
        feedback_period_s=args.feedback_period,
        silence_s=args.fleet_silence,
        resend_s=args.fleet_resend,
        live_view_port=args.live_view,
        component_files=args.components,
    )
    live = None
    try:
        live = open_foxglove(args, instance)  # --foxglove: docs/visualization.md
        if getattr(args, "verbose", 0):
            instance.engine.add_instrument(_traceback_printer())
        if recorder is not None:
            instance.engine.add_instrument(recorder)
            sys.stderr.write(f"temoto: recording to {recorder.path}\n")
        graphs = len(instance.engine.indexed_graphs())
        if instance.live_view is not None:
            sys.stderr.write(f"temoto: live view on {instance.live_view.url}\n")
        sys.stderr.write(
            f"temoto: instance '{args.actor}' serving on {args.fleet_url} (fleet"
            f" '{args.fleet}', {graphs} indexed graph(s)); Ctrl-C stops it\n"
        )
        sys.stdout.write("ready\n")
        sys.stdout.flush()
        signals.stop.wait()
        sys.stderr.write(f"temoto: instance '{args.actor}' stopping\n")
        make_devices_safe(f"instance '{args.actor}' stopped by a signal")
    finally:
        instance.close()
        close_foxglove(live)  # after the instance: its displays are released by then
    return EXIT_OK


def _traceback_printer() -> Any:
    """``serve -v``: an instrument that prints where each failing action raised, as it fails.

    One line naming the run and the node, then the Python traceback of what the action raised
    (the engine's :class:`~temoto.errors.ActionError` wraps it as ``__cause__``), the plugin's
    own lines included: what ``temoto -v run`` prints after its run.
    """
    import textwrap
    import traceback

    from temoto.core.instrument import Instrument

    class TracebackPrinter(Instrument):
        def action_failed(self, graph: str, node: str, error: BaseException) -> None:
            cause = error.__cause__ if error.__cause__ is not None else error
            lines = [f"temoto: {graph}/{node}: {error}\n"]
            if cause.__traceback__ is not None:
                for line in traceback.format_exception(cause):
                    lines.append(textwrap.indent(line, "    "))
            sys.stderr.write("".join(lines))
            sys.stderr.flush()

    return TracebackPrinter()


# ===================================================================================== graph


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
