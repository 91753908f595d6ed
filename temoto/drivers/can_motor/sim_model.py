"""The motion models behind the simulated CAN motors: an ODrive axis and an MIT-mode motor.

:class:`AxisModel` is one ODrive axis (state, control mode, set-points, the velocity and current
limits, first-order motion, the overspeed check); :class:`MitModel` a CubeMars AK motor under
MIT-mode impedance control. Both are plain data stepped by their simulator
(:mod:`~temoto.drivers.can_motor.sim`) on its clock: no I/O, no threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mit

__all__ = ["TORQUE_CONSTANT", "VEL_LIMIT_TOLERANCE", "AxisModel", "MitModel"]

#: N·m per A: ODrive's default ``motor.config.torque_constant``, turning a current limit into
#: a torque limit and a torque into Iq.
TORQUE_CONSTANT: Final = 0.04

#: ``controller.config.vel_limit_tolerance``'s default: an axis faster than this many times its
#: velocity limit disarms with ``VELOCITY_LIMIT_VIOLATION`` (``enable_overspeed_error``).
VEL_LIMIT_TOLERANCE: Final = 1.2


@dataclass
class AxisModel:
    """One simulated ODrive axis (motor side: rev, rev/s, N·m).

    The motor's torque works against viscous ``damping`` only, so in torque control the speed
    settles at ``torque / damping`` and holding a speed takes ``damping * speed``.

    **Limits**, as ``Set_Limits`` sets them (``controller.config.vel_limit`` and the motor's
    current limit) and as the ODrive documents them: the velocity set-point, the position
    loop's velocity and (``enable_torque_mode_vel_limit``) the speed in torque control are
    clamped to ``vel_limit``; the torque is clamped to ``current_limit * torque_constant``, so
    a speed that needs more torque than that is not reached. An axis that is found faster than
    :data:`VEL_LIMIT_TOLERANCE` times ``vel_limit`` (a limit lowered below the present speed)
    disarms with ``VELOCITY_LIMIT_VIOLATION``, as with ``enable_overspeed_error``.

    Attributes:
        node_id: Its CANSimple node id.
        time_constant: Seconds of the first-order response.
        vel_limit: rev/s.
        damping: N·m per rev/s.
        current_limit: A (infinite: not limited until ``Set_Limits``).
        torque_constant: N·m per A.
    """

    node_id: int
    time_constant: float = 0.05
    vel_limit: float = 50.0
    damping: float = 0.1
    current_limit: float = math.inf
    torque_constant: float = TORQUE_CONSTANT
    pos: float = 0.0
    vel: float = 0.0
    state: int = cs.AxisState.IDLE
    error: int = 0
    control_mode: int = cs.ControlMode.POSITION_CONTROL
    input_mode: int = cs.InputMode.PASSTHROUGH
    input_pos: float = 0.0
    input_vel: float = 0.0
    input_torque: float = 0.0
    stamp: float | None = None
    commands: int = 0  # set-points received (for tests)
    fed: float = -math.inf  # the watchdog's last feed, clock seconds

    def step(self, now: float) -> None:
        """Advance the model to ``now`` (clock seconds)."""
        if self.stamp is None or now <= self.stamp:
            self.stamp = now if self.stamp is None else self.stamp
            return
        dt, self.stamp = now - self.stamp, now
        decay = math.exp(-dt / self.time_constant)
        if self.state != cs.AxisState.CLOSED_LOOP_CONTROL:
            self.vel *= decay  # coasting
            self.pos += self.vel * dt
            return
        if abs(self.vel) > VEL_LIMIT_TOLERANCE * self.vel_limit:  # overspeed: disarm
            self.error |= cs.AxisError.VELOCITY_LIMIT_VIOLATION
            self.state = cs.AxisState.IDLE
            self.vel *= decay
            self.pos += self.vel * dt
            return
        # the fastest the axis may go: its velocity limit, and the speed its torque limit holds
        fastest = min(self.vel_limit, self.torque_limit / self.damping)
        if self.control_mode == cs.ControlMode.POSITION_CONTROL:
            target = self.input_pos + (self.pos - self.input_pos) * decay
            vel = (target - self.pos) / dt
            vel = max(-fastest, min(fastest, vel))
            self.pos += vel * dt
            self.vel = vel
            return
        if self.control_mode == cs.ControlMode.VELOCITY_CONTROL:
            goal = self.input_vel
        else:
            goal = self._torque_command() / self.damping
        goal = max(-fastest, min(fastest, goal))
        new = goal + (self.vel - goal) * decay
        self.pos += 0.5 * (self.vel + new) * dt
        self.vel = new

    @property
    def torque_limit(self) -> float:
        """The largest torque the current limit allows, N·m."""
        return self.current_limit * self.torque_constant

    def _torque_command(self) -> float:
        limit = self.torque_limit
        return max(-limit, min(limit, self.input_torque))

    def set_limits(self, vel_limit: float, current_limit: float) -> None:
        """Apply ``Set_Limits`` (rev/s, A); a value that is not finite and positive is ignored.

        Args:
            vel_limit: The velocity limit, rev/s.
            current_limit: The current limit, A.
        """
        if math.isfinite(vel_limit) and vel_limit > 0:
            self.vel_limit = vel_limit
        if math.isfinite(current_limit) and current_limit > 0:
            self.current_limit = current_limit

    @property
    def torque(self) -> float:
        """The torque estimate, N·m."""
        if self.state != cs.AxisState.CLOSED_LOOP_CONTROL:
            return 0.0
        if self.control_mode == cs.ControlMode.TORQUE_CONTROL:
            return self._torque_command()
        return self.damping * self.vel

    @property
    def torque_target(self) -> float:
        """The torque the controller aims at, N·m (``Get_Torques``' ``Torque_Target``)."""
        if self.state != cs.AxisState.CLOSED_LOOP_CONTROL:
            return 0.0
        if self.control_mode == cs.ControlMode.TORQUE_CONTROL:
            return self._torque_command()
        return self.torque


@dataclass
class MitModel:
    """One simulated MIT-mode motor (output side: rad, rad/s, N·m).

    The motor's torque ``kp (p_des - p) + kd (v_des - v) + t_ff`` works against viscous
    ``damping`` (none by default) with no inertia, which makes the position a first-order
    system with the time constant ``(kd + damping) / kp``.

    Attributes:
        motor_id: Its CAN id.
        ranges: Its field ranges.
        damping: N·m per rad/s.
    """

    motor_id: int
    ranges: mit.MitRanges = field(default_factory=mit.MitRanges)
    damping: float = 0.0
    enabled: bool = False
    pos: float = 0.0
    vel: float = 0.0
    torque: float = 0.0
    command: mit.MitCommand = field(default_factory=lambda: mit.MitCommand(0, 0, 0, 0, 0))
    error: int = 0
    temperature: int = 30
    stamp: float | None = None
    commands: int = 0
    fed: float = -math.inf  # the CAN timeout's last reset (a command frame), clock seconds
    timeouts: int = 0  # times the CAN timeout zeroed the command (for tests)

    def step(self, now: float) -> None:
        """Advance the model to ``now`` (clock seconds)."""
        if self.stamp is None or now <= self.stamp:
            self.stamp = now if self.stamp is None else self.stamp
            return
        dt, self.stamp = now - self.stamp, now
        if not self.enabled:
            self.vel *= math.exp(-dt * 20.0)
            self.pos += self.vel * dt
            self.torque = 0.0
            return
        c = self.command
        friction = self.damping + c.kd
        if c.kp > 0:
            goal = c.p + (c.kd * c.v + c.t) / c.kp
            decay = math.exp(-dt * c.kp / friction) if friction > 0 else 0.0
            new = goal + (self.pos - goal) * decay
            vel = (new - self.pos) / dt
        elif friction > 0:
            vel = (c.kd * c.v + c.t) / friction
        else:  # a free motor under a constant torque runs up to its limit
            vel = math.copysign(self.ranges.v_max, c.t) if c.t else 0.0
        limit = self.ranges.v_max
        vel = max(-limit, min(limit, vel))
        self.pos += vel * dt  # the shaft turns on past the reply's ±p_max field
        self.vel = vel
        torque = c.kp * (c.p - self.pos) + c.kd * (c.v - vel) + c.t
        self.torque = max(-self.ranges.t_max, min(self.ranges.t_max, torque))
