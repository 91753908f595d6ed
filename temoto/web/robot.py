"""The robot as the live view shows it: a sampler of the Robot Manager's robot.

:class:`RobotWatch` reads the robot that the Robot Manager of a registrar has loaded, a few
times a second on its own thread (``temoto-web-robot``), through the robot's public reads
(odometry pose and goal, arm joint positions, vehicle telemetry, each device's health). It
never requests the robot: a view must not load hardware. While no robot is loaded it answers
``None``. It keeps the rover's trail (a bounded list of poses, one per ``trail_step`` metres
moved), so a page opened late, or reloaded, still shows where the rover went.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from collections import deque
from typing import TYPE_CHECKING, Any, final

from temoto._closing import Closing
from temoto.errors import ResourceNotFoundError, StateError

if TYPE_CHECKING:
    from temoto.core.registrar import Registrar
    from temoto.managers.robot.manager import Robot, RobotManager

__all__ = ["RobotWatch", "robot_state"]

logger = logging.getLogger(__name__)

#: Trail points kept (the oldest are dropped).
MAX_TRAIL = 2000


def _find_manager(registrar: Registrar) -> RobotManager | None:
    from temoto.managers.robot.manager import RobotManager  # only when a registrar is given

    try:
        server = registrar.server(RobotManager.name)
    except ResourceNotFoundError:
        return None
    return server if isinstance(server, RobotManager) else None


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def robot_state(robot: Robot) -> dict[str, Any]:
    """One reading of a loaded robot, JSON-ready.

    Args:
        robot: The robot (from :meth:`RobotManager.robot`).

    Returns:
        ``{"name", "loaded", "features", "healthy", "health": [...], "pose", "goal", "joints",
        "vehicle"}``; ``pose``/``goal`` (navigation), ``joints`` (manipulation) and ``vehicle``
        (flight) are None for a robot without that feature (see ``docs/live-view.md``);
        a read that fails (a device gone meanwhile) leaves its part None.
    """
    out: dict[str, Any] = {
        "name": robot.name,
        "loaded": True,
        "features": list(robot.features),
        "pose": None,
        "goal": None,
        "joints": None,
        "vehicle": None,
    }
    health = []
    for device, h in robot.health().items():
        health.append({"device": device, "state": h.state.value, "ok": h.ok, "message": h.message})
    out["health"] = health
    out["healthy"] = all(h["ok"] and h["state"] == "ACTIVE" for h in health)
    if robot.drive is not None:
        x, y, yaw = robot.drive.pose()
        out["pose"] = {"x": x, "y": y, "yaw": yaw}
        goal = robot.drive.goal()
        if goal is not None:
            out["goal"] = {"x": goal[0], "y": goal[1], "yaw": goal[2]}
    if robot.arm is not None:
        limits = robot.profile.devices[robot.arm.feature.device].limits
        with contextlib.suppress(Exception):  # a device closing meanwhile
            positions = robot.arm.positions()
            out["joints"] = [
                {
                    "name": joint,
                    "position": _finite(value),
                    "min": limits[joint][0] if joint in limits else None,
                    "max": limits[joint][1] if joint in limits else None,
                }
                for joint, value in positions.items()
            ]
    if robot.flight is not None:
        with contextlib.suppress(Exception):
            t = robot.flight.telemetry()
            out["vehicle"] = {
                "lat": t.position.lat,
                "lon": t.position.lon,
                "alt": t.position.alt,
                "mode": t.mode,
                "armed": t.armed,
                "battery_voltage": _finite(t.battery_voltage),
                "battery_remaining": t.battery_remaining,
                "heartbeat_age": _finite(t.heartbeat_age),
                "status": list(t.status_texts[-3:]),
            }
    return out


@final
class RobotWatch(Closing):
    """Samples the robot of a registrar's Robot Manager (started at once).

    Args:
        registrar: The registrar the Robot Manager serves on (looked up at every sample, so a
            manager registered later is found).
        period_s: Real seconds between samples.
        trail_step: Metres the rover must move before another trail point is kept.
    """

    def __init__(
        self, registrar: Registrar, period_s: float = 0.2, trail_step: float = 0.02
    ) -> None:
        self.registrar = registrar
        self.period_s = period_s
        self.trail_step = trail_step
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._latest: dict[str, Any] | None = None
        self._trail: deque[tuple[float, float]] = deque(maxlen=MAX_TRAIL)
        self._robot_id = 0
        self._thread = threading.Thread(target=self._loop, name="temoto-web-robot", daemon=True)
        self._thread.start()

    def state(self) -> dict[str, Any] | None:
        """The newest reading with the trail, or None when no robot was ever loaded.

        Returns:
            :func:`robot_state`'s dict plus ``"trail": [[x, y], ...]`` (oldest first);
            ``"loaded"`` is False once the robot was released (the last reading stays,
            without a goal).
        """
        with self._lock:
            if self._latest is None:
                return None
            return {**self._latest, "trail": [list(p) for p in self._trail]}

    def sample(self) -> None:
        """Take one reading now (the thread calls this every ``period_s``).

        Returns:
            None.
        """
        manager = _find_manager(self.registrar)
        robot = None
        if manager is not None:
            with contextlib.suppress(StateError):
                robot = manager.robot()
        if robot is None:  # not loaded (yet, or released): the last reading stays, marked
            with self._lock:
                if self._latest is not None and self._latest["loaded"]:
                    self._latest = {**self._latest, "loaded": False, "goal": None}
            return
        try:
            reading = robot_state(robot)
        except Exception:  # a robot being unloaded: keep the last reading
            logger.debug("robot reading failed", exc_info=True)
            return
        with self._lock:
            if id(robot) != self._robot_id:  # a newly loaded robot: a new odometry frame
                self._robot_id = id(robot)
                self._trail.clear()
            elif self._latest is not None:  # a device closing: keep what it showed last
                for part in ("joints", "vehicle"):
                    if reading[part] is None:
                        reading[part] = self._latest[part]
            pose = reading["pose"]
            if pose is not None:
                here = (round(pose["x"], 4), round(pose["y"], 4))
                last = self._trail[-1] if self._trail else None
                if last is None or math.dist(last, here) >= self.trail_step:
                    self._trail.append(here)
            self._latest = reading

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.period_s)

    def close(self) -> None:
        """Stop sampling and join the thread. Idempotent.

        Returns:
            None.
        """
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join()
