"""DynamixelDriver: one chain of DYNAMIXEL X-series servos over dynamixel-sdk (Protocol 2.0).

Lifecycle (STYLE §3.5):

* ``configure`` opens the port at the baud rate (and warns when the USB adapter's latency timer
  is above 1 ms), PINGs every servo, checks its model number (a mismatch is a
  :class:`~temoto.errors.DriverInitError` naming the servo), reboots a servo that reports a
  hardware error (logged), turns torque off, checks the firmware has a Bus Watchdog (v38 on)
  when one is configured, writes the EEPROM registers the profile sets -- Operating Mode,
  Return Delay Time, Min/Max Position Limit -- each only when it differs, reads the Velocity
  and Current Limit registers, reads the state once and starts the poll thread;
* ``activate`` clears the Bus Watchdog (0: goals writable again), holds where each servo is
  (goal position = present position, goal velocity and goal current = 0), turns torque on and
  arms the Bus Watchdog; ``deactivate`` turns torque off;
* ``make_safe`` applies the declared ``safe_state``: ``torque_off`` (default; one SYNC_WRITE of
  Torque Enable = 0, confirmed by a SYNC_READ, or one WRITE per silent servo) or ``hold``
  (goal = present position, torque kept); it works from ``INACTIVE``, ``ACTIVE`` and ``FAULT``;
* ``recover`` (from ``FAULT``) stops polling, REBOOTs every servo whose Hardware Error Status
  is not 0 (a servo keeps such an error until rebooted), and configures again: the driver is
  ``INACTIVE``; ``activate`` re-enables torque;
* ``shutdown`` makes the servos safe (the base class), stops polling and closes the port.

:meth:`DynamixelDriver.detect` finds chains without a profile: it only sends a broadcast PING
(which no servo acts on) and lists the servos that answer as a profile entry.

The poll thread (``temoto-dxl-<name>``) SyncReads present current, velocity and position of
the chain every ``1 / poll_rate`` seconds of the driver's clock, writes every servo's newest goal
again while ``ACTIVE`` (so the servos' Bus Watchdog sees steady set-points and stops them when
this process dies or hangs), and every ``status_every`` polls also reads Present Input Voltage,
Present Temperature, Hardware Error Status and the Bus Watchdog. Supervision: a reply with a bad
CRC or garbage is logged and counted, and a fault only when 5 fall within 1 s
(:class:`~temoto.drivers.supervision.FaultWindow`); ``timeout_polls`` polls in a row without
replies are a :class:`~temoto.errors.DriverTimeoutError`; the present-position stream is stale
(a :class:`~temoto.errors.DriverTimeoutError` naming it) when no good poll came for 3 x (poll
period + ``reply_timeout``) clock seconds (:class:`~temoto.drivers.supervision.StreamAge`,
checked by the poll thread and by :meth:`DynamixelDriver.read_state`). The first good poll after
a communication fault reports recovery (unless a servo lost torque meanwhile, which stays a
fault until ``recover``; a servo that its Bus Watchdog stopped meanwhile is cleared and holds
where it stopped). A Bus Watchdog found expired while ``ACTIVE`` otherwise is a fault until
``recover``. A status packet with the alert bit, or a Hardware Error Status other than 0,
reports a :class:`~temoto.errors.DynamixelHardwareError` naming the servo and the bits
(overheating, overload, input voltage, electrical shock, motor encoder); it stays until
``recover``.

Time: the poll period and the stamps come from the driver's clock, so on a
:class:`~temoto.clock.ManualClock` a poll happens only when the test advances time. The serial
timeouts stay *real*: dynamixel-sdk times a missing reply out after about 34 ms of wall time
whatever the clock says, so a fault bound in clock seconds is ``timeout_polls`` x (period +
34 ms) on a real clock and has no fixed value in virtual time.

Units: position ``(ticks - 2048) x 2π/4096 / gear + offset`` rad; velocity
``units x 0.229 rev/min / gear``; effort ``current x torque_constant x gear`` N·m, with the
model's current unit and torque constant from :mod:`~temoto.drivers.dynamixel.control_table`
(XL430, 2XL430 and XC430 report load in 0.1 % of their stall torque instead of current, and
have no Current Limit to read).
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, ClassVar, Final, Self

from temoto.clock import Clock
from temoto.drivers.base import Driver, DriverState
from temoto.drivers.capabilities import ControlMode, JointCommand, JointState, JointStates
from temoto.drivers.dynamixel import _sdk, timing
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.detect import DETECT_BAUD_RATES, detect
from temoto.drivers.dynamixel.servos import (
    COMMAND_MODE,
    MODES,
    POSITION_MODES,
    ServoConfig,
    ServoStatus,
)
from temoto.drivers.dynamixel.settings import BAUD_RATES, PROFILE_FIELDS, settings
from temoto.drivers.dynamixel.sim import SimDynamixelChain
from temoto.drivers.dynamixel.timing import (
    DEFAULT_BUS_WATCHDOG,
    FACTORY_RETURN_DELAY,
    latency_timer,
    poll_cycle_time,
    return_delay_units,
    watchdog_units,
)
from temoto.drivers.profile import Field
from temoto.drivers.sim import Simulator
from temoto.drivers.supervision import FaultWindow, StreamAge
from temoto.errors import (
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    DriverUnavailableError,
    DynamixelHardwareError,
    StateError,
)

__all__ = [
    "BAUD_RATES",
    "DEFAULT_BUS_WATCHDOG",
    "DETECT_BAUD_RATES",
    "FACTORY_RETURN_DELAY",
    "MODES",
    "SAFE_STATES",
    "SIM_REPLY_TIMEOUT",
    "DynamixelDriver",
    "ServoConfig",
    "ServoStatus",
    "latency_timer",
    "poll_cycle_time",
]

logger = logging.getLogger(__name__)

#: The ``reply_timeout`` :meth:`DynamixelDriver.simulate` gives a driver on a simulated chain.
SIM_REPLY_TIMEOUT: Final = 0.1
#: ``safe_state`` values: ``torque_off`` (the default) writes Torque Enable = 0 to every servo;
#: ``hold`` keeps torque and sets each goal to where the servo is (goal velocity/current 0).
SAFE_STATES: Final = ("torque_off", "hold")
_SAFE_BUS_WAIT: Final = 0.5  # real s make_safe waits for a transaction of another thread
_PING_TRIES: Final = 3
_TRIES: Final = 3  # attempts of a single READ or WRITE (they are idempotent)
_REBOOT_WAIT_TRIES: Final = 20  # pings (each up to ~34 ms real) while a servo restarts


class DynamixelDriver(Driver):
    """One chain of DYNAMIXEL X-series servos (see the module docstring); an ``Actuator``.

    Args:
        name: The device's name in its profile.
        port: The serial device (``/dev/ttyUSB0``).
        servos: The servos of the chain.
        baud: Bits per second (one of :data:`BAUD_RATES`).
        poll_rate: State reads per second of the clock.
        status_every: Read temperature, voltage and hardware errors every this many polls.
        timeout_polls: Failed polls in a row that make a fault.
        reply_timeout: Real seconds a status packet may take beyond its transfer time.
        bus_watchdog: Seconds of the servos' Bus Watchdog (0: off; 0.02 to 2.54, rounded up to
            20 ms; at least two poll periods), armed at :meth:`activate`; None:
            :data:`DEFAULT_BUS_WATCHDOG` or three poll periods, whichever is longer.
        return_delay_time: Seconds of the servos' Return Delay Time written at configure (0 to
            508 µs, rounded to 2 µs), or None to leave the register as it is.
        clock: Poll periods and stamps.

    Raises:
        ValueError: A bad argument (duplicate ids or joints, no servos, a bad rate).
    """

    kind: ClassVar[str] = "dynamixel"
    safe_states: ClassVar[tuple[str, ...]] = SAFE_STATES

    def __init__(
        self,
        name: str,
        *,
        port: str,
        servos: Sequence[ServoConfig],
        baud: int = 57600,
        poll_rate: float = 50.0,
        status_every: int = 10,
        timeout_polls: int = 3,
        reply_timeout: float = 0.034,
        bus_watchdog: float | None = None,
        return_delay_time: float | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(name, clock=clock)
        if not servos:
            raise ValueError("a chain needs at least one servo")
        if len({s.id for s in servos}) != len(servos):
            raise ValueError("servo ids must be unique")
        if len({s.joint for s in servos}) != len(servos):
            raise ValueError("joint names must be unique")
        if baud not in BAUD_RATES:
            raise ValueError(f"baud must be one of {sorted(BAUD_RATES)}, got {baud}")
        if not (math.isfinite(poll_rate) and 0 < poll_rate <= 1000):
            raise ValueError(f"poll_rate must be in (0, 1000] Hz, got {poll_rate}")
        if not (math.isfinite(reply_timeout) and 0 < reply_timeout <= 1):
            raise ValueError(f"reply_timeout must be in (0, 1] s, got {reply_timeout}")
        if status_every < 1 or timeout_polls < 1:
            raise ValueError("status_every and timeout_polls must be at least 1")
        self.watchdog_units = watchdog_units(bus_watchdog, 1.0 / poll_rate)
        self.return_delay_units = return_delay_units(return_delay_time)
        self.port = port
        self.baud = baud
        self.servos: tuple[ServoConfig, ...] = tuple(servos)
        self.period = 1.0 / poll_rate
        self.status_every = status_every
        self.timeout_polls = timeout_polls
        self.reply_timeout = reply_timeout
        self._by_joint = {s.joint: s for s in self.servos}
        self._by_id = {s.id: s for s in self.servos}
        self._ids = [s.id for s in self.servos]
        self._bus = threading.RLock()  # one transaction on the wire at a time
        self._sdk: _sdk.SdkPort | None = None
        self._fast: _sdk.SyncReader | None = None
        self._slow: _sdk.SyncReader | None = None
        self._errors: _sdk.SyncReader | None = None
        self._torques: _sdk.SyncReader | None = None
        self._writers: dict[int, _sdk.SyncWriter] = {}
        self._limits: dict[int, tuple[int, int]] = {}  # id → (velocity limit, current limit)
        self._cache = threading.Lock()
        self._states: JointStates | None = None
        self._status: dict[int, ServoStatus] = {}
        self._poller: threading.Thread | None = None
        self._stop = threading.Event()
        self._wake = threading.Condition()
        self._failures = 0
        self._comm_fault = False
        self._hw_fault = False
        self._watchdogs: _sdk.SyncReader | None = None
        #: Each servo's goal register and value, written every poll while ACTIVE.
        self._goals: dict[int, tuple[ct.Register, bytes]] = {}
        # A good poll is due every period; one whose replies time out takes a reply timeout
        # more (real time, so as many seconds of the clock as pass meanwhile: three times
        # as many on a ScaledClock(3)), so the age limit allows for that: a lost reply is
        # not a fault.
        real_rate = self.clock.real_seconds(1.0)
        reply_clock_s = reply_timeout / real_rate if real_rate > 0 else reply_timeout
        self._feedback = StreamAge(f"{name} present position", self.period + reply_clock_s)
        self._bad_packets = FaultWindow()
        self._last_failure = ""

    @property
    def bus_watchdog(self) -> float:
        """The Bus Watchdog time armed at :meth:`activate` (s; 0: off)."""
        return self.watchdog_units * ct.BUS_WATCHDOG_UNIT

    @property
    def joint_limits(self) -> Mapping[str, tuple[float, float]]:
        """(min, max) position (rad) of every joint in a position mode."""
        return {
            s.joint: (s.min_position, s.max_position)
            for s in self.servos
            if s.operating_mode in POSITION_MODES
        }

    # ---- profile ------------------------------------------------------------------------------

    profile_fields: ClassVar[Mapping[str, Field[Any]]] = PROFILE_FIELDS

    @classmethod
    def profile_settings(cls, values: Mapping[str, Any], where: str) -> dict[str, Any]:
        """Constructor arguments from a checked entry (see ``docs/driver-dynamixel.md``).

        Args:
            values: The entry's checked values: ``link``, ``baud``, ``poll_rate``,
                ``status_every``, ``timeout_polls``, ``reply_timeout``, ``bus_watchdog``,
                ``return_delay_time``, ``servos`` (``sim`` is the simulator's).
            where: The entry's place for messages.

        Returns:
            The keyword arguments (``port`` and ``baud`` from the link).

        Raises:
            ProfileError: Keys that contradict each other (the message names the key).
        """
        return settings(values, super().profile_settings(values, where), where)

    @classmethod
    def from_profile(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock, where: str
    ) -> Self:
        """A driver from a profile's device entry (see :meth:`Driver.from_profile`).

        Args:
            name: The device's name.
            config: Its entry (:meth:`profile_settings` lists the keys).
            clock: The robot's clock.
            where: The entry's place for messages.

        Returns:
            The driver (``UNCONFIGURED``). A warning is logged when ``poll_rate`` cannot be
            met on the wire (:func:`~temoto.drivers.dynamixel.timing.poll_cycle_time`).

        Raises:
            ProfileError: An invalid entry; the message starts with the key path.
        """
        driver = super().from_profile(name, config, clock=clock, where=where)
        driver._warn_if_too_fast(where)
        return driver

    def _warn_if_too_fast(self, where: str) -> None:
        """Log a warning when one poll cycle takes longer on the wire than a poll period.

        Not for a pseudo-terminal (a simulated chain): it has no wire whose time to estimate.
        """
        if os.path.realpath(self.port).startswith("/dev/pts/"):
            return
        given = self.return_delay_units is not None
        delay = (
            (self.return_delay_units or 0) * ct.RETURN_DELAY_UNIT if given else FACTORY_RETURN_DELAY
        )
        cycle = poll_cycle_time(
            len(self.servos), self.baud, delay, self.status_every, self.watchdog_units > 0
        )
        if cycle <= self.period:
            return
        logger.warning(
            "%s.poll_rate: %g Hz cannot be met: one poll cycle of %d servos at %d baud takes"
            " about %.1f ms on the wire (Return Delay Time %g µs%s), so at most about %.0f Hz;"
            " raise the baud rate, set return_delay_time: 0, or lower poll_rate",
            where,
            1.0 / self.period,
            len(self.servos),
            self.baud,
            cycle * 1000.0,
            delay * 1e6,
            "" if given else ", the factory value",
            1.0 / cycle,
        )

    @classmethod
    def simulate(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock
    ) -> tuple[Simulator, dict[str, Any]]:
        """A simulated chain for a profile entry, and the entry pointing at it.

        The simulator opens its pseudo-terminal at once (so the returned ``link`` is valid)
        but is not started: start it (or enter it as a context manager) before configuring
        the driver, and close it after shutting the driver down.

        Args:
            name: The device's name.
            config: Its profile entry (validated as in :meth:`from_profile`).
            clock: Steps the simulated motion.

        Returns:
            (the :class:`SimDynamixelChain`, the entry with ``link`` = ``serial:<pty path>``
            and, unless the entry sets one, ``reply_timeout`` = :data:`SIM_REPLY_TIMEOUT`:
            the simulator shares the client's process and GIL, so on a loaded machine a
            reply can take longer than a real servo's).

        Raises:
            ProfileError: An invalid entry.
        """
        values = cls.read_profile(config, name)
        servos: Sequence[ServoConfig] = cls.profile_settings(values, name)["servos"]
        sim = SimDynamixelChain({s.id: s.model for s in servos}, clock=clock, name=name)
        out = dict(config)
        out["link"] = f"serial:{sim.path}"
        out.setdefault("reply_timeout", SIM_REPLY_TIMEOUT)
        return sim, out

    @classmethod
    def detect(
        cls, links: Sequence[Any] | None = None, *, timeout: float = 1.0
    ) -> list[dict[str, Any]]:
        """The chains of servos that answer a broadcast PING, as profile device entries.

        Each link's port is opened as :meth:`configure` opens it (dynamixel-sdk's
        ``PortHandler``), one Protocol 2.0 PING goes to the broadcast id, and the status
        packets that come back within ``timeout`` real seconds are the servos found. PING is
        the only instruction sent: nothing is written, no torque is enabled, nothing moves. A
        link without ``?baud=`` is tried at each of :data:`DETECT_BAUD_RATES` in turn (57600,
        1000000, 115200, 2000000, 3000000, 4000000, 9600), stopping at the first rate at which
        servos answer. A servo whose model number the driver does not know is left out with a
        warning naming its id and number; a port that cannot be opened is skipped with a
        warning.

        Args:
            links: Link URLs as in a profile's ``link`` (``serial:/dev/ttyUSB0?baud=1000000``,
                ``serial:/dev/ttyUSB0``, or a bare absolute path); a single string is one link.
                None: every serial port pyserial lists.
            timeout: Real seconds to wait for status packets on each link at each baud rate
                tried (so up to seven times this for a link without a baud rate).

        Returns:
            One entry per link where known servos answered, in the order given:
            ``{"driver": "dynamixel", "link": "serial:<device>?baud=<rate that answered>",
            "servos": [{"id": i, "joint": "joint_<i>", "model": <name>, "mode": "position",
            "min_position": -3.14, "max_position": 3.14}, ...]}`` with the servos in id order
            (the limits are the servo's whole single turn: narrow them to the joint's).
            :meth:`from_profile` accepts each as it is. Empty when nothing answered.

        Raises:
            ValueError: ``timeout`` is not a positive finite number of seconds, or a link is not
                a serial link (raised before any port is opened; the message names the link).
        """
        return detect(links, timeout)

    # ---- capability -------------------------------------------------------------------------

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The joints of the chain, in profile order."""
        return tuple(s.joint for s in self.servos)

    def read_state(self) -> JointStates:
        """The newest poll of every joint (no bus traffic).

        Returns:
            The states in SI units. When the newest poll is older than the present-position
            stream's limit (:attr:`feedback_max_age`), the driver reports a fault first.

        Raises:
            StateError: Never configured, or finalized.
        """
        state = self.state
        with self._cache:
            states = self._states
        if state in (DriverState.UNCONFIGURED, DriverState.FINALIZED) or states is None:
            raise StateError(f"{self.name}: no state while {state.value}")
        self._check_stale()
        return states

    def servo_status(self) -> Mapping[int, ServoStatus]:
        """The newest temperature, voltage and hardware-error reading of every servo.

        Returns:
            By servo id (empty before the first status poll).
        """
        with self._cache:
            return dict(self._status)

    def command(self, commands: Iterable[JointCommand]) -> None:
        """Send set-points with one SyncWrite per register (only ``ACTIVE``).

        A position command's ``velocity_limit`` sets the servo's Profile Velocity. The poll
        thread writes the newest goal of every servo again each period while ``ACTIVE``, so the
        servos' Bus Watchdog sees a steady stream of set-points.

        Args:
            commands: Set-points; each joint's mode must match its servo's operating mode.

        Raises:
            StateError: Not active.
            ValueError: An unknown joint, a mode the servo is not in, or a value beyond the
                servo's limits.
            DriverOperationError: The port refused to send.
        """
        self.require_active("command")
        goals: dict[int, dict[int, bytes]] = {}
        for cmd in commands:
            servo = self._by_joint.get(cmd.joint)
            if servo is None:
                raise ValueError(f"{self.name}: no joint {cmd.joint!r}")
            wanted = COMMAND_MODE[servo.operating_mode]
            if cmd.mode is not wanted:
                raise ValueError(
                    f"{self.name}: joint {cmd.joint} is in {servo.mode} mode and takes"
                    f" {wanted.value} commands, not {cmd.mode.value}"
                )
            vel_limit, cur_limit = self._limits.get(servo.id, (0, 0))
            if cmd.mode is ControlMode.POSITION:
                if not servo.min_position <= cmd.value <= servo.max_position:
                    raise ValueError(
                        f"{self.name}: joint {cmd.joint}: {cmd.value} rad is outside"
                        f" [{servo.min_position}, {servo.max_position}]"
                    )
                reg, value = ct.GOAL_POSITION, servo.ticks(cmd.value)
                if cmd.velocity_limit is not None:
                    units = min(abs(servo.velocity_units(cmd.velocity_limit)), vel_limit)
                    speed = goals.setdefault(ct.PROFILE_VELOCITY.address, {})
                    speed[servo.id] = p.to_le(max(units, 1), 4)
            elif cmd.mode is ControlMode.VELOCITY:
                reg, value = ct.GOAL_VELOCITY, servo.velocity_units(cmd.value)
                too_fast = servo.velocity_limit is not None and abs(cmd.value) > (
                    servo.velocity_limit
                )
                if too_fast or abs(value) > vel_limit:
                    raise ValueError(f"{self.name}: joint {cmd.joint}: {cmd.value} rad/s too fast")
            else:
                reg, value = ct.GOAL_CURRENT, servo.current_units(cmd.value)
                too_hard = servo.effort_limit is not None and abs(cmd.value) > servo.effort_limit
                if too_hard or abs(value) > cur_limit:
                    raise ValueError(f"{self.name}: joint {cmd.joint}: {cmd.value} N·m too much")
            goals.setdefault(reg.address, {})[servo.id] = p.to_le(value, reg.size)
        order = (ct.PROFILE_VELOCITY, ct.GOAL_POSITION, ct.GOAL_VELOCITY, ct.GOAL_CURRENT)
        with self._bus:
            for reg in order:
                if reg.address in goals:
                    result = self._writer(reg).write(goals[reg.address])
                    if result != _sdk.COMM_SUCCESS:
                        text = self._port().result_text(result)
                        raise DriverOperationError(f"{self.name}: SyncWrite of {reg.name}: {text}")
                    if reg is not ct.PROFILE_VELOCITY:
                        for dxl_id, raw in goals[reg.address].items():
                            self._goals[dxl_id] = (reg, raw)

    # ---- lifecycle hooks ----------------------------------------------------------------------

    def on_configure(self) -> None:
        """Open the port, check every servo, set its mode, read once and start polling."""
        self._stop_polling()
        port = self._sdk
        if port is None or not port.is_open:
            port = _sdk.SdkPort(self.port, self.baud, self.reply_timeout)
            try:
                port.open()
            except OSError as err:
                raise DriverUnavailableError(
                    f"{self.name}: cannot open {self.port}: {err}"
                ) from err
            except ValueError as err:
                raise DriverInitError(f"{self.name}: {err}") from err
            self._sdk = port
            _check_latency_timer(self.name, self.port)
        with self._bus:
            self._goals = {}
            for servo in self.servos:
                self._bring_up(servo)
            self._fast = port.sync_reader(*ct.FAST_READ, self._ids)
            self._slow = port.sync_reader(*ct.STATUS_READ, self._ids)
            self._errors = port.sync_reader(ct.HARDWARE_ERROR_STATUS.address, 1, self._ids)
            self._torques = port.sync_reader(ct.TORQUE_ENABLE.address, 1, self._ids)
            self._watchdogs = port.sync_reader(ct.BUS_WATCHDOG.address, 1, self._ids)
            self._writers = {}
        self._failures = 0
        self._comm_fault = self._hw_fault = False
        self._feedback.reset()
        self._bad_packets.clear()
        if not self._poll_fast():
            raise DriverInitError(f"{self.name}: the first SyncRead of the chain failed")
        self._poll_status()
        self._start_polling()

    def on_activate(self) -> None:
        """Clear the Bus Watchdog, hold where each servo is, turn torque on, arm the watchdog."""
        with self._bus:
            for servo in self.servos:  # 0 clears a Bus Watchdog error: goals writable again
                self._write(servo.id, ct.BUS_WATCHDOG, 0, "bus watchdog clear")
            result, data, errors = self._reader("fast").read()
            if result != _sdk.COMM_SUCCESS:
                raise self._comm_error("read before torque on", result)
            self._raise_alerts(errors)
            holds: dict[int, bytes] = {}
            for servo in self.servos:
                if servo.operating_mode in POSITION_MODES:
                    holds[servo.id] = data[servo.id][6:10]  # present position → goal
            if holds:
                self._check_tx(self._writer(ct.GOAL_POSITION).write(holds))
            zero = {s.id: p.to_le(0, 4) for s in self.servos if s.mode == "velocity"}
            if zero:
                self._check_tx(self._writer(ct.GOAL_VELOCITY).write(zero))
            zero = {s.id: p.to_le(0, 2) for s in self.servos if s.mode == "current"}
            if zero:
                self._check_tx(self._writer(ct.GOAL_CURRENT).write(zero))
            self._goals = self._hold_goals(data)
            for servo in self.servos:
                self._write(servo.id, ct.TORQUE_ENABLE, 1, "torque on")
            if self.watchdog_units:
                for servo in self.servos:
                    self._write(servo.id, ct.BUS_WATCHDOG, self.watchdog_units, "bus watchdog")

    def _hold_goals(self, fast: Mapping[int, bytes]) -> dict[int, tuple[ct.Register, bytes]]:
        """Each servo's goal that keeps it where a fast read found it (velocity/current 0)."""
        goals: dict[int, tuple[ct.Register, bytes]] = {}
        for servo in self.servos:
            if servo.operating_mode in POSITION_MODES:
                goals[servo.id] = (ct.GOAL_POSITION, bytes(fast[servo.id][6:10]))
            elif servo.mode == "velocity":
                goals[servo.id] = (ct.GOAL_VELOCITY, p.to_le(0, 4))
            else:
                goals[servo.id] = (ct.GOAL_CURRENT, p.to_le(0, 2))
        return goals

    def _write_goals(self, goals: Mapping[int, tuple[ct.Register, bytes]]) -> int:
        """One SYNC_WRITE per goal register; the first failing result (or success)."""
        by_register: dict[int, dict[int, bytes]] = {}
        registers: dict[int, ct.Register] = {}
        for dxl_id, (reg, value) in goals.items():
            by_register.setdefault(reg.address, {})[dxl_id] = value
            registers[reg.address] = reg
        outcome = _sdk.COMM_SUCCESS
        for address, values in by_register.items():
            result = self._writer(registers[address]).write(values)
            if result != _sdk.COMM_SUCCESS and outcome == _sdk.COMM_SUCCESS:
                outcome = result
        return outcome

    def on_deactivate(self) -> None:
        """Turn torque off."""
        with self._bus:
            self._goals = {}
            for servo in self.servos:
                self._write(servo.id, ct.TORQUE_ENABLE, 0, "torque off")

    def on_make_safe(self) -> str:
        """Apply :attr:`safe_state` to every servo; a short report of what was done.

        ``torque_off``: one SYNC_WRITE of Torque Enable = 0 to every servo (sent whatever the
        state, also in ``FAULT``), then one SYNC_READ of Torque Enable to confirm, each reply
        waited for at most ``reply_timeout``; servos that do not confirm get one WRITE each
        (with its status packet). ``hold``: a SYNC_READ of the present positions, then goal
        position = present position (goal velocity or current = 0 in those modes); torque is
        left as it is.

        Raises:
            DriverOperationError: The port is closed or refused to send, or (``hold``) the
                present positions could not be read.
        """
        port = self._sdk
        if port is None or not port.is_open:
            raise DriverOperationError(f"{self.name}: the port is not open")
        got = self._bus.acquire(timeout=_SAFE_BUS_WAIT)  # else the SDK says if it is busy
        try:
            self._goals = {}
            if self.safe_state == "hold":
                return self._hold(port)
            return self._torque_off(port)
        finally:
            if got:
                self._bus.release()

    def _torque_off(self, port: _sdk.SdkPort) -> str:
        count = len(self._ids)
        result = port.sync_writer(ct.TORQUE_ENABLE.address, 1).write(
            dict.fromkeys(self._ids, b"\x00")
        )
        if result != _sdk.COMM_SUCCESS:
            raise DriverOperationError(f"{self.name}: torque off: {port.result_text(result)}")
        reader = self._torques or port.sync_reader(ct.TORQUE_ENABLE.address, 1, self._ids)
        result, data, _ = reader.read()
        if result == _sdk.COMM_SUCCESS and not any(data[i][0] for i in self._ids):
            return f"{count} servos torque off"
        unconfirmed: list[int] = []
        for dxl_id in self._ids:
            if dxl_id in data and not data[dxl_id][0]:
                continue
            result, error = port.write(dxl_id, ct.TORQUE_ENABLE.address, 1, 0)
            if result != _sdk.COMM_SUCCESS or error & 0x7F:
                unconfirmed.append(dxl_id)
        if not unconfirmed:
            return f"{count} servos torque off"
        return (
            f"{count} servos torque off sent; not confirmed by servo"
            f" {', '.join(map(str, unconfirmed))}"
        )

    def _hold(self, port: _sdk.SdkPort) -> str:
        reader = self._fast or port.sync_reader(*ct.FAST_READ, self._ids)
        result, data, _ = reader.read()
        if result != _sdk.COMM_SUCCESS:
            raise DriverOperationError(
                f"{self.name}: hold: cannot read the present positions: {port.result_text(result)}"
            )
        result = self._write_goals(self._hold_goals(data))
        if result != _sdk.COMM_SUCCESS:
            raise DriverOperationError(f"{self.name}: hold: {port.result_text(result)}")
        return f"{len(self._ids)} servos hold"

    def on_recover(self) -> None:
        """Reboot servos with a hardware error and configure again (torque off)."""
        self._stop_polling()
        self.on_configure()

    def on_shutdown(self) -> None:
        """Stop polling and close the port (:meth:`shutdown` made the servos safe before)."""
        self._stop_polling()
        port, self._sdk = self._sdk, None
        if port is None:
            return
        with self._bus:
            port.close()
        self._fast = self._slow = self._errors = self._torques = self._watchdogs = None
        self._writers = {}
        self._goals = {}

    # ---- bring-up -----------------------------------------------------------------------------

    def _bring_up(self, servo: ServoConfig) -> None:
        port = self._port()
        model = self._ping(servo.id)
        if model != servo.spec.number:
            found = ct.MODELS_BY_NUMBER.get(model)
            raise DriverInitError(
                f"{self.name}: servo {servo.id} ({servo.joint}) is"
                f" {found.name if found else f'model {model}'}, the profile says {servo.model}"
            )
        bits = self._read(servo.id, ct.HARDWARE_ERROR_STATUS, "hardware error", alert_ok=True)
        if bits:
            logger.warning(
                "%s: servo %d (%s) reports %s: rebooting it",
                self.name,
                servo.id,
                servo.joint,
                ", ".join(p.decode_hardware_error(bits)),
            )
            result, _ = port.reboot(servo.id)
            if result != _sdk.COMM_SUCCESS:
                raise self._comm_error(f"reboot of servo {servo.id}", result)
            self._ping(servo.id, tries=_REBOOT_WAIT_TRIES)
            bits = self._read(servo.id, ct.HARDWARE_ERROR_STATUS, "hardware error", alert_ok=True)
            if bits:
                raise self._hardware_error(servo.id, bits)
        self._write(servo.id, ct.TORQUE_ENABLE, 0, "torque off")
        if self.watchdog_units:
            firmware = self._read(servo.id, ct.FIRMWARE_VERSION, "firmware version")
            if firmware < ct.BUS_WATCHDOG_FIRMWARE:
                raise DriverInitError(
                    f"{self.name}: servo {servo.id} ({servo.joint}) has firmware {firmware},"
                    f" which has no Bus Watchdog (v{ct.BUS_WATCHDOG_FIRMWARE} on): update it"
                    " (DYNAMIXEL Wizard) or set bus_watchdog: 0"
                )
        # EEPROM registers (torque is off now): written only when they differ.
        self._set_eeprom(servo, ct.OPERATING_MODE, servo.operating_mode, "operating mode")
        if self.return_delay_units is not None:
            self._set_eeprom(
                servo, ct.RETURN_DELAY_TIME, self.return_delay_units, "return delay time"
            )
        if servo.write_limits and servo.operating_mode is ct.OperatingMode.POSITION:
            low, high = servo.limit_ticks()
            self._set_eeprom(servo, ct.MIN_POSITION_LIMIT, low, "min position limit")
            self._set_eeprom(servo, ct.MAX_POSITION_LIMIT, high, "max position limit")
        velocity_limit = self._read(servo.id, _VELOCITY_LIMIT, "velocity limit")
        current_limit = 0  # a model that reports load has no Current Limit (nor current mode)
        if servo.spec.register(_CURRENT_LIMIT.name) is not None:
            current_limit = self._read(servo.id, _CURRENT_LIMIT, "current limit")
        self._limits[servo.id] = (velocity_limit, current_limit)

    def _set_eeprom(self, servo: ServoConfig, reg: ct.Register, value: int, what: str) -> None:
        """Write an EEPROM register only when it differs (spares the EEPROM's write cycles)."""
        old = self._read(servo.id, reg, what)
        if old != value:
            logger.info(
                "%s: servo %d (%s): %s %d -> %d", self.name, servo.id, servo.joint, what, old, value
            )
            self._write(servo.id, reg, value, what)

    def _ping(self, dxl_id: int, tries: int = _PING_TRIES) -> int:
        port = self._port()
        result = _sdk.COMM_TX_FAIL
        for _ in range(tries):
            model, result, _ = port.ping(dxl_id)
            if result == _sdk.COMM_SUCCESS:
                return model
        joint = self._by_id[dxl_id].joint
        raise DriverInitError(
            f"{self.name}: servo {dxl_id} ({joint}) does not answer PING on {self.port}:"
            f" {port.result_text(result)}"
        )

    # ---- polling ------------------------------------------------------------------------------

    def _start_polling(self) -> None:
        self._stop.clear()
        self._poller = threading.Thread(target=self._run, name=f"temoto-dxl-{self.name}")
        self._poller.start()

    def _stop_polling(self) -> None:
        thread, self._poller = self._poller, None
        if thread is None:
            return
        with self._wake:
            self._stop.set()
            self._wake.notify_all()
        thread.join(10.0)

    def _run(self) -> None:
        count = 0
        deadline = self.clock.monotonic()
        while not self._stop.is_set():
            count += 1
            try:
                self._check_stale()
                good = self._poll_fast()
                self._feed_goals()
                if good and count % self.status_every == 0:
                    self._poll_status()
            except Exception:  # keep polling; a bug must not silently end the thread
                logger.exception("%s: poll failed", self.name)
            deadline += self.period
            with self._wake:
                if self._stop.is_set():
                    break
                remaining = deadline - self.clock.monotonic()
                if remaining > 0:
                    self.clock.wait(self._wake, remaining)
                else:
                    deadline = self.clock.monotonic()  # late: do not try to catch up

    @property
    def feedback_max_age(self) -> float:
        """Clock seconds without a good poll after which the present position is stale.

        :data:`~temoto.drivers.supervision.STALE_PERIODS` (3) times a poll period plus one
        ``reply_timeout`` (the time a poll whose reply is lost takes on top of its period: real
        seconds, counted here in seconds of the driver's clock).
        """
        return self._feedback.max_age

    def _check_stale(self) -> None:
        """Report a fault when the present-position stream is older than its limit."""
        now = self.clock.monotonic()
        age = self._feedback.age(now)
        if self._feedback.last is None or age <= self._feedback.max_age:
            return
        if self.state not in (DriverState.INACTIVE, DriverState.ACTIVE):
            return
        last = f"; last poll: {self._last_failure}" if self._last_failure else ""
        self._comm_fault = True
        self.report_fault(
            DriverTimeoutError(
                f"{self.name}: present position stale: no good poll for {age:.3f} s (limit"
                f" {self._feedback.max_age:.3f} s at {1.0 / self.period:g} Hz){last}"
            )
        )

    def _feed_goals(self) -> None:
        """While ACTIVE, write every servo's newest goal again (the Bus Watchdog's feed)."""
        if self.state is not DriverState.ACTIVE:
            return
        with self._bus:
            if not self._goals or self._sdk is None or self.state is not DriverState.ACTIVE:
                return
            result = self._write_goals(self._goals)
        if result != _sdk.COMM_SUCCESS:
            logger.debug("%s: goal feed: %s", self.name, self._port().result_text(result))

    def _poll_fast(self) -> bool:
        """One SyncRead of the chain; faults and recovery follow from it. True if it worked.

        A reply with a bad CRC or garbage is counted in a sliding window (a fault only when
        :data:`~temoto.drivers.supervision.BAD_FRAMES_LIMIT` fall within
        :data:`~temoto.drivers.supervision.BAD_FRAMES_WINDOW`); a poll without replies counts
        towards ``timeout_polls`` in a row.
        """
        with self._bus:
            reader = self._fast
            if reader is None:
                return False
            result, data, errors = reader.read()
        stamp = self.clock.monotonic()
        if result != _sdk.COMM_SUCCESS:
            self._last_failure = self._port().result_text(result) if self._sdk else str(result)
            if result == _sdk.COMM_RX_CORRUPT:
                full = self._bad_packets.add(stamp)
                window = self._bad_packets
                logger.info(
                    "%s: a bad status packet (%d within %g s, %d in all): %s",
                    self.name,
                    window.recent(stamp),
                    window.window,
                    window.total,
                    self._last_failure,
                )
                if full:
                    self._comm_fault = True
                    self.report_fault(
                        DriverOperationError(
                            f"{self.name}: {window.recent(stamp)} bad status packets within"
                            f" {window.window:g} s (CRC errors or garbage): {self._last_failure}"
                        )
                    )
                return False
            self._failures += 1
            if self._failures >= self.timeout_polls:
                self._comm_fault = True
                self.report_fault(self._comm_error(f"{self._failures} polls in a row", result))
            return False
        self._failures = 0
        self._last_failure = ""
        self._feedback.feed(stamp)
        joints: dict[str, JointState] = {}
        for servo in self.servos:
            raw = data[servo.id]
            current = p.from_le(raw[0:2], signed=True)
            velocity = p.from_le(raw[2:6], signed=True)
            position = p.from_le(raw[6:10], signed=True)
            joints[servo.joint] = JointState(
                servo.joint,
                servo.position(position),
                servo.velocity(velocity),
                servo.effort(current),
                stamp,
            )
        with self._cache:
            self._states = JointStates(stamp, joints)
        if any(e & p.ALERT_BIT for e in errors.values()):
            self._poll_status()
        elif self._comm_fault and not self._hw_fault:
            self._comm_fault = False
            self._after_link_came_back()
        return True

    def _after_link_came_back(self) -> None:
        was_active = self.state is DriverState.FAULT and self._before_fault is DriverState.ACTIVE
        if was_active:
            with self._bus:
                result, data, _ = self._reader("torques").read()
            if result != _sdk.COMM_SUCCESS:
                self._comm_fault = True
                return
            off = [i for i in self._ids if data[i][0] == 0]
            if off:
                self.report_fault(
                    DriverOperationError(
                        f"{self.name}: servo(s) {', '.join(map(str, off))} lost torque while"
                        " unreachable (power cycled?); recover() and activate() again"
                    )
                )
                return
            expired = self._expired_watchdogs()
            if expired:
                try:
                    self._rearm(expired)
                except DriverError as err:
                    self.report_fault(err)
                    return
                self.report_recovered(
                    f"the chain answers again; the Bus Watchdog had stopped servo"
                    f" {', '.join(map(str, expired))}: it holds where it stopped"
                )
                return
        self.report_recovered("the chain answers again")

    def _rearm(self, expired: Sequence[int]) -> None:
        """Clear expired Bus Watchdogs, hold those servos where they stopped, arm again."""
        with self._bus:
            for dxl_id in expired:
                self._write(dxl_id, ct.BUS_WATCHDOG, 0, "bus watchdog clear")
            result, data, _ = self._reader("fast").read()
            if result != _sdk.COMM_SUCCESS:
                raise self._comm_error("read after the bus watchdog", result)
            holds = self._hold_goals(data)
            for dxl_id in expired:
                self._goals[dxl_id] = holds[dxl_id]
            self._check_tx(self._write_goals({i: holds[i] for i in expired}))
            for dxl_id in expired:
                self._write(dxl_id, ct.BUS_WATCHDOG, self.watchdog_units, "bus watchdog")

    def _expired_watchdogs(self) -> list[int]:
        """The servos whose Bus Watchdog reads -1 (expired); empty when off or unreadable."""
        if not self.watchdog_units:
            return []
        with self._bus:
            reader = self._watchdogs
            if reader is None:
                return []
            result, data, _ = reader.read()
        if result != _sdk.COMM_SUCCESS:
            return []
        return [i for i in self._ids if p.from_le(data[i], signed=True) < 0]

    def _poll_status(self) -> None:
        """Read voltage, temperature and hardware error status; report hardware errors."""
        with self._bus:
            if self._slow is None or self._errors is None:
                return
            result, slow, _ = self._slow.read()
            result2, bits, _ = self._errors.read() if result == _sdk.COMM_SUCCESS else (0, {}, {})
        if result != _sdk.COMM_SUCCESS or result2 != _sdk.COMM_SUCCESS:
            return  # the fast poll counts communication failures
        expired = self._expired_watchdogs()
        if expired and self.state is DriverState.ACTIVE:
            self._hw_fault = True  # stays until recover()
            self.report_fault(
                DriverOperationError(
                    f"{self.name}: the Bus Watchdog of servo {', '.join(map(str, expired))}"
                    f" expired (no instruction for over {self.bus_watchdog:g} s): stopped, goals"
                    " refused; recover() and activate() again"
                )
            )
        stamp = self.clock.monotonic()
        status: dict[int, ServoStatus] = {}
        failing: list[tuple[int, int]] = []
        for servo in self.servos:
            value = bits[servo.id][0]
            status[servo.id] = ServoStatus(
                servo.id,
                servo.joint,
                float(slow[servo.id][2]),
                p.from_le(slow[servo.id][0:2]) * ct.VOLT_PER_UNIT,
                value,
                p.decode_hardware_error(value),
                stamp,
            )
            if value:
                failing.append((servo.id, value))
        with self._cache:
            self._status = status
        if failing:
            self._hw_fault = True
            self.report_fault(self._hardware_error(*failing[0], also=failing[1:]))

    # ---- helpers ------------------------------------------------------------------------------

    def _port(self) -> _sdk.SdkPort:
        if self._sdk is None:
            raise StateError(f"{self.name}: the port is not open")
        return self._sdk

    def _reader(self, which: str) -> _sdk.SyncReader:
        reader = {"fast": self._fast, "torques": self._torques}[which]
        if reader is None:
            raise StateError(f"{self.name}: not configured")
        return reader

    def _writer(self, reg: ct.Register) -> _sdk.SyncWriter:
        writer = self._writers.get(reg.address)
        if writer is None:
            writer = self._port().sync_writer(reg.address, reg.size)
            self._writers[reg.address] = writer
        return writer

    def _check_tx(self, result: int) -> None:
        if result != _sdk.COMM_SUCCESS:
            raise self._comm_error("SyncWrite", result)

    def _read(self, dxl_id: int, reg: ct.Register, what: str, alert_ok: bool = False) -> int:
        for _ in range(_TRIES):
            value, result, error = self._port().read(dxl_id, reg.address, reg.size)
            if result == _sdk.COMM_SUCCESS:
                break
        self._check_reply(dxl_id, what, result, error & ~p.ALERT_BIT if alert_ok else error)
        if reg.signed and value >= 1 << (8 * reg.size - 1):
            value -= 1 << (8 * reg.size)
        return value

    def _write(self, dxl_id: int, reg: ct.Register, value: int, what: str) -> None:
        for _ in range(_TRIES):
            result, error = self._port().write(dxl_id, reg.address, reg.size, value)
            if result == _sdk.COMM_SUCCESS:
                break
        self._check_reply(dxl_id, what, result, error)

    def _check_reply(self, dxl_id: int, what: str, result: int, error: int) -> None:
        if result != _sdk.COMM_SUCCESS:
            raise self._comm_error(f"{what} of servo {dxl_id}", result)
        if error & p.ALERT_BIT:
            bits, result, _ = self._port().read(dxl_id, ct.HARDWARE_ERROR_STATUS.address, 1)
            raise self._hardware_error(dxl_id, bits if result == _sdk.COMM_SUCCESS else 0)
        if error:
            number = error & 0x7F
            name = p.ErrorNumber(number).name if number <= 7 else str(number)
            raise DriverOperationError(f"{self.name}: servo {dxl_id} refused {what}: {name}")

    def _raise_alerts(self, errors: Mapping[int, int]) -> None:
        for dxl_id, error in errors.items():
            if error & p.ALERT_BIT:
                bits, result, _ = self._port().read(dxl_id, ct.HARDWARE_ERROR_STATUS.address, 1)
                raise self._hardware_error(dxl_id, bits if result == _sdk.COMM_SUCCESS else 0)

    def _comm_error(self, what: str, result: int) -> DriverError:
        text = self._sdk.result_text(result) if self._sdk is not None else str(result)
        message = f"{self.name}: {what}: {text}"
        if result == _sdk.COMM_RX_TIMEOUT:
            return DriverTimeoutError(f"{message} (no reply)")
        return DriverOperationError(message)

    def _hardware_error(
        self, dxl_id: int, bits: int, also: Sequence[tuple[int, int]] = ()
    ) -> DynamixelHardwareError:
        servo = self._by_id[dxl_id]
        names = ", ".join(p.decode_hardware_error(bits)) or "alert bit"
        more = "".join(f"; servo {i}: {', '.join(p.decode_hardware_error(b))}" for i, b in also)
        return DynamixelHardwareError(
            f"{self.name}: servo {dxl_id} ({servo.joint}) hardware error: {names}{more}"
            " (recover() reboots it)",
            servo_id=dxl_id,
            error=bits,
        )


_VELOCITY_LIMIT: Final = next(r for r in ct.REGISTERS if r.name == "Velocity Limit")
_CURRENT_LIMIT: Final = next(r for r in ct.REGISTERS if r.name == "Current Limit")


def _check_latency_timer(name: str, port: str) -> None:
    """Log a warning when the USB serial adapter of ``port`` has a latency timer above 1 ms.

    Args:
        name: The device, for the message.
        port: The serial device.
    """
    value = latency_timer(port)
    if value is not None and value > 1:
        tty = os.path.basename(os.path.realpath(port))
        logger.warning(
            "%s: the USB serial latency timer of %s is %d ms: every read waits up to that long"
            " for the adapter; set it to 1 (echo 1 | sudo tee %s/%s/latency_timer, or a udev"
            " rule: docs/driver-dynamixel.md)",
            name,
            port,
            value,
            timing.USB_SERIAL_SYSFS,
            tty,
        )
