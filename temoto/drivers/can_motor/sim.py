"""Simulated CAN motors at the device end of a python-can bus: an ODrive and MIT-mode motors.

:class:`SimODrive` answers CANSimple for one or more axes (node ids) on one bus, like a board
per node on a real bus: the cyclic messages of ODrive 0.6 at the rates of its
``axis.config.can.*_msg_rate_ms`` settings (:data:`CYCLIC_RATES`: heartbeats every 100 ms and
encoder estimates every 10 ms by default, the others off; 0 turns one off), each also on request
(an RTR frame), axis states, controller modes, position / velocity / torque inputs,
``Set_Limits`` (the velocity limit and the current limit bound the motion: see
:class:`AxisModel`), errors, estop and clear errors, and ``RxSdo`` reads and writes of the
endpoints the driver checks a profile against (``vel_limit``, ``current_soft_max``,
``current_hard_max``, ``torque_constant``: :mod:`~temoto.drivers.can_motor.odrive_sdo`).
:class:`SimMitMotor` answers the MIT-mode protocol of CubeMars AK motors: enter / exit / zero
frames and impedance commands, each with a reply.

Both step a motion model (torque, inertia, friction) on the injected clock, on a thread that
waits with ``clock.wait`` (so a :class:`~temoto.clock.ManualClock` test runs in virtual time),
and read the bus on another thread. Faults (:meth:`~temoto.drivers.sim.Simulator.inject`,
optionally ``node=<id>`` for one axis or motor): ``silence`` (dead: no frames, commands
ignored), ``corrupt`` (frames go out truncated: a wrong DLC), ``hardware_error`` (``kind`` =
overheat, overload or voltage: error bits, the axis disarms; latched until Clear_Errors on an
ODrive), ``no_heartbeat`` (ODrive: cyclic heartbeats stop, everything else answers),
``no_encoder`` (ODrive: cyclic encoder estimates stop, heartbeats go on) and ``link_loss`` (no
frames in either direction, every node).

**Device watchdogs** (``docs/driver-can.md``), modelled as the vendors document them so that a
killed host is testable: :class:`SimODrive` with ``watchdog_timeout`` > 0 is an ODrive with
``axis.config.enable_watchdog`` set: an axis in ``CLOSED_LOOP_CONTROL`` that gets no set-point
(``Set_Input_Pos`` / ``_Vel`` / ``_Torque``) and no ``Set_Axis_State`` for that long disarms to
``IDLE`` with ``WATCHDOG_TIMER_EXPIRED`` (0x1000000) in its heartbeat. :class:`SimMitMotor` with
``can_timeout`` > 0 is a motor whose firmware CAN timeout is set: in motor mode, when no command
frame (the special frames do not count) arrived for that long, its command is zeroed
(p, v, kp, kd, t_ff = 0: no torque); it stays in motor mode.

**Realism** (``realism=``, :mod:`temoto.drivers.realism`; figures in ``docs/simulators.md``,
"Realism"): at ``typical`` or ``harsh`` the reported position, velocity, torque, current,
temperature and bus voltage carry seeded gaussian noise (the model's true state does not), and
each of an ODrive's cyclic frames is lost now and then (requested frames and MIT replies are
not: a lost one would look like a dead device to a host that asks once). Each cyclic frame and
each MIT reply leaves after the node's jitter, now and then late
(:class:`~temoto.drivers.realism.CanTransmitter`: a late frame stalls the node, whose frames stay
in order); the frames are held and sent at their clock time by the tick thread
(:meth:`~temoto.drivers.can_motor.sim_bus.CanDeviceSim.send_at`), not rounded to the tick. An
ODrive's answers to requests (RTR, ``RxSdo``) leave after the replies' jitter and behind the
node's frames still queued, as from the one transmit queue of a real node: an answer never
overtakes a late cyclic frame (at ``off``, at once).

The bus may be ``virtual`` (one process) or ``udp_multicast`` (across processes).

Code: the motion models are in :mod:`~temoto.drivers.can_motor.sim_model`, the bus, threads and
shared faults in :mod:`~temoto.drivers.can_motor.sim_bus`; this module is the two devices'
protocols.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar, Final

import can

from temoto.clock import Clock
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import mitmode as mit
from temoto.drivers.can_motor import odrive_sdo as sdo
from temoto.drivers.can_motor.sim_bus import CanDeviceSim
from temoto.drivers.can_motor.sim_model import (
    TORQUE_CONSTANT,
    VEL_LIMIT_TOLERANCE,
    AxisModel,
    MitModel,
)
from temoto.drivers.realism import CanTransmitter, Realism

logger = logging.getLogger(__name__)

__all__ = [
    "CYCLIC_RATES",
    "TORQUE_CONSTANT",
    "VEL_LIMIT_TOLERANCE",
    "VERSION",
    "AxisModel",
    "MitModel",
    "SimMitMotor",
    "SimODrive",
]


_HW_BITS: Final = {
    "overheat": cs.AxisError.MOTOR_OVER_TEMP,
    "overload": cs.AxisError.CURRENT_LIMIT_VIOLATION,
    "voltage": cs.AxisError.DC_BUS_UNDER_VOLTAGE,
}

_MIT_CODES: Final = {"overheat": 1, "overload": 2, "voltage": 4}

_ZERO: Final = mit.MitCommand(0.0, 0.0, 0.0, 0.0, 0.0)

#: Clock seconds a cyclic message may be early and still be due: a tick loop that adds its
#: period up (0.01 ten times) reaches a 100 ms message's time a rounding error before it.
_DUE_SLACK: Final = 1e-9

_TURN: Final = 2.0 * math.pi  # rad per turn: the realism figures are in rad, an ODrive's in turns


def _realism(realism: Realism | str, seed: int | None, device: str) -> Realism:
    """A device's realism from a level name (and seed) or as given."""
    if isinstance(realism, Realism):
        return realism
    made = Realism(realism, seed=seed, device=device)
    if made.enabled:
        logger.info("%s: %s", device, made.describe())
    return made


#: ODrive 0.6's cyclic messages: each ``axis.config.can`` rate setting → (the message, its
#: default period in ms; 0 = not sent). The defaults are the firmware's: heartbeats every
#: 100 ms and encoder estimates every 10 ms, the others off until set.
CYCLIC_RATES: Final[Mapping[str, tuple[cs.Cmd, int]]] = {
    "version_msg_rate_ms": (cs.Cmd.GET_VERSION, 0),
    "heartbeat_msg_rate_ms": (cs.Cmd.HEARTBEAT, 100),
    "encoder_msg_rate_ms": (cs.Cmd.GET_ENCODER_ESTIMATES, 10),
    "iq_msg_rate_ms": (cs.Cmd.GET_IQ, 0),
    "error_msg_rate_ms": (cs.Cmd.GET_ERROR, 0),
    "temperature_msg_rate_ms": (cs.Cmd.GET_TEMPERATURE, 0),
    "bus_voltage_msg_rate_ms": (cs.Cmd.GET_BUS_VOLTAGE_CURRENT, 0),
    "torques_msg_rate_ms": (cs.Cmd.GET_TORQUES, 0),
    "powers_msg_rate_ms": (cs.Cmd.GET_POWERS, 0),
}

_BUS_VOLTAGE: Final = 24.0  # V

_PHASE_RESISTANCE: Final = 0.1  # Ω: the copper losses in the electrical power

_TEMPERATURES: Final = (40.0, 35.0)  # FET, motor, °C

#: ``Get_Version`` (fields as the 0.6.10 DBC lays them out): protocol 2, hardware 4.4-58 (an
#: ODrive Pro, ``hw_version_major.minor-variant`` as odrivetool prints it), firmware 0.6.10
#: released (``Fw_Version_Unreleased`` 0): the firmware the DBC describes.
VERSION: Final = cs.Version(2, 4, 4, 58, 0, 6, 10, 0)


class SimODrive(CanDeviceSim):
    """ODrive axes answering CANSimple on a python-can bus.

    The cyclic messages are sent at the rates of ODrive 0.6's ``axis.config.can.*_msg_rate_ms``
    settings (:data:`CYCLIC_RATES`), the same for every axis: ``heartbeat_period``,
    ``encoder_period`` and ``torque_period`` set three of them in seconds, ``rates_ms`` any of
    them by the ODrive's own names in milliseconds (and wins where both are given). 0 turns a
    message off; every message is still answered on request (an RTR frame).

    Args:
        link: python-can ``Bus`` arguments (``interface``, ``channel``, ...).
        nodes: The node ids to serve, or :class:`AxisModel` instances.
        clock: Where time is read and waited.
        heartbeat_period: Seconds between heartbeats (``heartbeat_msg_rate_ms`` / 1000; 0 =
            off).
        encoder_period: Seconds between cyclic encoder estimates (0 = only on request).
        torque_period: Seconds between cyclic ``Get_Torques`` (0 = only on request).
        watchdog_timeout: The axes' ``watchdog_timeout`` with ``enable_watchdog`` set,
            seconds (0 = the watchdog is off). See the module docstring.
        rates_ms: ``{"<name>_msg_rate_ms": ms}`` over the periods (names in
            :data:`CYCLIC_RATES`).
        realism: ``off`` (default: the exact figures), ``typical``, ``harsh`` or a
            :class:`~temoto.drivers.realism.Realism` (see the module docstring).
        seed: The realism's top-level seed (None: a fresh one; ``realism.seed`` holds it).
        device: The device's name (its random numbers are its own).

    Raises:
        ValueError: No nodes, a duplicate node id, a negative or non-finite period or rate, or
            an unknown rate name.
    """

    FAULTS: ClassVar[frozenset[str]] = CanDeviceSim.FAULTS | {"no_heartbeat", "no_encoder"}
    _KIND: ClassVar[str] = "odrive"

    def __init__(
        self,
        link: Mapping[str, Any],
        nodes: Sequence[int | AxisModel],
        clock: Clock,
        *,
        heartbeat_period: float = 0.1,
        encoder_period: float = 0.01,
        torque_period: float = 0.0,
        watchdog_timeout: float = 0.0,
        rates_ms: Mapping[str, float] | None = None,
        realism: Realism | str = "off",
        seed: int | None = None,
        device: str = "odrive",
    ) -> None:
        periods = {name: ms / 1000.0 for name, (_, ms) in CYCLIC_RATES.items()}
        periods["heartbeat_msg_rate_ms"] = heartbeat_period
        periods["encoder_msg_rate_ms"] = encoder_period
        periods["torques_msg_rate_ms"] = torque_period
        for name, ms in (rates_ms or {}).items():
            if name not in CYCLIC_RATES:
                raise ValueError(f"unknown rate {name!r} (known: {', '.join(CYCLIC_RATES)})")
            periods[name] = ms / 1000.0
        for name, period in periods.items():
            if not (math.isfinite(period) and period >= 0):
                raise ValueError(f"{name} must be 0 (off) or a positive number of ms")
        if not (watchdog_timeout >= 0 and math.isfinite(watchdog_timeout)):
            raise ValueError(f"watchdog_timeout must be >= 0 s, got {watchdog_timeout!r}")
        ticks = [p for p in periods.values() if p > 0]
        if watchdog_timeout > 0:
            ticks.append(watchdog_timeout / 10)  # expiry seen within a tenth of the timeout
        super().__init__(link, clock, min(ticks) if ticks else 0.1)
        self.watchdog_timeout = watchdog_timeout
        self.realism = _realism(realism, seed, device)
        #: When each node's cyclic frames leave (the realism's jitter and late frames).
        self.transmitter = CanTransmitter(self.realism)
        #: Cyclic frames lost on purpose (realism), for tests and tools.
        self.frames_lost = 0
        models = [n if isinstance(n, AxisModel) else AxisModel(n) for n in nodes]
        if not models or len({m.node_id for m in models}) != len(models):
            raise ValueError("a SimODrive needs distinct node ids")
        self.axes: dict[int, AxisModel] = {m.node_id: m for m in models}
        #: Seconds between the cyclic messages, by the ODrive's setting names (0 = off).
        self.periods: dict[str, float] = periods
        self.heartbeat_period = periods["heartbeat_msg_rate_ms"]
        self.encoder_period = periods["encoder_msg_rate_ms"]
        self.torque_period = periods["torques_msg_rate_ms"]
        #: Frames received that the axes acted on or answered (a host at work), for tools.
        self.frames_received = 0
        #: ``RxSdo`` frames for an endpoint id the axes do not have (left unanswered).
        self.sdo_unknown = 0
        self._model_lock = threading.Lock()
        self._due = dict.fromkeys(periods, -math.inf)
        self._ids: dict[tuple[int, int], int] = {
            (nid, int(cmd)): cs.arbitration_id(nid, cmd) for nid in self.axes for cmd in cs.Cmd
        }

    def on_fault_changed(self, fault: str, active: bool) -> None:
        """Raise the error bits of a hardware error at once (and disarm)."""
        if fault != "hardware_error":
            return
        params = self.fault(fault) or {}
        with self._model_lock:
            for axis in self.axes.values():
                if active and params.get("node") in (None, axis.node_id):
                    axis.step(self.clock.monotonic())
                    axis.disarm(_HW_BITS[params.get("kind", "overheat")])

    def _hw_bits(self, node: int) -> int:
        params = self.fault("hardware_error")
        if params is None or params.get("node") not in (None, node):
            return 0
        return int(_HW_BITS[params.get("kind", "overheat")])

    def on_frame(self, msg: can.Message) -> None:
        """Apply a command or answer a request addressed to one of the axes."""
        node, cmd = cs.split_id(msg.arbitration_id)
        axis = self.axes.get(node)
        if axis is None or msg.is_extended_id or self._mute(node):
            return
        if not msg.is_remote_frame and cmd in _DEVICE_SENDS:
            return  # a message of the axis itself (a multicast bus hears its own frames)
        data = bytes(msg.data)
        now = self.clock.monotonic()
        reply: tuple[int, bytes] | None = None
        at = now
        with self._model_lock:
            self.frames_received += 1
            axis.step(now)
            if msg.is_remote_frame:
                payload = self._payload(axis, cmd)
                if payload is not None:
                    reply = (cmd, payload)
            elif cmd == cs.Cmd.SET_AXIS_STATE:
                axis.fed = now
                wanted = cs.decode_set_axis_state(data)
                if wanted == cs.AxisState.CLOSED_LOOP_CONTROL:
                    axis.arm()  # holds where it is; a faulted axis does not arm
                elif wanted == cs.AxisState.IDLE:
                    axis.idle()
            elif cmd == cs.Cmd.SET_CONTROLLER_MODE:
                axis.control_mode, axis.input_mode = cs.decode_set_controller_mode(data)
            elif cmd == cs.Cmd.SET_INPUT_POS:
                # Set_Input_Pos carries the velocity and torque feed-forwards too (input_vel,
                # input_torque in the firmware)
                axis.input_pos, axis.input_vel, axis.input_torque = cs.decode_set_input_pos(data)
                axis.commands += 1
                axis.fed = now
            elif cmd == cs.Cmd.SET_INPUT_VEL:
                axis.input_vel, axis.input_torque = cs.decode_set_input_vel(data)
                axis.commands += 1
                axis.fed = now
            elif cmd == cs.Cmd.SET_INPUT_TORQUE:
                axis.input_torque = cs.decode_set_input_torque(data)
                axis.commands += 1
                axis.fed = now
            elif cmd == cs.Cmd.SET_LIMITS:
                axis.set_limits(*cs.decode_set_limits(data))
            elif cmd == cs.Cmd.RXSDO:
                answer = self._sdo(axis, data)
                if answer is not None:
                    reply = (cs.Cmd.TXSDO, answer)
            elif cmd == cs.Cmd.ESTOP:
                axis.disarm(cs.AxisError.ESTOP_REQUESTED)
            elif cmd == cs.Cmd.CLEAR_ERRORS:
                cs.decode_clear_errors(data)
                axis.error = self._hw_bits(node)  # a present condition stays
            if reply is not None and self.transmitter.enabled:
                # behind the node's frames still queued: a late heartbeat is never overtaken
                at = self.transmitter.release(node, now, reply=True)
        if reply is not None:
            if at > now:
                self.send_at(at, self._ids[node, reply[0]], reply[1], node)
            else:
                self.send(self._ids[node, reply[0]], reply[1], node)

    def _sdo(self, axis: AxisModel, data: bytes) -> bytes | None:
        """Answer an ``RxSdo`` as firmware 0.6.10 does (:mod:`odrive_sdo`); ``_model_lock`` held.

        A read of a known endpoint is answered with a ``TxSdo`` carrying its value; a write
        sets it, unanswered (0.6.10 confirms no write; 0.6.11 does). An endpoint the axis does
        not have, a malformed frame or another opcode: nothing is sent (the firmware's answer
        to those is not documented; see ``docs/simulators.md``).
        """
        try:
            opcode, endpoint_id, value = sdo.decode_rxsdo(data)
        except ValueError:
            return None
        path = _SDO_PATHS.get(endpoint_id)
        if path is None:
            self.sdo_unknown += 1
            return None
        attribute = _SDO_ATTRIBUTES[path]
        if opcode == sdo.OPCODE_READ:
            return sdo.encode_txsdo(endpoint_id, sdo.float_value(getattr(axis, attribute)))
        if opcode == sdo.OPCODE_WRITE:
            written = sdo.read_float(value)
            if sdo.finite_positive(written):
                setattr(axis, attribute, written)
        return None

    def _payload(self, axis: AxisModel, cmd: int) -> bytes | None:
        """What the axis sends as ``cmd`` now (cyclic or on request); None for no such message.

        ``_model_lock`` held.
        """
        if cmd == cs.Cmd.HEARTBEAT:
            return cs.encode_heartbeat(axis.error, axis.state, axis.procedure_result, True)
        r = self.realism
        if cmd == cs.Cmd.GET_ENCODER_ESTIMATES:
            pos = r.noise("joint_position", axis.pos * _TURN) / _TURN if r.enabled else axis.pos
            vel = r.noise("joint_velocity", axis.vel * _TURN) / _TURN if r.enabled else axis.vel
            return cs.encode_encoder_estimates(pos, vel)
        if cmd == cs.Cmd.GET_ERROR:
            return cs.encode_error_status(axis.error, axis.error)
        if cmd == cs.Cmd.GET_TORQUES:
            return cs.encode_torques(axis.torque_target, r.noise("torque", axis.torque))
        if cmd == cs.Cmd.GET_IQ:
            kt = axis.torque_constant
            return cs.encode_iq(axis.torque_target / kt, r.noise("current", axis.torque / kt))
        hot = self._hw_bits(axis.node_id) & cs.AxisError.MOTOR_OVER_TEMP
        if cmd == cs.Cmd.GET_TEMPERATURE:
            fet, motor = _TEMPERATURES
            fet, motor = r.noise("temperature", fet), r.noise("temperature", motor)
            return cs.encode_temperature(fet, 130.0 if hot else motor)
        mechanical = axis.torque * axis.vel * 2.0 * math.pi
        electrical = mechanical + _PHASE_RESISTANCE * (axis.torque / axis.torque_constant) ** 2
        if cmd == cs.Cmd.GET_BUS_VOLTAGE_CURRENT:
            low = self._hw_bits(axis.node_id) & cs.AxisError.DC_BUS_UNDER_VOLTAGE
            volts = 8.0 if low else _BUS_VOLTAGE
            amps = r.noise("current", electrical / volts)
            return cs.encode_bus_voltage_current(r.noise("voltage", volts), amps)
        if cmd == cs.Cmd.GET_POWERS:
            return cs.encode_powers(electrical, mechanical)
        if cmd == cs.Cmd.GET_VERSION:
            return bytes(VERSION)
        return None

    def on_tick(self, now: float) -> None:
        """Send the cyclic messages that are due."""
        due: list[str] = []
        for name, period in self.periods.items():
            if period > 0 and now >= self._due[name] - _DUE_SLACK:
                due.append(name)
                after = self._due[name] + period  # keeps the phase; late by a period: skip
                self._due[name] = after if after > now else now + period
        frames: list[tuple[float, int, int, bytes]] = []
        timed = self.transmitter.enabled
        no_hb = self.fault("no_heartbeat")
        no_enc = self.fault("no_encoder")
        with self._model_lock:
            for node, axis in self.axes.items():
                axis.step(now)
                self._watchdog(axis, now)
                for name in due:
                    what = CYCLIC_RATES[name][0]
                    off = no_hb if what == cs.Cmd.HEARTBEAT else None
                    if what == cs.Cmd.GET_ENCODER_ESTIMATES:
                        off = no_enc
                    if off is not None and off.get("node") in (None, node):
                        continue
                    if self.realism.lost():  # lost on the way: the schedule goes on
                        self.frames_lost += 1
                        continue
                    payload = self._payload(axis, what)
                    if payload is not None:
                        at = self.transmitter.release(node, now) if timed else now
                        frames.append((at, node, what, payload))
        for at, node, cmd, data in frames:
            if timed:
                self.send_at(at, self._ids[node, cmd], data, node)
            else:
                self.send(self._ids[node, cmd], data, node)

    def _watchdog(self, axis: AxisModel, now: float) -> None:
        """Disarm an armed axis whose watchdog expired (``_model_lock`` held)."""
        timeout = self.watchdog_timeout
        if timeout <= 0 or axis.state != cs.AxisState.CLOSED_LOOP_CONTROL:
            return
        if now - axis.fed > timeout:
            axis.disarm(cs.AxisError.WATCHDOG_TIMER_EXPIRED)


#: Commands an axis sends on its own (a data frame with one of these ids is not for it).
_DEVICE_SENDS: Final = frozenset(cmd for cmd, _ in CYCLIC_RATES.values()) | {cs.Cmd.TXSDO}

#: The endpoints the simulated axes have (the reported version's ids), and the
#: :class:`AxisModel` attribute each one is: ``current_soft_max`` is the current limit that
#: ``Set_Limits`` sets too.
_SDO_ATTRIBUTES: Final = {
    sdo.VEL_LIMIT: "vel_limit",
    sdo.CURRENT_SOFT_MAX: "current_limit",
    sdo.TORQUE_CONSTANT: "torque_constant",
    "axis0.config.motor.current_hard_max": "current_hard_max",
}
_SDO_PATHS: Final = {
    endpoint.id: path
    for path, endpoint in sdo.KNOWN_ENDPOINTS[sdo.version_key(VERSION)].items()
    if path in _SDO_ATTRIBUTES
}


class SimMitMotor(CanDeviceSim):
    """MIT-mode motors answering on a python-can bus (one reply per received frame).

    Args:
        link: python-can ``Bus`` arguments.
        motors: The motor ids to serve, or :class:`MitModel` instances.
        clock: Where time is read and waited.
        host_id: The arbitration id replies are sent with.
        tick: Seconds between model steps.
        long_replies: Send 8-byte replies (temperature and error code) instead of 6.
        can_timeout: The firmware's CAN timeout, seconds (0 = off). See the module docstring.
        past_p_max: What a reply says of a position past the ±p_max field: ``"saturate"``
            (the field's end, as a clamping firmware sends) or ``"wrap"`` (the other end, as a
            conversion without clamping gives). The motor itself turns on either way.
        realism: ``off`` (default: the exact figures), ``typical``, ``harsh`` or a
            :class:`~temoto.drivers.realism.Realism`: the replies' position, velocity, torque
            and temperature carry its noise.
        seed: The realism's top-level seed (None: a fresh one; ``realism.seed`` holds it).
        device: The device's name (its random numbers are its own).

    Raises:
        ValueError: No motors, a duplicate motor id, a negative timeout or an unknown
            ``past_p_max``.
    """

    _KIND: ClassVar[str] = "mit"

    def __init__(
        self,
        link: Mapping[str, Any],
        motors: Sequence[int | MitModel],
        clock: Clock,
        *,
        host_id: int = 0,
        tick: float = 0.01,
        long_replies: bool = True,
        can_timeout: float = 0.0,
        past_p_max: str = "saturate",
        realism: Realism | str = "off",
        seed: int | None = None,
        device: str = "mit",
    ) -> None:
        if not (can_timeout >= 0 and math.isfinite(can_timeout)):
            raise ValueError(f"can_timeout must be >= 0 s, got {can_timeout!r}")
        if past_p_max not in ("saturate", "wrap"):
            raise ValueError(f"past_p_max must be 'saturate' or 'wrap', got {past_p_max!r}")
        self.past_p_max = past_p_max
        super().__init__(link, clock, min(tick, can_timeout / 10) if can_timeout > 0 else tick)
        self.can_timeout = can_timeout
        self.realism = _realism(realism, seed, device)
        #: When each motor's replies leave (the realism's jitter and late frames).
        self.transmitter = CanTransmitter(self.realism)
        models = [m if isinstance(m, MitModel) else MitModel(m) for m in motors]
        if not models or len({m.motor_id for m in models}) != len(models):
            raise ValueError("a SimMitMotor needs distinct motor ids")
        self.motors: dict[int, MitModel] = {m.motor_id: m for m in models}
        self.host_id = host_id
        #: Frames received that a motor answered (a host at work), for tools.
        self.frames_received = 0
        self.long_replies = long_replies
        self._model_lock = threading.Lock()

    def on_fault_changed(self, fault: str, active: bool) -> None:
        """Raise or drop the error code of a hardware error (and disable the motor)."""
        if fault != "hardware_error":
            return
        params = self.fault(fault) or {}
        with self._model_lock:
            for motor in self.motors.values():
                if not active:
                    motor.error = 0
                elif params.get("node") in (None, motor.motor_id):
                    motor.error = _MIT_CODES[params.get("kind", "overheat")]
                    motor.enabled = False

    def on_frame(self, msg: can.Message) -> None:
        """Answer a frame addressed to one of the motors."""
        motor = self.motors.get(msg.arbitration_id)
        if motor is None or msg.is_extended_id or msg.is_remote_frame:
            return
        if self._mute(motor.motor_id):
            return
        data = bytes(msg.data)
        with self._model_lock:
            now = self.clock.monotonic()
            motor.step(now)
            kind = mit.special(data)
            if kind == "enter":
                motor.enabled = motor.error == 0
                motor.command = mit.MitCommand(motor.pos, 0.0, 0.0, 0.0, 0.0)
            elif kind == "exit":
                motor.enabled = False
            elif kind == "zero":
                motor.pos = 0.0
            elif len(data) == 8:
                motor.fed = now
                if motor.enabled:
                    motor.command = mit.decode_command(data, motor.ranges)
                    motor.commands += 1
            else:
                return  # not a frame this motor understands: no reply
            self.frames_received += 1
            r = self.realism
            pos, top = r.noise("joint_position", motor.pos), motor.ranges.p_max
            if self.past_p_max == "wrap" and abs(pos) > top:
                pos = (pos + top) % (2 * top) - top
            reply = mit.MitReply(  # encode_reply clamps: a position past the field saturates
                motor.motor_id,
                pos,
                r.noise("joint_velocity", motor.vel),
                r.noise("torque", motor.torque),
                round(r.noise("temperature", motor.temperature)) if self.long_replies else None,
                motor.error if self.long_replies else None,
            )
            payload = mit.encode_reply(reply, motor.ranges)
            at = self.transmitter.release(motor.motor_id, now, reply=True)  # off: now
        if self.transmitter.enabled:
            self.send_at(at, self.host_id, payload, motor.motor_id)
        else:
            self.send(self.host_id, payload, motor.motor_id)

    def on_tick(self, now: float) -> None:
        """Step the models; zero the command of a motor whose CAN timeout expired."""
        timeout = self.can_timeout
        with self._model_lock:
            for motor in self.motors.values():
                motor.step(now)
                expired = timeout > 0 and motor.enabled and now - motor.fed > timeout
                if expired and motor.command != _ZERO:
                    motor.command = _ZERO
                    motor.timeouts += 1
