"""A simulated ArduCopter on UDP: the vehicle's side of MAVLink 2 (docs/development.md §6).

:class:`SimVehicle` binds a UDP socket (on ``127.0.0.1`` unless told ``host=``) and *sends*
to the ground stations it is given (``gcs=[(host, port)]``, like a real autopilot streaming
to ``udpin:`` listeners on 14550 or MAVSDK on 14540); it also answers anyone who sends to its
own port (so a ``udpout:`` client works too). It behaves like a small ArduCopter 4.5, so
that MAVProxy, QGroundControl, MAVSDK and a pymavlink ground station work with it as with SITL:

* HEARTBEAT at 1 Hz (``MAV_TYPE_QUADROTOR``, ``MAV_AUTOPILOT_ARDUPILOTMEGA``, ArduCopter custom
  modes, the armed flag) and the streams of :data:`DEFAULT_RATES`, grouped as ArduCopter's
  ``SRx_*`` stream groups (:data:`STREAM_GROUPS`) so that REQUEST_DATA_STREAM sets a group's
  rate; ``MAV_CMD_SET_MESSAGE_INTERVAL`` sets one message's. AUTOPILOT_VERSION (with the
  capabilities it really has: MAVLINK2, PARAM_FLOAT, MISSION_INT, COMMAND_INT,
  SET_POSITION_TARGET_GLOBAL_INT, MISSION_FENCE, MISSION_RALLY; not FTP) and any streamed
  message on ``MAV_CMD_REQUEST_MESSAGE``; TIMESYNC answered.
* The parameter protocol over :data:`PARAMETERS` (ArduCopter's names, defaults and types):
  PARAM_REQUEST_LIST streams every PARAM_VALUE with its index and the count (paced, a few per
  model step, after the version banner), PARAM_REQUEST_READ by name (answered with index -1,
  as ArduPilot does) or index, PARAM_SET answered with the stored value (an unknown name or
  NaN gets no answer; a read-only one "Param write denied" and the kept value). The
  parameters drive the model (below). ``params_file=`` loads them from a ``.param`` file and
  writes every accepted PARAM_SET back to it. FILE_TRANSFER_PROTOCOL requests are NAKed
  (the vehicle has no files), so MAVProxy's ``param fetch`` falls back to PARAM_REQUEST_LIST
  at once.
* The mission protocol (:class:`~temoto.drivers.mavlink.sim_mission.MissionService`: upload
  and download with MISSION_INT or the legacy messages, CLEAR_ALL (refused while the mission
  flies), fence and rally plans stored), MISSION_SET_CURRENT and
  ``MAV_CMD_DO_SET_MISSION_CURRENT``, MISSION_CURRENT (streamed and on every change),
  MISSION_ITEM_REACHED. The guided forms of MISSION_ITEM(_INT)
  (``current`` 2: fly there, 3: change altitude) act in GUIDED.
* AUTO flies the mission: NAV_TAKEOFF, NAV_WAYPOINT (acceptance radius: param2, else
  ``WPNAV_RADIUS``; hold: param1 s), NAV_LOITER_TIME, NAV_LOITER_UNLIM, NAV_LAND,
  NAV_RETURN_TO_LAUNCH, DO_CHANGE_SPEED and DO_JUMP; other commands are skipped. Entering AUTO
  needs a mission and, armed on the ground, a NAV_TAKEOFF first ("Auto: Missing Takeoff
  Cmd"); arming in AUTO needs ``AUTO_OPTIONS`` bit 0, as in ArduCopter; a takeoff from the
  ground waits for the throttle (never raised: no RC) unless ``AUTO_OPTIONS`` bit 1, a GUIDED
  takeoff before or ``MAV_CMD_MISSION_START`` stands in for it (``ModeAuto::takeoff_run``);
  ``MAV_CMD_MISSION_START`` switches to AUTO and starts a stopped mission. At the end of the
  mission the vehicle holds in the air, or disarms on the ground.
* A COMMAND_ACK for every COMMAND_LONG and COMMAND_INT addressed to the autopilot (component 1
  or broadcast 0; messages for another component, e.g. a camera's 100, are not acted on):
  arm/disarm (400) with pre-arm checks (``ARMING_CHECK``; a battery below
  ``min_arm_battery`` %, ``BATT_ARM_VOLT`` or ``BATT_ARM_MAH``, a hardware error → ``FAILED``
  and a ``PreArm:`` STATUSTEXT *after* the ack, as ArduPilot sends it; a mode that cannot arm
  → ``FAILED``, "Arm: Mode not armable"), set mode (176, and SET_MODE), takeoff (22, GUIDED and
  armed), land (21), return to launch (20), reposition (192), GET_HOME_POSITION (410),
  DO_SET_HOME (179; home is also set where the vehicle arms, unless DO_SET_HOME fixed it),
  DO_CHANGE_SPEED (178), MISSION_START (300), SET_POSITION_TARGET_GLOBAL_INT in GUIDED;
  ``UNSUPPORTED`` for the rest. SYS_STATUS carries ``MAV_SYS_STATUS_PREARM_CHECK`` (present;
  enabled when ``ARMING_CHECK`` is not 0; healthy when the pre-arm checks pass, always when
  armed).
* ArduCopter's GCS failsafe, on the injected clock: once a HEARTBEAT from the GCS system id
  ``SYSID_MYGCS`` (255) was seen, ``FS_GCS_TIMEOUT`` seconds (5) without one trigger it if
  ``FS_GCS_ENABLE`` is not 0: disarmed → nothing but a "GCS Failsafe" text; armed and landed →
  disarm; in the air → RTL (1, 2, 6), SmartRTL-or-RTL (3; SmartRTL is not simulated: RTL),
  SmartRTL-or-LAND (4: LAND), LAND (5), BRAKE (7), RTL for any other value. A heartbeat ends
  the failsafe ("GCS Failsafe Cleared"); the mode stays. In AUTO, ``FS_GCS_ENABLE`` 2 or
  ``FS_OPTIONS`` bit 1 (2) continue the mission; the other ``FS_OPTIONS`` bits are not
  simulated.
  The battery failsafe likewise: ``BATT_LOW_VOLT`` (for ``BATT_LOW_TIMER`` s) or
  ``BATT_LOW_MAH`` (of ``BATT_CAPACITY``) → ``BATT_FS_LOW_ACT``, the ``CRT`` ones →
  ``BATT_FS_CRT_ACT`` (0 none, 1 LAND, 2 RTL, 3 RTL, 4 LAND, 5 disarm, 6 RTL, 7 BRAKE);
  both latch. Each datagram received is parsed on its own.
* A first-order kinematic model stepped on the injected clock at ``step_rate`` Hz: the
  position approaches its target with time constant ``tau``, its horizontal acceleration
  bounded by the lean limit ``ANGLE_MAX`` (g·tan(angle); ATTITUDE leans within it), limited to
  ``WPNAV_SPEED``
  horizontally (``RTL_SPEED`` in RTL, a DO_CHANGE_SPEED in AUTO/GUIDED), ``WPNAV_SPEED_UP`` up
  and ``WPNAV_SPEED_DN`` down; LAND descends at ``LAND_SPEED_HIGH`` (0: ``WPNAV_SPEED_DN``)
  above ``LAND_ALT_LOW`` and ``LAND_SPEED`` below, and disarms on touchdown; RTL climbs to
  ``RTL_ALT``, flies home, hovers ``RTL_LOIT_TIME`` ms and lands (or stays at
  ``RTL_ALT_FINAL``). The battery drains while armed (``drain_idle`` %/s) and more in the air
  (``drain_flight`` %/s at hover, more with the lean's thrust and a climb); its current is
  reported and its voltage sags under it. Wind (SITL's ``SIM_WIND_SPD``, ``SIM_WIND_DIR``)
  pushes the vehicle; the lean counters it within ``ANGLE_MAX``, a stronger wind drifts it.

An imperfect world on request (``realism=``, :mod:`temoto.drivers.realism`; the figures are in
``docs/simulators.md``, "Realism"): at ``typical`` or ``harsh`` the reported position, altitude,
velocity, attitude, heading and battery voltage carry seeded sensor noise (the model flies on its
true state), streamed frames are now and then lost, and every batch of frames the vehicle sends
(streams and replies alike, kept in order) leaves after a jitter and now and then a stall of
the link. ``off`` (the default) sends the model's exact figures at once.

Faults (:class:`~temoto.drivers.sim.Simulator`): ``silence`` and ``link_loss`` (nothing in or out),
``uplink_loss`` (nothing in: a radio that lost its uplink; the vehicle's GCS failsafe counts while
its telemetry still reaches the ground), ``corrupt`` (every frame leaves with its CRC inverted),
``no_heartbeat`` (no HEARTBEAT, everything else flows), ``hardware_error`` (``overheat`` → the
motor-outputs health bit cleared and the battery's over-temperature fault, ``overload`` → the
propulsion health bit cleared, ``voltage`` → battery voltage far below minimum and the battery
health bit cleared; each with ``MAV_STATE_CRITICAL`` and a STATUSTEXT).

The vehicle holds its parts, each a class of its own module that can be built and driven
alone over a :class:`~temoto.drivers.mavlink.sim_state.VehicleState` (the one state object
they share by reference): :attr:`SimVehicle.state`, :attr:`SimVehicle.telemetry` (what it
sends, at what rates), :attr:`SimVehicle.auto` (the mission in AUTO), :attr:`SimVehicle.flight`
(kinematics and flight modes), :attr:`SimVehicle.failsafes` and :attr:`SimVehicle.commands`
(what it does with what it receives); this module adds the UDP endpoint and the threads. The
mission and parameter protocols are :mod:`~temoto.drivers.mavlink.sim_mission` and
:mod:`~temoto.drivers.mavlink.sim_params`.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar, Unpack

from temoto.clock import Clock
from temoto.drivers.mavlink import protocol as p
from temoto.drivers.mavlink.link import LinkSpec, UdpLink
from temoto.drivers.mavlink.protocol import Codec
from temoto.drivers.mavlink.sim_auto import AutoMission
from temoto.drivers.mavlink.sim_commands import CommandHandler
from temoto.drivers.mavlink.sim_failsafe import Failsafes
from temoto.drivers.mavlink.sim_flight import FlightModel
from temoto.drivers.mavlink.sim_mission import MissionItem
from temoto.drivers.mavlink.sim_params import PARAMETERS
from temoto.drivers.mavlink.sim_state import (
    DEFAULT_RATES,
    HW_TEXT,
    STREAM_GROUPS,
    VehicleModel,
    VehicleState,
)
from temoto.drivers.mavlink.sim_state import EARTH_RADIUS as EARTH_RADIUS
from temoto.drivers.mavlink.sim_telemetry import VehicleTelemetry
from temoto.drivers.realism import Realism
from temoto.drivers.sim import Simulator

__all__ = ["DEFAULT_RATES", "PARAMETERS", "STREAM_GROUPS", "SimVehicle"]

logger = logging.getLogger(__name__)


class SimVehicle(Simulator):
    """A simulated ArduCopter quad on UDP loopback (see the module docstring).

    The keyword arguments ``speed``, ``climb_rate``, ``descent_rate`` and ``rtl_altitude``
    (and ``system_id``) are the initial values of the ArduCopter parameters that hold them
    (``WPNAV_SPEED``, ``WPNAV_SPEED_UP``, ``WPNAV_SPEED_DN``, ``RTL_ALT``, ``SYSID_THISMAV``;
    their defaults are ArduCopter's: 10, 2.5 and 1.5 m/s, 15 m); ``params`` is applied over
    them, and the ``params_file`` over that (it is the vehicle's stored configuration, as
    ArduPilot's EEPROM).

    Args:
        name: For thread names and logs.
        gcs: Where to send (host, port) pairs; more are learned from whoever sends to us.
        port: This vehicle's own UDP port (0: any free port).
        host: The address it binds: loopback by default; ``0.0.0.0`` or a network address
            for ground stations on other machines.
        rates: Stream rates in Hz by message name (merged over :data:`DEFAULT_RATES`; 0 stops
            a stream).
        realism: ``off`` (default: the exact figures), ``typical`` or ``harsh``, or a
            :class:`~temoto.drivers.realism.Realism` (see :mod:`temoto.drivers.realism`).
        seed: The top-level seed of the realism's random numbers (None: a fresh one, logged;
            :attr:`realism` ``.seed`` holds it). Ignored when ``realism`` is a Realism.
        **model: The model, :class:`~temoto.drivers.mavlink.sim_state.VehicleModel`, each
            keyword optional (the defaults are ArduCopter's, in
            :class:`~temoto.drivers.mavlink.sim_state.VehicleState`):

            - ``clock``: Steps the model and paces the streams.
            - ``system_id``: The vehicle's MAVLink system id (``SYSID_THISMAV``; a value in
              the parameter file wins).
            - ``home``: Home latitude, longitude (degrees) and altitude above mean sea level
              (m); also the origin of the model's local frame and its ground level.
            - ``battery``: Initial charge, percent.
            - ``cells``: Battery cells in series (4.2 V full, 3.3 V empty each).
            - ``min_arm_battery``: Below this charge (%) arming is refused.
            - ``speed``: Horizontal speed, m/s (``WPNAV_SPEED``).
            - ``climb_rate``: Vertical speed up, m/s (``WPNAV_SPEED_UP``).
            - ``descent_rate``: Vertical speed down, m/s (``WPNAV_SPEED_DN``; the landing's
              last ``LAND_ALT_LOW`` is flown at ``LAND_SPEED``, ArduCopter's 0.5 m/s unless
              ``params`` says otherwise).
            - ``tau``: Time constant of the position model, s.
            - ``rtl_altitude``: Minimum altitude above home for the flight home in RTL, m
              (``RTL_ALT``).
            - ``drain_idle``: Battery drain while armed on the ground, %/s.
            - ``drain_flight``: Battery drain in the air at hover, %/s (more with lean and
              climb).
            - ``step_rate``: Model steps per clock second.
            - ``params``: Parameter values (e.g. ``{"FS_GCS_ENABLE": 5}`` for a vehicle whose
              GCS failsafe lands it); names from :data:`PARAMETERS`.
            - ``params_file``: A ``.param`` file (``NAME VALUE`` or ``NAME,VALUE`` lines,
              ``#`` comments) loaded at construction if it exists and rewritten, atomically,
              after every accepted PARAM_SET. Names the table does not have are kept and
              served as ``REAL32`` parameters.

    Raises:
        ValueError: A parameter out of range, an unknown parameter name in ``params``, a bad
            line in ``params_file`` (naming the file and line), an unknown realism level.
        OSError: ``params_file`` exists but cannot be read.
    """

    FAULTS: ClassVar[frozenset[str]] = frozenset(
        {"silence", "corrupt", "hardware_error", "no_heartbeat", "link_loss", "uplink_loss"}
    )

    def __init__(
        self,
        name: str = "vehicle",
        *,
        gcs: Iterable[tuple[str, int]] = (),
        port: int = 0,
        host: str = "127.0.0.1",
        rates: Mapping[str, float] | None = None,
        realism: Realism | str = "off",
        seed: int | None = None,
        **model: Unpack[VehicleModel],
    ) -> None:
        super().__init__()
        if not isinstance(realism, Realism):
            realism = Realism(realism, seed=seed, device=name)
        #: The vehicle's imperfections: noise, lost frames, jitter and stalls.
        self.realism = realism
        if realism.enabled:
            logger.info("%s: %s", name, realism.describe())
        #: The state the parts share.
        self.state = VehicleState(name, fault=self._active_fault, **model)
        state = self.state
        #: The messages it sends and their rates.
        self.telemetry = VehicleTelemetry(state, rates, realism)
        #: The mission flown in AUTO.
        self.auto = AutoMission(state, self.telemetry)
        #: The kinematic model and the flight modes.
        self.flight = FlightModel(state, self.telemetry, self.auto)
        #: The GCS and battery failsafes.
        self.failsafes = Failsafes(state, self.flight)
        #: What it does with each received message.
        self.commands = CommandHandler(
            state, self.telemetry, self.auto, self.flight, self.failsafes
        )
        self.name = name
        self.port = port
        self.host = host
        self._gcs = list(gcs)
        self._peers: list[Any] = []
        self._wake = threading.Condition(state.lock)
        self._link: UdpLink | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        #: Frames received (counted once handled) by message name, for tests and benchmarks.
        self.received: dict[str, int] = {}
        # the link's delay (realism): batches of frames held until their time, in order
        self._held: deque[tuple[float, list[bytes]]] = deque()
        self._held_until = 0.0
        # for settled(): the model's next step, and whether a thread is between reading the
        # clock (or a datagram) and handing the frames it made to the socket
        self._next_tick = math.inf
        self._sending = False
        self._handling = False

    def _active_fault(self, name: str) -> dict[str, Any] | None:
        params = self.fault(name)
        return None if params is None else dict(params)

    # ---- the state, read ------------------------------------------------------------------------

    @property
    def clock(self) -> Clock:
        """The clock that steps the model and paces the streams."""
        return self.state.clock

    @property
    def codec(self) -> Codec:
        """The vehicle's MAVLink codec (its system and component id)."""
        return self.state.codec

    @property
    def params_file(self) -> str | None:
        """The ``.param`` file the parameters are kept in (None: none)."""
        return self.state.params_file

    @property
    def armed(self) -> bool:
        """Whether the motors are armed."""
        return self.state.armed

    @property
    def airborne(self) -> bool:
        """Whether the vehicle is flying (taking off, in the air or landing)."""
        return self.state.airborne

    @property
    def mode(self) -> str:
        """The ArduCopter flight mode's name."""
        return self.state.mode

    @property
    def pos(self) -> list[float]:
        """The model's position: north, east, up (m from the origin, home at start)."""
        return self.state.pos

    @property
    def vel(self) -> list[float]:
        """The model's velocity: north, east, up (m/s)."""
        return self.state.vel

    @property
    def yaw(self) -> float:
        """The heading, rad from north."""
        return self.state.yaw

    @property
    def battery(self) -> float:
        """The remaining charge, %."""
        return self.state.battery

    @property
    def home(self) -> tuple[float, float, float]:
        """Home: latitude, longitude (degrees), altitude above mean sea level (m)."""
        return self.state.home

    @property
    def acks(self) -> list[tuple[int, int]]:
        """Every command answered: (MAV_CMD, MAV_RESULT), oldest first."""
        return self.commands.acks

    def param(self, name: str) -> float:
        """A parameter's value, as the vehicle stores it (takes the lock).

        Args:
            name: A parameter's name.

        Returns:
            The value.

        Raises:
            KeyError: Not a parameter of this vehicle.
        """
        return self.state.param(name)

    def position(self) -> tuple[float, float, float]:
        """Where the vehicle is: latitude, longitude (degrees), altitude above home (m).

        Returns:
            The position.
        """
        return self.state.position()

    def mission(self) -> list[MissionItem]:
        """The stored mission, item 0 (home as uploaded) included; empty if none.

        Returns:
            A copy of the items.
        """
        return self.auto.mission()

    @property
    def mission_current(self) -> int:
        """The sequence number of the current mission command (0: none)."""
        return self.auto.mission_current

    @property
    def gcs_failsafe(self) -> bool:
        """Whether the GCS failsafe is active."""
        return self.failsafes.gcs_failsafe

    @property
    def battery_failsafe(self) -> int:
        """The battery failsafe level: 0 none, 1 low, 2 critical (they latch)."""
        return self.failsafes.battery_failsafe

    def set_rate(self, message: str, hz: float) -> None:
        """Stream ``message`` at ``hz`` from now on (see :meth:`VehicleTelemetry.set_rate`).

        Args:
            message: One of :data:`DEFAULT_RATES`.
            hz: The rate (≥ 0).

        Raises:
            ValueError: Not a simulated stream, or a negative rate.
        """
        self.telemetry.set_rate(message, hz)

    def rate(self, message: str) -> float:
        """The rate a message is streamed at now, Hz (0: not streamed).

        Args:
            message: One of :data:`DEFAULT_RATES`.

        Returns:
            The rate.

        Raises:
            KeyError: Not a simulated stream.
        """
        return self.telemetry.rate(message)

    # ---- lifecycle ---------------------------------------------------------------------------

    @property
    def address(self) -> tuple[str, int]:
        """The vehicle's own UDP address (after :meth:`start`).

        Raises:
            RuntimeError: Not started.
        """
        if self._link is None:
            raise RuntimeError("the simulator is not started")
        return self._link.address

    def add_gcs(self, host: str, port: int) -> None:
        """Also stream to ``(host, port)``.

        Args:
            host: The ground station's host.
            port: Its UDP port.
        """
        with self.state.lock:
            if (host, port) not in self._gcs:
                self._gcs.append((host, port))

    def start(self) -> None:
        """Bind the socket and start the model and receive threads.

        Raises:
            RuntimeError: Already started.
            OSError: The port cannot be bound.
        """
        if self._link is not None:
            raise RuntimeError("the simulator is already started")
        self._link = UdpLink(LinkSpec("udpin", self.host, self.port))
        self.port = self._link.address[1]
        self._stop.clear()
        now = self.state.clock.monotonic()
        self.state.t0 = self.state.last = now
        self._next_tick = now
        self._threads = [
            threading.Thread(target=self._step_loop, name=f"temoto-sim-{self.name}-step"),
            threading.Thread(target=self._rx_loop, name=f"temoto-sim-{self.name}-rx"),
        ]
        for thread in self._threads:
            thread.start()

    def close(self) -> None:
        """Stop the threads and close the socket (idempotent)."""
        self._stop.set()
        with self.state.lock:
            self._wake.notify_all()
        for thread in self._threads:
            thread.join()
        self._threads = []
        if self._link is not None:
            self._link.close()
            self._link = None

    def on_fault_changed(self, fault: str, active: bool) -> None:
        """Announce a hardware error at once (STATUSTEXT); see :meth:`Simulator.inject`."""
        if fault == "hardware_error" and active:
            kind = (self.fault("hardware_error") or {}).get("kind", "overheat")
            with self.state.lock:
                self.state.texts.append((p.MAV_SEVERITY_CRITICAL, HW_TEXT[kind]))

    def send_raw(self, datagram: bytes) -> None:
        """Send bytes as one datagram to every ground station, from the vehicle's own port.

        For fault injection (a malformed frame from the vehicle's address).

        Args:
            datagram: The bytes, sent as they are.

        Raises:
            RuntimeError: Not started.
        """
        link = self._link
        if link is None:
            raise RuntimeError("the simulator is not started")
        with self.state.lock:
            peers = list(dict.fromkeys([*self._gcs, *self._peers]))
        for peer in peers:
            link.send_to(datagram, peer)

    def settled(self) -> bool:
        """Whether the vehicle has done everything due by its clock's time.

        True when the model has stepped to the clock's reading, every frame due by then (its
        telemetry, the link's delayed batches, the replies to what it received) has been
        handed to the socket, and nothing waits in its socket. For tests that move a
        :class:`~temoto.clock.ManualClock` from a thread of their own: advancing it only when
        the vehicle is settled keeps the vehicle in step with the clock however the threads
        are scheduled (else a starved step thread sees the clock jump past several of its
        frames, and the driver rightly calls a stream stale). A stopped vehicle is settled.

        Returns:
            Whether nothing is due.
        """
        link = self._link
        if link is None or self._stop.is_set():
            return True
        with self.state.lock:
            now = self.state.clock.monotonic()
            if self._sending or self._handling or now >= self._next_tick:
                return False
            if self._held and self._held[0][0] <= now:
                return False
        return not link.pending()

    # ---- threads -----------------------------------------------------------------------------

    def _step_loop(self) -> None:
        with self.state.lock:
            next_tick = self.state.clock.monotonic()
            while not self._stop.is_set():
                now = self.state.clock.monotonic()
                frames: list[bytes] = []
                if now >= next_tick:
                    self.flight.advance(now)
                    self.failsafes.check(now)
                    frames = self._delayed(self.telemetry.streams(now), now)
                    next_tick = now + self.state.dt
                    self._next_tick = next_tick
                while self._held and self._held[0][0] <= now:  # the link's delay is over
                    frames += self._held.popleft()[1]
                if frames:
                    self._sending = True
                    self.state.lock.release()
                    try:
                        self._send(frames)
                    finally:
                        self.state.lock.acquire()
                        self._sending = False
                    if self._stop.is_set():  # close() notified while the lock was released
                        break
                wake = min(next_tick, self._held[0][0]) if self._held else next_tick
                self.state.clock.wait(self._wake, max(wake - now, 0.0))

    def _delayed(self, frames: list[bytes], now: float, *, reply: bool = False) -> list[bytes]:
        """What of ``frames`` leaves now; the rest is held for the link's delay (lock held).

        Realism: the batch leaves after the link's jitter (and now and then a stall), never
        before a batch sent earlier.
        """
        if not frames or not self.realism.enabled:
            return frames
        release = max(now + self.realism.delay(reply=reply), self._held_until)
        if release <= now and not self._held:
            return frames
        self._held.append((release, frames))
        self._held_until = release
        self._wake.notify_all()
        return []

    def _rx_loop(self) -> None:
        link = self._link
        assert link is not None
        while not self._stop.is_set():
            try:
                data, peer = link.receive(0.05)
            except OSError:
                if self._stop.is_set():
                    return
                raise
            if not data:
                continue
            self._handling = True
            try:
                self._handle(data, peer)
            finally:
                self._handling = False

    def _handle(self, data: bytes, peer: Any) -> None:
        """One datagram from a ground station: answer its messages."""
        if self.fault("silence") is not None:
            return
        if self.fault("link_loss") is not None or self.fault("uplink_loss") is not None:
            return  # nothing heard from the ground: the GCS failsafe counts
        with self.state.lock:
            if peer not in self._peers:
                self._peers.append(peer)
        for msg in self.state.codec.decode_datagram(data):
            replies = self.commands.handle(msg)
            # counted once handled: a test that waits for the count sees its effect
            self.received[msg.name] = self.received.get(msg.name, 0) + 1
            if self.realism.enabled:
                with self.state.lock:
                    now = self.state.clock.monotonic()
                    replies = self._delayed(replies, now, reply=True)
            self._send(replies)

    def _send(self, frames: list[bytes]) -> None:
        link = self._link
        if not frames or link is None:
            return
        if self.fault("silence") is not None or self.fault("link_loss") is not None:
            return
        if self.fault("corrupt") is not None:
            frames = [p.corrupt(f) for f in frames]
        with self.state.lock:
            peers = list(dict.fromkeys([*self._gcs, *self._peers]))
        for frame in frames:
            for peer in peers:
                link.send_to(frame, peer)
