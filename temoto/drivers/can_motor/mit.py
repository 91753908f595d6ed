"""CubeMars/T-Motor AK motors in MIT mode (profile ``driver: mit_can``).

The MIT protocol has no heartbeat: a motor answers every frame it gets. So the driver polls:
its supervisor thread sends every motor a frame each ``1 / poll_rate`` seconds (the held
command while ``ACTIVE``, the harmless *exit motor mode* frame otherwise), and a motor that
leaves ``timeout_periods`` polls in a row unanswered is a
:class:`~temoto.errors.DriverTimeoutError` (recovered by itself when replies return). An error
code in a reply (newer firmware's 8-byte replies) is a :class:`~temoto.errors.MotorFaultError`,
latched until :meth:`recover`.

The polls are also what feeds the motors' own CAN timeout (``can_timeout``, set on the device):
while ``ACTIVE`` every poll is a command frame, so a motor whose host died zeroes its command.

Supervision (``docs/driver-can.md``): besides the unanswered polls, a motor whose newest reply
is older than ``timeout_periods + 1`` poll periods is a
:class:`~temoto.errors.DriverTimeoutError` naming its replies (a poll that was never sent is
noticed too). Malformed replies (wrong length, or an unknown motor id on the host id) are
counted (:attr:`MitMotorDriver.bad_frames`) and logged; :data:`BAD_REPLIES_LIMIT` of them on the
bus within :data:`~temoto.drivers.supervision.BAD_FRAMES_WINDOW` seconds make a
:class:`~temoto.errors.DriverOperationError` until the next good reply (the replies come only
at the poll rate, so fewer are needed than on a cyclic bus). More replies from a motor than
frames sent to it (:data:`DUPLICATE_LIMIT` unasked replies within a second) means two motors
answer on one id: a :class:`~temoto.errors.DriverOperationError`.

**Safe state** (``safe_state: zero_torque``, the only one): a zero-torque command (p, v, kp, kd,
t_ff all 0) and then *exit motor mode*, which the polls then keep sending; confirmed by the
motors' replies within :data:`SAFE_CONFIRM` real seconds.

``activate`` sends *enter motor mode* and then holds the current position with the profile's
``kp`` / ``kd``; ``deactivate`` sends *exit motor mode*. Joint commands map onto the impedance
command: position → ``(p, 0, kp, kd, 0)``, velocity → ``(0, v, 0, kd, 0)``, effort →
``(0, 0, 0, 0, t)``. The protocol's units are the motor's output side (rad, rad/s, N·m); a
further gearbox is ``gear_ratio`` (motor turns per joint turn).
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Final

import can

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.base import DriverState
from temoto.drivers.can_motor import mitmode as mm
from temoto.drivers.can_motor._common import (
    LINK_HINT,
    JointLimits,
    check_limits,
    read_limits,
    read_link,
    read_members,
)
from temoto.drivers.can_motor._driver import (
    DUPLICATE_LISTEN,
    DUPLICATE_PROBES,
    GAP_MIN,
    GAP_PERIODS,
    CanMotorDriver,
)
from temoto.drivers.capabilities import ControlMode, JointCommand, JointState, JointStates
from temoto.drivers.profile import Field, ProfileReader, custom, integer, number
from temoto.drivers.realism import SIM_KEYS, read_sim_realism
from temoto.drivers.sim import Simulator
from temoto.drivers.supervision import BAD_FRAMES_WINDOW, FaultWindow, StreamAge
from temoto.errors import (
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    MotorFaultError,
    StateError,
)

__all__ = [
    "BAD_REPLIES_LIMIT",
    "CAN_TIMEOUT_MAX",
    "DUPLICATE_LIMIT",
    "SAFE_CONFIRM",
    "MitMotor",
    "MitMotorDriver",
]

logger = logging.getLogger(__name__)

#: Real seconds :meth:`MitMotorDriver.make_safe` waits for the motors' replies.
SAFE_CONFIRM: Final = 0.1
#: Malformed replies on the bus within the window that make a fault.
BAD_REPLIES_LIMIT: Final = 2
#: Unasked replies from one motor within a second that mean two motors share its id.
DUPLICATE_LIMIT: Final = 5
#: The longest CAN timeout the AK firmware takes, seconds: its setup menu's ``CAN Timeout
#: (cycles)`` is 0..100000 cycles of the 40 kHz current loop (``docs/driver-can.md``).
CAN_TIMEOUT_MAX: Final = 2.5
_ZERO_TORQUE: Final = mm.MitCommand(0.0, 0.0, 0.0, 0.0, 0.0)

_MOTOR_KEYS: Final = frozenset(
    {
        "motor_id",
        "joint",
        "model",
        "p_max",
        "v_max",
        "t_max",
        "gear_ratio",
        "kp",
        "kd",
        "position_min",
        "position_max",
        "velocity_limit",
        "torque_limit",
    }
)
_KINDS: Final = {1: "overheat", 2: "overload", 3: "voltage", 4: "voltage"}


@dataclass(frozen=True, slots=True)
class MitMotor:
    """One motor of a device entry.

    Attributes:
        motor_id: Its CAN id (1..255).
        joint: The joint it moves.
        ranges: The MIT field ranges of its model.
        gear_ratio: Motor turns per joint turn, beyond the motor's own gearbox.
        kp: Position stiffness for position commands, N·m/rad (motor side).
        kd: Damping for position and velocity commands, N·m·s/rad (motor side).
        limits: Joint-side limits of set-points.
        model: Its AK model (a key of ``MODELS``; the simulator takes its mechanics from it).
    """

    motor_id: int
    joint: str
    ranges: mm.MitRanges = field(default_factory=mm.MitRanges)
    gear_ratio: float = 1.0
    kp: float = 20.0
    kd: float = 1.0
    limits: JointLimits = field(default_factory=JointLimits)
    model: str = "AK80-9"


def _check_model(
    reader: ProfileReader,
    path: str,
    model: str,
    ranges: mm.MitRanges,
    gear: float,
    limits: JointLimits,
) -> None:
    """Refuse joint limits the motor's MIT fields cannot carry (its model's table).

    A joint's position, velocity and torque reach the motor multiplied (torque: divided) by
    ``gear_ratio``; beyond ±p_max, ±v_max or ±t_max the field clamps, so such a limit would
    let commands through that the motor cannot be sent.

    Raises:
        ProfileError: The first limit beyond its field (naming the key, the model and the field).
    """
    what = f"the {model}'s"
    geared = "" if gear == 1 else f" (gear_ratio {gear:g})"
    reach = max(abs(limits.position_min), abs(limits.position_max))
    if math.isfinite(reach) and reach * gear > ranges.p_max:
        key = (
            "position_max"
            if abs(limits.position_max) >= abs(limits.position_min)
            else "position_min"
        )
        value = getattr(limits, key)
        reader.fail(
            f"{path}.{key}",
            f"{value:g} rad{geared} is beyond {what} position field ±{ranges.p_max:g} rad (p_max)",
        )
    if math.isfinite(limits.velocity) and limits.velocity * gear > ranges.v_max:
        reader.fail(
            f"{path}.velocity_limit",
            f"{limits.velocity:g} rad/s{geared} is above {what} velocity range"
            f" ±{ranges.v_max:g} rad/s (v_max)",
        )
    if math.isfinite(limits.torque) and limits.torque / gear > ranges.t_max:
        reader.fail(
            f"{path}.torque_limit",
            f"{limits.torque:g} N·m{geared} is above {what} torque range ±{ranges.t_max:g} N·m"
            " (t_max)",
        )


def _past_field(c: _Motor, data: bytes | bytearray, p: float) -> str | None:
    """Why a reply's position is past the ±p_max field (at its end, or wrapped), or None.

    The CubeMars manual gives the field's range, not what a motor past it sends: a firmware
    that clamps reports the end of the field, one that converts without clamping wraps to the
    other end. A jump of more than ``p_max`` between two replies cannot be motion (it would take
    ``p_max * poll_rate`` rad/s, far beyond every model's ``v_max``), so it is a wrap.
    """
    top = c.motor.ranges.p_max
    raw = data[1] << 8 | data[2]
    if raw in (0, 0xFFFF):
        return (
            f"reported position {p:+.2f} rad is at the end of the MIT position field"
            f" (±{top:g} rad, p_max of its model)"
        )
    if c.reply is not None and abs(p - c.reply[0]) > top:
        return (
            f"reported position jumped from {c.reply[0]:+.2f} to {p:+.2f} rad: it wrapped past"
            f" the end of the MIT position field (±{top:g} rad, p_max of its model)"
        )
    return None


class _Motor:
    """The receive thread's cache of one motor."""

    __slots__ = (
        "age",
        "error",
        "held",
        "motor",
        "outstanding",
        "polled",
        "replies",
        "reply",
        "saturated",
        "sent",
        "seq",
        "temperature",
        "unanswered",
        "unasked",
    )

    def __init__(self, motor: MitMotor, poll_period: float, periods: int) -> None:
        self.motor = motor
        self.age = StreamAge(f"{self.label()} replies", poll_period, periods + 1)
        self.unasked = FaultWindow(DUPLICATE_LIMIT, 1.0)
        #: When the polls since its newest reply were sent (the newest ``periods + 2``)
        self.polled: collections.deque[float] = collections.deque(maxlen=periods + 2)
        self.reset()

    def reset(self) -> None:
        self.reply: tuple[float, float, float, float] | None = None  # p, v, t, stamp
        self.replies = 0
        self.seq = 0  # the receive thread's frame number of the newest reply
        self.sent = 0  # frames sent to it
        #: frames sent and not answered yet (a motor answers every frame, in order), forgotten
        #: when the supervisor finds the motor silent
        self.outstanding = 0
        self.unanswered = 0
        self.polled.clear()
        self.error = 0
        self.temperature: int | None = None
        #: Why the reported position is no longer the motor's (past the field's end), or None.
        self.saturated: str | None = None
        self.held = mm.CMD_EXIT
        self.age.reset()
        self.unasked.clear()

    def label(self) -> str:
        return f"motor {self.motor.motor_id} ({self.motor.joint})"


class MitMotorDriver(CanMotorDriver):
    """MIT-mode motors on one CAN bus; an :class:`~temoto.drivers.capabilities.Actuator`.

    Args:
        name: The device's name.
        link: python-can ``Bus`` arguments.
        motors: The motors.
        clock: Where time is read.
        poll_rate: Frames per second to every motor (Hz).
        timeout_periods: Unanswered polls in a row that make a fault.
        host_id: The arbitration id the motors reply with.
        init_timeout: Seconds a motor may take to answer in configure / activate / recover.
        can_timeout: The motors' CAN timeout as set on the devices, seconds (0 = not used);
            the poll period must be at most half of it.

    Raises:
        ValueError: No motors, duplicate ids or joints, a non-positive rate, or a poll period
            too long for the CAN timeout.
    """

    kind = "mit_can"
    safe_states = ("zero_torque",)
    profile_fields: ClassVar[Mapping[str, Field[Any]]] = {
        "link": custom(read_link, hint=LINK_HINT),
        "host_id": integer(0, low=0, high=0x7FF),
        "motors": custom(lambda r, v, k: v, hint="the motors on the bus"),  # read with host_id
        "poll_rate": number(100.0),
        "timeout_periods": integer(3, low=1, high=1000),
        "init_timeout": number(0.5),
        "can_timeout": number(0.0, low=0, low_open=False, describe="0 (not used) or positive"),
        "sim": custom(lambda r, v, k: dict(r.mapping(v, k)), {}, init=False),
    }

    def __init__(
        self,
        name: str,
        *,
        link: Mapping[str, Any],
        motors: Sequence[MitMotor],
        clock: Clock | None = None,
        poll_rate: float = 100.0,
        timeout_periods: int = 3,
        host_id: int = 0,
        init_timeout: float = 0.5,
        can_timeout: float = 0.0,
    ) -> None:
        ids = {m.motor_id for m in motors}
        if not motors or len(ids) != len(motors) or len({m.joint for m in motors}) != len(motors):
            raise ValueError("a MitMotorDriver needs motors with distinct ids and joints")
        if host_id in ids:
            raise ValueError(f"host id {host_id} is also a motor id")
        if not (poll_rate > 0 and timeout_periods > 0 and init_timeout > 0 and can_timeout >= 0):
            raise ValueError("rates and timeouts must be positive (can_timeout >= 0)")
        if can_timeout > 0 and 1.0 / poll_rate > can_timeout / 2:
            raise ValueError(
                f"the poll period 1/{poll_rate} s must be at most half the can_timeout"
                f" ({can_timeout} s)"
            )
        if can_timeout > CAN_TIMEOUT_MAX:
            raise ValueError(
                f"can_timeout {can_timeout} s is above the firmware's maximum {CAN_TIMEOUT_MAX} s"
            )
        period = 1.0 / poll_rate
        super().__init__(
            name,
            link=link,
            clock=clock,
            init_timeout=init_timeout,
            supervise_period=period,
            # a gap longer than the motors' CAN timeout may have zeroed their commands
            gap_limit=min(
                max(GAP_PERIODS * period, GAP_MIN / (clock or MonotonicClock()).real_seconds(1.0)),
                can_timeout or math.inf,
            ),
        )
        self.motors = tuple(motors)
        self.poll_rate = poll_rate
        self.timeout_periods = timeout_periods
        self.host_id = host_id
        self.can_timeout = can_timeout
        #: Malformed replies received since the driver was made.
        self._bad_window = FaultWindow(BAD_REPLIES_LIMIT, BAD_FRAMES_WINDOW)
        self._bad: str | None = None  # why the bus's replies are a fault, until a good one
        #: Why a gap in the loop outlasted the motors' CAN timeout (a fault until recover()).
        self._expired: str | None = None
        self._cache = [_Motor(m, 1.0 / poll_rate, timeout_periods) for m in self.motors]
        self._by_id = {c.motor.motor_id: c for c in self._cache}
        self._by_joint = {c.motor.joint: c for c in self._cache}
        # Guards each motor's held frame together with its sending: once a new frame is held,
        # no poll can still send the old one after it (a supervisor thread descheduled between
        # reading and sending once sent EXIT after activate's ENTER: the motors then ignored
        # every set-point).
        self._held_lock = threading.Lock()

    # ---- profile ---------------------------------------------------------------------------

    @classmethod
    def profile_settings(cls, values: Mapping[str, Any], where: str) -> dict[str, Any]:
        """Constructor arguments from a checked entry (see ``docs/driver-can.md``).

        Reads the motors (their ids must differ from ``host_id``) and checks ``can_timeout``
        against the poll period.

        Args:
            values: The entry's checked values (:meth:`read_profile`).
            where: The entry's place for messages.

        Returns:
            The keyword arguments.

        Raises:
            ProfileError: A bad motor, or keys that contradict each other (named).
        """
        reader = ProfileReader.at(where)
        kwargs = super().profile_settings(values, where)
        host = kwargs["host_id"]
        motors: list[MitMotor] = []
        members = read_members(
            reader,
            kwargs["motors"],
            "motors",
            _MOTOR_KEYS,
            "motor_id",
            (1, 0xFF),
            reserved={host: "host_id"},
        )
        for path, raw, motor_id, joint in members:
            model = raw.get("model", "AK80-9")
            if model not in mm.MODELS:
                reader.fail(
                    f"{path}.model", f"unknown model {model!r} (known: {', '.join(mm.MODELS)})"
                )
            base = mm.MODELS[model]
            ranges = mm.MitRanges(
                reader.field(raw, "p_max", number(base.p_max), path),
                reader.field(raw, "v_max", number(base.v_max), path),
                reader.field(raw, "t_max", number(base.t_max), path),
            )
            kp = reader.field(raw, "kp", number(20.0), path)
            kd = reader.field(raw, "kd", number(1.0), path)
            if kp > ranges.kp_max:
                reader.fail(f"{path}.kp", f"must be at most {ranges.kp_max}")
            if kd > ranges.kd_max:
                reader.fail(f"{path}.kd", f"must be at most {ranges.kd_max}")
            gear = reader.field(raw, "gear_ratio", number(1.0), path)
            limits = read_limits(reader, raw, path)
            _check_model(reader, path, model, ranges, gear, limits)
            motors.append(MitMotor(motor_id, joint, ranges, gear, kp, kd, limits, model))
        kwargs["motors"] = motors
        for key in values["sim"]:  # checked here, used by simulate()
            if key not in SIM_KEYS:
                reader.fail(f"sim.{key}", "unknown; the simulator's settings are realism, seed")
        read_sim_realism(reader, values["sim"])
        rate, timeout = kwargs["poll_rate"], kwargs["can_timeout"]
        if timeout > CAN_TIMEOUT_MAX:
            reader.fail(
                "can_timeout",
                f"{timeout:g} s is above the motors' firmware maximum {CAN_TIMEOUT_MAX:g} s"
                " (CAN timeout 0..100000 cycles of the 40 kHz loop)",
            )
        if timeout > 0 and 1.0 / rate > timeout / 2:
            reader.fail(
                "can_timeout",
                f"must be at least two poll periods (2/{rate:g} s), got {timeout}",
            )
        return kwargs

    @classmethod
    def simulate(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock
    ) -> tuple[Simulator, dict[str, Any]]:
        """A simulator (not started) serving this device entry, and the entry to drive it.

        Args:
            name: The device's name.
            config: The entry (``driver``, when present, must name this driver).
            clock: The clock the simulator steps on.

        Returns:
            ``(simulator, config)``; for CAN the config is the entry without ``sim``.

        Raises:
            ProfileError: A bad entry.
        """
        from temoto.drivers.can_motor.sim import MitModel, SimMitMotor

        driver = cls.from_profile(name, config, clock=clock, where=name)
        driver.shutdown()
        models = [MitModel.of(m.motor_id, m.model, m.ranges) for m in driver.motors]
        level, seed = read_sim_realism(ProfileReader.at(name), config.get("sim"))
        sim = SimMitMotor(
            driver.link,
            models,
            clock,
            host_id=driver.host_id,
            tick=driver.supervise_period,
            can_timeout=driver.can_timeout,
            realism=level,
            seed=seed,
            device=name,
        )
        return sim, {k: v for k, v in config.items() if k != "sim"}

    # ---- lifecycle -------------------------------------------------------------------------

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The joints, in profile order."""
        return tuple(m.joint for m in self.motors)

    @property
    def joint_velocity_limits(self) -> Mapping[str, float]:
        """Each joint's ``velocity_limit`` (rad/s; infinite when the profile sets none)."""
        return {m.joint: m.limits.velocity for m in self.motors}

    def on_configure(self) -> None:
        """Open the bus and wait for every motor to answer (it stays out of motor mode).

        Raises:
            DriverInitError: A motor did not answer within ``init_timeout`` (named).
            MotorFaultError: A motor reports an error code.
        """
        for c in self._cache:
            c.reset()
        self._latched = False
        self._bad = None
        self._expired = None
        self._bad_window.clear()
        self._open()
        with self._held_lock:
            for c in self._cache:
                self._send_to(c, mm.CMD_EXIT)
        if not self._wait_for(
            lambda: all(c.reply is not None for c in self._cache),
            self.init_timeout,
        ):
            silent = [c.label() for c in self._cache if c.reply is None]
            raise DriverInitError(
                f"{self.name}: no reply within {self.init_timeout} s from {', '.join(silent)}"
            )
        self._refuse_duplicates()
        problem = self._problem(self.clock.monotonic())
        if problem is not None:
            raise problem
        self._supervising = True

    def _refuse_duplicates(self) -> None:
        """Refuse a motor id that two motors answer, before any enters motor mode.

        Each motor is sent *exit motor mode* :data:`DUPLICATE_PROBES` times; once every motor
        answered them all, the driver listens :data:`DUPLICATE_LISTEN` real seconds more. A
        motor answers each frame once: more replies than frames (those outstanding before
        included) are a second motor on the id.

        Raises:
            DriverInitError: Two motors answer as one id (named: "duplicate MIT motor id").
        """
        with self._held_lock:
            before = {c: (c.replies, c.sent, c.outstanding) for c in self._cache}
            for _ in range(DUPLICATE_PROBES):
                for c in self._cache:
                    self._send_to(c, mm.CMD_EXIT)
        self._wait_for(
            lambda: all(c.replies - r >= DUPLICATE_PROBES for c, (r, _, _) in before.items()),
            self.init_timeout,
        )
        self._listen_real(DUPLICATE_LISTEN)
        for c, (replies, sent, outstanding) in before.items():
            got, asked = c.replies - replies, c.sent - sent + outstanding
            if got > asked:
                motor = c.motor.motor_id
                raise DriverInitError(
                    f"{self.name}: duplicate MIT motor id {motor} ({c.motor.joint}): {got}"
                    f" replies to {asked} frames: two motors answer as id {motor}; give one of"
                    " them another id. None entered motor mode."
                )

    def on_activate(self) -> None:
        """Enter motor mode and hold the current position.

        First makes sure no motor id is answered by two motors (both would enter motor mode).

        Raises:
            DriverInitError: Two motors answer as one id.
            DriverError: A motor did not answer.
        """
        with self._held_lock:  # out of motor mode while the probes go out
            for c in self._cache:
                c.held = mm.CMD_EXIT
        self._refuse_duplicates()
        self._hold(dict.fromkeys(self._cache, mm.CMD_ENTER))  # the polls now re-send ENTER
        self._ping(mm.CMD_ENTER)
        for c in self._cache:
            m = c.motor
            pos = c.reply[0] if c.reply is not None else 0.0
            self._hold({c: mm.encode_command(mm.MitCommand(pos, 0.0, m.kp, m.kd, 0.0), m.ranges)})

    def on_deactivate(self) -> None:
        """Exit motor mode (the motors go limp)."""
        self._hold(dict.fromkeys(self._cache, mm.CMD_EXIT))
        self._ping(mm.CMD_EXIT)

    def on_make_safe(self) -> str:
        """Zero torque, then exit motor mode, on every motor; confirm by reply, briefly.

        The polls keep sending *exit* afterwards. A motor that does not answer within
        :data:`SAFE_CONFIRM` real seconds is reported unconfirmed, not waited for.

        Returns:
            One item per motor, e.g. ``"shoulder off (zero torque, exit motor mode)"``.

        Raises:
            DriverError: A frame could not be sent (after trying every motor).
        """
        failed: list[str] = []
        with self._held_lock:
            counts = {c: c.replies + c.outstanding for c in self._cache}
            for c in self._cache:
                c.held = mm.CMD_EXIT
                try:
                    self._send_to(c, mm.encode_command(_ZERO_TORQUE, c.motor.ranges))
                    self._send_to(c, mm.CMD_EXIT)
                except (DriverError, StateError) as err:
                    failed.append(f"{c.label()}: {err}")
        if failed:
            raise DriverOperationError(f"{self.name}: safe state not sent: {'; '.join(failed)}")
        deadline = time.monotonic() + SAFE_CONFIRM
        with self._cond:
            while not all(c.replies >= n + 2 for c, n in counts.items()):
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)  # real time: never held up by a paused test clock
        done = []
        for c, n in counts.items():
            ok = c.replies >= n + 2
            what = "(zero torque, exit motor mode)" if ok else "(sent, unconfirmed)"
            done.append(f"{c.motor.joint} off {what}")
        return ", ".join(done)

    def on_recover(self) -> None:
        """Ask every motor again (out of motor mode) and clear the latch if all are fine.

        Raises:
            DriverError: A motor is still silent or still reports an error.
        """
        if self._bus is None:
            self.on_configure()
            return
        self._bad = None
        self._expired = None
        self._bad_window.clear()
        for c in self._cache:
            c.unasked.clear()
            c.saturated = None  # judged again from the replies to the pings
        self._hold(dict.fromkeys(self._cache, mm.CMD_EXIT))
        self._ping(mm.CMD_EXIT)
        problem = self._problem(self.clock.monotonic())
        if problem is not None:
            raise problem
        self._latched = False

    def _hold(self, frames: Mapping[_Motor, bytes], *, send: bool = False) -> None:
        """Make these the frames the supervisor re-sends (and, with ``send``, send them now).

        Raises:
            DriverOperationError: ``send`` and the bus refused a frame.
        """
        with self._held_lock:
            for c, frame in frames.items():
                c.held = frame
                if send:  # held back if a gap was found meanwhile: sent once judged
                    self._send_to(c, frame, setpoint=True)

    def _send_to(self, c: _Motor, frame: bytes, *, setpoint: bool = False) -> bool:
        """Send a frame to one motor, counted until it answers (``_held_lock`` held).

        With ``setpoint``, a command frame (not enter, exit or zero) is held back while a gap
        in the loop is being judged (:meth:`_send`); returns whether the frame went out.
        """
        if not self._send(c.motor.motor_id, frame, setpoint=setpoint and mm.special(frame) is None):
            return False
        c.outstanding += 1
        c.sent += 1
        return True

    def _ping(self, frame: bytes) -> None:
        """Send ``frame`` to every motor and wait for each to answer it.

        A motor answers every frame, in order, so the answer to ``frame`` is the reply after
        those to the frames still outstanding (a supervisor poll sent just before can be
        answered after the snapshot: counting any reply as the answer once let ``activate``
        return before ENTER had reached the motor).
        """
        with self._held_lock:
            counts = {c: c.replies + c.outstanding for c in self._cache}
            for c in self._cache:
                self._send_to(c, frame)
        if not self._wait_for(
            lambda: all(c.replies > n for c, n in counts.items()), self.init_timeout
        ):
            silent = [c.label() for c, n in counts.items() if c.replies <= n]
            raise DriverTimeoutError(
                f"{self.name}: no reply within {self.init_timeout} s from {', '.join(silent)}"
            )

    # ---- verbs -----------------------------------------------------------------------------

    def command(self, commands: Iterable[JointCommand]) -> None:
        """Send set-points (rad, rad/s or N·m on the joint side); they are held and re-sent.

        Args:
            commands: One per joint to change; others keep their set-point.

        Raises:
            StateError: Not active.
            ValueError: An unknown joint or a set-point outside the joint's or motor's range.
            DriverOperationError: The bus refused a frame.
        """
        self.require_active("command")
        plan: list[tuple[_Motor, bytes]] = []
        for cmd in commands:
            c = self._by_joint.get(cmd.joint)
            if c is None:
                raise ValueError(
                    f"{self.name}: no joint {cmd.joint!r} (joints: {self.joint_names})"
                )
            m = c.motor
            check_limits(cmd.joint, m.limits, cmd.mode.value, cmd.value)
            if cmd.mode is ControlMode.POSITION:
                value, top = cmd.value * m.gear_ratio, m.ranges.p_max
                fields = mm.MitCommand(value, 0.0, m.kp, m.kd, 0.0)
            elif cmd.mode is ControlMode.VELOCITY:
                value, top = cmd.value * m.gear_ratio, m.ranges.v_max
                fields = mm.MitCommand(0.0, value, 0.0, m.kd, 0.0)
            else:
                value, top = cmd.value / m.gear_ratio, m.ranges.t_max
                fields = mm.MitCommand(0.0, 0.0, 0.0, 0.0, value)
            if abs(value) > top:
                raise ValueError(
                    f"joint {cmd.joint}: {cmd.mode.value} {cmd.value} is beyond the motor's"
                    f" range ±{top} (motor side)"
                )
            plan.append((c, mm.encode_command(fields, m.ranges)))
        wait = self._check_gap(self.clock.monotonic())  # after a gap: held, sent once judged
        self._hold(dict(plan), send=not wait)

    def read_state(self) -> JointStates:
        """The newest reply of every motor (the cache; no bus traffic).

        Returns:
            Joint states stamped with the clock time each reply arrived.

        Raises:
            StateError: Never configured, or finalized.
        """
        self._require_open("read the state")
        joints: dict[str, JointState] = {}
        newest = -math.inf
        for c in self._cache:
            p, v, t, stamp = c.reply or (0.0, 0.0, 0.0, -math.inf)
            g = c.motor.gear_ratio
            joints[c.motor.joint] = JointState(c.motor.joint, p / g, v / g, t * g, stamp)
            newest = max(newest, stamp)
        return JointStates(newest, joints)

    # ---- receive and supervise -------------------------------------------------------------

    def _on_frame(self, msg: can.Message) -> None:
        if msg.arbitration_id != self.host_id or msg.is_extended_id:
            return
        data = msg.data
        now = self.clock.monotonic()
        c = self._by_id.get(data[0]) if data else None
        if c is None:
            self._malformed(f"a reply from unknown motor id {data[0] if data else None}", now)
            return
        with self._held_lock:  # an answer, even a malformed one
            unasked = c.outstanding == 0
            c.outstanding = max(0, c.outstanding - 1)
        if unasked and c.unanswered <= self.timeout_periods:  # not a late one after silence
            c.unasked.add(now)
        if len(data) not in (6, 8):
            self._malformed(f"{c.label()}: a reply of {len(data)} data bytes", now)
            return
        reply = mm.decode_reply(data, c.motor.ranges)
        was_fine = c.unanswered <= self.timeout_periods and self._bad is None and not c.error
        if c.saturated is None:
            c.saturated = _past_field(c, data, reply.p)
            if c.saturated is not None:
                was_fine = False
                with self._held_lock:  # its feedback is worthless: it is told to stop
                    if mm.special(c.held) is None:
                        c.held = self._brake(c)
        c.reply = (reply.p, reply.v, reply.t, now)
        c.seq = self._rx_count
        c.age.feed(now)
        c.temperature = reply.temperature
        c.error = reply.error or 0
        c.unanswered = 0
        c.polled.clear()
        if self._bad is not None:
            self._bad = None
            self._bad_window.clear()
        c.replies += 1
        self._notify()
        if not was_fine or c.error or self.state is DriverState.FAULT:
            self._evaluate()

    def _malformed(self, what: str, now: float) -> None:
        """Count one malformed reply; too many within the window make a fault."""
        text = f"malformed reply ({what})"
        bad = self._count_malformed(
            self._bad_window, text, "replies", now, latched=self._bad is not None
        )
        if bad is not None:
            self._bad = bad
            self._evaluate()

    def _on_period(self, now: float) -> None:
        if self._bus is None:
            return
        waiting = self._resync is not None
        answered_by = self._answered_by(now)
        for c in self._cache:
            c.unanswered += 1
            c.polled.append(now)
            with contextlib.suppress(DriverError), self._held_lock:  # a broken bus shows as
                if self._silent(c, answered_by):  # missing replies; the motor is silent:
                    c.outstanding = 0  # what it was sent is lost, not pending
                frame = c.held
                if waiting and mm.special(frame) is None:  # a set-point waits for feedback:
                    frame = self._brake(c)  # the poll that asks for it only damps
                if not self._send_to(c, frame, setpoint=not waiting):  # a gap found just now
                    self._send_to(c, self._brake(c))

    @staticmethod
    def _brake(c: _Motor) -> bytes:
        """The poll while a gap is judged: v = 0 with the motor's ``kd`` (kp, t_ff 0)."""
        m = c.motor
        return mm.encode_command(mm.MitCommand(0.0, 0.0, 0.0, m.kd, 0.0), m.ranges)

    def _on_gap(self, now: float, gap: float) -> None:
        if self.can_timeout <= 0 or gap <= self.can_timeout:
            return
        driving = [c.label() for c in self._cache if mm.special(c.held) is None]
        if driving:
            self._expired = (
                f"the driver's loop stalled for {gap:.3f} s, longer than the motors' can_timeout"
                f" ({self.can_timeout:g} s): {', '.join(driving)} zeroed their commands;"
                " recover() and activate() to go on"
            )

    def _fresh(self, mark: int) -> bool:
        return all(c.seq > mark for c in self._cache)

    def _sent_late(self, arbitration_id: int) -> None:
        """Damp the motor at once (its sender holds ``_held_lock``): the gap is judged first."""
        c = self._by_id.get(arbitration_id)
        if c is not None:
            with contextlib.suppress(DriverError, StateError):
                self._send_to(c, self._brake(c))

    def _answered_by(self, now: float) -> float:
        """Polls sent up to this clock time had a period to be answered and read.

        As of :meth:`_link_seen` (without moving it): a receive thread the machine did not
        schedule (heavy load) has not read the replies that queued meanwhile.
        """
        seen = now if self._rx_idle and self._resync is None else min(now, self._rx_seen)
        return max(seen, self._seen_hi) - 1.0 / self.poll_rate

    def _silent(self, c: _Motor, answered_by: float) -> bool:
        """Whether ``c`` left ``timeout_periods`` polls in a row unanswered.

        Only polls whose answers the receive thread would have read by now count.
        """
        if c.unanswered <= self.timeout_periods:
            return False
        return sum(1 for t in tuple(c.polled) if t <= answered_by) >= self.timeout_periods

    def _problem(self, now: float) -> DriverError | None:
        if self._expired is not None:
            return DriverTimeoutError(f"{self.name}: {self._expired}")
        seen = self._link_seen(now)
        answered_by = seen - 1.0 / self.poll_rate
        for c in self._cache:
            if self._silent(c, answered_by):
                return DriverTimeoutError(
                    f"{self.name}: {c.label()}: no reply to {c.unanswered - 1} polls in a row"
                    f" ({self.timeout_periods / self.poll_rate:g} s)"
                )
            if c.saturated is not None:
                return DriverOperationError(
                    f"{self.name}: {c.label()}: {c.saturated}; its true position is unknown and"
                    " it was told to stop (v = 0); set its zero (or turn it back) and recover()"
                )
            if c.error:
                what = mm.ERROR_CODES.get(c.error, f"error code {c.error}")
                kind = _KINDS.get(c.error)
                return MotorFaultError(
                    f"{self.name}: {c.label()}: {what}" + (f" ({kind})" if kind else ""),
                    node_id=c.motor.motor_id,
                    error=c.error,
                )
            # The replies answer our polls: after a gap in our loop (no polls, so no replies)
            # their age says nothing about the motor until it answered the polls sent since;
            # a motor silent to those is caught by ``unanswered`` above.
            stale = None if self._resync is not None else c.age.stale(seen)
            if stale is not None:
                return DriverTimeoutError(f"{self.name}: {stale}")
            if c.unasked.recent(now) >= DUPLICATE_LIMIT:
                return DriverOperationError(
                    f"{self.name}: {c.label()}: more replies than frames sent"
                    f" ({c.unasked.recent(now)} unasked within 1 s): two motors answer as id"
                    f" {c.motor.motor_id}? (duplicate MIT motor id {c.motor.motor_id})"
                )
        if self._bad is not None:
            return DriverOperationError(f"{self.name}: {self._bad}")
        return None
