"""The ``"ros2"`` resource server: a bridge process per request, started by the Process Manager.

:class:`Ros2Manager` loads a :class:`Ros2BridgeRequest` by asking the registrar's ``"process"``
server for ``python -m temoto.ros2.bridge --socket PATH`` (a dependency: the Process Manager
watches it, and its exit reaches the bridge's consumers as a resource failure, FATAL), then
waits for the bridge's ready frame. Equal requests share one bridge (a graph run's ROS 2 actions
hold it until the run ends); a failed bridge is not shared again, so the next request after a
crash starts a new one. After a crash, the Fast DDS segments the bridge left in ``/dev/shm`` are
removed (:func:`~temoto.ros2.shm.clean_stale_segments`).

The bridge inherits this process's environment: the user's ``ROS_DOMAIN_ID``,
``ROS_AUTOMATIC_DISCOVERY_RANGE`` and ``RMW_IMPLEMENTATION`` (a request's ``domain_id``
overrides the first). A wrong RMW is a one-line :class:`~temoto.errors.ConfigError`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

from temoto.core.registrar import LoadContext, Registrar, ResourceInfo, ResourceServer, Status
from temoto.core.registrar.messages import StatusUpdate
from temoto.errors import ConfigError, ResourceError
from temoto.managers.process import ProcessRequest
from temoto.ros2 import require_rclpy
from temoto.ros2.client import BridgeClient, BridgeError
from temoto.ros2.shm import clean_stale_segments

__all__ = [
    "PYTHON_VARIABLE",
    "Ros2BridgeRequest",
    "Ros2BridgeResponse",
    "Ros2Manager",
    "program_request",
    "ros_python",
]

logger = logging.getLogger(__name__)

#: The exit status of a process whose ``import rclpy`` found the wrong RMW.
EXIT_WRONG_RMW = 102
#: The environment variable naming another interpreter (with rclpy) for the bridge.
PYTHON_VARIABLE = "TEMOTO_ROS2_PYTHON"
#: The directory that holds the ``temoto`` package (put on the other interpreter's path).
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[2])


@dataclass(frozen=True)
class Ros2BridgeRequest:
    """A bridge. Equal requests share one.

    Attributes:
        domain_id: The ``ROS_DOMAIN_ID`` to use, or -1 for the environment's.
    """

    domain_id: int = -1

    def __post_init__(self) -> None:
        if not isinstance(self.domain_id, int) or not -1 <= self.domain_id <= 232:
            raise ValueError(
                f"domain_id must be -1 (the environment's) or 0..232, not {self.domain_id!r}"
            )


@dataclass(frozen=True)
class Ros2BridgeResponse:
    """A running bridge.

    Attributes:
        socket: The Unix socket path to connect a :class:`~temoto.ros2.client.BridgeClient` to.
        pid: The bridge's process id.
    """

    socket: str
    pid: int


def ros_python() -> str:
    """The interpreter that has rclpy: ``$TEMOTO_ROS2_PYTHON``, else this one.

    Returns:
        Its path.
    """
    return os.environ.get(PYTHON_VARIABLE) or sys.executable


def program_request(
    argv: tuple[str, ...], python: str | None = None, domain_id: int = -1
) -> ProcessRequest:
    """A Process Manager request for a ROS 2 program: a Python node file or an executable.

    A ``.py`` file runs with the interpreter that has rclpy (:func:`ros_python`); anything
    else is an executable. Both inherit the environment (the user's ROS variables); a
    ``domain_id`` other than -1 sets the program's ``ROS_DOMAIN_ID`` (as it does the bridge's).

    Args:
        argv: The program and its arguments.
        python: The interpreter for ``.py`` files (default :func:`ros_python`).
        domain_id: The program's ``ROS_DOMAIN_ID``, or -1 for the environment's.

    Returns:
        The request.

    Raises:
        ValueError: An empty ``argv``, or a domain id outside -1..232.
    """
    if not argv or not argv[0]:
        raise ValueError("a ROS 2 program needs a file or an executable")
    Ros2BridgeRequest(domain_id)  # the same check as the bridge's
    env = () if domain_id == -1 else (("ROS_DOMAIN_ID", str(domain_id)),)
    if argv[0].endswith(".py"):
        args = (str(Path(argv[0]).resolve()), *argv[1:])
        return ProcessRequest(python or ros_python(), args, env)
    return ProcessRequest(argv[0], tuple(argv[1:]), env)


def bridge_args(path: Path) -> tuple[str, ...]:
    """The bridge's arguments (after the interpreter): its socket, and this process as parent.

    Args:
        path: The socket path.

    Returns:
        The arguments.
    """
    return ("-m", "temoto.ros2.bridge", "--socket", str(path), "--parent", str(os.getpid()))


class Ros2Manager(ResourceServer[Ros2BridgeRequest, Ros2BridgeResponse]):
    """Serves ``"ros2"``: ROS 2 bridge processes, through the registrar's ``"process"`` server.

    Args:
        registrar: The registrar (with a Process Manager on it).
        start_timeout: Seconds a bridge may take to be ready (rclpy's import and init).
        python: The interpreter that runs the bridge: default ``$TEMOTO_ROS2_PYTHON`` (the
            python of another environment that has rclpy, keeping the ROS wheels' start-up
            hook out of this one), else this interpreter.
    """

    name: ClassVar[str] = "ros2"
    request_type: ClassVar[type] = Ros2BridgeRequest
    response_type: ClassVar[type] = Ros2BridgeResponse

    def __init__(
        self, registrar: Registrar, *, start_timeout: float = 30.0, python: str | None = None
    ) -> None:
        self.registrar = registrar
        self.start_timeout = start_timeout
        self.python = python or ros_python()
        self._used = False
        registrar.register(self)

    def on_load(self, request: Ros2BridgeRequest, ctx: LoadContext) -> Ros2BridgeResponse:
        """Start a bridge and wait until it is ready.

        Args:
            request: The request.
            ctx: The load's context.

        Returns:
            Its socket and pid.

        Raises:
            ConfigError: rclpy is not installed, or the RMW named by ``RMW_IMPLEMENTATION``
                cannot be used (one line).
            ResourceError: The bridge exited while starting, or was not ready in time.
        """
        if self.python == sys.executable:
            require_rclpy()  # else the bridge checks, and answers with the same line
        elif not os.access(self.python, os.X_OK):
            raise ConfigError(f"{PYTHON_VARIABLE}={self.python}: no such executable")
        self._used = True
        folder = Path(tempfile.mkdtemp(prefix="temoto-ros2-"))
        path = folder / "bridge.sock"
        env: list[tuple[str, str]] = []
        if request.domain_id >= 0:
            env.append(("ROS_DOMAIN_ID", str(request.domain_id)))
        if self.python != sys.executable:
            path_now = os.environ.get("PYTHONPATH", "")
            env.append(("PYTHONPATH", os.pathsep.join(p for p in (_PACKAGE_ROOT, path_now) if p)))
        died = threading.Event()
        why: list[str] = []

        def on_status(update: StatusUpdate) -> None:
            if update.status is Status.FATAL and not died.is_set():
                why.append(update.message)
                died.set()

        try:
            process = ctx.call(
                "process",
                ProcessRequest(self.python, bridge_args(path), tuple(env)),
                on_status=on_status,
            )
            pid = int(getattr(process.response, "pid", 0))
            self._wait_ready(path, died, why)
        except BaseException:
            shutil.rmtree(folder, ignore_errors=True)
            raise
        logger.info("ROS 2 bridge %d ready on %s", pid, path)
        return Ros2BridgeResponse(str(path), pid)

    def _wait_ready(self, path: Path, died: threading.Event, why: list[str]) -> None:
        deadline = time.monotonic() + self.start_timeout
        while True:
            if died.is_set():
                message = why[0] if why else "it exited"
                if f"exited with code {EXIT_WRONG_RMW}" in message:
                    rmw = os.environ.get("RMW_IMPLEMENTATION", "")
                    raise ConfigError(
                        f"RMW_IMPLEMENTATION={rmw}: this rclpy cannot use it (the ROS 2 bridge "
                        f"exited with code {EXIT_WRONG_RMW}); unset it or install that RMW"
                    )
                raise ResourceError(f"the ROS 2 bridge exited while starting: {message}")
            if path.exists():
                try:
                    probe = BridgeClient(str(path), timeout=max(0.1, deadline - time.monotonic()))
                except BridgeError as exc:
                    if "does not answer" not in str(exc):
                        raise ConfigError(str(exc)) from None  # the bridge refused: bad env
                else:
                    probe.close()
                    return
            if time.monotonic() >= deadline:
                raise ResourceError(
                    f"the ROS 2 bridge was not ready within {self.start_timeout:g} s"
                )
            died.wait(0.05)

    def on_unload(self, request: Ros2BridgeRequest, response: Ros2BridgeResponse) -> None:
        """The process (a dependency) is stopped by now; remove its folder (and any segments).

        Args:
            request: The request.
            response: The bridge.
        """
        self._cleanup(response)

    def on_status(self, resource: ResourceInfo, status: Status, message: str) -> None:
        """A bridge failed (its process exited): remove what it left.

        Args:
            resource: The bridge's resource.
            status: The status.
            message: What happened.
        """
        if status is Status.FATAL and isinstance(resource.response, Ros2BridgeResponse):
            logger.warning("the ROS 2 bridge failed: %s", message)
            self._cleanup(resource.response)

    def shutdown(self) -> None:
        """Remove the Fast DDS segments crashed processes left.

        Call it after the Process Manager's shutdown (its bridges are stopped by then). Nothing
        is looked at if this manager never started a bridge.
        """
        if not self._used:
            return
        with contextlib.suppress(OSError):
            clean_stale_segments()

    @staticmethod
    def _cleanup(response: Ros2BridgeResponse) -> None:
        folder = Path(response.socket).parent
        if folder.name.startswith("temoto-ros2-"):
            shutil.rmtree(folder, ignore_errors=True)
        with contextlib.suppress(OSError):
            clean_stale_segments()
