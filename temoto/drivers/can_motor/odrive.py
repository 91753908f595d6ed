"""ODrive motor controllers over CANSimple (profile ``driver: odrive_can``).

One :class:`ODriveDriver` drives every axis (node id) of one device entry on one CAN bus.
``configure`` opens the bus and waits for each node's heartbeat and encoder estimate;
``activate`` puts every axis in ``CLOSED_LOOP_CONTROL`` (holding its position) and waits for the
heartbeats to confirm it; ``deactivate`` sets ``IDLE``. ``command`` sends ``Set_Input_Pos`` /
``Set_Input_Vel`` / ``Set_Input_Torque`` (with ``Set_Controller_Mode`` when a joint's mode
changes); ``read_state`` reads the cache that the receive thread fills from the cyclic
encoder estimates (and ``Get_Torques``, when the ODrive is set to send them).

Faults: a node silent for 3 heartbeat periods is a :class:`~temoto.errors.DriverTimeoutError`
(recovered by itself when heartbeats return); error bits in a heartbeat are a
:class:`~temoto.errors.MotorFaultError` naming the decoded bits (latched: :meth:`recover` sends
``Clear_Errors``); a malformed frame (wrong length) is a
:class:`~temoto.errors.DriverOperationError` until the node's next good heartbeat.

Discovery: :meth:`ODriveDriver.detect` only listens for the nodes' cyclic heartbeats and
sends nothing, so looking at a bus never moves an axis.

Units: the ODrive speaks motor turns; joints are radians on the output side of
``gear_ratio`` (motor turns per joint turn): ``joint_rad = motor_rev * 2π / gear_ratio``,
``joint_Nm = motor_Nm * gear_ratio``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Final, Self

import can

from temoto.clock import Clock
from temoto.drivers.base import DriverState, detect_links
from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor._common import JointLimits, Profile, check_limits, open_bus
from temoto.drivers.can_motor._driver import CanMotorDriver
from temoto.drivers.capabilities import ControlMode, JointCommand, JointState, JointStates
from temoto.drivers.sim import Simulator
from temoto.errors import (
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeoutError,
    MotorFaultError,
    ProfileError,
)

__all__ = ["ODriveDriver", "ODriveNode"]

logger = logging.getLogger(__name__)

TAU: Final = 2.0 * math.pi
_KEYS: Final = frozenset(
    {
        "driver",
        "link",
        "nodes",
        "heartbeat_period",
        "encoder_period",
        "init_timeout",
        "timeout_periods",
    }
)
_NODE_KEYS: Final = frozenset(
    {
        "node_id",
        "joint",
        "gear_ratio",
        "position_min",
        "position_max",
        "velocity_limit",
        "torque_limit",
    }
)
_MODES: Final = {
    ControlMode.POSITION: cs.ControlMode.POSITION_CONTROL,
    ControlMode.VELOCITY: cs.ControlMode.VELOCITY_CONTROL,
    ControlMode.EFFORT: cs.ControlMode.TORQUE_CONTROL,
}
#: Error bits behind the simulator's (and the Robot Manager's) hardware-error kinds.
_KINDS: Final = (
    (cs.AxisError.MOTOR_OVER_TEMP | cs.AxisError.INVERTER_OVER_TEMP, "overheat"),
    (
        cs.AxisError.CURRENT_LIMIT_VIOLATION
        | cs.AxisError.DC_BUS_OVER_CURRENT
        | cs.AxisError.DC_BUS_OVER_REGEN_CURRENT,
        "overload",
    ),
    (cs.AxisError.DC_BUS_OVER_VOLTAGE | cs.AxisError.DC_BUS_UNDER_VOLTAGE, "voltage"),
)


@dataclass(frozen=True, slots=True)
class ODriveNode:
    """One axis of a device entry.

    Attributes:
        node_id: CANSimple node id (0..63).
        joint: The joint it moves.
        gear_ratio: Motor turns per joint turn (> 0).
        limits: Joint-side limits of set-points.
    """

    node_id: int
    joint: str
    gear_ratio: float = 1.0
    limits: JointLimits = field(default_factory=JointLimits)


class _Axis:
    """The receive thread's cache of one node (plain attributes: one writer)."""

    __slots__ = (
        "bad",
        "enc",
        "error",
        "hb_stamp",
        "ids",
        "mode",
        "node",
        "rad",
        "state",
        "torque",
    )

    def __init__(self, node: ODriveNode) -> None:
        self.node = node
        self.rad = TAU / node.gear_ratio  # motor rev → joint rad
        self.ids = {cmd: cs.arbitration_id(node.node_id, cmd) for cmd in cs.Cmd}
        self.reset()

    def reset(self) -> None:
        self.hb_stamp: float | None = None
        self.state = int(cs.AxisState.UNDEFINED)
        self.error = 0
        self.enc: tuple[float, float, float] | None = None  # pos rev, vel rev/s, stamp
        self.torque = 0.0
        self.mode: ControlMode | None = None
        self.bad: str | None = None  # why the newest frame was malformed

    def label(self) -> str:
        return f"node {self.node.node_id} ({self.node.joint})"


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

    Raises:
        ValueError: No nodes, a duplicate node id or joint, or a non-positive period.
    """

    kind = "odrive_can"

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
    ) -> None:
        if not nodes:
            raise ValueError("an ODriveDriver needs at least one node")
        if len({n.node_id for n in nodes}) != len(nodes) or len({n.joint for n in nodes}) != len(
            nodes
        ):
            raise ValueError("node ids and joints must be distinct")
        if not (heartbeat_period > 0 and init_timeout > 0 and timeout_periods > 0):
            raise ValueError("periods and timeouts must be positive")
        super().__init__(
            name,
            link=link,
            clock=clock,
            init_timeout=init_timeout,
            supervise_period=heartbeat_period / 4,
        )
        self.nodes = tuple(nodes)
        self.heartbeat_period = heartbeat_period
        self.timeout_periods = timeout_periods
        self._axes = [_Axis(n) for n in self.nodes]
        self._by_joint = {a.node.joint: a for a in self._axes}
        self._rx: dict[int, tuple[_Axis, int]] = {}
        for axis in self._axes:
            for cmd in (cs.Cmd.HEARTBEAT, cs.Cmd.GET_ENCODER_ESTIMATES, cs.Cmd.GET_TORQUES):
                self._rx[axis.ids[cmd]] = (axis, cmd)

    # ---- profile ---------------------------------------------------------------------------

    @classmethod
    def from_profile(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock, where: str
    ) -> Self:
        """Build the driver from its profile entry (see ``docs/driver-can.md``).

        Args:
            name: The device's name.
            config: The entry (``driver``, when present, must name this driver).
            clock: The robot's clock.
            where: The entry's key path, for messages.

        Returns:
            The driver (``UNCONFIGURED``).

        Raises:
            ProfileError: A bad entry; the message names the key path.
        """
        p = Profile(where)
        cfg = p.entry(config, _KEYS, cls.kind)
        link = p.link(cfg)
        nodes: list[ODriveNode] = []
        members = p.members(
            cfg, "nodes", _NODE_KEYS, "node_id", (0, cs.MAX_NODE_ID), id_word="node id"
        )
        for path, node, node_id, joint in members:
            gear = p.number(node, "gear_ratio", path, 1.0)
            nodes.append(ODriveNode(node_id, joint, gear, p.limits(node, path)))
        hb = p.number(cfg, "heartbeat_period", "", 0.1)
        p.number(cfg, "encoder_period", "", 0.01)
        init = p.number(cfg, "init_timeout", "", 1.0)
        periods = p.number(cfg, "timeout_periods", "", 3.0)
        return cls(
            name,
            link=link,
            nodes=nodes,
            clock=clock,
            heartbeat_period=hb,
            init_timeout=init,
            timeout_periods=periods,
        )

    @classmethod
    def simulate(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock
    ) -> tuple[Simulator, dict[str, Any]]:
        """A simulator (not started) serving this device entry, and the entry to drive it.

        Args:
            name: The device's name.
            config: The entry without ``driver`` (valid: see :meth:`from_profile`).
            clock: The clock the simulator steps on.

        Returns:
            ``(simulator, config)``; for CAN the config is the same (the link is shared).

        Raises:
            ProfileError: A bad entry.
        """
        from temoto.drivers.can_motor.sim import SimODrive

        driver = cls.from_profile(name, config, clock=clock, where=name)
        driver.shutdown()
        encoder = config.get("encoder_period", 0.01)
        sim = SimODrive(
            driver.link,
            [n.node_id for n in driver.nodes],
            clock,
            heartbeat_period=driver.heartbeat_period,
            encoder_period=float(encoder),
        )
        return sim, dict(config)

    # ---- discovery -------------------------------------------------------------------------

    @classmethod
    def detect(
        cls, links: Sequence[Any] | None = None, *, timeout: float = 1.0
    ) -> list[dict[str, Any]]:
        """The ODrive axes heartbeating on CAN buses, as profile device entries.

        Listens only: each link's bus is opened, read for ``timeout`` real seconds and closed
        again, and no frame is sent (no RTR request either), so nothing moves. A node is an
        ODrive axis when a well-formed CANSimple ``Heartbeat`` (command 0x01, 8 data bytes,
        standard id) arrives from it; the newest heartbeat's axis state and error bits are
        logged at INFO. Only the ODrives' cyclic heartbeats are seen: an axis whose
        ``heartbeat_msg_rate_ms`` is 0, or slower than ``timeout``, may be missed.

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
        if links is not None and (
            isinstance(links, str | bytes | Mapping) or not isinstance(links, Sequence)
        ):
            raise ValueError(
                f"{cls.kind} detect: links must be a sequence of link mappings, got {links!r}"
            )
        found = detect_links(links, timeout, _available_links)
        candidates = [_link(i, link) for i, link in enumerate(found)]
        entries: list[dict[str, Any]] = []
        for link in candidates:
            seen = _listen(link, timeout)
            if seen:
                nodes = [{"node_id": n, "joint": f"joint_{n}"} for n in sorted(seen)]
                entries.append({"driver": cls.kind, "link": dict(link), "nodes": nodes})
        return entries

    # ---- lifecycle -------------------------------------------------------------------------

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The joints, in profile order."""
        return tuple(n.joint for n in self.nodes)

    def on_configure(self) -> None:
        """Open the bus and wait for every node's heartbeat and encoder estimate.

        Raises:
            DriverInitError: A node did not answer within ``init_timeout`` (named).
            MotorFaultError: A node reports error bits.
        """
        for axis in self._axes:
            axis.reset()
        self._latched = False
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
        problem = self._problem(self.clock.monotonic())
        if problem is not None:
            raise problem
        self._supervising = True

    def on_activate(self) -> None:
        """Hold position, enter ``CLOSED_LOOP_CONTROL`` on every axis and wait for it."""
        for axis in self._axes:
            pos = axis.enc[0] if axis.enc is not None else 0.0
            self._send(
                axis.ids[cs.Cmd.SET_CONTROLLER_MODE],
                cs.encode_set_controller_mode(
                    cs.ControlMode.POSITION_CONTROL, cs.InputMode.PASSTHROUGH
                ),
            )
            axis.mode = ControlMode.POSITION
            self._send(axis.ids[cs.Cmd.SET_INPUT_POS], cs.encode_set_input_pos(pos))
        self._request_state(cs.AxisState.CLOSED_LOOP_CONTROL)

    def on_deactivate(self) -> None:
        """Set every axis ``IDLE`` and wait for it."""
        self._request_state(cs.AxisState.IDLE)

    def on_recover(self) -> None:
        """Clear the nodes' errors (``Clear_Errors``) and wait until they report none.

        Raises:
            DriverError: A node is still silent or still reports errors.
        """
        if self._bus is None:
            self.on_configure()
            return
        for axis in self._axes:
            self._send(axis.ids[cs.Cmd.CLEAR_ERRORS], cs.encode_clear_errors())
            axis.bad = None
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
            self._send(axis.ids[cs.Cmd.HEARTBEAT], b"", remote=True)
            self._send(axis.ids[cs.Cmd.GET_ENCODER_ESTIMATES], b"", remote=True)

    def _request_state(self, state: cs.AxisState) -> None:
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
        plan: list[tuple[_Axis, JointCommand]] = []
        for c in commands:
            axis = self._by_joint.get(c.joint)
            if axis is None:
                raise ValueError(f"{self.name}: no joint {c.joint!r} (joints: {self.joint_names})")
            check_limits(c.joint, axis.node.limits, c.mode.value, c.value)
            plan.append((axis, c))
        for axis, c in plan:
            mode = c.mode
            if axis.mode is not mode:
                self._send(
                    axis.ids[cs.Cmd.SET_CONTROLLER_MODE],
                    cs.encode_set_controller_mode(_MODES[mode], cs.InputMode.PASSTHROUGH),
                )
                axis.mode = mode
            if mode is ControlMode.POSITION:
                data = cs.INPUT_POS.pack(c.value / axis.rad, 0, 0)
                self._send(axis.ids[cs.Cmd.SET_INPUT_POS], data)
            elif mode is ControlMode.VELOCITY:
                self._send(axis.ids[cs.Cmd.SET_INPUT_VEL], cs.F32X2.pack(c.value / axis.rad, 0.0))
            else:
                torque = c.value / axis.node.gear_ratio
                self._send(axis.ids[cs.Cmd.SET_INPUT_TORQUE], cs.F32_PAD.pack(torque))

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
        if len(data) != 8:
            what = cs.Cmd(cmd).name
            axis.bad = f"{axis.label()}: malformed {what} frame ({len(data)} data bytes)"
            self._evaluate()
            return
        now = self.clock.monotonic()
        if cmd == cs.Cmd.GET_ENCODER_ESTIMATES:
            pos, vel = cs.F32X2.unpack(data)
            axis.enc = (pos, vel, now)
        elif cmd == cs.Cmd.HEARTBEAT:
            error, state, _, _ = cs.HEARTBEAT.unpack(data)
            changed = error != axis.error or state != axis.state or axis.bad is not None
            changed = changed or self.state is DriverState.FAULT
            axis.error, axis.state, axis.hb_stamp, axis.bad = error, state, now, None
            self._notify()
            if changed:
                self._evaluate()
        else:
            axis.torque = cs.F32X2.unpack(data)[1]

    def _on_period(self, now: float) -> None:
        pass  # the ODrives send on their own; the supervisor only checks the heartbeats' age

    def _problem(self, now: float) -> DriverError | None:
        limit = self.timeout_periods * self.heartbeat_period
        for axis in self._axes:
            if axis.hb_stamp is None or now - axis.hb_stamp > limit:
                return DriverTimeoutError(
                    f"{self.name}: {axis.label()}: no heartbeat within {limit:g} s"
                )
            if axis.error:
                return _motor_fault(self.name, axis)
            if axis.bad is not None:
                return DriverOperationError(f"{self.name}: {axis.bad}")
        return None


def _link(index: int, link: object) -> dict[str, Any]:
    """A link to look at, checked as :meth:`ODriveDriver.from_profile` checks ``link``."""
    try:
        return Profile(f"links[{index}]").link({"link": link})
    except ProfileError as err:
        raise ValueError(
            f"{ODriveDriver.kind} detect: links[{index}] is not a python-can bus mapping with"
            f" interface and channel (e.g. {{interface: socketcan, channel: can0}}): {link!r}"
        ) from err


def _available_links() -> list[dict[str, Any]]:
    """What python-can can open here (a configuration not in profile form is skipped).

    python-can imports every interface module to ask it, and each one that lacks its vendor
    library logs a WARNING on the ``can`` logger (a dozen on a machine without them); those
    are not shown: that logger is quieted to ERROR for the call.
    """
    quiet = logging.getLogger("can")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        configs = can.detect_available_configs()
    finally:
        quiet.setLevel(level)
    links: list[dict[str, Any]] = []
    for index, config in enumerate(configs):
        try:
            links.append(_link(index, config))
        except ValueError as err:
            logger.debug("%s", err)
    return links


def _heartbeat(msg: can.Message) -> tuple[int, cs.Heartbeat] | None:
    """``(node id, heartbeat)`` of a CANSimple heartbeat frame, None for any other frame."""
    if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
        return None  # a remote Heartbeat is some host's request, not a node's beat
    if msg.arbitration_id > 0x7FF:
        return None
    node, cmd = cs.split_id(msg.arbitration_id)
    if cmd != cs.Cmd.HEARTBEAT:
        return None
    try:
        return node, cs.decode_heartbeat(msg.data)
    except ValueError:
        return None  # wrong length: not a (well-formed) ODrive heartbeat


def _listen(link: dict[str, Any], timeout: float) -> dict[int, cs.Heartbeat]:
    """The newest heartbeat of each node heard on ``link`` within ``timeout`` real seconds."""
    what = f"{ODriveDriver.kind} detect"
    try:
        bus = open_bus(link, what)
    except DriverError as err:
        logger.warning("%s: skipping %s: %s", what, link, err)
        return {}
    seen: dict[int, cs.Heartbeat] = {}
    try:
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                msg = bus.recv(timeout=left)
            except (can.CanError, OSError) as err:
                logger.warning("%s: receiving on %s failed, stopped listening: %s", what, link, err)
                break
            found = _heartbeat(msg) if msg is not None else None
            if found is not None:
                seen[found[0]] = found[1]
    finally:
        bus.shutdown()
    for node in sorted(seen):
        beat = seen[node]
        try:
            state = cs.AxisState(beat.axis_state).name
        except ValueError:
            state = str(beat.axis_state)
        errors = " | ".join(cs.error_names(beat.axis_error)) or "none"
        logger.info(
            "%s: node %d on %s: axis state %s, axis errors %s, procedure result %d",
            what,
            node,
            link,
            state,
            errors,
            beat.procedure_result,
        )
    return seen


def _motor_fault(name: str, axis: _Axis) -> MotorFaultError:
    names = cs.error_names(axis.error)
    kinds = [kind for bits, kind in _KINDS if axis.error & bits]
    what = f" ({', '.join(kinds)})" if kinds else ""
    return MotorFaultError(
        f"{name}: {axis.label()}: axis error {' | '.join(names)}{what}",
        node_id=axis.node.node_id,
        error=axis.error,
    )
