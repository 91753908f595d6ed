"""What the commands that join a fleet share: its options, its key, its link, state files.

Used by ``temoto serve``, ``temoto run`` (a shared graph), ``temoto graph start|...|watch``
and the robot command: ``--fleet-url``/``--fleet``/key options, ``--catalog``/``--world``
state files, ``--components``, ``--live-view`` and ``--record`` (a recorder opened and finished
for the command). The two commands that run an instance, ``temoto serve`` and the robot
command, add all of them, and ``--foxglove``, with :func:`add_instance_options`. The fleet
stack itself is imported only when a link is opened.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

from temoto._files import read_regular_text
from temoto.errors import ConfigError, GraphInputError
from temoto.managers.visualization.live import add_foxglove_commands_option, add_foxglove_option

if TYPE_CHECKING:
    from temoto.transport.identity import Credentials

__all__ = [
    "DEFAULT_FLEET_URL",
    "StateFiles",
    "add_components_option",
    "add_fleet_options",
    "add_instance_options",
    "add_live_view_option",
    "add_record_option",
    "add_state_options",
    "close_recorder",
    "fleet_key",
    "fleet_link",
    "instance_recording",
    "open_recorder",
    "state_files",
]

#: The fleet's LCM URL unless --fleet-url says otherwise (ttl=1: the robots' own network).
DEFAULT_FLEET_URL = "udpm://239.255.76.67:7667?ttl=1"


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


def add_instance_options(parser: argparse.ArgumentParser, description: str) -> None:
    """The options of a command that runs an instance (``temoto serve``, the robot command).

    Its state files, ``--components``, ``--live-view``, ``--record``, ``--foxglove`` (and its
    layout, host and commands) and the fleet's options.

    Args:
        parser: The command's parser.
        description: The fleet options' group title (which fleet the instance joins).
    """
    add_state_options(parser)
    add_components_option(parser)
    add_live_view_option(parser)
    add_record_option(parser)
    add_foxglove_option(parser)
    add_foxglove_commands_option(parser)
    add_fleet_options(parser, description)


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


@contextmanager
def instance_recording(
    args: argparse.Namespace, command: str, actor: str, transport: Any
) -> Iterator[Any]:
    """``--record`` around the life of an instance that is to own ``transport``.

    ``temoto serve`` and the robot command: if the recorder cannot be opened, the transport
    (which no instance owns yet) is closed; the recording is finished (:func:`close_recorder`)
    at every way out, after the instance, so that its runs' last transitions are in.

    Args:
        args: The parsed arguments (``args.record``).
        command: What runs (kept in the recording's metadata).
        actor: The instance's actor.
        transport: The fleet transport, listened to by the recorder.

    Yields:
        The recorder, or None without ``--record``.

    Raises:
        ConfigError: The file cannot be written.
    """
    try:
        recorder = open_recorder(args, command, actor, transport)
    except BaseException:
        transport.close()
        raise
    try:
        yield recorder
    finally:
        close_recorder(recorder)


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
