"""``temoto view FILE``: replay a recorded run in the live view's page, until a signal.

The page and the readers of recordings are :mod:`temoto.web.replay`'s. Like every module of
:mod:`temoto.cli`, it prints.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import threading
from typing import Any

from temoto.cli.signals import stop_on_signals
from temoto.web.replay import ReplayView, load_recording

__all__ = ["add_parser", "main"]


def add_parser(sub: Any) -> None:
    """Add ``temoto view FILE [--graph GRAPH.json] [--port N] [--host ADDR]``.

    Args:
        sub: The ``add_subparsers()`` object of the top-level parser.

    Returns:
        None.
    """
    p = sub.add_parser(
        "view",
        help="replay a recorded run in the live view's page",
        description="Serve a recorded run (a `temoto run --trace` file, or a `--record"
        " FILE.mcap` recording) in the live view's page, with a time slider, until Ctrl-C.",
    )
    p.add_argument(
        "file", metavar="FILE", help="the recording (--trace JSON lines, or --record .mcap)"
    )
    p.add_argument("--graph", metavar="GRAPH.json", help="the run's graph, to draw its edges")
    p.add_argument("--port", type=_port, default=0, help="port to serve on (default: any free)")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")


def _port(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0 to 65535, got {value}")
    return value


def main(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Run ``temoto view``: print the page's address, serve until SIGINT/SIGTERM (or ``stop``).

    Args:
        args: The parsed arguments (``file``, ``graph``, ``port``, ``host``).
        stop: Set to end the command (tests); signals do the same.

    Returns:
        0 after an interruption; 1 when the address cannot be bound.

    Raises:
        ConfigError: The recording or the graph file is invalid (the command line prints it
            as one line and exits 2).
    """
    recording = load_recording(args.file, args.graph)
    try:
        site = ReplayView(recording, host=args.host, port=args.port)
    except OSError as err:
        sys.stderr.write(f"temoto: error: cannot serve on {args.host}:{args.port}: {err}\n")
        return 1
    done = stop or threading.Event()
    with contextlib.ExitStack() as signals:
        if threading.current_thread() is threading.main_thread():
            # set on a thread of its own, never in the handler (which may interrupt done.wait)
            signals.enter_context(stop_on_signals(done))
        with site:
            sys.stdout.write(
                f"replaying {recording.source} ({len(recording.events)} node changes,"
                f" result {recording.result or 'none'})\nopen {site.url}\n"
            )
            sys.stdout.flush()
            while not done.wait(0.5):
                pass
    return 0


if __name__ == "__main__":  # python -m temoto.cli.view: temoto view, on its own
    from temoto.cli import command_main

    sys.exit(command_main("view"))
