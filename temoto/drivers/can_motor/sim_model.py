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

__all__ = [
    "MIT_MECHANICS",
    "MIT_SUBSTEP",
    "TORQUE_CONSTANT",
    "VEL_LIMIT_TOLERANCE",
    "AxisModel",
    "MitMechanics",
    "MitModel",
]

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


#: Seconds of the MIT model's integration step (at most): the AK firmware evaluates its
#: impedance law in its 40 kHz current loop; a quarter millisecond keeps the semi-implicit Euler
#: steps well inside the stable range of every model's stiffest gains (kp 500, kd 5).
MIT_SUBSTEP: Final = 0.00025

#: Simulated seconds a single :meth:`MitModel.step` integrates at most; the rest of a longer
#: jump of the clock goes on at the velocity reached (settled by then).
MIT_MAX_INTEGRATION: Final = 10.0


@dataclass(frozen=True, slots=True)
class MitMechanics:
    """The mechanics of one motor model, output side.

    Attributes:
        inertia: Rotor inertia seen at the output shaft (rotor x gear ratio²), kg·m².
        damping: Viscous friction, N·m per rad/s.
        coulomb: Dry (Coulomb) friction of the gearbox, N·m; it also holds a motor at rest
            against a smaller torque.
    """

    inertia: float
    damping: float
    coulomb: float


#: Plausible mechanics per AK model (output side). The inertias are of the order of the
#: CubeMars specification sheets' rotor inertia (hundreds of g·cm² for the 60-100 mm frames)
#: reflected through the planetary gearbox (x ratio²); the frictions are assumed (a few tenths
#: of a percent to one percent of the peak torque, typical of a single-stage planetary
#: quasi-direct-drive actuator). Not measured on a motor: set your own on :class:`MitModel`.
MIT_MECHANICS: Final = {
    "AK10-9": MitMechanics(inertia=0.0081, damping=0.04, coulomb=0.3),
    "AK60-6": MitMechanics(inertia=0.0009, damping=0.01, coulomb=0.08),
    "AK70-10": MitMechanics(inertia=0.0040, damping=0.02, coulomb=0.15),
    "AK80-6": MitMechanics(inertia=0.0022, damping=0.02, coulomb=0.08),
    "AK80-9": MitMechanics(inertia=0.0049, damping=0.02, coulomb=0.1),
}


@dataclass
class MitModel:
    """One simulated MIT-mode motor (output side: rad, rad/s, N·m).

    In motor mode the firmware (Ben Katz's mini-cheetah ``motorcontrol``, ``torque_control``
    in ``foc.c``, which the CubeMars AK firmware follows) evaluates, in its current loop, on the
    *measured* position and velocity::

        torque = clamp(kp (p_des - p) + kd (v_des - v) + t_ff, ±t_max)

    The model integrates that torque (every :data:`MIT_SUBSTEP` at most) against the rotor's
    and the load's inertia, viscous ``damping`` and Coulomb ``coulomb`` friction; the torque a
    reply reports is the one applied last. The supply voltage bounds the speed: driving
    torque falls linearly to zero at ``v_max`` (the velocity field's range standing for the
    no-load speed), so a free motor under a constant torque runs up to ``v_max`` at most.
    Out of motor mode (after ``exit``, or before
    ``enter``) no current flows: the motor coasts to rest under its friction.

    A zero command as a host packs it (p, v, kp, kd, t_ff = 0) decodes in the firmware to
    t_ff = -0.0044 N·m and v_des = -0.012 rad/s on an AK80-9 (``uint_to_float`` of the fields'
    rounded-down midpoints 2047 of 0..4095): far below the gearbox's dry friction, so the motor
    stays where it is, as a real one does.

    Attributes:
        motor_id: Its CAN id.
        ranges: Its field ranges.
        inertia: Rotor inertia at the output, kg·m² (:data:`MIT_MECHANICS`; AK80-9 by default).
        load_inertia: What the shaft carries, kg·m² (none by default).
        damping: Viscous friction, N·m per rad/s.
        coulomb: Dry friction, N·m.
    """

    motor_id: int
    ranges: mit.MitRanges = field(default_factory=mit.MitRanges)
    inertia: float = MIT_MECHANICS["AK80-9"].inertia
    load_inertia: float = 0.0
    damping: float = MIT_MECHANICS["AK80-9"].damping
    coulomb: float = MIT_MECHANICS["AK80-9"].coulomb
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

    @classmethod
    def of(cls, motor_id: int, model: str, ranges: mit.MitRanges | None = None) -> MitModel:
        """A motor of a named AK model, with its ranges and :data:`MIT_MECHANICS`.

        Args:
            motor_id: Its CAN id.
            model: A key of :data:`~temoto.drivers.can_motor.mitmode.MODELS`.
            ranges: Ranges other than the model's (a profile's ``p_max`` ...).

        Returns:
            The model.

        Raises:
            KeyError: An unknown model.
        """
        mech = MIT_MECHANICS[model]
        return cls(
            motor_id,
            ranges if ranges is not None else mit.MODELS[model],
            inertia=mech.inertia,
            damping=mech.damping,
            coulomb=mech.coulomb,
        )

    def _motor_torque(self) -> float:
        """The impedance law on the present state, clamped to ±t_max (0 out of motor mode)."""
        if not self.enabled:
            return 0.0
        c = self.command
        torque = c.kp * (c.p - self.pos) + c.kd * (c.v - self.vel) + c.t
        limit = self.ranges.t_max
        torque = max(-limit, min(limit, torque))
        if torque * self.vel > 0:  # the back-EMF leaves less torque the faster it turns
            top = limit * max(0.0, 1.0 - abs(self.vel) / self.ranges.v_max)
            torque = math.copysign(min(abs(torque), top), torque)
        return torque

    def step(self, now: float) -> None:
        """Advance the model to ``now`` (clock seconds)."""
        if self.stamp is None or now <= self.stamp:
            self.stamp = now if self.stamp is None else self.stamp
            return
        dt, self.stamp = now - self.stamp, now
        inertia = self.inertia + self.load_inertia
        c = self.command
        kd = c.kd if self.enabled else 0.0
        kp = c.kp if self.enabled else 0.0
        h = MIT_SUBSTEP  # inside the stable range of semi-implicit Euler, with margin
        if kd + self.damping > 0:
            h = min(h, 0.5 * inertia / (kd + self.damping))
        if kp > 0:
            h = min(h, 0.2 * math.sqrt(inertia / kp))
        span = min(dt, MIT_MAX_INTEGRATION)
        steps = max(1, math.ceil(span / h))
        h = span / steps
        torque = 0.0
        for _ in range(steps):
            torque = self._motor_torque()
            self.vel = self._accelerate(torque, inertia, h)
            self.pos += self.vel * h  # the shaft turns on past the reply's ±p_max field
        self.pos += self.vel * (dt - span)
        self.torque = torque

    def _accelerate(self, torque: float, inertia: float, h: float) -> float:
        """The velocity after ``h`` seconds under ``torque`` and the friction."""
        v, dry = self.vel, self.coulomb
        if v == 0.0 and abs(torque) <= dry:
            return 0.0  # static friction holds it
        direction = v if v != 0.0 else torque
        friction = math.copysign(dry, direction) + self.damping * v
        new = v + h * (torque - friction) / inertia
        if v != 0.0 and (new > 0) != (v > 0) and abs(torque) <= dry:
            return 0.0  # friction stops a motor; it does not turn it round
        return new
