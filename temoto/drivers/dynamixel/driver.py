"""DynamixelDriver: one chain of DYNAMIXEL X-series servos over dynamixel-sdk (Protocol 2.0).

Lifecycle (docs/development.md §5):

* ``configure`` opens the port at the baud rate (and warns when the USB adapter's latency timer
  is above 1 ms), then checks every servo before it writes anything to any of them (PING and
  READ only): one servo per id (a second status packet to a PING, or replies to PING garbled
  every time, is "duplicate servo id N"), its model number, its firmware (a Bus Watchdog needs
  v38 on when one is configured), its Hardware Error Status and its Velocity and Current Limit
  registers; every problem goes into one :class:`~temoto.errors.DriverInitError` naming each
  servo. Only then it reboots a servo that reported a hardware error (logged), turns torque
  off, writes the EEPROM registers the profile sets -- Operating Mode, Return Delay Time,
  Min/Max Position Limit -- each only when it differs, reads the state once and starts the
  poll thread;
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
Present Temperature, Hardware Error Status and the Bus Watchdog. Supervision: every status
packet with a bad CRC or garbage is logged and counted (each packet, not each poll), and a
fault only when 5 fall within 1 s (:class:`~temoto.drivers.supervision.FaultWindow`);
``timeout_polls`` polls in a row without replies are a
:class:`~temoto.errors.DriverTimeoutError`; the present-position stream is stale (a
:class:`~temoto.errors.DriverTimeoutError` naming it) when no good poll came for 3 x (poll
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

Modules, one concept each: the port, the poll thread and supervision
(:mod:`~temoto.drivers.dynamixel._chain`, the class this one is built on), a servo's settings
and units (:mod:`~temoto.drivers.dynamixel.servos`), the profile's keys
(:mod:`~temoto.drivers.dynamixel.settings`), wire timing and the adapter's latency timer
(:mod:`~temoto.drivers.dynamixel.timing`) and detection (:mod:`~temoto.drivers.dynamixel.detect`);
their public names are importable from here too.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, ClassVar, Final, Self

from temoto.clock import Clock
from temoto.drivers.base import DriverState
from temoto.drivers.capabilities import ControlMode, JointCommand, JointStates
from temoto.drivers.dynamixel import _sdk, timing
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel._chain import ServoChain, register_label
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
)
from temoto.drivers.profile import Field, ProfileReader
from temoto.drivers.realism import read_sim_realism
from temoto.drivers.sim import Simulator
from temoto.errors import (
    DriverInitError,
    DriverOperationError,
    DriverUnavailableError,
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
_REBOOT_WAIT_TRIES: Final = 20  # pings (each up to ~34 ms real) while a servo restarts
_IDENTIFY_TRIES: Final = 3  # PINGs of each servo at configure
#: Real seconds to listen after a servo's status packet for a second one (two servos on one
#: id); bounded by ``reply_timeout``.
_DUPLICATE_SETTLE: Final = 0.02
#: PINGs answered twice before a servo id counts as duplicate (a late reply can follow once).
_DUPLICATE_CONFIRM: Final = 2
_GARBLED: Final = "garbled"  # _check_identity: only garbled replies (reported together)


class DynamixelDriver(ServoChain):
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

    @property
    def joint_limits(self) -> Mapping[str, tuple[float, float]]:
        """(min, max) position (rad) of every joint in a position mode."""
        return {
            s.joint: (s.min_position, s.max_position)
            for s in self.servos
            if s.operating_mode in POSITION_MODES
        }

    @property
    def joint_velocity_limits(self) -> Mapping[str, float]:
        """The largest speed of every joint (rad/s; the profile checks navigation against it).

        Its ``velocity_limit``, or else the most its model's Velocity Limit (44) can be set to.
        """
        return {s.joint: s.speed_limit for s in self.servos}

    @property
    def device_watchdog(self) -> float:
        """Seconds of the servos' own watchdog (the Bus Watchdog; 0: off)."""
        return self.bus_watchdog

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
        level, seed = read_sim_realism(ProfileReader.at(name), config.get("sim"))
        sim = SimDynamixelChain(
            {s.id: s.model for s in servos}, clock=clock, name=name, realism=level, seed=seed
        )
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
        servos' Bus Watchdog sees a steady stream of set-points. The SyncWrite goes before the
        poll thread's transactions waiting for the bus: it waits only for the one in flight.

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
        with self._bus.urgent():  # before the polls waiting: a hold must not queue behind them
            for reg in order:
                if reg.address in goals:
                    result = self._writer(reg).write(goals[reg.address])
                    if result != _sdk.COMM_SUCCESS:
                        text = self._port().result_text(result)
                        raise DriverOperationError(f"{self.name}: {_sync_write(reg)}: {text}")
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
            errors = self._identify()  # PING and READ only: nothing written yet
            for servo in self.servos:
                self._bring_up(servo, errors[servo.id])
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
        if not self._poll_fast() and not self._poll_fast():  # one lost reply is no failure
            raise DriverInitError(f"{self.name}: the first SyncRead of the chain failed")
        self._poll_status()
        self._start_polling()

    def on_activate(self) -> None:
        """Clear the Bus Watchdog, hold where each servo is, arm the watchdog, turn torque on."""
        with self._bus:
            for servo in self.servos:  # 0 clears a Bus Watchdog error: goals writable again
                self._write(servo.id, ct.BUS_WATCHDOG, 0, "bus watchdog clear")
            result, data, errors = self._read_twice(self._reader("fast"))
            if result != _sdk.COMM_SUCCESS:
                raise self._sync_error(self._reader("fast"), result, "read before torque on")
            self._raise_alerts(errors)
            holds: dict[int, bytes] = {}
            for servo in self.servos:
                if servo.operating_mode in POSITION_MODES:
                    holds[servo.id] = data[servo.id][6:10]  # present position → goal
            if holds:
                self._check_tx(
                    self._writer(ct.GOAL_POSITION).write(holds), _sync_write(ct.GOAL_POSITION)
                )
            zero = {s.id: p.to_le(0, 4) for s in self.servos if s.mode == "velocity"}
            if zero:
                self._check_tx(
                    self._writer(ct.GOAL_VELOCITY).write(zero), _sync_write(ct.GOAL_VELOCITY)
                )
            zero = {s.id: p.to_le(0, 2) for s in self.servos if s.mode == "current"}
            if zero:
                self._check_tx(
                    self._writer(ct.GOAL_CURRENT).write(zero), _sync_write(ct.GOAL_CURRENT)
                )
            self._goals = self._hold_goals(data)
            # armed before torque on (it only watches while torque is on, e-Manual address
            # 98): a SIGKILL between two writes never leaves a torqued servo unwatched
            if self.watchdog_units:
                for servo in self.servos:
                    self._write(servo.id, ct.BUS_WATCHDOG, self.watchdog_units, "bus watchdog")
            for servo in self.servos:
                self._write(servo.id, ct.TORQUE_ENABLE, 1, "torque on")

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
        # before the polls waiting; else (a transaction stuck) the SDK says if it is busy
        got = self._bus.acquire(timeout=_SAFE_BUS_WAIT, urgent=True)
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
            raise DriverOperationError(
                f"{self.name}: torque off: {_sync_write(ct.TORQUE_ENABLE)}:"
                f" {port.result_text(result)}"
            )
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
        result, data, _ = self._read_twice(reader)
        if result != _sdk.COMM_SUCCESS:
            raise DriverOperationError(
                f"{self.name}: hold: cannot read the present positions: "
                + self._sync_failure(*ct.FAST_READ, reader.failed, result)
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
    def _identify(self) -> dict[int, int]:
        """Check every servo before anything is written to any of them (PING and READ only).

        Each servo is PINGed (a second status packet, or replies to PING garbled every time,
        mean two servos answer its id), its model number compared with the profile's, its
        firmware checked for a Bus Watchdog when one is configured, and its Velocity and
        Current Limit registers read (velocity and current modes: the profile's limit must not
        exceed them). Every problem found is reported together.

        Returns:
            Each servo's Hardware Error Status (non-zero: reboot it before use).

        Raises:
            DriverInitError: A servo is missing, duplicated, of another model, has old firmware
                or settings the servo refuses; the message names each and says that nothing
                was written.
            DriverError: A read failed (naming the servo and the register).
        """
        problems: list[str] = []
        errors: dict[int, int] = {}
        garbled: list[ServoConfig] = []
        for servo in self.servos:
            problem, answered = self._check_identity(servo)
            if problem == _GARBLED:
                garbled.append(servo)
                continue
            if problem:
                problems.append(problem)
                if not answered:
                    break  # a silent servo: likely the chain; do not wait for each one
                continue
            errors[servo.id] = self._read(servo.id, ct.HARDWARE_ERROR_STATUS, alert_ok=True)
            problems += self._check_settings(servo)
        if len(garbled) == 1:
            servo = garbled[0]
            problems.insert(
                0,
                f"duplicate servo id {servo.id} ({servo.joint})? its replies to PING were"
                f" garbled ({_IDENTIFY_TRIES} tries): two servos answering at once, or a noisy"
                " line",
            )
        elif garbled:
            problems.insert(
                0,
                f"the replies to PING of servos {', '.join(str(s.id) for s in garbled)} were"
                " garbled: a noisy line or a wrong baud rate (or duplicate servo ids)",
            )
        if problems:
            raise DriverInitError(
                f"{self.name}: {'; '.join(problems)} (nothing was written to any servo)"
            )
        return errors

    def _check_identity(self, servo: ServoConfig) -> tuple[str, bool]:
        """PING one servo: ('', True) when exactly one servo of the profile's model answers.

        A second status packet to the PING must come again on the next PING to count (a late
        reply to an earlier instruction can follow a reply once); garbled replies must come on
        every try that was answered, at least twice.

        Returns:
            (the problem, :data:`_GARBLED`, or '', whether the servo answered at all).
        """
        port = self._port()
        settle = min(self.reply_timeout, _DUPLICATE_SETTLE)
        garbled = doubled = 0
        reason = ""
        for _ in range(_IDENTIFY_TRIES):
            model, result, _ = port.ping(servo.id)
            if result == _sdk.COMM_RX_CORRUPT:
                garbled += 1
                port.leftover(settle)  # the rest of a collision, before the next try
                continue
            if result != _sdk.COMM_SUCCESS:
                continue
            reason, sure = _duplicate_reply(servo.id, port.leftover(settle))
            if sure:
                doubled += 1
                if doubled >= _DUPLICATE_CONFIRM:
                    return f"duplicate servo id {servo.id} ({servo.joint}): {reason}", True
                continue
            if reason:  # garbage after the reply: a collision, or noise; ask again
                garbled += 1
                continue
            if model != servo.spec.number:
                found = ct.MODELS_BY_NUMBER.get(model)
                name = found.name if found else "an unknown model"
                return (
                    f"servo {servo.id} ({servo.joint}) is {name} (model number {model}),"
                    f" the profile says {servo.model} ({servo.spec.number})"
                ), True
            return "", True
        if garbled >= _DUPLICATE_CONFIRM and not doubled:  # the other tries: no reply
            return _GARBLED, True
        if doubled or garbled:
            return (
                f"servo {servo.id} ({servo.joint}): no clean reply to PING in"
                f" {_IDENTIFY_TRIES} tries ({doubled} doubled, {garbled} garbled)"
            ), True
        return (
            f"servo {servo.id} ({servo.joint}): {port.result_text(result)} to PING on"
            f" {self.port} ({_IDENTIFY_TRIES} tries)"
        ), False

    def _check_settings(self, servo: ServoConfig) -> list[str]:
        """The profile's settings against what one servo has (READ only); the problems.

        The alert bit is ignored here: a servo with a hardware error is rebooted afterwards.
        """
        problems: list[str] = []
        firmware = self._read(servo.id, ct.FIRMWARE_VERSION, alert_ok=True)
        logger.debug("%s: servo %d (%s): %s, firmware v%d", *self._who(servo), firmware)
        if self.watchdog_units and firmware < ct.BUS_WATCHDOG_FIRMWARE:
            problems.append(
                f"servo {servo.id} ({servo.joint}) has firmware {firmware}, which has no Bus"
                f" Watchdog (v{ct.BUS_WATCHDOG_FIRMWARE} on): update it (DYNAMIXEL Wizard)"
                " or set bus_watchdog: 0"
            )
        velocity_limit = self._read(servo.id, _VELOCITY_LIMIT, alert_ok=True)
        current_limit = 0  # a model that reports load has no Current Limit (nor current mode)
        if servo.spec.register(_CURRENT_LIMIT.name) is not None:
            current_limit = self._read(servo.id, _CURRENT_LIMIT, alert_ok=True)
        self._limits[servo.id] = (velocity_limit, current_limit)
        if servo.mode == "velocity" and servo.velocity_limit is not None:
            units = abs(servo.velocity_units(servo.velocity_limit))
            if units > velocity_limit:
                problems.append(
                    f"servo {servo.id} ({servo.joint}): velocity_limit {servo.velocity_limit:g}"
                    f" rad/s is {units} units, above its Velocity Limit (44) of {velocity_limit}"
                    f" ({abs(servo.velocity(velocity_limit)):.3g} rad/s): lower velocity_limit"
                    " or raise the register (DYNAMIXEL Wizard)"
                )
        if servo.mode == "current" and servo.effort_limit is not None:
            units = abs(servo.current_units(servo.effort_limit))
            if units > current_limit:
                problems.append(
                    f"servo {servo.id} ({servo.joint}): effort_limit {servo.effort_limit:g} N·m"
                    f" is {units} units, above its Current Limit (38) of {current_limit}"
                    f" ({abs(servo.effort(current_limit)):.3g} N·m): lower effort_limit or raise"
                    " the register (DYNAMIXEL Wizard)"
                )
        return problems

    def _who(self, servo: ServoConfig) -> tuple[str, int, str, str]:
        return self.name, servo.id, servo.joint, servo.model

    def _bring_up(self, servo: ServoConfig, error_bits: int) -> None:
        """Reboot a servo with an old hardware error, torque off, write the EEPROM settings."""
        port = self._port()
        if error_bits:
            logger.warning(
                "%s: servo %d (%s) reports %s: rebooting it",
                self.name,
                servo.id,
                servo.joint,
                ", ".join(p.decode_hardware_error(error_bits)),
            )
            result, _ = port.reboot(servo.id)
            if result != _sdk.COMM_SUCCESS:
                raise self._comm_error(f"servo {servo.id}: REBOOT", result)
            self._ping(servo.id, tries=_REBOOT_WAIT_TRIES)
            bits = self._read(servo.id, ct.HARDWARE_ERROR_STATUS, alert_ok=True)
            if bits:
                raise self._hardware_error(servo.id, bits)
        self._write(servo.id, ct.TORQUE_ENABLE, 0)
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

    def _set_eeprom(self, servo: ServoConfig, reg: ct.Register, value: int, what: str) -> None:
        """Write an EEPROM register only when it differs (spares the EEPROM's write cycles)."""
        old = self._read(servo.id, reg, what)
        if old != value:
            logger.info(
                "%s: servo %d (%s): %s %d -> %d", self.name, servo.id, servo.joint, what, old, value
            )
            self._write(servo.id, reg, value, what)


def _sync_write(reg: ct.Register) -> str:
    """``SYNC_WRITE of Goal Position (116)``: what a failed SYNC_WRITE was, for messages."""
    return f"SYNC_WRITE of {register_label(reg.address, reg.size)}"


_VELOCITY_LIMIT: Final = next(r for r in ct.REGISTERS if r.name == "Velocity Limit")
_CURRENT_LIMIT: Final = next(r for r in ct.REGISTERS if r.name == "Current Limit")


_PING_REPLY: Final = 3  # parameter bytes of a status packet answering PING


def _duplicate_reply(dxl_id: int, extra: bytes) -> tuple[str, bool]:
    """Why the bytes that followed a servo's reply to PING mean two servos on one id.

    Args:
        dxl_id: The id PINGed.
        extra: What arrived after the status packet dynamixel-sdk took.

    Returns:
        (reason, sure): a second status packet from the id is sure; garbage may be a collision
        or noise; ('', False) when nothing (or only another id's packet) followed.
    """
    if not extra:
        return "", False
    packets = list(p.PacketReader().feed(extra))
    mine = [  # a reply to PING: model number and firmware, no error
        x
        for x in packets
        if isinstance(x, p.Packet) and x.is_status and x.id == dxl_id
        if len(x.params) == _PING_REPLY and not x.error
    ]
    if mine:
        models = [p.from_le(x.params[:2]) for x in mine if len(x.params) >= 2]
        names = ", ".join(
            ct.MODELS_BY_NUMBER[m].name if m in ct.MODELS_BY_NUMBER else f"model {m}"
            for m in models
        )
        return f"{1 + len(mine)} status packets answered one PING (also {names})", True
    if any(isinstance(x, p.PacketError) for x in packets) or not packets:
        return f"{len(extra)} garbled bytes followed its reply to PING", False
    return "", False


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
