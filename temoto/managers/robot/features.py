"""What a robot can do, built from its drivers: drive, arm, flight (the Robot Manager's verbs).

Each feature turns a goal into set-points for its drivers' capability APIs and says when the
goal is reached, through a :class:`Motion`. The drive and the arm are stepped by the robot's
control thread at a fixed rate on the robot's clock; a vehicle's commands are sent at once
(its autopilot does the control) and its motion is checked on every step.

A new goal for a feature replaces the one it had (the old motion fails with "superseded");
:meth:`Motion.hold` stops where it is (a paused graph) and :meth:`Motion.resume` goes on;
:meth:`Motion.cancel` stops for good.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from temoto.config import ArmFeature, DriveFeature, FlightFeature
from temoto.drivers import (
    Actuator,
    ControlMode,
    GeoPoint,
    JointCommand,
    MissionItem,
    MissionVehicle,
    Vehicle,
)
from temoto.errors import StateError

__all__ = ["ArmController", "DriveController", "FlightController", "Motion"]

logger = logging.getLogger(__name__)

_EARTH_RADIUS = 6_371_000.0  # m


class Motion:
    """One goal of one feature, and how it is going.

    Args:
        what: A description for messages (``navigate to (1.0, 2.0)``).
    """

    def __init__(self, what: str) -> None:
        self.what = what
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._error: BaseException | None = None
        self._held = False
        self._superseded = False
        self._listeners: list[Callable[[], None]] = []
        self.progress = ""

    def __repr__(self) -> str:
        state = "done" if self.done else ("held" if self.held else "moving")
        return f"<Motion {self.what} {state}>"

    @property
    def done(self) -> bool:
        """Reached, failed or cancelled."""
        return self._done.is_set()

    @property
    def error(self) -> BaseException | None:
        """Why it did not reach its goal, or None."""
        with self._lock:
            return self._error

    @property
    def superseded(self) -> bool:
        """Ended because a newer goal for the same feature replaced it."""
        with self._lock:
            return self._superseded

    @property
    def held(self) -> bool:
        """Held where it is (see :meth:`hold`)."""
        with self._lock:
            return self._held

    def add_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener`` (no arguments) when the motion ends or makes progress.

        Args:
            listener: E.g. an action's ``wake``.
        """
        with self._lock:
            self._listeners.append(listener)
        if self.done:
            listener()

    def wait(self, timeout: float | None = None) -> bool:
        """Block (real time) until it ends.

        Args:
            timeout: Real seconds, or None.

        Returns:
            Whether it ended.
        """
        return self._done.wait(timeout)

    def hold(self) -> None:
        """Stop where it is until :meth:`resume`."""
        with self._lock:
            self._held = True

    def resume(self) -> None:
        """Go on after :meth:`hold`."""
        with self._lock:
            self._held = False

    def supersede(self) -> None:
        """End it because a newer goal for the same feature replaced it."""
        with self._lock:
            if self._done.is_set():
                return
            self._superseded = True
        self.cancel("superseded by a new goal")

    def cancel(self, why: str = "cancelled") -> None:
        """End it without reaching the goal.

        Args:
            why: Recorded as the error.
        """
        self.finish(StateError(f"{self.what}: {why}"))

    def finish(self, error: BaseException | None = None) -> None:
        """Controller: the goal was reached (or not, with ``error``). Idempotent."""
        with self._lock:
            if self._done.is_set():
                return
            self._error = error
            self._done.set()
            listeners = list(self._listeners)
        for listener in listeners:
            try:
                listener()
            except Exception:
                logger.exception("a motion listener raised")


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


class DriveController:
    """A differential-drive base: odometry from the wheel joints, go-to-pose control.

    Args:
        feature: The profile's drive settings.
        wheels: The driver of each wheel joint (left, right).
    """

    #: Proportional gains: linear speed per metre of distance, turn rate per radian.
    K_LINEAR = 1.5
    K_ANGULAR = 3.0
    #: Heading error beyond which the base turns in place before driving.
    TURN_FIRST = 0.35

    def __init__(self, feature: DriveFeature, wheels: tuple[Actuator, Actuator]) -> None:
        self.feature = feature
        self._left, self._right = wheels
        self._lock = threading.Lock()
        self.x = self.y = self.yaw = 0.0
        self._last: tuple[float, float] | None = None
        self._goal: tuple[float, float, float | None] | None = None
        self._motion: Motion | None = None
        self._commanded = (0.0, 0.0)

    def pose(self) -> tuple[float, float, float]:
        """The odometry pose: x, y (m), yaw (rad) since the robot was loaded."""
        with self._lock:
            return self.x, self.y, self.yaw

    def goal(self) -> tuple[float, float, float | None] | None:
        """The goal it drives to: x, y (m), yaw (rad, or None), or None when it has none."""
        with self._lock:
            return self._goal

    def navigate_to(self, x: float, y: float, yaw: float | None = None) -> Motion:
        """Drive to ``(x, y)`` (odometry frame), then turn to ``yaw`` if given.

        Raises:
            ValueError: A coordinate is not finite.
        """
        if not all(math.isfinite(v) for v in (x, y, 0.0 if yaw is None else yaw)):
            raise ValueError("a goal must be finite")
        motion = Motion(f"navigate to ({x:g}, {y:g})")
        with self._lock:
            old, self._motion, self._goal = self._motion, motion, (x, y, yaw)
        if old is not None:
            old.supersede()
        return motion

    def stop(self) -> None:
        """Cancel the goal and stop the wheels at the next step."""
        with self._lock:
            old, self._motion, self._goal = self._motion, None, None
        if old is not None:
            old.cancel()

    def step(self, dt: float) -> None:
        """Control thread: update odometry, command the wheels."""
        r = self.feature.wheel_radius
        sep = self.feature.wheel_separation
        left = self._left.read_state().joints[self.feature.left_wheel].position
        right = self._right.read_state().joints[self.feature.right_wheel].position
        with self._lock:
            if self._last is not None:
                dl = (left - self._last[0]) * r
                dr = (right - self._last[1]) * r
                d, dyaw = (dl + dr) / 2, (dr - dl) / sep
                self.x += d * math.cos(self.yaw + dyaw / 2)
                self.y += d * math.sin(self.yaw + dyaw / 2)
                self.yaw = _wrap(self.yaw + dyaw)
            self._last = (left, right)
            motion, goal = self._motion, self._goal
            v = w = 0.0
            reached = False
            if motion is not None and goal is not None and motion.done:
                self._motion = self._goal = None  # cancelled from outside
            elif motion is not None and goal is not None and not motion.held:
                v, w, reached = self._control(goal)
                motion.progress = f"at ({self.x:.2f}, {self.y:.2f})"
            if reached:
                self._motion = self._goal = None
        wl = (v - w * sep / 2) / r
        wr = (v + w * sep / 2) / r
        if (wl, wr) != self._commanded:
            self._send(wl, wr)
        if reached and motion is not None:
            motion.finish()

    def _control(self, goal: tuple[float, float, float | None]) -> tuple[float, float, bool]:
        gx, gy, gyaw = goal
        dx, dy = gx - self.x, gy - self.y
        dist = math.hypot(dx, dy)
        f = self.feature
        if dist > f.tolerance:
            err = _wrap(math.atan2(dy, dx) - self.yaw)
            w = _clamp(self.K_ANGULAR * err, f.max_turn_rate)
            v = 0.0 if abs(err) > self.TURN_FIRST else _clamp(self.K_LINEAR * dist, f.max_speed)
            return v, w, False
        if gyaw is not None:
            err = _wrap(gyaw - self.yaw)
            if abs(err) > f.tolerance:
                return 0.0, _clamp(self.K_ANGULAR * err, f.max_turn_rate), False
        return 0.0, 0.0, True

    def _send(self, wl: float, wr: float) -> None:
        f = self.feature
        left = JointCommand(f.left_wheel, ControlMode.VELOCITY, wl)
        right = JointCommand(f.right_wheel, ControlMode.VELOCITY, wr)
        if self._left is self._right:
            self._left.command([left, right])
        else:
            self._left.command([left])
            self._right.command([right])
        self._commanded = (wl, wr)


class ArmController:
    """An arm: joint position goals and named poses.

    Args:
        feature: The profile's arm settings.
        driver: The device that moves the joints.
    """

    def __init__(self, feature: ArmFeature, driver: Actuator) -> None:
        self.feature = feature
        self._driver = driver
        self._lock = threading.Lock()
        self._motion: Motion | None = None
        self._targets: dict[str, float] = {}
        self._sent_hold = False

    def positions(self) -> dict[str, float]:
        """The arm's joint positions (rad)."""
        joints = self._driver.read_state().joints
        return {j: joints[j].position for j in self.feature.joints}

    def move_joints(self, targets: Mapping[str, float]) -> Motion:
        """Move joints to positions (rad); joints not named stay.

        Raises:
            ValueError: An unknown joint or a non-finite value.
        """
        unknown = sorted(set(targets) - set(self.feature.joints))
        if unknown:
            raise ValueError(f"the arm has no joint {', '.join(unknown)}")
        commands = [JointCommand(j, ControlMode.POSITION, float(v)) for j, v in targets.items()]
        motion = Motion("move " + ", ".join(f"{j}={v:.3g}" for j, v in targets.items()))
        with self._lock:
            old, self._motion, self._targets = self._motion, motion, dict(targets)
            self._sent_hold = False
        if old is not None:
            old.supersede()
        self._driver.command(commands)
        return motion

    def move_to_pose(self, pose: str) -> Motion:
        """Move to a named pose of the profile.

        Raises:
            KeyError: No pose of that name.
        """
        if pose not in self.feature.poses:
            known = ", ".join(sorted(self.feature.poses)) or "none"
            raise KeyError(f"the arm has no pose {pose!r} (poses: {known})")
        return self.move_joints(self.feature.poses[pose])

    def stop(self) -> None:
        """Cancel the goal (the joints hold their set-points)."""
        with self._lock:
            old, self._motion = self._motion, None
        if old is not None:
            old.cancel()

    def step(self, dt: float) -> None:
        """Control thread: check arrival; hold where it is while held."""
        with self._lock:
            motion, targets = self._motion, dict(self._targets)
        if motion is None:
            return
        if motion.done:
            with self._lock:
                if self._motion is motion:
                    self._motion = None
            return
        now = self.positions()
        if motion.held:
            if not self._sent_hold:
                self._driver.command(
                    [JointCommand(j, ControlMode.POSITION, now[j]) for j in targets]
                )
                self._sent_hold = True
            return
        if self._sent_hold:  # resumed: the goal again
            self._driver.command(
                [JointCommand(j, ControlMode.POSITION, v) for j, v in targets.items()]
            )
            self._sent_hold = False
        worst = max((abs(now[j] - v) for j, v in targets.items()), default=0.0)
        motion.progress = f"{worst:.3f} rad to go"
        if worst <= self.feature.tolerance:
            with self._lock:
                if self._motion is motion:
                    self._motion = None
            motion.finish()


def _distance(a: GeoPoint, b: GeoPoint) -> float:
    """Metres between two points (haversine over the ground, plus the altitude difference)."""
    p1, p2 = math.radians(a.lat), math.radians(b.lat)
    dp, dl = p2 - p1, math.radians(b.lon - a.lon)
    h = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    ground = 2 * _EARTH_RADIUS * math.asin(min(1.0, math.sqrt(h)))
    return math.hypot(ground, b.alt - a.alt)


class FlightController:
    """A flying vehicle: take off, fly to, land, fly a mission; arrival checked on every step.

    A held motion makes the vehicle LOITER; resumed, it goes on in GUIDED (a mission: in AUTO,
    from the item it was at). A mission that ends without being done (stopped, timed out)
    leaves the vehicle in LOITER, holding where it is, not flying the rest on its own.

    Args:
        feature: The profile's flight settings.
        vehicle: The vehicle driver.
    """

    #: Altitude (m) below which a landing vehicle counts as down.
    LANDED_ALT = 0.3

    def __init__(self, feature: FlightFeature, vehicle: Vehicle) -> None:
        self.feature = feature
        self._vehicle = vehicle
        self._lock = threading.Lock()
        self._motion: Motion | None = None
        self._check: Callable[[Any], bool] | None = None
        self._resend: Callable[[], None] | None = None
        self._resume_mode = "GUIDED"
        self._describe: Callable[[Any], str] | None = None
        self._holding = False

    def telemetry(self) -> Any:
        """The vehicle's newest telemetry."""
        return self._vehicle.telemetry()

    def takeoff(self, altitude: float, mode: str = "GUIDED") -> Motion:
        """Switch to ``mode``, arm and climb to ``altitude`` m above home.

        Raises:
            ValueError: ``altitude`` is not positive.
            DriverError: The vehicle refused (MavlinkCommandError) or did not answer.
        """
        if not (math.isfinite(altitude) and altitude > 0):
            raise ValueError(f"a take-off altitude must be positive, got {altitude}")
        self._vehicle.set_mode(mode)
        if not self._vehicle.telemetry().armed:
            self._vehicle.arm()
        self._vehicle.takeoff(altitude)
        target = altitude - self.feature.tolerance
        return self._start(
            f"take off to {altitude:g} m",
            lambda t: t.position.alt >= target,
            lambda: self._vehicle.takeoff(altitude),
        )

    def fly_to(self, target: GeoPoint) -> Motion:
        """Fly to a position.

        Raises:
            DriverError: The vehicle refused or did not answer.
        """
        self._vehicle.goto(target)
        tol = self.feature.tolerance
        return self._start(
            f"fly to ({target.lat:.6f}, {target.lon:.6f}, {target.alt:g} m)",
            lambda t: _distance(t.position, target) <= tol,
            lambda: self._vehicle.goto(target),
        )

    def land(self) -> Motion:
        """Land where it is.

        Raises:
            DriverError: The vehicle refused or did not answer.
        """
        self._vehicle.land()
        return self._start("land", lambda t: t.position.alt <= self.LANDED_ALT, self._vehicle.land)

    def fly_mission(self, items: Sequence[MissionItem]) -> Motion:
        """Upload a mission, start it (arming and taking off as the vehicle needs) and follow it.

        The motion is reached when the vehicle reports its last item done (a mission that ends
        with ``land`` or ``rtl``: also down, within :attr:`LANDED_ALT`); its progress says
        ``item 2/5 (waypoint), alt 9.8 m``. Ended without being reached (cancelled, timed
        out), it sets the vehicle to LOITER.

        Args:
            items: The mission.

        Raises:
            StateError: The vehicle cannot fly missions.
            ValueError: No items.
            DriverError: The vehicle refused the mission or its start, or did not answer.
        """
        vehicle = self._vehicle
        if not isinstance(vehicle, MissionVehicle):
            raise StateError(
                f"the flight feature's vehicle ({type(vehicle).__name__}) cannot fly missions"
            )
        mission = list(items)
        if not mission:
            raise ValueError("a mission needs at least one item")
        vehicle.upload_mission(mission)
        vehicle.start_mission()
        total = len(mission)
        lands = mission[-1].kind in ("land", "rtl")

        def done(telemetry: Any) -> bool:
            progress = vehicle.mission_progress
            down = telemetry.position.alt <= self.LANDED_ALT
            if lands and progress.current >= total and down and not telemetry.armed:
                return True  # landed at the end and disarmed, as ArduCopter does
            return progress.finished and (not lands or down)

        def describe(telemetry: Any) -> str:
            at = vehicle.mission_progress.current
            kind = f" ({mission[at - 1].kind})" if 1 <= at <= total else ""
            return f"item {at}/{total}{kind}, alt {telemetry.position.alt:.1f} m"

        motion = self._start(
            f"fly a mission of {total} items", done, None, resume_mode="AUTO", describe=describe
        )
        motion.add_listener(lambda: self._hold_unfinished(motion))
        return motion

    def _hold_unfinished(self, motion: Motion) -> None:
        """A mission that ended unreached (not superseded): LOITER, not the rest of it."""
        if not motion.done or motion.error is None or motion.superseded:
            return
        try:
            self._vehicle.set_mode("LOITER")
        except Exception as err:
            logger.warning("%s ended (%s); LOITER refused: %s", motion.what, motion.error, err)
        else:
            logger.info("%s ended (%s): vehicle LOITER", motion.what, motion.error)

    def _start(
        self,
        what: str,
        check: Callable[[Any], bool],
        resend: Callable[[], None] | None,
        *,
        resume_mode: str = "GUIDED",
        describe: Callable[[Any], str] | None = None,
    ) -> Motion:
        motion = Motion(what)
        with self._lock:
            old, self._motion, self._check, self._resend = self._motion, motion, check, resend
            self._resume_mode, self._describe = resume_mode, describe
            self._holding = False
        if old is not None:
            old.supersede()
        return motion

    def step(self, dt: float) -> None:
        """Control thread: check arrival; loiter while held, go on when resumed."""
        with self._lock:
            motion, check, resend = self._motion, self._check, self._resend
            resume_mode, describe = self._resume_mode, self._describe
        if motion is None or check is None:
            return
        if motion.done:
            with self._lock:
                if self._motion is motion:
                    self._motion = None
            return
        try:
            if motion.held and not self._holding:
                self._vehicle.set_mode("LOITER")
                self._holding = True
                return
            if not motion.held and self._holding:
                self._vehicle.set_mode(resume_mode)
                if resend is not None:
                    resend()
                self._holding = False
        except Exception as err:  # a refused mode change ends the motion with the reason
            motion.finish(err)
            return
        telemetry = self._vehicle.telemetry()
        motion.progress = (
            describe(telemetry) if describe is not None else f"alt {telemetry.position.alt:.1f} m"
        )
        if not motion.held and check(telemetry):
            with self._lock:
                if self._motion is motion:
                    self._motion = None
            motion.finish()


def controllers_step(controllers: Sequence[Any], dt: float) -> list[BaseException]:
    """Step every controller; what each raised (the robot thread logs them)."""
    errors: list[BaseException] = []
    for controller in controllers:
        try:
            controller.step(dt)
        except Exception as err:
            errors.append(err)
    return errors
