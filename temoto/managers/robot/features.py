"""What a robot can do, built from its drivers: drive, arm, flight (the Robot Manager's verbs).

Each feature turns a goal into set-points for its drivers' capability APIs and says when the
goal is reached, through a :class:`Motion`. The drive and the arm are stepped by the robot's
control thread at a fixed rate on the robot's clock; a vehicle's commands are sent at once
(its autopilot does the control) and its motion is checked on every step.

A new goal for a feature replaces the one it had (the old motion fails with "superseded");
:meth:`Motion.hold` stops where it is (a paused graph) and :meth:`Motion.resume` goes on;
:meth:`Motion.cancel` stops for good.

**Stop and hold act on the devices at once.** :meth:`Motion.cancel` and :meth:`Motion.hold`
return only after the feature's devices were told to be still, on the caller's thread: the
arm's position set-points become the joints' present positions, the base's wheels are
commanded zero velocity, the vehicle is switched to LOITER (ArduCopter brakes to a stop and
holds its position; the acknowledgement is awaited). The controller sends every set-point under
its lock, so the control thread can never send the old goal's set-point after a stop or a hold.
:meth:`Motion.resume` sends the goal again (the arm's targets; the vehicle's mode and target)
and the motion goes on from where it is.

**Own mode changes of a vehicle** (an ArduCopter failsafe's RTL or LAND, a pilot's mode
switch) end its flight motion with an error naming the mode: the controller knows the modes it
commanded and checks the vehicle's reported mode on every step.

**Deadlines.** Each controller estimates how long a goal takes from the motion and its limits
(:meth:`DriveController.estimate`, :meth:`ArmController.estimate`, the flight controller's
``estimate_*``); the built-in robot actions add a margin to it (see
:mod:`temoto.actions.builtin.robot._common`).
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from temoto.clock import Clock
from temoto.config import ArmFeature, DriveFeature
from temoto.drivers import Actuator, ControlMode, JointCommand
from temoto.errors import StateError
from temoto.managers.robot.flight import FlightController
from temoto.managers.robot.motion import Motion

__all__ = ["ArmController", "DriveController", "FlightController", "Motion"]

logger = logging.getLogger(__name__)


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


class DriveController:
    """A differential-drive base: odometry from the wheel joints, go-to-pose control.

    Args:
        feature: The profile's drive settings.
        wheels: The driver of each wheel joint (left, right).
        clock: The robot's clock, for how long a velocity command holds (without one, the
            control steps' ``dt`` are counted).
    """

    #: Proportional gains: linear speed per metre of distance, turn rate per radian.
    K_LINEAR = 1.5
    K_ANGULAR = 3.0
    #: Heading error beyond which the base turns in place before driving.
    TURN_FIRST = 0.35

    def __init__(
        self,
        feature: DriveFeature,
        wheels: tuple[Actuator, Actuator],
        clock: Clock | None = None,
    ) -> None:
        self.feature = feature
        self._clock = clock
        self._left, self._right = wheels
        self._lock = threading.Lock()
        self.x = self.y = self.yaw = 0.0
        self._last: tuple[float, float] | None = None
        self._goal: tuple[float, float, float | None] | None = None
        self._motion: Motion | None = None
        self._commanded = (0.0, 0.0)
        #: A velocity command (``cmd_vel``): v (m/s), w (rad/s), and until when it holds (the
        #: clock's reading; without a clock, the seconds it still holds).
        self._velocity: tuple[float, float, float] | None = None

    def pose(self) -> tuple[float, float, float]:
        """The odometry pose: x, y (m), yaw (rad) since the robot was loaded."""
        with self._lock:
            return self.x, self.y, self.yaw

    def velocity(self) -> tuple[float, float]:
        """The base's velocity from its wheels' joint velocities: v (m/s), w (rad/s)."""
        r, sep = self.feature.wheel_radius, self.feature.wheel_separation
        left = self._left.read_state().joints[self.feature.left_wheel].velocity * r
        right = self._right.read_state().joints[self.feature.right_wheel].velocity * r
        return (left + right) / 2, (right - left) / sep

    def command_velocity(self, v: float, w: float, hold: float) -> tuple[float, float]:
        """Drive at ``v`` m/s turning at ``w`` rad/s, for at most ``hold`` clock seconds.

        A velocity command (a ROS 2 ``cmd_vel``) is clamped to ``max_speed`` and
        ``max_turn_rate``, as the goal controller's commands are; unless a new one comes within
        ``hold`` seconds, the control thread commands the wheels zero velocity (a stale command
        never drives on). A goal (an action's motion) has the base: a velocity command is
        refused while one runs, and a new goal or a stop ends the velocity command.

        Args:
            v: Linear speed, m/s (forward positive).
            w: Turn rate, rad/s (counter-clockwise positive).
            hold: Clock seconds the command holds.

        Returns:
            The command applied (after clamping).

        Raises:
            ValueError: A value is not finite, or ``hold`` is not positive.
            StateError: A goal drives the base.
        """
        if not (math.isfinite(v) and math.isfinite(w)):
            raise ValueError("a velocity command must be finite")
        if not hold > 0:
            raise ValueError("a velocity command must hold for a positive time")
        v = _clamp(v, self.feature.max_speed)
        w = _clamp(w, self.feature.max_turn_rate)
        with self._lock:
            if self._motion is not None and not self._motion.done:
                raise StateError(f"the base is driven by a goal ({self._motion.what})")
            until = hold if self._clock is None else self._clock.monotonic() + hold
            self._velocity = (v, w, until)
        return v, w

    def goal(self) -> tuple[float, float, float | None] | None:
        """The goal it drives to: x, y (m), yaw (rad, or None), or None when it has none."""
        with self._lock:
            return self._goal

    def estimate(self, x: float, y: float, yaw: float | None = None) -> float:
        """Seconds the base needs from where it is to ``(x, y)`` (and ``yaw``), at its limits.

        The turn towards the goal at ``max_turn_rate``, the distance at ``max_speed``, the
        proportional controller's approach from ``max_speed / K_LINEAR`` metres down to the
        tolerance (``ln(d0 / tolerance) / K_LINEAR``), and the final turn to ``yaw``.

        Returns:
            The estimate, clock seconds.
        """
        f = self.feature
        px, py, pyaw = self.pose()
        dist = math.hypot(x - px, y - py)
        seconds = 0.0
        heading = pyaw
        if dist > f.tolerance:
            heading = math.atan2(y - py, x - px)
            seconds += abs(_wrap(heading - pyaw)) / f.max_turn_rate
            seconds += dist / f.max_speed
            slow = min(dist, f.max_speed / self.K_LINEAR)
            seconds += math.log(max(1.0, slow / f.tolerance)) / self.K_LINEAR
        if yaw is not None:
            seconds += abs(_wrap(yaw - heading)) / f.max_turn_rate
        return seconds

    def navigate_to(self, x: float, y: float, yaw: float | None = None) -> Motion:
        """Drive to ``(x, y)`` (odometry frame), then turn to ``yaw`` if given.

        Raises:
            ValueError: A coordinate is not finite.
        """
        if not all(math.isfinite(v) for v in (x, y, 0.0 if yaw is None else yaw)):
            raise ValueError("a goal must be finite")
        motion = Motion(f"navigate to ({x:g}, {y:g})", self)
        with self._lock:
            old, self._motion, self._goal = self._motion, motion, (x, y, yaw)
            self._velocity = None
        if old is not None:
            old.supersede()
        return motion

    def stop(self, error: BaseException | None = None) -> None:
        """Cancel the goal and command the wheels zero velocity now (if they were not).

        Args:
            error: What the goal's motion fails with (None: "cancelled").
        """
        with self._lock:
            old, self._motion, self._goal = self._motion, None, None
            self._velocity = None
            if self._commanded != (0.0, 0.0):
                self._still()
        if old is not None and error is not None:
            old.fail(error)
        elif old is not None:
            old.cancel()

    def _still(self) -> None:
        """Lock held: zero wheel velocity on the wire (sent even if it was sent before)."""
        try:
            self._send(0.0, 0.0)
        except StateError as err:  # not ACTIVE (faulted, closed): the manager makes it safe
            logger.info("drive: zero velocity not sent: %s", err)
        except Exception as err:
            logger.warning("drive: zero velocity not sent: %s", err)

    def _halt(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is not motion:
                return
            self._motion = self._goal = None
            self._still()

    def _hold(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is motion:
                self._still()

    def _resume(self, motion: Motion) -> None:
        """Nothing to send: the next step drives on from where the base is."""

    def step(self, dt: float) -> None:
        """Control thread: update odometry, command the wheels (under the lock)."""
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
            if motion is None and self._velocity is not None:
                cv, cw, until = self._velocity
                if self._clock is None:
                    until -= dt
                    left_s = until
                else:  # clock time: a control loop that fell behind does not stretch it
                    left_s = until - self._clock.monotonic()
                if left_s > 0:
                    v, w = cv, cw
                    self._velocity = (cv, cw, until)
                else:  # no new command within its hold time: stop
                    self._velocity = None
            wl = (v - w * sep / 2) / r
            wr = (v + w * sep / 2) / r
            if (wl, wr) != self._commanded:
                self._send(wl, wr)  # under the lock: a stop or hold cannot be overtaken
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
        self._commanded = (wl, wr)  # even if sending fails: the next step does not resend it
        if self._left is self._right:
            self._left.command([left, right])
        else:
            self._left.command([left])
            self._right.command([right])


class ArmController:
    """An arm: joint position goals and named poses.

    Args:
        feature: The profile's arm settings.
        driver: The device that moves the joints.
        joint_speed: Each joint's speed limit (rad/s), for :meth:`estimate`; by default the
            driver's servos' ``velocity_limit`` where the profile gives one.
    """

    #: Joint speed (rad/s) assumed for a joint without a limit in the profile, for
    #: :meth:`estimate`: a slow Dynamixel X at a light load (the e-Manual gives 46-57 rpm,
    #: 4.8-6 rad/s, without load; position-mode profiles are often far slower).
    DEFAULT_JOINT_SPEED = 1.0
    #: Longest age (s) of a reading that :meth:`here` moves on by its velocity.
    EXTRAPOLATE_MAX = 0.05

    def __init__(
        self,
        feature: ArmFeature,
        driver: Actuator,
        joint_speed: Mapping[str, float] | None = None,
    ) -> None:
        self.feature = feature
        self._driver = driver
        self._lock = threading.Lock()
        self._motion: Motion | None = None
        self._targets: dict[str, float] = {}
        if joint_speed is None:  # the servos' velocity_limit of the profile, where given
            joint_speed = {
                str(servo.joint): float(servo.velocity_limit)
                for servo in getattr(driver, "servos", ())
                if getattr(servo, "velocity_limit", None)
            }
        self.joint_speed = dict(joint_speed)

    def positions(self) -> dict[str, float]:
        """The arm's joint positions (rad)."""
        joints = self._driver.read_state().joints
        return {j: joints[j].position for j in self.feature.joints}

    def estimate(self, targets: Mapping[str, float]) -> float:
        """Seconds the slowest joint needs to reach its target at its speed limit.

        Returns:
            The estimate, clock seconds.
        """
        now = self.positions()
        return max(
            (
                abs(float(v) - now.get(j, float(v)))
                / self.joint_speed.get(j, self.DEFAULT_JOINT_SPEED)
                for j, v in targets.items()
            ),
            default=0.0,
        )

    def move_joints(self, targets: Mapping[str, float]) -> Motion:
        """Move joints to positions (rad); joints not named stay.

        Raises:
            ValueError: An unknown joint or a non-finite value.
        """
        unknown = sorted(set(targets) - set(self.feature.joints))
        if unknown:
            raise ValueError(f"the arm has no joint {', '.join(unknown)}")
        commands = [JointCommand(j, ControlMode.POSITION, float(v)) for j, v in targets.items()]
        motion = Motion("move " + ", ".join(f"{j}={v:.3g}" for j, v in targets.items()), self)
        with self._lock:
            old, self._motion, self._targets = self._motion, motion, dict(targets)
            self._driver.command(commands)
        if old is not None:
            old.supersede()
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

    def stop(self, error: BaseException | None = None) -> None:
        """Cancel the goal; the joints hold where they are.

        Args:
            error: What the goal's motion fails with (None: "cancelled").
        """
        with self._lock:
            old, self._motion = self._motion, None
            if old is not None and not old.done:
                self._still(self._targets)
        if old is not None and error is not None:
            old.fail(error)
        elif old is not None:
            old.cancel()

    def here(self, joints: Iterable[str]) -> dict[str, float]:
        """Where the joints are now: the newest reading moved on by its velocity for its age.

        The driver's reading is up to a poll period old (20 ms at 50 Hz: 0.1 rad at 5 rad/s);
        a hold at that older position would send a moving joint back. The age counted is at
        most :attr:`EXTRAPOLATE_MAX`, and the result stays within the joint's limits.

        Args:
            joints: The joints.

        Returns:
            Position (rad) by joint.
        """
        states = self._driver.read_state().joints
        clock = getattr(self._driver, "clock", None)
        now = clock.monotonic() if clock is not None else None
        limits: Mapping[str, tuple[float, float]] = getattr(self._driver, "joint_limits", {})
        out: dict[str, float] = {}
        for j in joints:
            state = states[j]
            age = 0.0 if now is None else min(max(now - state.stamp, 0.0), self.EXTRAPOLATE_MAX)
            position = state.position + state.velocity * age
            if j in limits:
                low, high = limits[j]
                position = min(max(position, low), high)
            out[j] = position
        return out

    def _still(self, joints: Iterable[str]) -> None:
        """Lock held: position set-points = where the joints are now (:meth:`here`)."""
        try:
            now = self.here(joints)
            self._driver.command([JointCommand(j, ControlMode.POSITION, p) for j, p in now.items()])
        except StateError as err:  # not ACTIVE (faulted, closed): the manager makes it safe
            logger.info("arm: hold where it is not sent: %s", err)
        except Exception as err:
            logger.warning("arm: hold where it is not sent: %s", err)

    def _halt(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is not motion:
                return
            self._motion = None
            self._still(self._targets)

    def _hold(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is motion:
                self._still(self._targets)

    def _resume(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is motion:
                self._driver.command(
                    [JointCommand(j, ControlMode.POSITION, v) for j, v in self._targets.items()]
                )

    def step(self, dt: float) -> None:
        """Control thread: check arrival (set-points are sent by the verbs, hold and resume)."""
        with self._lock:
            motion, targets = self._motion, dict(self._targets)
        if motion is None:
            return
        if motion.done:
            with self._lock:
                if self._motion is motion:
                    self._motion = None
            return
        if motion.held:
            return
        now = self.positions()
        worst = max((abs(now[j] - v) for j, v in targets.items()), default=0.0)
        motion.progress = f"{worst:.3f} rad to go"
        if worst <= self.feature.tolerance:
            with self._lock:
                if self._motion is not motion or motion.held:
                    return
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
