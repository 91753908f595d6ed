"""The consumers' side of the Robot Manager: :class:`RobotManagerClient` and :class:`RobotHandle`.

An action (or any consumer) requests the robot through the registrar — one reference, so it is
told of every fault of the robot's devices — and gets a handle with the robot's verbs. Each verb
returns a :class:`~temoto.managers.robot.features.Motion`; :func:`follow` waits for one inside
an action, stop- and pause-aware.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from temoto.core.registrar import Registrar, Resource
from temoto.drivers import DriverState, GeoPoint, MissionItem
from temoto.errors import ResourceBrokenError, StateError, StopRequested
from temoto.managers._client import find_manager, registrar_of
from temoto.managers.robot.features import (
    ArmController,
    DriveController,
    FlightController,
    Motion,
)
from temoto.managers.robot.manager import Robot, RobotManager, RobotRequest

if TYPE_CHECKING:
    from temoto.core.action import Action

__all__ = ["RobotHandle", "RobotManagerClient", "follow"]


class RobotHandle:
    """A consumer's robot: its verbs, while the reference is held.

    Args:
        robot: The loaded robot.
        resource: The consumer's reference.
    """

    def __init__(self, robot: Robot, resource: Resource[Any]) -> None:
        self._robot = robot
        self.resource = resource

    @property
    def name(self) -> str:
        """The robot's name."""
        return self._robot.name

    @property
    def features(self) -> tuple[str, ...]:
        """``navigation``, ``manipulation``, ``flight`` (those it has)."""
        return self._robot.features

    def healthy(self) -> bool:
        """Whether every device of the robot works."""
        return self._robot.healthy()

    def devices_of(self, feature: str) -> tuple[str, ...]:
        """The devices a feature moves (``navigation``, ``manipulation``, ``flight``).

        Raises:
            StateError: The robot has no such feature.
        """
        profile = self._robot.profile
        if feature == "navigation" and profile.navigation is not None:
            nav = profile.navigation
            left, right = (
                profile.joint_device(nav.left_wheel),
                profile.joint_device(nav.right_wheel),
            )
            return (left,) if left == right else (left, right)
        if feature == "manipulation" and profile.manipulation is not None:
            return (profile.manipulation.device,)
        if feature == "flight" and profile.flight is not None:
            return (profile.flight.device,)
        raise StateError(f"robot '{self.name}' has no {feature} feature")

    def require(self, feature: str) -> None:
        """Fail at once when a device the feature moves is not ACTIVE (FAULT, INACTIVE, ...).

        The robot's consumers are told of a fault when it happens; one that happened before
        they held the robot (or before the motion started) would otherwise leave a motion
        waiting for a device that does not move.

        Args:
            feature: ``navigation``, ``manipulation`` or ``flight``.

        Raises:
            StateError: The robot has no such feature.
            ResourceBrokenError: A device is not ACTIVE; the message names it, its state and
                its reason (``robot 'mm': device 'arm' is FAULT: lost torque ...``).
        """
        health = self._robot.health()
        for device in self.devices_of(feature):
            h = health.get(device)
            if h is None or h.state is DriverState.ACTIVE:
                continue
            reason = f": {h.message}" if h.message else ""
            raise ResourceBrokenError(
                f"robot '{self.name}': device '{device}' is {h.state.value}{reason}"
            )

    # ---- navigation ----------------------------------------------------------------------------

    def navigate_to(self, x: float, y: float, yaw: float | None = None) -> Motion:
        """Drive the base to ``(x, y)`` metres (odometry frame), then turn to ``yaw`` (rad)."""
        self.require("navigation")
        return self._drive().navigate_to(x, y, yaw)

    def pose(self) -> tuple[float, float, float]:
        """The base's odometry pose: x, y (m), yaw (rad)."""
        return self._drive().pose()

    # ---- manipulation --------------------------------------------------------------------------

    def move_joints(self, targets: Mapping[str, float]) -> Motion:
        """Move arm joints to positions (rad)."""
        self.require("manipulation")
        return self._arm().move_joints(targets)

    def move_to_pose(self, pose: str) -> Motion:
        """Move the arm to a named pose of the profile."""
        self.require("manipulation")
        return self._arm().move_to_pose(pose)

    def joint_positions(self) -> dict[str, float]:
        """The arm's joint positions (rad)."""
        return self._arm().positions()

    # ---- flight ---------------------------------------------------------------------------------

    def takeoff(self, altitude: float) -> Motion:
        """Arm and climb to ``altitude`` m above home."""
        self.require("flight")
        return self._flight().takeoff(altitude)

    def fly_to(self, lat: float, lon: float, alt: float) -> Motion:
        """Fly to a position (degrees, metres above home)."""
        self.require("flight")
        return self._flight().fly_to(GeoPoint(lat, lon, alt))

    def land(self) -> Motion:
        """Land where it is."""
        self.require("flight")
        return self._flight().land()

    def fly_mission(self, items: Sequence[MissionItem]) -> Motion:
        """Upload and fly a mission (:class:`~temoto.drivers.MissionItem` list) to its end."""
        self.require("flight")
        return self._flight().fly_mission(items)

    def telemetry(self) -> Any:
        """The vehicle's newest telemetry."""
        return self._flight().telemetry()

    # ---- deadlines (clock seconds at the feature's limits, no margin) --------------------------

    def estimate_navigate(self, x: float, y: float, yaw: float | None = None) -> float:
        """Seconds the base needs to get to ``(x, y)`` (:meth:`DriveController.estimate`)."""
        return self._drive().estimate(x, y, yaw)

    def estimate_joints(self, targets: Mapping[str, float]) -> float:
        """Seconds the arm needs for these targets (:meth:`ArmController.estimate`)."""
        return self._arm().estimate(targets)

    def pose_targets(self, pose: str) -> dict[str, float]:
        """The joint targets of a named pose (an empty dict for an unknown one)."""
        return dict(self._arm().feature.poses.get(pose, {}))

    def estimate_takeoff(self, altitude: float) -> float:
        """Seconds to climb to ``altitude`` m."""
        return self._flight().estimate_takeoff(altitude)

    def estimate_fly_to(self, lat: float, lon: float, alt: float) -> float:
        """Seconds to fly to a position."""
        return self._flight().estimate_fly_to(GeoPoint(lat, lon, alt))

    def estimate_land(self) -> float:
        """Seconds to land from here."""
        return self._flight().estimate_land()

    def estimate_mission(self, items: Sequence[MissionItem]) -> float:
        """Seconds to fly a mission from here."""
        return self._flight().estimate_mission(items)

    def _drive(self) -> DriveController:
        if self._robot.drive is None:
            raise StateError(f"robot '{self.name}' has no navigation feature")
        return self._robot.drive

    def _arm(self) -> ArmController:
        if self._robot.arm is None:
            raise StateError(f"robot '{self.name}' has no manipulation feature")
        return self._robot.arm

    def _flight(self) -> FlightController:
        if self._robot.flight is None:
            raise StateError(f"robot '{self.name}' has no flight feature")
        return self._robot.flight


class RobotManagerClient:
    """Finds the Robot Manager on a registrar and hands out robots.

    Args:
        registrar: The registrar the Robot Manager serves on.

    Raises:
        ResourceNotFoundError: No Robot Manager serves there.
    """

    def __init__(self, registrar: Registrar) -> None:
        self.registrar = registrar
        self.manager = find_manager(registrar, RobotManager, "Robot Manager")

    @classmethod
    def for_action(cls, action: Action) -> RobotManagerClient:
        """The client on the registrar of the engine running ``action``.

        Raises:
            ResourceNotFoundError: The engine has no registrar, or no Robot Manager on it.
        """
        return cls(registrar_of(action))

    def acquire(self, action: Action, robot: str = "") -> RobotHandle:
        """Request the robot for an action (released when its graph ends).

        Args:
            action: The action that uses it.
            robot: The robot's name (empty: the manager's robot).

        Returns:
            The handle.

        Raises:
            ResourceError: The robot cannot be loaded (a device does not answer, ...).
        """
        resource = action.acquire("robot", RobotRequest(robot))
        return RobotHandle(self.manager.robot(resource.response.robot), resource)

    def request(self, robot: str = "", *, client: str = "", on_status: Any = None) -> RobotHandle:
        """Request the robot outside an action (release ``handle.resource`` when done).

        Args:
            robot: The robot's name (empty: the manager's robot).
            client: Who holds it (for the registrar's accounting).
            on_status: Called with every status of the robot (faults, recoveries).

        Returns:
            The handle.
        """
        resource = self.registrar.call(
            "robot", RobotRequest(robot), client=client, on_status=on_status
        )
        return RobotHandle(self.manager.robot(resource.response.robot), resource)


def follow(action: Action, motion: Motion, timeout: float | None = None) -> bool:
    """Inside an action: wait for a motion (paused time does not count).

    Hold the motion in the action's ``on_pause`` and resume it in ``on_resume`` (the built-in
    robot actions do). A stop cancels the motion, its devices told to be still before this
    raises :class:`~temoto.errors.StopRequested`; a fault of the robot raises
    :class:`~temoto.errors.ResourceBrokenError` (and cancels it).

    Args:
        action: The running action.
        motion: What it waits for.
        timeout: Clock seconds (paused time not counted), or None.

    Returns:
        True if the goal was reached, False on timeout (the motion is cancelled).

    Raises:
        StopRequested: The node is being stopped.
        ResourceBrokenError: The robot failed.
        Exception: What ended the motion without reaching its goal.
    """
    motion.add_listener(action.wake)
    try:
        reached = action.wait_for(lambda: motion.done, timeout)
    except (StopRequested, Exception):
        motion.cancel("the action ended")
        raise
    if not reached:
        motion.cancel("timed out")
        return False
    if motion.error is not None:
        raise motion.error
    return True
