"""``--foxglove [PORT]`` on ``temoto serve`` and the robot command (``docs/visualization.md``).

:func:`add_foxglove_option` declares the options; :func:`open_foxglove` starts, for an
:class:`~temoto.instance.Instance`, the live Foxglove server with the recording's channels
(:class:`~temoto.managers.visualization.foxglove.LiveRecorder`) and a Visualization Manager
on the instance's registrar; :func:`close_foxglove` ends them. This module imports neither the
SDK nor the manager until a server is asked for.
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets
import sys
from dataclasses import dataclass
from typing import Any

from temoto.errors import ConfigError

__all__ = [
    "TOKEN_ENV",
    "LiveSession",
    "add_foxglove_commands_option",
    "add_foxglove_option",
    "close_foxglove",
    "open_foxglove",
]

#: The environment variable that gives ``--foxglove-commands`` its token (else a random one).
TOKEN_ENV = "TEMOTO_FOXGLOVE_TOKEN"

logger = logging.getLogger(__name__)

_DEFAULT_PORT = 8765  # foxglove.DEFAULT_PORT, without importing it


def _port(text: str) -> int:
    """An argparse type: a TCP port (0: any free one)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0..65535, not {port}")
    return port


def add_foxglove_option(parser: argparse.ArgumentParser) -> None:
    """``--foxglove [PORT]``, ``--foxglove-layout FILE`` and ``--foxglove-host HOST``."""
    parser.add_argument(
        "--foxglove",
        nargs="?",
        type=_port,
        const=_DEFAULT_PORT,
        metavar="PORT",
        help="serve the recording's topics and the loaded displays live to Foxglove on"
        f" ws://127.0.0.1:PORT (default {_DEFAULT_PORT}; extra temoto[foxglove];"
        " docs/visualization.md)",
    )
    parser.add_argument(
        "--foxglove-layout",
        metavar="FILE",
        help="write a Foxglove layout for these channels (the robot's panels by its features)"
        " to FILE (import it in Foxglove: Layouts, Import from file)",
    )
    parser.add_argument(
        "--foxglove-host",
        default="127.0.0.1",
        metavar="HOST",
        help="the address --foxglove listens on (default 127.0.0.1: the protocol has no"
        " authentication)",
    )


def add_foxglove_commands_option(parser: argparse.ArgumentParser) -> None:
    """``--foxglove-commands``: the operator's commands as services, behind a token."""
    parser.add_argument(
        "--foxglove-commands",
        action="store_true",
        help="with --foxglove: offer the services /temoto/start, /temoto/pause, /temoto/resume"
        " and /temoto/stop, each call carrying the token printed on stderr (or"
        f" ${TOKEN_ENV}); off by default (docs/visualization.md)",
    )


@dataclass
class LiveSession:
    """What :func:`open_foxglove` started: the server, its recorder, the display manager.

    Without ``--foxglove`` (a live view only): the manager alone, ``server`` and ``recorder``
    None.
    """

    server: Any
    recorder: Any
    manager: Any

    def close(self) -> None:
        """Stop sampling and publishing, unload nothing, stop the server; idempotent."""
        if self.recorder is not None:
            self.recorder.close()
        self.manager.shutdown()
        if self.server is not None:
            self.server.close()


def open_foxglove(args: argparse.Namespace, instance: Any, robot: Any = None) -> LiveSession | None:
    """The live server ``--foxglove`` asks for, serving ``instance``; or a display manager alone.

    With ``--foxglove``: the server, its recorder and a Visualization Manager. Without it, when
    the instance has a live view (``--live-view``): a Visualization Manager with no server, so
    that graphs can show displays (``ShowDisplay``) and the page draws them. Else None.

    Args:
        args: The parsed arguments (``foxglove``, ``foxglove_host``).
        instance: The :class:`~temoto.instance.Instance` (its engine, registrar, transport).
        robot: A robot handle to sample (the robot command's), or None.

    Returns:
        The session (close it with :func:`close_foxglove`), or None.

    Raises:
        ConfigError: The SDK is missing (the message names the extra), the port cannot be
            listened on, the ``--foxglove-layout`` file cannot be written, or
            ``--foxglove-commands`` is given without ``--foxglove``.
    """
    layout = getattr(args, "foxglove_layout", None)
    if layout:
        _write_layout(layout, robot)
    port = getattr(args, "foxglove", None)
    commands = bool(getattr(args, "foxglove_commands", False))
    if port is None:
        if commands:
            raise ConfigError("--foxglove-commands needs --foxglove")
        if getattr(instance, "live_view", None) is None:
            return None
        # a live view only: its page shows the displays, served nowhere else
        from temoto.managers.visualization.manager import VisualizationManager

        return LiveSession(None, None, VisualizationManager(instance.registrar, None))
    from temoto.managers.visualization.foxglove import FoxgloveServer, LiveRecorder
    from temoto.managers.visualization.manager import VisualizationManager

    actor = str(getattr(instance, "actor", "") or "")
    host = getattr(args, "foxglove_host", None) or "127.0.0.1"
    server = FoxgloveServer(host, port, name=f"temoto {actor}".strip(), services=commands)
    recorder = None
    try:
        recorder = LiveRecorder(server)
        recorder.capture_logs()
        transport = getattr(instance, "transport", None)
        if transport is not None:
            recorder.listen(transport, [actor] if actor else [])
        instance.engine.add_instrument(recorder)
        if robot is not None:
            recorder.sample(robot)
        manager = VisualizationManager(instance.registrar, server)
        if commands:
            from temoto.managers.visualization.commands import add_operator_commands

            token = os.environ.get(TOKEN_ENV) or secrets.token_urlsafe(24)
            add_operator_commands(server, instance.engine, token)
            shown = f"${TOKEN_ENV}" if os.environ.get(TOKEN_ENV) else token
            sys.stderr.write(
                f"temoto: foxglove commands /temoto/start|pause|resume|stop, token {shown}\n"
            )
    except BaseException:
        if recorder is not None:
            recorder.close()
        server.close()
        raise
    sys.stderr.write(f"temoto: foxglove on {server.url}\n")
    return LiveSession(server, recorder, manager)


def _write_layout(path: str, robot: Any) -> None:
    """``--foxglove-layout FILE``: the layout of the channels ``open_foxglove`` serves."""
    from temoto.managers.visualization.layout import robot_layout, write_layout

    name, features, joints = "", (), []
    if robot is not None:
        name, features = robot.name, tuple(robot.features)
        if "manipulation" in features:
            try:
                joints = list(robot.joint_positions())
            except Exception as err:  # a device in fault: a layout without the joints' plot
                logger.warning("--foxglove-layout: no joint names: %s", err)
    write_layout(path, robot_layout(name, features, joints))
    sys.stderr.write(f"temoto: foxglove layout written to {path}\n")


def close_foxglove(session: LiveSession | None) -> None:
    """End what :func:`open_foxglove` started (None: nothing)."""
    if session is not None:
        session.close()
