"""ODrive motor controllers over CANSimple (profile ``driver: odrive_can``).

One :class:`ODriveDriver` drives every axis (node id) of one device entry on one CAN bus.
``configure`` opens the bus and waits for each node's heartbeat and encoder estimate;
``activate`` puts every axis in ``CLOSED_LOOP_CONTROL`` (holding its position) and waits for the
heartbeats to confirm it; ``deactivate`` sets ``IDLE``. ``command`` sends ``Set_Input_Pos`` /
``Set_Input_Vel`` / ``Set_Input_Torque`` (with ``Set_Controller_Mode`` when a joint's mode
changes); ``read_state`` reads the cache that the receive thread fills from the cyclic
encoder estimates (and ``Get_Torques``, when the ODrive is set to send them).

While ``ACTIVE`` the supervisor re-sends every axis's newest set-point each
``command_period`` (not only when it changes), so the ODrive's axis watchdog
(``watchdog_timeout``) can be enabled on the device: if TeMoto dies, the axes disarm.

**Safe state** (``safe_state:``): ``idle`` (default) sends ``SetAxisCache_State(IDLE)`` to every
axis; ``hold`` commands zero velocity (``VELOCITY_CONTROL``, input 0 rev/s) and leaves each axis
in the state it is in (an armed axis stays in ``CLOSED_LOOP_CONTROL``; the zero set-point keeps
being sent, feeding the watchdog). Both are confirmed by a heartbeat requested at once, waited
for at most :data:`SAFE_CONFIRM` real seconds.

Supervision (``docs/driver-can.md``): a node silent for ``timeout_periods`` heartbeat periods
is a :class:`~temoto.errors.DriverTimeoutError` (recovered by itself when heartbeats return);
encoder estimates older than 3 ``encoder_period`` (as of the receive thread's last look at
the bus, at two supervisor checks in a row) while heartbeats go on are a
:class:`~temoto.errors.DriverTimeoutError` naming the stream (recovered when they return);
error bits in a heartbeat are a :class:`~temoto.errors.MotorFaultError` naming the decoded bits
(latched: :meth:`recover` sends ``Clear_Errors``); an axis that leaves ``CLOSED_LOOP_CONTROL``
while the driver is ``ACTIVE``, without an error bit, is a
:class:`~temoto.errors.DriverOperationError` until :meth:`recover`; a node whose heartbeats or
estimates arrive at well over their configured rate (:data:`DUPLICATE_FACTOR` times, counted
over :data:`DUPLICATE_PERIODS` periods, the replies to the driver's own requests not counted)
is answered by two devices: a :class:`~temoto.errors.DriverOperationError` naming it. Malformed
frames (wrong length, or a heartbeat with undefined fields) are counted
(:attr:`ODriveDriver.bad_frames`) and logged; only
:data:`~temoto.drivers.supervision.BAD_FRAMES_LIMIT` of them from one node within
:data:`~temoto.drivers.supervision.BAD_FRAMES_WINDOW` seconds make a
:class:`~temoto.errors.DriverOperationError`, until that node's next good heartbeat.

Discovery: :meth:`ODriveDriver.detect` only listens for the nodes' cyclic heartbeats and
sends nothing, so looking at a bus never moves an axis.

Units: the ODrive speaks motor turns; joints are radians on the output side of
``gear_ratio`` (motor turns per joint turn): ``joint_rad = motor_rev * 2π / gear_ratio``,
``joint_Nm = motor_Nm * gear_ratio``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Final

import can

from temoto.clock import Clock
from temoto.drivers.base import DriverState
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor import odrive_sdo as sdo
from temoto.drivers.can_motor._common import (
    LINK_HINT,
    check_limits,
    read_link,
)
from temoto.drivers.can_motor._driver import (
    DUPLICATE_LISTEN,
    DUPLICATE_PROBES,
    CanMotorDriver,
)
from temoto.drivers.can_motor.detect import DETECT_MIN_BEATS, detect
from temoto.drivers.can_motor.odrive_axes import (
    DUPLICATE_FACTOR,
    DUPLICATE_PERIODS,
    AxisCache,
    ODriveNode,
    motor_fault,
)
from temoto.drivers.can_motor.odrive_settings import read_nodes, sim_mechanics, sim_rates
from temoto.drivers.capabilities import ControlMode, JointCommand, JointState, JointStates
from temoto.drivers.profile import Field, ProfileReader, custom, flag, number
from temoto.drivers.realism import read_sim_realism
from temoto.drivers.sim import Simulator
from temoto.drivers.supervision import stale_periods
from temoto.errors import (
    DeviceLimitError,
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    MotorFaultError,
    StateError,
)

__all__ = [
    "DETECT_MIN_BEATS",
    "DUPLICATE_FACTOR",
    "DUPLICATE_PERIODS",
    "SAFE_CONFIRM",
    "ODriveDriver",
    "ODriveNode",
    "sim_rates",
]

logger = logging.getLogger(__name__)

#: Real seconds :meth:`ODriveDriver.make_safe` waits for the heartbeats that confirm it.
SAFE_CONFIRM: Final = 0.1
#: Clock seconds after a stream's stale moment the supervisor wakes to judge it.
_AFTER: Final = 1e-4
#: Heartbeat periods an armed axis must stay out of CLOSED_LOOP_CONTROL to be a fault (a
#: second device on its node id would send a CLOSED_LOOP_CONTROL heartbeat meanwhile).
_OFF_PERIODS: Final = 1.5
#: Answers to requests from before the duplicate probe that may still come during it.
_LATE_ANSWERS: Final = 2
#: Stream periods between the two looks that find a stream stale.
_SECOND_LOOK: Final = 0.1
_MODES: Final = {
    ControlMode.POSITION: cs.ControlMode.POSITION_CONTROL,
    ControlMode.VELOCITY: cs.ControlMode.VELOCITY_CONTROL,
    ControlMode.EFFORT: cs.ControlMode.TORQUE_CONTROL,
}


def _read_flat_endpoints(
    reader: ProfileReader, value: object, key: str
) -> tuple[tuple[str, str], dict[str, sdo.Endpoint]]:
    """The ``flat_endpoints`` key: a release's file, relative to the profile's folder."""
    if not isinstance(value, str) or not value:
        reader.fail(key, f"must be the path of a flat_endpoints.json, got {value!r}")
    path = Path(value)
    if not path.is_absolute() and reader.file:
        path = Path(reader.file).parent / path
    try:
        return sdo.load_flat_endpoints(path)
    except ValueError as err:
        reader.fail(key, str(err))


def _alternating(recent: Iterable[tuple[int, int, int]]) -> str | None:
    """Why these heartbeats come from two devices (A, B, A with no state asked), or None."""
    runs: list[tuple[int, int]] = []
    asked: set[int] = set()
    for state, error, requests in recent:
        asked.add(requests)
        if not runs or runs[-1] != (state, error):
            runs.append((state, error))
    if len(asked) > 1 or len(set(runs)) == len(runs):
        return None
    (s0, e0), (s1, e1) = runs[0], next(r for r in runs if r != runs[0])
    return (
        f"its heartbeats alternate between {cs.state_name(s0)} (error {e0:#x})"
        f" and {cs.state_name(s1)} (error {e1:#x})"
    )


class ODriveDriver(CanMotorDriver):
    """ODrive axes on one CAN bus; an :class:`~temoto.drivers.capabilities.Actuator`.

    Args:
        name: The device's name.
        link: python-can ``Bus`` arguments (``interface``, ``channel``, ...).
        nodes: The axes.
        clock: Where time is read.
        heartbeat_period: The ODrives' heartbeat period, seconds.
        init_timeout: Seconds a node may take to answer in configure / activate / recover.
        timeout_periods: Heartbeat periods of silence that make a fault.
        encoder_period: The ODrives' cyclic encoder estimate period, seconds (stale after 3).
        command_period: Seconds between re-sends of the set-points while active.
        watchdog_timeout: The axes' watchdog timeout as set on the devices, seconds (0 = not
            used); ``command_period`` must be at most half of it.
        check_device_limits: Read each node's velocity limit, current limit and torque
            constant over CAN in configure and refuse limits beyond them (see
            :meth:`_check_device_limits`); False skips it (with a warning).
        flat_endpoints: ``((firmware, hardware), {path: Endpoint})`` of a release's
            ``flat_endpoints.json`` (:func:`~temoto.drivers.can_motor.odrive_sdo.
            load_flat_endpoints`), for firmware whose ids TeMoto does not know.
        where: The entry's place in its profile (``robot.yaml: devices.base``), for the
            messages of that check (default: the device's name).

    Raises:
        ValueError: No nodes, a duplicate node id or joint, a non-positive period, or a
            ``command_period`` too long for the watchdog.
    """

    kind = "odrive_can"
    safe_states = ("idle", "hold")
    profile_fields: ClassVar[Mapping[str, Field[Any]]] = {
        "link": custom(read_link, hint=LINK_HINT),
        "nodes": custom(lambda r, v, k: read_nodes(r, v, k), hint="the ODrive axes on the bus"),
        "heartbeat_period": number(0.1),
        "encoder_period": number(0.01),
        "init_timeout": number(1.0),
        "timeout_periods": number(3.0),
        "command_period": number(0.05),
        "watchdog_timeout": number(0.0, low=0, low_open=False, describe="0 (not used) or positive"),
        "check_device_limits": flag(True),
        "flat_endpoints": custom(
            lambda r, v, k: _read_flat_endpoints(r, v, k),
            None,
            hint="the firmware release's flat_endpoints.json",
        ),
        "sim": custom(lambda r, v, k: dict(r.mapping(v, k)), {}, init=False),
    }

    def __init__(
        self,
        name: str,
        *,
        link: Mapping[str, Any],
        nodes: Sequence[ODriveNode],
        clock: Clock | None = None,
        heartbeat_period: float = 0.1,
        init_timeout: float = 1.0,
        timeout_periods: float = 3.0,
        encoder_period: float = 0.01,
        command_period: float = 0.05,
        watchdog_timeout: float = 0.0,
        check_device_limits: bool = True,
        flat_endpoints: tuple[tuple[str, str], Mapping[str, sdo.Endpoint]] | None = None,
        where: str = "",
    ) -> None:
        if not nodes:
            raise ValueError("an ODriveDriver needs at least one node")
        if len({n.node_id for n in nodes}) != len(nodes) or len({n.joint for n in nodes}) != len(
            nodes
        ):
            raise ValueError("node ids and joints must be distinct")
        if not (heartbeat_period > 0 and init_timeout > 0 and timeout_periods > 0):
            raise ValueError("periods and timeouts must be positive")
        if not (encoder_period > 0 and command_period > 0 and watchdog_timeout >= 0):
            raise ValueError("periods must be positive and watchdog_timeout >= 0")
        if watchdog_timeout > 0 and command_period > watchdog_timeout / 2:
            raise ValueError(
                f"command_period {command_period} s must be at most half the watchdog_timeout"
                f" ({watchdog_timeout} s)"
            )
        super().__init__(
            name,
            link=link,
            clock=clock,
            init_timeout=init_timeout,
            supervise_period=min(heartbeat_period / 4, command_period),
        )
        self.nodes = tuple(nodes)
        self.heartbeat_period = heartbeat_period
        self.timeout_periods = timeout_periods
        self.encoder_period = encoder_period
        self.command_period = command_period
        self.watchdog_timeout = watchdog_timeout
        self.check_device_limits = check_device_limits
        self._flat_endpoints = flat_endpoints
        self._where = where or name
        self._versions: dict[int, cs.Version] = {}  # Get_Version answers, by node id
        self._sdo_values: dict[tuple[int, int], bytes] = {}  # TxSdo answers (node, endpoint)
        #: Malformed frames received from the nodes since the driver was made.
        self._armed = False  # the axes were confirmed in CLOSED_LOOP_CONTROL by activate
        self._feeding = False  # the supervisor re-sends the held set-points
        self._holding = False  # ... also in FAULT: the safe state "hold" is applied
        self._due_feed = -math.inf
        self._held_lock = threading.Lock()  # a held set-point and its sending, together
        self._state_requests = 0  # Set_Axis_State frames sent (a heartbeat's change asked for)
        self._asked_at = -math.inf  # the latest status request while a gap was judged
        in_process = self.link.get("interface") == "virtual"  # a simulator in our process
        stale = stale_periods(encoder_period, self.clock.real_seconds(1.0), in_process=in_process)
        self._axes = [AxisCache(n, heartbeat_period, encoder_period, stale) for n in self.nodes]
        self._by_joint = {a.node.joint: a for a in self._axes}
        self._rx: dict[int, tuple[AxisCache, int]] = {}
        for axis in self._axes:
            for cmd in (
                cs.Cmd.HEARTBEAT,
                cs.Cmd.GET_ENCODER_ESTIMATES,
                cs.Cmd.GET_TORQUES,
                cs.Cmd.GET_VERSION,
                cs.Cmd.TXSDO,
            ):
                self._rx[cs.arbitration_id(axis.node.node_id, cmd)] = (axis, cmd)

    # ---- profile ---------------------------------------------------------------------------

    @classmethod
    def profile_settings(cls, values: Mapping[str, Any], where: str) -> dict[str, Any]:
        """Constructor arguments from a checked entry (see ``docs/driver-can.md``).

        Checks ``command_period`` against ``watchdog_timeout``, the ``sim`` rates against the
        supervised periods, and refuses ``safe_state: hold`` without a watchdog.

        Args:
            values: The entry's checked values (:meth:`read_profile`).
            where: The entry's place for messages.

        Returns:
            The keyword arguments.

        Raises:
            ProfileError: Keys that contradict each other (the message names the key).
        """
        reader = ProfileReader.at(where)
        kwargs = super().profile_settings(values, where)
        watchdog, command = kwargs["watchdog_timeout"], kwargs["command_period"]
        if watchdog > 0 and command > watchdog / 2:
            reader.fail(
                "command_period",
                f"must be at most half the watchdog_timeout ({watchdog} s), got {command}",
            )
        # checked here, used by simulate()
        sim_rates(reader, values["sim"], kwargs["heartbeat_period"], kwargs["encoder_period"])
        sim_mechanics(reader, values["sim"])
        read_sim_realism(reader, values["sim"] or None)
        kwargs["where"] = where  # the device-limit check names the file and the key
        # safe_state hold without watchdog_timeout: refused by the profile (temoto.config), which
        # alone can take its acknowledgement (hold_without_watchdog: true), for every driver alike
        return kwargs

    @classmethod
    def simulate(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock
    ) -> tuple[Simulator, dict[str, Any]]:
        """A simulator (not started) serving this device entry, and the entry to drive it.

        The simulated ODrives send their heartbeats every ``heartbeat_period`` and their
        encoder estimates every ``encoder_period``; the entry's optional ``sim`` mapping sets
        the rates of their other cyclic messages by the ODrive's own names, in ms
        (``{torques_msg_rate_ms: 10, iq_msg_rate_ms: 100}``: :func:`sim_rates`).

        Args:
            name: The device's name.
            config: The entry without ``driver`` (valid: see :meth:`from_profile`).
            clock: The clock the simulator steps on.

        Returns:
            ``(simulator, config)``; for CAN the config is the entry without ``sim`` (the link
            is shared).

        Raises:
            ProfileError: A bad entry.
        """
        from temoto.drivers.can_motor.sim import AxisModel, SimODrive

        driver = cls.from_profile(name, config, clock=clock, where=name)
        driver.shutdown()
        reader = ProfileReader(name)
        rates = sim_rates(reader, config.get("sim"), driver.heartbeat_period, driver.encoder_period)
        mechanics = sim_mechanics(reader, config.get("sim"))
        level, seed = read_sim_realism(reader, config.get("sim"))
        axes = [AxisModel(n.node_id) for n in driver.nodes]
        for axis in axes:
            for key, value in mechanics.items():
                setattr(axis, key, value)
        sim = SimODrive(
            driver.link,
            axes,
            clock,
            heartbeat_period=driver.heartbeat_period,
            encoder_period=driver.encoder_period,
            watchdog_timeout=driver.watchdog_timeout,
            rates_ms=rates,
            realism=level,
            seed=seed,
            device=name,
        )
        return sim, {k: v for k, v in config.items() if k != "sim"}

    # ---- discovery -------------------------------------------------------------------------

    @classmethod
    def detect(
        cls, links: Sequence[Any] | None = None, *, timeout: float = 1.0
    ) -> list[dict[str, Any]]:
        """The ODrive axes heartbeating on CAN buses, as profile device entries.

        Listens only, sending nothing, so nothing moves; which nodes count as ODrive axes
        (and what is logged of each) is told by :func:`~temoto.drivers.can_motor.detect.detect`.

        Each entry is ``{driver: odrive_can, link: {...}, nodes: [{node_id: <id>, joint:
        joint_<id>}, ...]}`` (node ids sorted); everything else takes :meth:`from_profile`'s
        defaults (among them ``heartbeat_period: 0.1``: set it if the ODrives send slower).

        Args:
            links: python-can ``Bus`` mappings, each in the form of the profile's ``link``
                (``{interface: socketcan, channel: can0}`` plus optional ``Bus`` arguments
                such as ``bitrate``). None: every configuration
                :func:`can.detect_available_configs` reports (it may report none).
            timeout: Real seconds to listen on each link, one link after the other.

        Returns:
            One entry per link on which at least one node sent a heartbeat, in link order.
            A link whose bus cannot be opened is skipped with a logged warning.

        Raises:
            ValueError: ``timeout`` is not a positive finite number, ``links`` is not a
                sequence, or a link is not a mapping with ``interface`` and ``channel`` (named
                by its index).
        """
        return detect(cls.kind, links, timeout)

    # ---- lifecycle -------------------------------------------------------------------------

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The joints, in profile order."""
        return tuple(n.joint for n in self.nodes)

    @property
    def joint_velocity_limits(self) -> Mapping[str, float]:
        """Each joint's ``velocity_limit`` (rad/s; infinite when the profile sets none)."""
        return {n.joint: n.limits.velocity for n in self.nodes}

    @property
    def device_watchdog(self) -> float:
        """Seconds of the axes' own watchdog (``watchdog_timeout``; 0: off)."""
        return self.watchdog_timeout

    def on_configure(self) -> None:
        """Open the bus, wait for every node, then check the profile's limits against them.

        Waits for each node's heartbeat and encoder estimate, refuses a node id answered by
        two devices, and reads each node's limits over CAN (:meth:`_check_device_limits`).
        Nothing is written to any node (only requests: RTR frames and ``RxSdo`` reads).

        Raises:
            DriverInitError: A node did not answer within ``init_timeout`` (named).
            DeviceLimitError: A profile limit beyond what a node is configured for, or a
                firmware whose endpoint ids are not known (names the file and the key).
            MotorFaultError: A node reports error bits.
        """
        for axis in self._axes:
            axis.reset()
        self._latched = False
        self._armed = self._feeding = self._holding = False
        self._open()
        self._request_status()
        ready = self._wait_for(
            lambda: all(a.hb_stamp is not None and a.enc is not None for a in self._axes),
            self.init_timeout,
            self._request_status,
        )
        if not ready:
            silent = [a.label() for a in self._axes if a.hb_stamp is None or a.enc is None]
            raise DriverInitError(
                f"{self.name}: no heartbeat within {self.init_timeout} s from {', '.join(silent)}"
            )
        self._refuse_duplicates()
        problem = self._problem(self.clock.monotonic())
        if problem is not None:
            raise problem
        self._check_device_limits()
        self._supervising = True

    def _refuse_duplicates(self) -> None:
        """Refuse a node id that two devices answer, before anything is armed.

        After :data:`DUPLICATE_LISTEN` real seconds for the answers to earlier requests, each
        node is asked for its heartbeat :data:`DUPLICATE_PROBES` times at once (RTR); once
        every node answered them all, the driver listens :data:`DUPLICATE_LISTEN` real seconds
        more. One device answers each request once, plus the cyclic heartbeats of the time it
        took and a few late answers to earlier requests; two devices answer every request
        twice, so at least twice the probes, and more than one device's most, are a second
        device on the id. A node over that count is probed once more, and refused only if it
        is over again: a second device answers every probe twice, while a burst of late answers
        (a busy machine's queue) does not come back.

        Raises:
            DriverInitError: Two devices answer as one node (named: "duplicate ODrive node").
        """
        suspects = self._probe_heartbeats(self._axes)
        if suspects:
            suspects = self._probe_heartbeats([axis for axis, _ in suspects])
        for axis, said in suspects:
            node = axis.node.node_id
            raise DriverInitError(
                f"{self.name}: duplicate ODrive node {node} ({axis.node.joint}): {said},"
                f" and over that again when probed a second time: two devices answer as node"
                f" {node}; give one of them another node id. Nothing was armed."
            )

    def _probe_heartbeats(self, axes: Sequence[AxisCache]) -> list[tuple[AxisCache, str]]:
        """One heartbeat probe of ``axes`` (see :meth:`_refuse_duplicates`).

        Returns:
            The axes answered more often than one device would, each with what was counted.
        """
        self._listen_real(DUPLICATE_LISTEN)  # answers to earlier requests come in first
        start = self.clock.monotonic()
        before = [a.beats for a in axes]
        for _ in range(DUPLICATE_PROBES):
            for axis in axes:
                axis.hb_rate.ask()
                self._send(axis.ids[cs.Cmd.HEARTBEAT], b"", remote=True)
        self._wait_for(
            lambda: all(a.beats - n >= DUPLICATE_PROBES for a, n in zip(axes, before, strict=True)),
            self.init_timeout,
        )
        self._listen_real(DUPLICATE_LISTEN)
        for axis in axes:  # the probe's answers are not the cyclic rate: count anew
            axis.hb_rate.clear()
        elapsed = self.clock.monotonic() - start
        cyclic = math.floor(elapsed / self.heartbeat_period) + 1  # the most one device sent
        most = max(2 * DUPLICATE_PROBES - 1, DUPLICATE_PROBES + cyclic + _LATE_ANSWERS)
        suspects = []
        for axis, n in zip(axes, before, strict=True):
            got = axis.beats - n
            if got > most:
                said = (
                    f"{got} heartbeats answered {DUPLICATE_PROBES} requests in {elapsed:.3f} s"
                    f" (one device sends at most {most})"
                )
                suspects.append((axis, said))
        return suspects

    def _check_device_limits(self) -> None:
        """Refuse profile limits beyond what each node, as it is configured, allows.

        For every node with a ``velocity_limit`` or a ``torque_limit``: ``Get_Version`` (RTR)
        tells its firmware and hardware; the endpoint ids of that release (the profile's
        ``flat_endpoints`` file, else :data:`~temoto.drivers.can_motor.odrive_sdo.
        KNOWN_ENDPOINTS`) give ``RxSdo`` reads of ``vel_limit``, ``current_soft_max`` and
        ``torque_constant`` (:func:`~temoto.drivers.can_motor.odrive_sdo.limit_problems`).
        Every read has a deadline of ``init_timeout`` and is asked again meanwhile. A release
        whose ids are not known is refused (the limits would go unchecked), unless
        ``check_device_limits`` is false: then the check is skipped with a warning.

        Raises:
            DeviceLimitError: Every problem found, in one line naming the file and each key.
            DriverInitError: A node did not answer ``Get_Version`` or a read (named).
        """
        checked = [
            (i, a)
            for i, a in enumerate(self._axes)
            if math.isfinite(a.node.limits.velocity) or math.isfinite(a.node.limits.torque)
        ]
        if not checked:
            return
        if not self.check_device_limits:
            logger.warning(
                "%s: check_device_limits is false: velocity_limit and torque_limit are not"
                " checked against the ODrives",
                self._where,
            )
            return
        axes = [a for _, a in checked]
        versions = self._read_versions(axes)
        reader = ProfileReader.at(self._where)
        problems: list[str] = []
        reads: dict[AxisCache, Mapping[str, sdo.Endpoint]] = {}
        for index, axis in checked:
            version = versions[axis.node.node_id]
            table, why = self._endpoint_table(version)
            if table is None:
                key = "flat_endpoints" if self._flat_endpoints is not None else f"nodes[{index}]"
                problems.append(f"{reader.path(key)}: {axis.label()} {why}")
            else:
                reads[axis] = table
        values = self._read_endpoints(reads)
        for index, axis in checked:
            if axis not in reads:
                continue
            node = axis.node
            found = sdo.limit_problems(
                node.node_id,
                node.joint,
                node.gear_ratio,
                node.limits.velocity,
                node.limits.torque,
                values[axis],
            )
            problems += [f"{reader.path(f'nodes[{index}].{key}')}: {text}" for key, text in found]
        if problems:
            raise DeviceLimitError("; ".join(problems) + " (nothing was written)", file=reader.file)

    def _endpoint_table(self, version: cs.Version) -> tuple[Mapping[str, sdo.Endpoint] | None, str]:
        """The endpoint ids of a node's release, or None and why not."""
        fw, hw = sdo.version_key(version)
        said = f"runs ODrive firmware {fw} on hardware {version.hardware}"
        if self._flat_endpoints is not None:
            (file_fw, file_hw), table = self._flat_endpoints
            if file_fw.partition("-")[0] == fw and file_hw == hw:
                return table, ""
            return None, f"{said}; flat_endpoints is for firmware {file_fw}, hardware {file_hw}"
        known = sdo.KNOWN_ENDPOINTS.get((fw, hw))
        if known is not None:
            return known, ""
        return None, (
            f"{said}, whose endpoint ids TeMoto does not know: its velocity_limit and"
            " torque_limit cannot be checked against the device. Give flat_endpoints (that"
            " release's flat_endpoints.json, from ODrive's firmware releases page) or set"
            " check_device_limits: false"
        )

    def _read_versions(self, axes: Sequence[AxisCache]) -> dict[int, cs.Version]:
        """Each node's ``Get_Version`` (RTR, asked again until ``init_timeout``)."""
        for axis in axes:
            self._versions.pop(axis.node.node_id, None)

        def ask() -> None:
            for axis in axes:
                if axis.node.node_id not in self._versions:
                    self._send(axis.ids[cs.Cmd.GET_VERSION], b"", remote=True)

        ask()
        if not self._wait_for(
            lambda: all(a.node.node_id in self._versions for a in axes), self.init_timeout, ask
        ):
            silent = [a.label() for a in axes if a.node.node_id not in self._versions]
            raise DriverInitError(
                f"{self.name}: no answer to Get_Version within {self.init_timeout} s from"
                f" {', '.join(silent)} (needed to check the profile's limits; nothing was"
                " written)"
            )
        return {a.node.node_id: self._versions[a.node.node_id] for a in axes}

    def _read_endpoints(
        self, reads: Mapping[AxisCache, Mapping[str, sdo.Endpoint]]
    ) -> dict[AxisCache, dict[str, float]]:
        """``RxSdo`` reads of :data:`~...odrive_sdo.LIMIT_PATHS` on every node, together."""
        wanted = [
            (axis, path, table[path].id)
            for axis, table in reads.items()
            for path in sdo.LIMIT_PATHS
        ]
        for axis, _, endpoint in wanted:
            self._sdo_values.pop((axis.node.node_id, endpoint), None)

        def missing() -> list[tuple[AxisCache, str, int]]:
            return [w for w in wanted if (w[0].node.node_id, w[2]) not in self._sdo_values]

        def ask() -> None:
            for axis, _, endpoint in missing():
                data = sdo.encode_rxsdo(sdo.OPCODE_READ, endpoint)
                self._send(cs.arbitration_id(axis.node.node_id, cs.Cmd.RXSDO), data)

        ask()
        if not self._wait_for(lambda: not missing(), self.init_timeout, ask):
            late = [f"{a.label()}: {path} (endpoint {e})" for a, path, e in missing()]
            raise DriverInitError(
                f"{self.name}: no TxSdo answer within {self.init_timeout} s to reading"
                f" {'; '.join(late)} (needed to check the profile's limits; nothing was"
                " written)"
            )
        values: dict[AxisCache, dict[str, float]] = {axis: {} for axis in reads}
        for axis, path, endpoint in wanted:
            raw = self._sdo_values[axis.node.node_id, endpoint]
            values[axis][path] = sdo.read_float(raw)
        return values

    def on_activate(self) -> None:
        """Hold position, enter ``CLOSED_LOOP_CONTROL`` on every axis and wait for it.

        First makes sure no node id is answered by two devices (a second device that came
        since configure would be armed too). From then on the supervisor re-sends each axis's
        set-point every ``command_period``.

        Raises:
            DriverInitError: Two devices answer as one node.
            DriverError: An axis did not reach ``CLOSED_LOOP_CONTROL``.
        """
        self._refuse_duplicates()
        with self._held_lock:
            for axis in self._axes:
                pos = axis.enc[0] if axis.enc is not None else 0.0
                self._send(
                    axis.ids[cs.Cmd.SET_CONTROLLER_MODE],
                    cs.encode_set_controller_mode(
                        cs.ControlMode.POSITION_CONTROL, cs.InputMode.PASSTHROUGH
                    ),
                )
                axis.mode = ControlMode.POSITION
                axis.held = (axis.ids[cs.Cmd.SET_INPUT_POS], cs.encode_set_input_pos(pos))
                self._send(*axis.held)
        self._request_state(cs.AxisState.CLOSED_LOOP_CONTROL)
        self._due_feed = self.clock.monotonic() + self.command_period
        self._holding = False
        self._armed = self._feeding = True

    def on_deactivate(self) -> None:
        """Stop re-sending set-points, set every axis ``IDLE`` and wait for it."""
        with self._held_lock:
            self._armed = self._feeding = self._holding = False
            for axis in self._axes:
                axis.held = None
        self._request_state(cs.AxisState.IDLE)

    def on_make_safe(self) -> str:
        """Apply :attr:`safe_state` to every axis; confirm by heartbeat, briefly.

        ``idle``: ``SetAxisCache_State(IDLE)``. ``hold``: ``Set_Controller_Mode(VELOCITY_CONTROL)``
        and ``Set_Input_Vel(0)``, kept being sent (an axis in ``IDLE`` stays there). Every
        axis is sent its frames even when one fails; a heartbeat is then requested and waited
        for at most :data:`SAFE_CONFIRM` real seconds (a device that does not answer is not
        waited for longer).

        Returns:
            One item per axis, e.g. ``"left_wheel IDLE, right_wheel IDLE"``.

        Raises:
            DriverError: A frame could not be sent (after trying every axis).
        """
        hold = self.safe_state == "hold"
        self._armed = False  # an axis leaving CLOSED_LOOP_CONTROL now is what was asked
        failed: list[str] = []
        with self._held_lock:
            self._feeding = self._holding = hold
            for axis in self._axes:
                try:
                    if hold:
                        self._send(
                            axis.ids[cs.Cmd.SET_CONTROLLER_MODE],
                            cs.encode_set_controller_mode(
                                cs.ControlMode.VELOCITY_CONTROL, cs.InputMode.PASSTHROUGH
                            ),
                        )
                        axis.mode = ControlMode.VELOCITY
                        axis.held = (axis.ids[cs.Cmd.SET_INPUT_VEL], cs.encode_set_input_vel(0.0))
                        self._send(*axis.held)
                    else:
                        axis.held = None
                        self._state_requests += 1
                        self._send(
                            axis.ids[cs.Cmd.SET_AXIS_STATE],
                            cs.encode_set_axis_state(cs.AxisState.IDLE),
                        )
                except (DriverError, StateError) as err:
                    failed.append(f"{axis.label()}: {err}")
        if failed:
            raise DriverOperationError(f"{self.name}: safe state not sent: {'; '.join(failed)}")
        confirmed = self._confirm(None if hold else cs.AxisState.IDLE)
        done: list[str] = []
        for axis, ok in zip(self._axes, confirmed, strict=True):
            state = cs.state_name(axis.state)
            if hold:
                what = f"hold 0 rev/s ({state})" if ok else "hold 0 rev/s sent (unconfirmed)"
            else:
                what = "IDLE" if ok else "IDLE sent (unconfirmed)"
            done.append(f"{axis.node.joint} {what}")
        return ", ".join(done)

    def _confirm(self, state: cs.AxisState | None) -> list[bool]:
        """Request heartbeats; wait up to :data:`SAFE_CONFIRM` real seconds for new ones."""
        before = [a.beats for a in self._axes]
        try:
            self._request_status()
        except (DriverError, StateError):
            return [False] * len(self._axes)

        def fine() -> list[bool]:
            return [
                a.beats > n and (state is None or a.state == state)
                for a, n in zip(self._axes, before, strict=True)
            ]

        deadline = time.monotonic() + SAFE_CONFIRM
        ask_again = time.monotonic() + SAFE_CONFIRM / 4
        with self._cond:
            while not all(fine()) and (left := deadline - time.monotonic()) > 0:
                if time.monotonic() >= ask_again:  # an answer sent before the axis switched
                    ask_again = time.monotonic() + SAFE_CONFIRM / 4
                    with contextlib.suppress(DriverError, StateError):
                        self._request_status()
                # real time: never held up by a paused test clock
                self._cond.wait(min(left, max(ask_again - time.monotonic(), 0.001)))
        return fine()

    def needs_hands(self, error: BaseException | None) -> str:
        """An axis error other than ``WATCHDOG_TIMER_EXPIRED`` needs a person (see the base).

        An expired watchdog (the host stopped sending set-points: a paused process, a stall)
        only disarmed the axis; ``Clear_Errors`` and arming again are what the ODrive
        documentation prescribes (``axis.config.enable_watchdog``, ``watchdog_timeout``).
        """
        watchdog = int(cs.AxisError.WATCHDOG_TIMER_EXPIRED)
        if isinstance(error, MotorFaultError) and error.error and not error.error & ~watchdog:
            return ""
        return super().needs_hands(error)

    def on_recover(self) -> None:
        """Clear the nodes' errors (``Clear_Errors``) and wait until they report none.

        Raises:
            DriverError: A node is still silent or still reports errors.
        """
        self._armed = self._feeding = self._holding = False
        if self._bus is None:
            self.on_configure()
            return
        for axis in self._axes:
            self._send(axis.ids[cs.Cmd.CLEAR_ERRORS], cs.encode_clear_errors())
            axis.bad = axis.dup = None
            axis.recent.clear()
            axis.malformed.clear()
            axis.hb_rate.clear()
            axis.enc_rate.clear()
        self._request_status()
        now = self.clock.monotonic()
        fine = self._wait_for(
            lambda: (
                self._problem(self.clock.monotonic()) is None
                and all(a.hb_stamp is not None and a.hb_stamp >= now for a in self._axes)
            ),
            self.init_timeout,
            self._request_status,
        )
        problem = self._problem(self.clock.monotonic())
        if not fine or problem is not None:
            raise problem or DriverTimeoutError(f"{self.name}: no heartbeat after clearing errors")
        self._latched = False

    def _request_status(self) -> None:
        for axis in self._axes:
            axis.hb_rate.ask()
            self._send(axis.ids[cs.Cmd.HEARTBEAT], b"", remote=True)
            axis.enc_rate.ask()
            self._send(axis.ids[cs.Cmd.GET_ENCODER_ESTIMATES], b"", remote=True)

    def _request_state(self, state: cs.AxisState) -> None:
        self._state_requests += 1
        for axis in self._axes:
            self._send(axis.ids[cs.Cmd.SET_AXIS_STATE], cs.encode_set_axis_state(state))
        self._request_status()
        if not self._wait_for(
            lambda: all(a.state == state or a.error for a in self._axes),
            self.init_timeout,
            self._request_status,
        ):
            late = [a.label() for a in self._axes if a.state != state]
            raise DriverTimeoutError(
                f"{self.name}: {', '.join(late)} did not reach {state.name}"
                f" in {self.init_timeout} s"
            )
        problem = self._problem(self.clock.monotonic())
        if problem is not None:
            raise problem

    # ---- verbs -----------------------------------------------------------------------------

    def command(self, commands: Iterable[JointCommand]) -> None:
        """Send set-points (rad, rad/s or N·m on the joint side).

        Args:
            commands: One per joint to change; others keep their set-point.

        Raises:
            StateError: Not active.
            ValueError: An unknown joint or a set-point outside the joint's limits.
            DriverOperationError: The bus refused a frame.
        """
        self.require_active("command")
        plan: list[tuple[AxisCache, JointCommand]] = []
        for c in commands:
            axis = self._by_joint.get(c.joint)
            if axis is None:
                raise ValueError(f"{self.name}: no joint {c.joint!r} (joints: {self.joint_names})")
            check_limits(c.joint, axis.node.limits, c.mode.value, c.value)
            plan.append((axis, c))
        wait = self._check_gap(self.clock.monotonic())  # after a gap: held, sent once judged
        with self._held_lock:  # no re-send of an older set-point can follow this one
            for axis, c in plan:
                mode = c.mode
                if axis.mode is not mode:
                    # held back (also if a gap is found just now): sent once it was judged
                    if wait or not self._send(
                        axis.ids[cs.Cmd.SET_CONTROLLER_MODE],
                        cs.encode_set_controller_mode(_MODES[mode], cs.InputMode.PASSTHROUGH),
                        setpoint=True,
                    ):
                        axis.mode_due = wait = True
                    axis.mode = mode
                if mode is ControlMode.POSITION:
                    data = cs.INPUT_POS.pack(c.value / axis.rad, 0, 0)
                    axis.held = (axis.ids[cs.Cmd.SET_INPUT_POS], data)
                elif mode is ControlMode.VELOCITY:
                    data = cs.F32X2.pack(c.value / axis.rad, 0.0)
                    axis.held = (axis.ids[cs.Cmd.SET_INPUT_VEL], data)
                else:
                    torque = c.value / axis.node.gear_ratio
                    axis.held = (axis.ids[cs.Cmd.SET_INPUT_TORQUE], cs.F32_PAD.pack(torque))
                if not wait and not self._send(*axis.held, setpoint=True):
                    wait = True  # a gap found just now: the rest waits too

    def read_state(self) -> JointStates:
        """The newest estimate of every joint (the receive thread's cache; no bus traffic).

        Returns:
            Joint states stamped with the clock time each estimate arrived.

        Raises:
            StateError: Never configured, or finalized.
        """
        self._require_open("read the state")
        joints: dict[str, JointState] = {}
        newest = -math.inf
        for axis in self._axes:
            pos, vel, stamp = axis.enc or (0.0, 0.0, -math.inf)
            name = axis.node.joint
            joints[name] = JointState(
                name, pos * axis.rad, vel * axis.rad, axis.torque * axis.node.gear_ratio, stamp
            )
            newest = max(newest, stamp)
        return JointStates(newest, joints)

    def estop(self) -> None:
        """Send ``Estop`` to every node (they disarm and latch ``ESTOP_REQUESTED``).

        Raises:
            StateError: Never configured, or finalized.
            DriverOperationError: The bus refused a frame.
        """
        self._require_open("estop")
        for axis in self._axes:
            self._send(axis.ids[cs.Cmd.ESTOP], cs.encode_estop())

    # ---- receive and supervise -------------------------------------------------------------

    def _on_frame(self, msg: can.Message) -> None:
        entry = self._rx.get(msg.arbitration_id)
        if entry is None or msg.is_extended_id:
            return
        axis, cmd = entry
        data = msg.data
        now = self.clock.monotonic()
        if cmd == cs.Cmd.HEARTBEAT:
            why = cs.heartbeat_problem(data)
        else:
            why = None if len(data) == 8 else f"{len(data)} data bytes instead of 8"
        if why is not None:
            self._malformed(axis, cs.Cmd(cmd).name, why, now)
            return
        if cmd == cs.Cmd.GET_VERSION:
            self._versions[axis.node.node_id] = cs.decode_version(data)
            self._notify()
            return
        if cmd == cs.Cmd.TXSDO:
            endpoint, value = sdo.decode_txsdo(data)
            self._sdo_values[axis.node.node_id, endpoint] = value
            self._notify()
            return
        if cmd == cs.Cmd.GET_ENCODER_ESTIMATES:
            pos, vel = cs.F32X2.unpack(data)
            axis.enc = (pos, vel, now)
            axis.enc_age.feed(now)
            axis.enc_rate.add(now)
            axis.stale_at = None
            if axis.stale is not None:
                axis.stale = None
                self._evaluate()
        elif cmd == cs.Cmd.HEARTBEAT:
            error, state, _, _ = cs.HEARTBEAT.unpack(data)
            changed = error != axis.error or state != axis.state or axis.bad is not None
            changed = changed or self.state is DriverState.FAULT
            if axis.bad is not None:
                axis.bad = None
                axis.malformed.clear()
            axis.error, axis.state, axis.hb_stamp = error, state, now
            axis.hb_seq = self._rx_count
            if state == cs.AxisState.CLOSED_LOOP_CONTROL:
                axis.off_since = None
            elif axis.off_since is None:
                axis.off_since = now
            axis.recent.append((state, error, self._state_requests))
            if axis.dup is None:
                axis.dup = _alternating(axis.recent)
                changed = changed or axis.dup is not None
            axis.beats += 1
            axis.hb_rate.add(now)
            self._notify()
            if changed:
                self._evaluate()
        else:
            axis.torque = cs.F32X2.unpack(data)[1]

    def _malformed(self, axis: AxisCache, what: str, why: str, now: float) -> None:
        """Count one malformed frame; too many within the window make a fault."""
        text = f"{axis.label()}: malformed {what} frame ({why})"
        bad = self._count_malformed(
            axis.malformed, text, "frames", now, latched=axis.bad is not None
        )
        if bad is not None:
            axis.bad = bad
            self._evaluate()

    def _on_period(self, now: float) -> None:
        """Judge the encoder streams' age; re-send the held set-points every ``command_period``.

        The set-points feed the watchdog. Not while a gap in the loop is judged (the devices'
        feedback after it decides first), and not in ``FAULT`` (unless the safe state ``hold``
        was applied): a driver that lost its device or its data stops feeding, so the
        device's watchdog disarms the axes if nobody makes them safe.
        """
        self._judge_streams(now)
        if not self._feeding or now < self._due_feed or self._resync is not None:
            return
        if not self._holding and self.state is DriverState.FAULT:
            return
        self._due_feed = max(self._due_feed + self.command_period, now)
        with self._held_lock:  # make_safe and deactivate drop the held frames under it
            for axis in self._axes:
                if axis.held is not None:
                    try:
                        if not self._send(*axis.held, setpoint=True):
                            break  # a gap in the loop found just now: judged first
                    except DriverError as err:  # the link's state shows in the replies
                        logger.debug("driver %s: re-send failed: %s", self.name, err)

    def _judge_streams(self, now: float) -> None:
        """Mark each axis's encoder stream stale or fresh, as of the link as last seen.

        A stream is stale when its newest estimate is older than 3 ``encoder_period`` as of
        :meth:`_link_seen`, at two looks a tenth of a period apart (the supervisor wakes for
        both: :meth:`_deadline`), so a receive thread that was slow to take a frame, or a
        frame a little late, is not a fault.
        """
        seen = self._link_seen(now)
        for axis in self._axes:
            why = axis.enc_age.stale(seen)
            if why is None:
                axis.stale = axis.stale_at = None
            elif axis.stale is None:
                if axis.stale_at is None:
                    axis.stale_at = now
                elif now - axis.stale_at >= axis.enc_age.period * _SECOND_LOOK:
                    axis.stale = why

    def _deadline(self) -> float:
        if not self._supervising:
            return math.inf
        ends = [
            a.enc_age.last + a.enc_age.max_age + _AFTER
            if a.stale_at is None
            else a.stale_at + a.enc_age.period * _SECOND_LOOK
            for a in self._axes
            if a.enc_age.last is not None and a.stale is None
        ]
        return min(ends, default=math.inf)

    def _on_deadline(self, now: float) -> None:
        self._judge_streams(now)

    def _fresh(self, mark: int) -> bool:
        return all(a.hb_seq > mark for a in self._axes)

    def _ask_feedback(self, now: float) -> None:
        if now - self._asked_at < self.supervise_period:
            return  # once a period is enough
        self._asked_at = now
        with contextlib.suppress(DriverError, StateError):
            self._request_status()

    def _resume(self) -> None:
        """Send the held set-points (and a mode set while they waited) after a gap.

        The streams' rates are counted anew: the backlog drained after the gap came in a burst
        (spread over more than a window when the receiver is slow), not at the devices' rate.
        """
        for axis in self._axes:
            axis.hb_rate.clear()
            axis.enc_rate.clear()
        with self._held_lock:
            if not self._feeding:
                return
            for axis in self._axes:
                try:  # a new gap (the process stopped while resuming): judged first
                    if (
                        axis.mode_due
                        and axis.mode is not None
                        and not self._send(
                            axis.ids[cs.Cmd.SET_CONTROLLER_MODE],
                            cs.encode_set_controller_mode(
                                _MODES[axis.mode], cs.InputMode.PASSTHROUGH
                            ),
                            setpoint=True,
                        )
                    ):
                        break
                    axis.mode_due = False
                    if axis.held is not None and not self._send(*axis.held, setpoint=True):
                        break
                except DriverError as err:
                    logger.debug("driver %s: re-send failed: %s", self.name, err)
            self._due_feed = self.clock.monotonic() + self.command_period

    def _problem(self, now: float) -> DriverError | None:
        limit = self.timeout_periods * self.heartbeat_period
        seen = self._link_seen(now)  # heartbeats queued during a pause are not missing
        for axis in self._axes:
            if axis.hb_stamp is None or seen - axis.hb_stamp > limit:
                return DriverTimeoutError(
                    f"{self.name}: {axis.label()}: no heartbeat within {limit:g} s"
                )
            if axis.error:
                return motor_fault(self.name, axis)
            if axis.bad is not None:
                return DriverOperationError(f"{self.name}: {axis.bad}")
            if axis.stale is not None:
                bad = axis.malformed.recent(now)
                if bad:  # what arrives is corrupt: that is the fault, not silence
                    return DriverOperationError(
                        f"{self.name}: {axis.stale}; {bad} malformed frames from the node within"
                        f" {axis.malformed.window:g} s"
                    )
                return DriverTimeoutError(f"{self.name}: {axis.stale}")
            if axis.dup is not None:
                node = axis.node.node_id
                return DriverOperationError(
                    f"{self.name}: {axis.label()}: {axis.dup}: two devices answer as node {node}"
                    f" (duplicate ODrive node {node}); recovering would arm both: give one of"
                    " them another node id"
                )
            off = axis.off_since
            if (
                self._armed
                and off is not None
                and seen - off > _OFF_PERIODS * self.heartbeat_period
            ):
                return DriverOperationError(
                    f"{self.name}: {axis.label()}: the axis left CLOSED_LOOP_CONTROL (now"
                    f" {cs.state_name(axis.state)}) without an error bit; recover() to go on"
                )
            for stream, rate in (
                ("heartbeats", axis.hb_rate),
                ("encoder estimates", axis.enc_rate),
            ):
                excess = rate.excess(now)
                if excess is not None:
                    return DriverOperationError(
                        f"{self.name}: {axis.label()}: {stream} arrive at {excess:.1f}x the"
                        f" configured rate: two devices answer as node {axis.node.node_id}?"
                        f" (duplicate ODrive node {axis.node.node_id})"
                    )
        return None
