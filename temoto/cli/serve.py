"""``temoto serve``: an instance that takes graph commands from the fleet, until a signal.

The first SIGINT or SIGTERM makes every device safe and closes the instance (its runs and
processes stopped) and the command exits 0 (a service stopped as asked); a second one skips
the grace periods. Like every module of :mod:`temoto.cli`, it prints.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

from temoto.cli.common import EXIT_OK, add_paths, non_empty, not_negative, positive
from temoto.cli.fleet import (
    StateFiles,
    add_instance_options,
    fleet_key,
    instance_recording,
    state_files,
)
from temoto.cli.signals import FORCE_EXIT_S, SignalExit, make_devices_safe
from temoto.managers.visualization.live import close_foxglove, open_foxglove

if TYPE_CHECKING:
    from temoto.transport.identity import Credentials

__all__ = ["add_parser", "main"]


def add_parser(sub: Any) -> None:
    """Add ``temoto serve``."""
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
    add_paths(serve_p)
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
    add_instance_options(serve_p, "the fleet this instance joins")


def main(args: argparse.Namespace) -> int:
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
        with instance_recording(args, "temoto serve", args.actor, transport) as recorder:
            return _serve(args, key, state, transport, recorder, signals)


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


if __name__ == "__main__":  # python -m temoto.cli.serve: temoto serve, on its own
    from temoto.cli import command_main

    sys.exit(command_main("serve"))
