"""The motion models behind the simulated CAN motors: an ODrive axis and an MIT-mode motor.

:class:`AxisModel` is one ODrive axis (state, control mode, set-points, the velocity and current
limits, the cascaded controller driving inertia and friction, the overspeed check);
:class:`MitModel` a CubeMars AK motor under MIT-mode impedance control. Both are plain data
stepped by their simulator (:mod:`~temoto.drivers.can_motor.sim`) on its clock: no I/O, no
threads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Final

from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mit

__all__ = [
    "CURRENT_HARD_MAX",
    "CURRENT_LIMIT",
    "MIT_MECHANICS",
    "MIT_SUBSTEP",
    "POS_GAIN",
    "TORQUE_CONSTANT",
    "VEL_GAIN",
    "VEL_INTEGRATOR_GAIN",
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

#: The ODrive firmware's controller defaults (``controller.config``, firmware 0.5/0.6
#: ``controller.hpp``): ``pos_gain`` (turn/s)/turn, ``vel_gain`` N·m/(turn/s),
#: ``vel_integrator_gain`` N·m/(turn/s·s), ``vel_ramp_rate`` (turn/s)/s.
POS_GAIN: Final = 20.0
VEL_GAIN: Final = 1.0 / 6.0
VEL_INTEGRATOR_GAIN: Final = 2.0 / 6.0
VEL_RAMP_RATE: Final = 1.0

#: ``motor.config.current_lim``'s default, A (firmware ``motor.hpp``; ``Set_Limits`` sets it).
CURRENT_LIMIT: Final = 10.0

#: ``axis.config.motor.current_hard_max`` as the simulated axes report it over ``RxSdo``, A:
#: the simulator's own figure (the trip level is not modelled; firmware defaults differ by
#: board), above the current limit as the firmware requires.
CURRENT_HARD_MAX: Final = 20.0

#: Seconds of the axis model's integration step (at most; the firmware's loop runs at 8 kHz).
AXIS_SUBSTEP: Final = 0.001

#: The integrator's decay while the torque is limited, per second: the firmware multiplies it by
#: 0.99 every 8 kHz control cycle (``controller.cpp``'s anti-windup).
_WINDUP_DECAY: Final = 0.01 * 8000.0

_TAU: Final = 2.0 * math.pi

#: Simulated seconds a single step integrates at most; the rest of a longer jump of the clock
#: goes on at the velocity reached (settled by then).
MAX_INTEGRATION: Final = 10.0


@dataclass
class AxisModel:
    """One simulated ODrive axis (motor side: turn, turn/s, N·m).

    **Control**, as the ODrive firmware's cascaded controller (``controller.cpp``; docs
    "Control Structure and Tuning"): in ``POSITION_CONTROL`` the velocity set-point is
    ``pos_gain * (input_pos - pos)``; in ``VELOCITY_CONTROL`` it is ``input_vel`` (ramped at
    ``vel_ramp_rate`` with ``input_mode`` ``VEL_RAMP``); both are clamped to ``vel_limit``. The
    velocity loop is a PI: ``torque = vel_gain * (vel_setpoint - vel) + integrator`` (the
    integrator decays instead of growing while the torque is limited, the firmware's
    anti-windup). In ``TORQUE_CONTROL`` the torque is ``input_torque``. Every torque is then
    clamped to ``current_limit * torque_constant`` (in torque control first held inside
    ``±(vel_limit - vel) * vel_gain``: ``enable_torque_mode_vel_limit``, on by default): a stop
    decelerates as fast as the current limit allows.

    **Mechanics**: the torque turns ``inertia + load_inertia`` (kg·m², at the motor) against
    viscous ``damping`` (N·m per turn/s, the load's rolling or bearing friction); an axis out
    of closed loop coasts under that friction.

    **Limits**, as ``Set_Limits`` sets them (``controller.config.vel_limit`` and the motor's
    current limit). An axis that is found faster than :data:`VEL_LIMIT_TOLERANCE` times
    ``vel_limit`` (a limit lowered below the present speed) disarms with
    ``VELOCITY_LIMIT_VIOLATION``, as with ``enable_overspeed_error``.

    **Procedure result** (the heartbeat's ``Procedure_Result``, ODrive 0.6): ``SUCCESS`` at
    power-on; ``BUSY`` while closed-loop control runs; ``CANCELLED`` when a state request (IDLE)
    ends it; ``DISARMED`` when an error ends it (a watchdog, an estop, overspeed, a hardware
    fault) or refuses it (an axis with active errors does not arm).

    Attributes:
        node_id: Its CANSimple node id.
        vel_limit: turn/s (the simulator's default is generous: the driver sends no
            ``Set_Limits``; the firmware's own default is 2 turn/s).
        damping: N·m per turn/s.
        current_limit: A (``motor.config.current_lim``, 10 A by default; 0.6 names it
            ``axis.config.motor.current_soft_max``, which ``RxSdo`` reads and writes).
        current_hard_max: A, reported over ``RxSdo`` only (no trip is modelled).
        torque_constant: N·m per A.
        inertia: The rotor's inertia, kg·m² (assumed: a 50-65 mm outrunner such as ODrive's
            D5065/D6374 class).
        load_inertia: What the axis drives, reflected to the motor, kg·m².
        pos_gain: (turn/s) per turn.
        vel_gain: N·m per turn/s.
        vel_integrator_gain: N·m per turn/s per s.
        vel_ramp_rate: (turn/s) per s, for ``VEL_RAMP``.
    """

    node_id: int
    vel_limit: float = 50.0
    damping: float = 0.01
    current_limit: float = CURRENT_LIMIT
    current_hard_max: float = CURRENT_HARD_MAX
    torque_constant: float = TORQUE_CONSTANT
    inertia: float = 3e-4
    load_inertia: float = 7e-4
    pos_gain: float = POS_GAIN
    vel_gain: float = VEL_GAIN
    vel_integrator_gain: float = VEL_INTEGRATOR_GAIN
    vel_ramp_rate: float = VEL_RAMP_RATE
    pos: float = 0.0
    vel: float = 0.0
    state: int = cs.AxisState.IDLE
    error: int = 0
    procedure_result: int = cs.ProcedureResult.SUCCESS
    control_mode: int = cs.ControlMode.POSITION_CONTROL
    input_mode: int = cs.InputMode.PASSTHROUGH
    input_pos: float = 0.0
    input_vel: float = 0.0
    input_torque: float = 0.0
    vel_setpoint: float = 0.0  # the ramped velocity set-point (VEL_RAMP), turn/s
    integrator: float = 0.0  # the velocity integrator's torque, N·m
    torque: float = 0.0  # the torque applied last, N·m (Get_Torques' estimate)
    torque_target: float = 0.0  # the controller's torque before the limits, N·m
    stamp: float | None = None
    commands: int = 0  # set-points received (for tests)
    fed: float = -math.inf  # the watchdog's last feed, clock seconds

    @property
    def armed(self) -> bool:
        """Whether the axis is in closed-loop control."""
        return self.state == cs.AxisState.CLOSED_LOOP_CONTROL

    def arm(self) -> None:
        """Enter closed-loop control (a ``Set_Axis_State`` request): hold where it is."""
        if self.error:
            self.procedure_result = cs.ProcedureResult.DISARMED  # does not arm
            return
        self.input_pos = self.pos
        self.input_vel = self.input_torque = 0.0
        self.vel_setpoint = self.vel if self.input_mode == cs.InputMode.VEL_RAMP else 0.0
        self.integrator = 0.0
        self.state = cs.AxisState.CLOSED_LOOP_CONTROL
        self.procedure_result = cs.ProcedureResult.BUSY

    def idle(self) -> None:
        """An IDLE request: closed-loop control (if it ran) is cancelled."""
        if self.armed:
            self.procedure_result = cs.ProcedureResult.CANCELLED
        self.state = cs.AxisState.IDLE

    def disarm(self, error: int) -> None:
        """Raise ``error`` and leave closed loop, as the firmware does on an error."""
        self.error |= error
        if self.armed:
            self.procedure_result = cs.ProcedureResult.DISARMED
        self.state = cs.AxisState.IDLE

    def step(self, now: float) -> None:
        """Advance the model to ``now`` (clock seconds)."""
        if self.stamp is None or now <= self.stamp:
            self.stamp = now if self.stamp is None else self.stamp
            return
        dt, self.stamp = now - self.stamp, now
        span = min(dt, MAX_INTEGRATION)
        inertia = _TAU * (self.inertia + self.load_inertia)  # N·m per turn/s²
        h = AXIS_SUBSTEP
        stiff = self.vel_gain + self.damping
        if stiff > 0:
            h = min(h, 0.5 * inertia / stiff)
        steps = max(1, math.ceil(span / h))
        h = span / steps
        for _ in range(steps):
            if self.armed and abs(self.vel) > VEL_LIMIT_TOLERANCE * self.vel_limit:
                self.disarm(cs.AxisError.VELOCITY_LIMIT_VIOLATION)  # overspeed
            torque = self._control(h) if self.armed else 0.0
            self.torque = torque
            self.vel += h * (torque - self.damping * self.vel) / inertia
            self.pos += self.vel * h
        if not self.armed:
            self.torque = self.torque_target = 0.0
        self.pos += self.vel * (dt - span)

    def _control(self, h: float) -> float:
        """One control cycle of ``h`` seconds: the torque the controller applies, N·m."""
        limit = self.vel_limit
        if self.control_mode == cs.ControlMode.TORQUE_CONTROL:
            torque = self.input_torque
            self.integrator = 0.0
        else:
            if self.control_mode == cs.ControlMode.POSITION_CONTROL:
                goal = self.pos_gain * (self.input_pos - self.pos) + self.input_vel
                self.vel_setpoint = goal
            elif self.input_mode == cs.InputMode.VEL_RAMP:
                ramp = self.vel_ramp_rate * h
                goal = self.vel_setpoint + max(-ramp, min(ramp, self.input_vel - self.vel_setpoint))
                self.vel_setpoint = goal
            else:
                goal = self.vel_setpoint = self.input_vel
            feedforward = self.input_torque  # Set_Input_Pos / _Vel's torque feed-forward
            goal = max(-limit, min(limit, goal))
            error = goal - self.vel
            torque = self.vel_gain * error + self.integrator + feedforward
        self.torque_target = torque
        bounded = torque
        if self.control_mode == cs.ControlMode.TORQUE_CONTROL:  # enable_torque_mode_vel_limit
            low = (-limit - self.vel) * self.vel_gain
            high = (limit - self.vel) * self.vel_gain
            bounded = max(low, min(high, torque))
        top = self.torque_limit
        bounded = max(-top, min(top, bounded))
        if self.control_mode != cs.ControlMode.TORQUE_CONTROL:
            if bounded != torque:  # limited: the integrator decays (anti-windup)
                self.integrator *= math.exp(-_WINDUP_DECAY * h)
            else:
                self.integrator += self.vel_integrator_gain * error * h
        return bounded

    @property
    def torque_limit(self) -> float:
        """The largest torque the current limit allows, N·m."""
        return self.current_limit * self.torque_constant

    def set_limits(self, vel_limit: float, current_limit: float) -> None:
        """Apply ``Set_Limits`` (turn/s, A); a value that is not finite and positive is ignored.

        Args:
            vel_limit: The velocity limit, turn/s.
            current_limit: The current limit, A.
        """
        if math.isfinite(vel_limit) and vel_limit > 0:
            self.vel_limit = vel_limit
        if math.isfinite(current_limit) and current_limit > 0:
            self.current_limit = current_limit


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
