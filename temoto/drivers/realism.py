"""An imperfect world on request: seeded sensor noise, stream jitter, late and lost frames.

Every simulator reports its model's true state unless told otherwise (level ``off``: today's
exact figures, for tests that need them). At ``typical`` or ``harsh`` a simulator asks its
:class:`Realism` for

* **sensor noise**: :meth:`Realism.noise` adds a gaussian error of the level's standard
  deviation for a named quantity (:data:`QUANTITIES`) to a reported value (never to the model's
  true state);
* **lost frames**: :meth:`Realism.lost` says whether a streamed frame is lost on the way;
* **jitter and late frames**: :meth:`Realism.delay` is the extra time a batch of frames takes to
  leave: a half-normal jitter of the level's standard deviation, and now and then a stall of
  the link (a radio buffering, a busy USB hub) of a uniform duration; the simulator keeps the
  frames in order, so a stall delays what follows it too.

The figures of each level (:data:`LEVELS`) and the reasoning behind them are in
``docs/simulators.md`` (section "Realism"). Each device has its own random generators, seeded
from a top-level seed and the device's name (:func:`derive_seed`), so a run is replayed by
giving the same seed again; the noise and the link draw from separate generators, so a lost
frame does not shift the noise that follows it, and replies (sent from another thread than the
streams) draw their delays from a third. The seed is chosen at random when none is
given (:func:`new_seed`); whoever starts the simulators prints it.
"""

from __future__ import annotations

import hashlib
import logging
import math
import random
import secrets
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from temoto.drivers.profile import ProfileReader

__all__ = [
    "CAN_TIMING",
    "LEVELS",
    "LEVEL_NAMES",
    "QUANTITIES",
    "SERIAL_REPLY_TIMING",
    "SIM_KEYS",
    "CanTiming",
    "CanTransmitter",
    "Realism",
    "RealismLevel",
    "SerialReplyDelay",
    "SerialReplyTiming",
    "derive_seed",
    "new_seed",
    "read_sim_realism",
    "realism_level",
]

logger = logging.getLogger(__name__)

#: The quantities a level gives a noise figure for, and their unit.
QUANTITIES: Final[Mapping[str, str]] = MappingProxyType(
    {
        "position": "m (each horizontal axis)",
        "altitude": "m",
        "velocity": "m/s (each axis)",
        "attitude": "rad (roll, pitch)",
        "heading": "rad",
        "voltage": "V",
        "current": "A",
        "temperature": "°C",
        "joint_position": "rad",
        "joint_velocity": "rad/s",
        "torque": "N·m",
    }
)


@dataclass(frozen=True)
class RealismLevel:
    """The figures of one level (see ``docs/simulators.md``, "Realism").

    Args:
        name: ``off``, ``typical`` or ``harsh``.
        sigma: Standard deviation of the noise of each quantity of :data:`QUANTITIES`.
        jitter: Standard deviation, s, of a half-normal extra delay of every batch of frames.
        drop: Probability that a streamed frame is lost.
        late: Probability that a batch of frames stalls the link.
        late_delay: The stall's duration, s: uniform between these two.
    """

    name: str
    sigma: Mapping[str, float] = field(default_factory=dict)
    jitter: float = 0.0
    drop: float = 0.0
    late: float = 0.0
    late_delay: tuple[float, float] = (0.0, 0.0)

    @property
    def enabled(self) -> bool:
        """Whether anything differs from the exact world."""
        return bool(self.jitter or self.drop or self.late or any(self.sigma.values()))


#: The levels by name. Figures and reasons: ``docs/simulators.md``, "Realism".
LEVELS: Final[Mapping[str, RealismLevel]] = MappingProxyType(
    {
        "off": RealismLevel("off"),
        "typical": RealismLevel(
            "typical",
            MappingProxyType(
                {
                    "position": 0.3,
                    "altitude": 0.2,
                    "velocity": 0.05,
                    "attitude": math.radians(0.2),
                    "heading": math.radians(0.5),
                    "voltage": 0.02,
                    "current": 0.1,
                    "temperature": 0.5,
                    "joint_position": 0.0005,
                    "joint_velocity": 0.01,
                    "torque": 0.02,
                }
            ),
            jitter=0.002,
            drop=0.002,
            late=0.001,
            late_delay=(0.02, 0.1),
        ),
        "harsh": RealismLevel(
            "harsh",
            MappingProxyType(
                {
                    "position": 0.6,
                    "altitude": 0.5,
                    "velocity": 0.2,
                    "attitude": math.radians(1.0),
                    "heading": math.radians(3.0),
                    "voltage": 0.1,
                    "current": 0.5,
                    "temperature": 1.0,
                    "joint_position": 0.002,
                    "joint_velocity": 0.05,
                    "torque": 0.1,
                }
            ),
            jitter=0.01,
            drop=0.03,
            late=0.01,
            late_delay=(0.1, 0.8),
        ),
    }
)

#: The level names, mildest first.
LEVEL_NAMES: Final = tuple(LEVELS)


def realism_level(name: str) -> RealismLevel:
    """The level of a name.

    Args:
        name: ``off``, ``typical`` or ``harsh``.

    Returns:
        Its figures.

    Raises:
        ValueError: Another name (the message lists the levels).
    """
    level = LEVELS.get(name) if isinstance(name, str) else None
    if level is None:
        raise ValueError(f"realism must be one of {', '.join(LEVEL_NAMES)}, got {name!r}")
    return level


def new_seed() -> int:
    """A fresh random seed (32 bits), to be printed so the run can be replayed.

    Returns:
        The seed.
    """
    return secrets.randbits(32)


def derive_seed(seed: int, device: str, purpose: str) -> int:
    """A device's own seed for one purpose, stable across runs and Python versions.

    Python's ``hash()`` of a string changes from process to process; a BLAKE2b digest does not.

    Args:
        seed: The top-level seed.
        device: The device's name.
        purpose: ``noise``, ``link`` or ``reply``.

    Returns:
        A 64-bit seed.
    """
    digest = hashlib.blake2b(f"{seed}/{device}/{purpose}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


class Realism:
    """One device's imperfections at a level, drawn from its own seeded generators.

    Not thread-safe: the simulator calls it under its own lock.

    Args:
        level: A level or its name (``off``, ``typical``, ``harsh``).
        seed: The top-level seed (None: :func:`new_seed`; ignored at ``off``).
        device: The device's name (each device draws its own numbers).

    Raises:
        ValueError: An unknown level name, or a seed that is not a non-negative integer.
    """

    def __init__(
        self, level: RealismLevel | str = "off", *, seed: int | None = None, device: str = ""
    ) -> None:
        self.level = level if isinstance(level, RealismLevel) else realism_level(level)
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise ValueError(f"the realism seed must be a non-negative integer, got {seed!r}")
        #: The top-level seed this device's numbers come from (None at ``off``).
        self.seed: int | None = None
        if self.level.enabled:
            self.seed = new_seed() if seed is None else seed
        self.device = device
        base = 0 if self.seed is None else self.seed
        self._noise = random.Random(derive_seed(base, device, "noise"))
        self._link = random.Random(derive_seed(base, device, "link"))
        self._reply = random.Random(derive_seed(base, device, "reply"))

    @property
    def enabled(self) -> bool:
        """Whether the level changes anything."""
        return self.level.enabled

    def describe(self) -> str:
        """One line for logs: ``realism typical, seed 123``."""
        if self.seed is None:
            return f"realism {self.level.name}"
        return f"realism {self.level.name}, seed {self.seed}"

    def noise(self, quantity: str, value: float) -> float:
        """``value`` as a sensor reports it: with a gaussian error at the level's sigma.

        Args:
            quantity: One of :data:`QUANTITIES`.
            value: The true value.

        Returns:
            The reported value (``value`` itself at ``off`` or a sigma of 0).

        Raises:
            KeyError: Not one of :data:`QUANTITIES`.
        """
        if quantity not in QUANTITIES:
            raise KeyError(f"not a realism quantity: {quantity!r} (known: {list(QUANTITIES)})")
        sigma = self.level.sigma.get(quantity, 0.0)
        if sigma <= 0.0:
            return value
        return value + self._noise.gauss(0.0, sigma)

    def lost(self) -> bool:
        """Whether the next streamed frame is lost on the way."""
        drop = self.level.drop
        return drop > 0.0 and self._link.random() < drop

    def delay(self, *, reply: bool = False) -> float:
        """The extra seconds the next batch of frames takes: jitter, and now and then a stall.

        Args:
            reply: The batch answers a request (drawn from the replies' own generator, so
                that the streams' numbers do not depend on when requests arrive).

        Returns:
            Seconds (0 at ``off``).
        """
        level = self.level
        rng = self._reply if reply else self._link
        extra = 0.0
        if level.jitter > 0.0:
            extra += abs(rng.gauss(0.0, level.jitter))
        if level.late > 0.0 and rng.random() < level.late:
            extra += rng.uniform(*level.late_delay)
        return extra


#: The keys of a device entry's ``sim`` mapping that set its realism (every simulated driver
#: accepts them).
SIM_KEYS: Final = frozenset({"realism", "seed"})


def read_sim_realism(reader: ProfileReader, sim: object) -> tuple[str, int | None]:
    """The ``realism`` and ``seed`` keys of a device entry's ``sim`` mapping.

    Args:
        reader: The entry's profile reader (errors name the file and ``<entry>.sim.<key>``).
        sim: The entry's ``sim`` value (None: absent).

    Returns:
        ``(level name, seed or None)``; ``("off", None)`` when absent.

    Raises:
        ProfileError: ``sim`` is not a mapping, an unknown level or a seed that is not a
            non-negative integer.
    """
    if sim is None:
        return "off", None
    values = reader.mapping(sim, "sim")
    level = values.get("realism", "off")
    if level not in LEVEL_NAMES:
        reader.fail("sim.realism", f"must be one of {', '.join(LEVEL_NAMES)}, got {level!r}")
    seed = values.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
        reader.fail("sim.seed", f"must be a non-negative integer, got {seed!r}")
    return str(level), seed


# ---- late frames: what the CAN and the serial timing share ------------------------------------


@dataclass(frozen=True)
class _LateTiming:
    """A half-normal jitter on every frame and, now and then, a late one (one level's figures).

    What :class:`CanTiming` and :class:`SerialReplyTiming` share; their docstrings say what the
    figures mean on their wire.
    """

    name: str
    jitter: float = 0.0
    late: float = 0.0
    late_delay: tuple[float, float] = (0.0, 0.0)

    @property
    def enabled(self) -> bool:
        """Whether anything ever comes later than scheduled."""
        return bool(self.jitter or self.late)

    def draw(self, rng: random.Random, *, may_be_late: bool = True) -> tuple[float, float | None]:
        """One frame's extra delay, drawn from ``rng``.

        Args:
            rng: The generator (one gauss draw when there is a jitter; then, when it may be
                late and there is a ``late`` share, one draw to decide, one for the delay).
            may_be_late: Whether this one can be late at all (no draw for it when not).

        Returns:
            The jitter, s (0 without one), and the late delay, s, or None when it is not late.
        """
        jitter = abs(rng.gauss(0.0, self.jitter)) if self.jitter > 0.0 else 0.0
        if may_be_late and self.late > 0.0 and rng.random() < self.late:
            return jitter, rng.uniform(*self.late_delay)
        return jitter, None


# ---- CAN: a node's transmit timing (jitter and late frames) -----------------------------------


@dataclass(frozen=True)
class CanTiming(_LateTiming):
    """When a CAN node's frames leave at one level (``docs/simulators.md``, "Realism").

    A frame is ready at its scheduled time (a cyclic message's period, a reply's request) and
    leaves after a half-normal **jitter** of standard deviation ``jitter``; now and then (share
    ``late`` of the frames) the node's transmitter **stalls** for a uniform time in
    ``late_delay``, and the frame and everything the node sends after it wait for the stall
    to end: a node's frames leave in the order it made them (one transmit queue per node).

    Args:
        name: The level's name.
        jitter: Standard deviation, s, of the half-normal extra delay of every frame.
        late: Share of the frames that stall the node's transmitter.
        late_delay: The stall's duration, s: uniform between these two.
    """


#: The CAN timing of each level by name; a level of another name has none. Figures and reasons:
#: ``docs/simulators.md``, "Realism".
CAN_TIMING: Final[Mapping[str, CanTiming]] = MappingProxyType(
    {
        "off": CanTiming("off"),
        "typical": CanTiming("typical", jitter=0.0005, late=0.001, late_delay=(0.002, 0.008)),
        "harsh": CanTiming("harsh", jitter=0.002, late=0.01, late_delay=(0.005, 0.02)),
    }
)


class CanTransmitter:
    """The transmit timing of the CAN nodes of one simulated device, drawn from seeded generators.

    Streams and replies draw from generators of their own (seeded from the device's
    :class:`Realism` seed and name, :func:`derive_seed` purposes ``can-stream`` and
    ``can-reply``), so the streams' timing does not depend on when requests arrive and the
    noise and losses of :class:`Realism` are the same as without it. Each node keeps its frames
    in order: a frame never leaves before one the node made earlier.

    Not thread-safe: the simulator calls it under its own lock.

    Args:
        realism: The device's realism (its level's name picks :data:`CAN_TIMING`).
    """

    def __init__(self, realism: Realism) -> None:
        self.timing = CAN_TIMING.get(realism.level.name, CAN_TIMING["off"])
        base = 0 if realism.seed is None else realism.seed
        self._stream = random.Random(derive_seed(base, realism.device, "can-stream"))
        self._reply = random.Random(derive_seed(base, realism.device, "can-reply"))
        self._free: dict[int, float] = {}  # node -> when its last frame left
        #: Frames that stalled their node's transmitter (late frames), for tests and tools.
        self.stalls = 0

    @property
    def enabled(self) -> bool:
        """Whether frames ever leave later than scheduled."""
        return self.timing.enabled

    def release(self, node: int, ready: float, *, reply: bool = False) -> float:
        """When a frame of ``node`` made at ``ready`` leaves.

        Args:
            node: The node (an ODrive's node id, a motor's id): its frames stay in order.
            ready: Clock seconds the frame was made.
            reply: The frame answers a request (drawn from the replies' generator).

        Returns:
            Clock seconds, never before ``ready`` nor before the node's previous frame
            (``ready`` itself at ``off``).
        """
        timing = self.timing
        if not timing.enabled:
            return ready
        jitter, stall = timing.draw(self._reply if reply else self._stream)
        at = ready + jitter
        if stall is not None:
            at += stall
            self.stalls += 1
        at = max(at, self._free.get(node, -math.inf))
        self._free[node] = at
        return at


# ---- serial lines (DYNAMIXEL): late status packets ---------------------------------------------
#
# A DYNAMIXEL status packet leaves the servo after its Return Delay Time (register 9, 2 µs per
# unit, at most 508 µs: ROBOTIS e-Manual, X series control table) and reaches the host through
# a USB serial adapter, which holds short packets until its latency timer runs out (16 ms by
# default on the U2D2's FTDI chip, 1 ms once set: e-Manual, "U2D2" and "DYNAMIXEL Wizard 2.0"
# FAQ) and through a USB host a busy machine serves late now and then. dynamixel-sdk waits
# twice the default latency timer plus 2 ms (34 ms) beyond a packet's transfer time before it
# gives up (``PortHandler.LATENCY_TIMER``). The figures: ``docs/simulators.md``, "Realism".


@dataclass(frozen=True)
class SerialReplyTiming(_LateTiming):
    """How late a serial line's status packets come, at one level.

    Args:
        name: The level's name.
        jitter: Standard deviation, s, of a half-normal extra delay of every status packet
            (the servo's processing and the adapter's latency timer at 1 ms).
        late: Probability that a poll's status packets come late (the latency timer at its
            16 ms default, a busy USB host).
        late_delay: How late, s: uniform between these two.
    """


#: The serial lines' reply timing by level name. ``typical`` stays within dynamixel-sdk's
#: 34 ms (never a timeout); a late ``harsh`` poll goes past it nine times in ten (past the
#: simulated driver's 0.1 s four times in ten), so the host sees a timeout and the packets
#: arrive during its next transaction.
SERIAL_REPLY_TIMING: Final[Mapping[str, SerialReplyTiming]] = MappingProxyType(
    {
        "off": SerialReplyTiming("off"),
        "typical": SerialReplyTiming(
            "typical", jitter=0.0002, late=0.01, late_delay=(0.002, 0.016)
        ),
        "harsh": SerialReplyTiming("harsh", jitter=0.001, late=0.04, late_delay=(0.02, 0.15)),
    }
)


class SerialReplyDelay:
    """One serial line's status-packet delays, from its own seeded generator.

    The generator is seeded from the realism's top-level seed, the device's name and the
    purpose ``serial`` (:func:`derive_seed`), so the noise, lost frames and delays of a device
    do not shift one another. Not thread-safe: the simulator's serving thread alone calls it.

    Args:
        realism: The device's realism (its level names the timing; its seed and device seed
            the generator).
        timing: Other figures than the level's (tests).
    """

    def __init__(self, realism: Realism, timing: SerialReplyTiming | None = None) -> None:
        self.timing = timing or SERIAL_REPLY_TIMING.get(
            realism.level.name, SERIAL_REPLY_TIMING["off"]
        )
        #: The realism the figures and the seed come from.
        self.realism = realism
        #: How many times :meth:`delay` made a poll's packets late, and the longest delay (s).
        self.late = 0
        self.longest = 0.0
        base = 0 if realism.seed is None else realism.seed
        self._rng = random.Random(derive_seed(base, realism.device, "serial"))

    @property
    def enabled(self) -> bool:
        """Whether any status packet comes late."""
        return self.timing.enabled

    def delay(self, *, poll: bool) -> float:
        """The extra seconds the next status packet(s) take.

        Args:
            poll: They answer a host's poll (SYNC_READ and the like): only those come late by
                more than the jitter (a late single READ or WRITE status would be retried or
                refused; the same reason as for :meth:`Realism.lost`).

        Returns:
            Seconds (0 at ``off``).
        """
        extra, late = self.timing.draw(self._rng, may_be_late=poll)
        if late is not None:
            extra += late
            self.late += 1
            self.longest = max(self.longest, extra)
        return extra
