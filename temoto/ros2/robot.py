"""The robot on ROS 2: a profile's ``ros2:`` block, served through a bridge process.

A :class:`RobotRos2Link` publishes a loaded robot's state at the profile's rates
(:class:`~temoto.config.Ros2Settings`):

* ``nav_msgs/msg/Odometry`` on ``/<robot>/odom`` (the drive's odometry pose and its wheels'
  velocity; frames ``odom`` -> ``base_link``);
* ``sensor_msgs/msg/JointState`` on ``/<robot>/joint_states`` (every joint of its ACTIVE devices);
* ``sensor_msgs/msg/NavSatFix`` on ``/<robot>/fix`` (a vehicle's position; altitude above home);
* ``diagnostic_msgs/msg/DiagnosticArray`` on ``/diagnostics`` (one status per device).

With ``cmd_vel: true`` it subscribes to ``geometry_msgs/msg/Twist`` on ``/<robot>/cmd_vel`` and
hands each command to the drive through the checks an action's motion goes through: every
device of the base must be ACTIVE, the speeds are clamped to ``max_speed`` and
``max_turn_rate``, a goal of an action has the base (the command is then ignored), and a
command holds for ``cmd_vel_timeout`` seconds only: when no new one comes, the base stops
(:meth:`~temoto.managers.robot.features.DriveController.command_velocity`). Without the
opt-in nothing subscribes to ``cmd_vel``.

The bridge (``"ros2"``) is held outside the robot's dependencies: a crashed bridge does not fail
the robot's consumers; the link logs it, lets the bridge go and requests a new one after
:data:`RETRY_S` seconds. One thread per robot, ``temoto-ros2-robot-<robot>``, publishes and
supervises; the ``cmd_vel`` subscription waits in ``temoto-ros2-cmd-vel-<robot>``. Both are
joined by :meth:`RobotRos2Link.close`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any, Final, Protocol

from temoto.config import Ros2Settings
from temoto.core.registrar import Registrar, Status
from temoto.core.registrar.messages import StatusUpdate
from temoto.drivers import DriverState, Health, JointState
from temoto.errors import ConfigError, ProfileError, ResourceError, StateError
from temoto.ros2.client import BridgeClient, BridgeError
from temoto.ros2.manager import Ros2BridgeRequest

__all__ = ["RETRY_S", "Robot", "RobotRos2Link", "diagnostics_message", "odometry_message"]

logger = logging.getLogger(__name__)

#: Real seconds between a lost bridge and the request for a new one.
RETRY_S: Final = 1.0
#: Real seconds a publication may take (the bridge answers at once: no subscriber is awaited).
PUBLISH_TIMEOUT_S: Final = 5.0
#: ``diagnostic_msgs/DiagnosticStatus`` levels.
OK, WARN, ERROR, STALE = 0, 1, 2, 3

_TYPES: Final = {
    "odom": "nav_msgs/msg/Odometry",
    "joint_states": "sensor_msgs/msg/JointState",
    "fix": "sensor_msgs/msg/NavSatFix",
    "diagnostics": "diagnostic_msgs/msg/DiagnosticArray",
}


class Robot(Protocol):
    """What the link needs of a loaded robot (:class:`temoto.managers.robot.manager.Robot`)."""

    name: str
    #: The drive (``DriveController``): ``pose()``, ``velocity()``, ``command_velocity()``.
    drive: Any
    #: The flight controller: ``telemetry()``.
    flight: Any

    def health(self) -> dict[str, Health]:
        """Each device's health."""
        ...

    def joint_states(self) -> list[JointState]:
        """The joints of the ACTIVE devices."""
        ...

    def navigation_devices(self) -> tuple[str, ...]:
        """The devices the drive moves."""
        ...


def _stamp(now: float) -> dict[str, int]:
    sec = math.floor(now)
    return {"sec": int(sec), "nanosec": min(int((now - sec) * 1e9), 999_999_999)}


def odometry_message(
    pose: tuple[float, float, float], velocity: tuple[float, float], now: float, prefix: str = ""
) -> dict[str, Any]:
    """A ``nav_msgs/Odometry`` as JSON.

    Args:
        pose: x, y (m), yaw (rad) in the odometry frame.
        velocity: v (m/s), w (rad/s) in the base frame.
        now: Wall-clock seconds for the stamp.
        prefix: Put before the frame ids.

    Returns:
        The message.
    """
    x, y, yaw = pose
    v, w = velocity
    return {
        "header": {"stamp": _stamp(now), "frame_id": f"{prefix}odom"},
        "child_frame_id": f"{prefix}base_link",
        "pose": {
            "pose": {
                "position": {"x": x, "y": y, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)},
            }
        },
        "twist": {"twist": {"linear": {"x": v}, "angular": {"z": w}}},
    }


def diagnostics_message(robot: str, health: dict[str, Any], now: float) -> dict[str, Any]:
    """A ``diagnostic_msgs/DiagnosticArray`` as JSON: one status per device.

    ACTIVE and ok is OK; FAULT is ERROR; any other state (INACTIVE, UNCONFIGURED, FINALIZED) is
    WARN.

    Args:
        robot: The robot's name (the statuses are named ``<robot>/<device>``).
        health: Device name -> its :class:`~temoto.drivers.Health`.
        now: Wall-clock seconds for the stamp.

    Returns:
        The message.
    """
    statuses = []
    for device, h in health.items():
        if h.state is DriverState.FAULT or not h.ok:
            level = ERROR
        elif h.state is DriverState.ACTIVE:
            level = OK
        else:
            level = WARN
        statuses.append(
            {
                "level": level,
                "name": f"{robot}/{device}",
                "message": h.message or h.state.value,
                "hardware_id": h.driver,
                "values": [{"key": "state", "value": h.state.value}],
            }
        )
    return {"header": {"stamp": _stamp(now)}, "status": statuses}


class RobotRos2Link:
    """A robot's state on ROS 2, and (opted in) its ``cmd_vel``.

    Args:
        registrar: The registrar (with a :class:`~temoto.ros2.manager.Ros2Manager` on it).
        robot: The loaded robot.
        settings: The profile's ``ros2:`` block.
        source: The profile's file (for errors).
    """

    def __init__(
        self, registrar: Registrar, robot: Robot, settings: Ros2Settings, source: str = ""
    ) -> None:
        self.registrar = registrar
        self.robot = robot
        self.settings = settings
        self.source = source
        self.prefix = f"/{robot.name}"
        self._stop = threading.Event()
        self._lost = threading.Event()
        self._ref = ""
        self._client: BridgeClient | None = None
        self._thread: threading.Thread | None = None
        self._cmd_thread: threading.Thread | None = None
        #: What happened to the ``cmd_vel`` commands (counts, for the log and the tests).
        self.commands = {"applied": 0, "refused": 0}
        self._said: set[str] = set()

    # ---------------------------------------------------------------------------- the bridge

    def _connect(self) -> None:
        """Hold a bridge and connect to it.

        Raises:
            ProfileError: rclpy (the extra) or the RMW is missing (one line naming ``ros2``).
            ResourceError: The bridge did not start.
        """
        self._lost.clear()

        def on_status(update: StatusUpdate) -> None:
            if update.status is Status.FATAL:
                name = self.robot.name
                logger.warning("robot %s: the ROS 2 bridge failed: %s", name, update.message)
                self._lost.set()

        try:
            res = self.registrar.call(
                "ros2",
                Ros2BridgeRequest(self.settings.domain_id),
                client=f"{self.registrar.name}/robot-ros2/{self.robot.name}",
                holder="",
                on_status=on_status,
            )
        except ResourceError as err:
            inner: BaseException = err
            while inner.__cause__ is not None:
                inner = inner.__cause__
            if isinstance(inner, ConfigError):  # no rclpy (the extra), a wrong RMW: one line
                text = str(inner).replace("the ROS 2 actions need", "the ros2 block needs")
                raise ProfileError(text, file=self.source or None, path="ros2") from None
            raise
        self._ref = res.id
        try:
            self._client = BridgeClient(res.response.socket)
        except BridgeError:
            self._release()
            raise

    def _release(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._ref:
            with contextlib.suppress(ResourceError):
                self.registrar.release(self._ref)
            self._ref = ""

    # ------------------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Hold a bridge, then publish (and subscribe) in threads of their own.

        Raises:
            ProfileError: The ``ros2:`` block cannot be served here: rclpy (the ``temoto[ros2]``
                extra) is missing, or the RMW cannot be used (one line).
            ResourceError: The bridge did not start.
        """
        self._connect()
        self._thread = threading.Thread(
            target=self._run, name=f"temoto-ros2-robot-{self.robot.name}"
        )
        self._thread.start()
        logger.info(
            "robot %s on ROS 2: %s%s",
            self.robot.name,
            ", ".join(f"{t} at {r:g} Hz" for t, r in self.settings.rates.items()) or "nothing",
            f"; cmd_vel on {self.prefix}/cmd_vel" if self.settings.cmd_vel else "",
        )

    def close(self) -> None:
        """Stop publishing and subscribing, join the threads, let the bridge go."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self._release()

    def _run(self) -> None:
        while not self._stop.is_set():
            client = self._client
            if client is not None:
                if self.settings.cmd_vel:
                    self._cmd_thread = threading.Thread(
                        target=self._subscribe,
                        args=(client,),
                        name=f"temoto-ros2-cmd-vel-{self.robot.name}",
                    )
                    self._cmd_thread.start()
                try:
                    self._publish_loop(client)
                except BridgeError as err:
                    if not self._stop.is_set():
                        logger.warning("robot %s: ROS 2 bridge lost: %s", self.robot.name, err)
                self._lost.set()
                with contextlib.suppress(OSError):
                    client.close()  # ends the subscription's request
                if self._cmd_thread is not None:
                    self._cmd_thread.join()
                    self._cmd_thread = None
                self._release()
            if self._stop.wait(RETRY_S):
                return
            try:
                self._connect()
            except (ResourceError, ConfigError) as err:
                logger.warning("robot %s: no ROS 2 bridge: %s", self.robot.name, err)

    # ----------------------------------------------------------------------------- publishing

    def _publish_loop(self, client: BridgeClient) -> None:
        periods = {topic: 1.0 / rate for topic, rate in self.settings.rates.items()}
        due = dict.fromkeys(periods, time.monotonic())
        builders: dict[str, Callable[[float], dict[str, Any] | None]] = {
            "odom": self._odom,
            "joint_states": self._joint_states,
            "fix": self._fix,
            "diagnostics": self._diagnostics,
        }
        while not self._stop.is_set() and not self._lost.is_set():
            now = time.monotonic()
            for topic, at in due.items():
                if at > now:
                    continue
                due[topic] = max(at + periods[topic], now)
                try:
                    message = builders[topic](time.time())
                except (StateError, KeyError, AttributeError) as err:  # a device not readable
                    self._once(topic, f"robot {self.robot.name}: {topic} not published: {err}")
                    continue
                if message is None:
                    continue
                name = "/diagnostics" if topic == "diagnostics" else f"{self.prefix}/{topic}"
                try:
                    client.request(
                        "publish",
                        reply_timeout=PUBLISH_TIMEOUT_S,
                        topic=name,
                        type=_TYPES[topic],
                        message=message,
                        timeout=0,
                    )
                except BridgeError as err:
                    if err.gone:
                        raise
                    self._once(topic, f"robot {self.robot.name}: {name} not published: {err}")
            wait = min(due.values(), default=now + 1.0) - time.monotonic()
            self._stop.wait(max(wait, 0.001))

    def _once(self, key: str, text: str) -> None:
        if key not in self._said:
            self._said.add(key)
            logger.warning("%s", text)

    def _odom(self, now: float) -> dict[str, Any] | None:
        drive = self.robot.drive
        if drive is None:
            return None
        health = self.robot.health()
        moving = all(
            health[d].state is DriverState.ACTIVE
            for d in self.robot.navigation_devices()
            if d in health
        )
        velocity = drive.velocity() if moving else (0.0, 0.0)  # a device not readable: at rest
        return odometry_message(drive.pose(), velocity, now, self.settings.frame_prefix)

    def _joint_states(self, now: float) -> dict[str, Any] | None:
        joints = self.robot.joint_states()
        return {
            "header": {"stamp": _stamp(now), "frame_id": ""},
            "name": [j.joint for j in joints],
            "position": [j.position for j in joints],
            "velocity": [j.velocity for j in joints],
            "effort": [j.effort for j in joints],
        }

    def _fix(self, now: float) -> dict[str, Any] | None:
        flight = self.robot.flight
        if flight is None:
            return None
        where = flight.telemetry().position
        return {
            "header": {"stamp": _stamp(now), "frame_id": f"{self.settings.frame_prefix}gps"},
            "status": {"status": 0, "service": 1},  # STATUS_FIX, SERVICE_GPS
            "latitude": where.lat,
            "longitude": where.lon,
            "altitude": where.alt,
            "position_covariance_type": 0,  # COVARIANCE_TYPE_UNKNOWN
        }

    def _diagnostics(self, now: float) -> dict[str, Any] | None:
        return diagnostics_message(self.robot.name, self.robot.health(), now)

    # ------------------------------------------------------------------------------- cmd_vel

    def _subscribe(self, client: BridgeClient) -> None:
        with contextlib.suppress(BridgeError):
            client.request(
                "subscribe",
                stop=lambda: self._stop.is_set() or self._lost.is_set(),
                on_event=self._on_cmd_vel,
                topic=f"{self.prefix}/cmd_vel",
                type="geometry_msgs/msg/Twist",
                depth=1,
            )

    def _on_cmd_vel(self, event: dict[str, Any]) -> None:
        """A ``Twist`` arrived (the bridge client's reader thread): check it, then drive."""
        msg = event.get("message") or {}
        try:
            v = float(msg["linear"]["x"])
            w = float(msg["angular"]["z"])
        except (KeyError, TypeError, ValueError):
            return
        self.drive(v, w)

    def drive(self, v: float, w: float) -> bool:
        """Apply one velocity command through the safety checks (see the module).

        Args:
            v: Linear speed, m/s.
            w: Turn rate, rad/s.

        Returns:
            Whether it was applied.
        """
        drive = self.robot.drive
        why = ""
        if drive is None:
            why = "the robot has no navigation feature"
        else:
            for device in self.robot.navigation_devices():
                h = self.robot.health().get(device)
                if h is not None and h.state is not DriverState.ACTIVE:
                    why = f"device '{device}' is {h.state.value}"
                    break
        if not why and drive is not None:
            try:
                drive.command_velocity(v, w, self.settings.cmd_vel_timeout)
            except (StateError, ValueError) as err:
                why = str(err)
        if why:
            self.commands["refused"] += 1
            self._once(f"cmd_vel:{why}", f"robot {self.robot.name}: cmd_vel ignored: {why}")
            return False
        self.commands["applied"] += 1
        return True
