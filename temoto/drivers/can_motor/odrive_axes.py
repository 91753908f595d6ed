"""The axes of an ODrive bus as the driver sees them: settings, caches, stream rates, faults.

:class:`ODriveNode` is one axis of a profile entry; :class:`AxisCache` is what the receive
thread of :class:`~temoto.drivers.can_motor.odrive.ODriveDriver` knows of it (heartbeat,
encoder estimates, held set-point, staleness), with a :class:`StreamRate` per cyclic stream
that tells a node answered by two devices; :func:`motor_fault` names an axis's error bits.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Final

from temoto.drivers.can_motor import cansimple as cs
from temoto.drivers.can_motor._common import JointLimits
from temoto.drivers.capabilities import ControlMode
from temoto.drivers.supervision import STALE_PERIODS, FaultWindow, StreamAge
from temoto.errors import MotorFaultError

__all__ = [
    "DUPLICATE_FACTOR",
    "DUPLICATE_PERIODS",
    "TAU",
    "AxisCache",
    "ODriveNode",
    "StreamRate",
    "motor_fault",
]

#: One turn, in radians.
TAU: Final = 2.0 * math.pi
#: A stream arriving at more than this many times its configured rate is two devices.
DUPLICATE_FACTOR: Final = 1.5
#: Over how many of its periods a stream's rate is counted.
DUPLICATE_PERIODS: Final = 20
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


class StreamRate:
    """Arrivals of one cyclic stream, for the duplicate-node check (one writer).

    Args:
        period: The stream's configured period (s).
    """

    __slots__ = ("asked", "limit", "period", "since", "times", "window")

    def __init__(self, period: float) -> None:
        self.period = period
        self.window = period * DUPLICATE_PERIODS
        self.limit = DUPLICATE_FACTOR * DUPLICATE_PERIODS + 2
        self.times: deque[float] = deque()
        self.asked = 0  # replies still due to the driver's own requests (not counted)
        self.since: float | None = None  # when the rate went over the limit

    def ask(self) -> None:
        """A reply to the driver's own request is due: it is not counted."""
        self.asked = min(self.asked + 1, 4)

    def add(self, now: float) -> None:
        """One arrival at ``now`` (clock seconds)."""
        if self.asked:
            self.asked -= 1
            return
        self.times.append(now)

    def excess(self, now: float) -> float | None:
        """The rate as a multiple of the configured one, when it is a duplicate's.

        Only when it stayed over the limit for a whole window: a backlog of frames handled in
        a burst after a pause of our process (or of the receive thread) fills one window, not
        two; a second device keeps it full.
        """
        times = self.times
        while times and times[0] <= now - self.window:
            times.popleft()
        if len(times) <= self.limit:
            self.since = None
            return None
        if self.since is None:
            self.since = now
        if now - self.since < self.window:
            return None
        return len(times) / DUPLICATE_PERIODS

    def clear(self) -> None:
        """Forget every arrival."""
        self.times.clear()
        self.asked = 0
        self.since = None


class AxisCache:
    """The receive thread's cache of one node (plain attributes: one writer).

    Args:
        node: The node's settings.
        heartbeat_period: Its heartbeat period (s).
        encoder_period: Its encoder estimates' period (s).
        stale_periods: Periods without an estimate that make them stale.
    """

    __slots__ = (
        "bad",
        "beats",
        "dup",
        "enc",
        "enc_age",
        "enc_rate",
        "error",
        "hb_rate",
        "hb_seq",
        "hb_stamp",
        "held",
        "ids",
        "malformed",
        "mode",
        "mode_due",
        "node",
        "off_since",
        "rad",
        "recent",
        "stale",
        "stale_at",
        "state",
        "torque",
    )

    def __init__(
        self,
        node: ODriveNode,
        heartbeat_period: float,
        encoder_period: float,
        stale_periods: float = STALE_PERIODS,
    ) -> None:
        self.node = node
        self.rad = TAU / node.gear_ratio  # motor rev → joint rad
        self.ids = {cmd: cs.arbitration_id(node.node_id, cmd) for cmd in cs.Cmd}
        self.enc_age = StreamAge(f"{self.label()} encoder estimates", encoder_period, stale_periods)
        self.hb_rate = StreamRate(heartbeat_period)
        self.enc_rate = StreamRate(encoder_period)
        self.malformed = FaultWindow()
        self.reset()

    def reset(self) -> None:
        """Forget everything received (a new configure)."""
        self.hb_stamp: float | None = None
        self.beats = 0  # heartbeats received
        self.hb_seq = 0  # the receive thread's frame number of the newest heartbeat
        #: The newest heartbeats' (state, error, the driver's state-request count).
        self.recent: deque[tuple[int, int, int]] = deque(maxlen=6)
        self.dup: str | None = None  # why two devices answer as this node
        #: Clock time of the first of the heartbeats in a row out of CLOSED_LOOP_CONTROL.
        self.off_since: float | None = None
        self.state = int(cs.AxisState.UNDEFINED)
        self.error = 0
        self.enc: tuple[float, float, float] | None = None  # pos rev, vel rev/s, stamp
        self.torque = 0.0
        self.mode: ControlMode | None = None
        self.mode_due = False  # ``mode`` was set while set-points waited (a gap): not sent yet
        self.bad: str | None = None  # why too many frames were malformed
        self.held: tuple[int, bytes] | None = None  # the set-point re-sent while active
        self.stale: str | None = None  # why the estimates are stale (two looks)
        self.stale_at: float | None = None  # clock time of the first look that found them so
        self.enc_age.reset()
        self.hb_rate.clear()
        self.enc_rate.clear()
        self.malformed.clear()

    def label(self) -> str:
        """How messages name the node: ``node 1 (left)``."""
        return f"node {self.node.node_id} ({self.node.joint})"


def motor_fault(name: str, axis: AxisCache) -> MotorFaultError:
    """The fault of a node whose heartbeat carries error bits.

    Args:
        name: The driver's name.
        axis: The node's cache.

    Returns:
        A :class:`~temoto.errors.MotorFaultError` naming the bits and their kinds.
    """
    names = cs.error_names(axis.error)
    kinds = [kind for bits, kind in _KINDS if axis.error & bits]
    what = f" ({', '.join(kinds)})" if kinds else ""
    return MotorFaultError(
        f"{name}: {axis.label()}: axis error {' | '.join(names)}{what}",
        node_id=axis.node.node_id,
        error=axis.error,
    )
