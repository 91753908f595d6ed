"""``temoto router``: a Zenoh router in this process, for fleets that span subnets.

Robots on different subnets (or behind NAT, or on 4G) cannot hear each other's LCM multicast;
with ``--fleet-url zenoh:tcp/HOST:7447`` they are Zenoh clients of a router at ``HOST``, which
this command runs (the standard ``zenohd`` does the same job; docs/zenoh.md shows both). The
router forwards the fleet's envelopes without opening them: it needs no fleet key.

The command prints one line saying where it listens and how robots connect, then serves until
SIGINT or SIGTERM and exits 0 (docs/design.md §8: a server stopped by a signal); invalid input
(a malformed endpoint, an address in use, eclipse-zenoh missing) is exit status 2 with a one-line
message. Kept apart from :mod:`temoto.cli` so that other commands do not import Zenoh. Like
:mod:`temoto.cli`, this module prints.
"""

from __future__ import annotations

import argparse
import sys
from typing import IO, Any, Final

from temoto.errors import ConfigError, TransportError

__all__ = ["DEFAULT_LISTEN", "add_parser", "main"]

#: Where the router listens without --listen or --config (Zenoh's router port, every address;
#: the same as :data:`temoto.transport.zenoh.DEFAULT_ROUTER_LISTEN`, which is not imported
#: to build the parser).
DEFAULT_LISTEN: Final = "tcp/0.0.0.0:7447"

#: How often the serving loop looks at the stop flag, in seconds.
_WAIT_S: Final = 0.5


def add_parser(sub: Any) -> None:
    """Add ``temoto router`` to the top-level subparsers.

    Args:
        sub: The ``add_subparsers()`` object of the top-level parser.
    """
    router = sub.add_parser(
        "router",
        help="run a Zenoh router that joins robots on different networks (docs/zenoh.md)",
        description="Run a Zenoh router until SIGINT or SIGTERM (exit 0). Robots reach it with"
        " --fleet-url zenoh:tcp/HOST:PORT (Zenoh clients) and exchange the fleet's messages"
        " through it, across subnets. Needs the zenoh extra: pip install 'temoto[zenoh]'.",
    )
    router.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to listen on, repeatable (default {DEFAULT_LISTEN})",
    )
    router.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="another router to connect to, repeatable (routers in a chain)",
    )
    router.add_argument(
        "--config",
        metavar="FILE",
        help="a Zenoh configuration file (JSON5) to start from: TLS, access control, ...",
    )


def _join_url(listen: tuple[str, ...], config: str | None) -> str:
    """What robots pass as --fleet-url to reach a router on these endpoints (or its file's)."""
    endpoints = list(listen)
    if not endpoints and config is not None:
        from temoto.transport.zenoh import config_endpoints

        endpoints = config_endpoints(config, "listen")
    if any(e.startswith(("tls/", "quic/")) for e in endpoints):
        return "zenoh:ROBOT.json5 (a configuration that trusts its certificate: docs/zenoh.md)"
    first = endpoints[0].replace("0.0.0.0", "HOST") if endpoints else "tcp/HOST:PORT"
    return f"zenoh:{first}"


def main(args: argparse.Namespace, out: IO[str] | None = None) -> int:
    """Run ``temoto router`` until SIGINT or SIGTERM.

    Args:
        args: The parsed arguments.
        out: Where the announcement goes (default standard output).

    Returns:
        0 (stopped by a signal).

    Raises:
        ConfigError: A malformed endpoint, an unusable configuration file, an address in use,
            or eclipse-zenoh missing.
    """
    from temoto.cli.signals import FORCE_EXIT_S, SignalExit
    from temoto.transport.zenoh import open_router

    listen = tuple(args.listen) if args.listen else ()
    if not listen and args.config is None:
        listen = (DEFAULT_LISTEN,)
    stream = sys.stdout if out is None else out
    with SignalExit(force_exit=FORCE_EXIT_S, force_exit_code=0) as signals:
        try:
            session = open_router(listen, connect=tuple(args.connect), config_file=args.config)
        except (ValueError, TransportError) as err:
            raise ConfigError(f"temoto router: {err}") from err
        try:
            where = ", ".join(listen) or f"the endpoints of {args.config}"
            stream.write(
                f"temoto: Zenoh router {session.zid()} listening on {where};"
                f" robots join with --fleet-url {_join_url(listen, args.config)}\n"
            )
            stream.flush()
            while not signals.stop.wait(_WAIT_S):
                pass
        finally:
            session.close()
    return 0


if __name__ == "__main__":  # python -m temoto.cli.router: temoto router, on its own
    from temoto.cli import command_main

    sys.exit(command_main("router"))
