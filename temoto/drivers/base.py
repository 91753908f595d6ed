"""The driver lifecycle every device driver shares (docs/development.md §5, §6).

A :class:`Driver` moves through ``UNCONFIGURED → INACTIVE → ACTIVE → FINALIZED``, plus
``FAULT``. The public transitions (:meth:`~Driver.configure`, :meth:`~Driver.activate`,
:meth:`~Driver.deactivate`, :meth:`~Driver.shutdown`, :meth:`~Driver.recover`) live here: they
check the transition table, call the subclass hook (``on_configure`` opens the link and pings
the device, ``on_activate`` enables torque or readiness, ``on_deactivate`` holds or disables,
``on_shutdown`` closes the link, ``on_recover`` reconnects), and turn failures into the right
:class:`~temoto.errors.DriverError` category.

A running driver that loses its device (no heartbeat, no reply, hardware-error bits) calls
:meth:`Driver.report_fault`: the state becomes ``FAULT`` and every health listener is told. When
the device answers again the driver calls :meth:`Driver.report_recovered` (or someone calls
:meth:`Driver.recover`): it returns to the state it was in. The Robot Manager turns those
reports into registrar statuses (FATAL, then OK) for every consumer of the robot.

``__init__`` stores configuration only and never touches hardware. A driver is built from its
profile entry by :meth:`Driver.from_profile`, from the keys it declares in
:attr:`Driver.profile_fields` (:mod:`temoto.drivers.profile`); :meth:`Driver.simulate` gives
the simulator that serves an entry, and :meth:`Driver.detect` the devices a driver can reach.

**Safe state** (``docs/safety.md``). Every driver declares the states it can leave its device
in when TeMoto lets go of it (:attr:`Driver.safe_states`, the first is the default; a profile
picks one with ``safe_state:``). :meth:`Driver.make_safe` applies it from any configured state,
``FAULT`` included (best effort: a frame is still sent to a device that stopped answering), and
:meth:`Driver.shutdown` applies it before closing the link, so every path that shuts a driver
down (mission end, release, fault, exception) leaves the device safe. For paths that skip the
shutdown, :func:`make_all_safe` reaches every configured driver of the process: the robot
command calls it on SIGINT/SIGTERM, and it runs at interpreter exit. A process that dies
without running Python code (SIGKILL, a hang) is covered by the devices' own watchdogs, which
the drivers feed by sending set-points at a steady rate.
"""

from __future__ import annotations

import atexit
import enum
import logging
import math
import threading
import time
import warnings
import weakref
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, ClassVar, Final, Self

from temoto.clock import Clock, MonotonicClock
from temoto.drivers.profile import Field, ProfileReader, choice
from temoto.drivers.recovery import RECOVERY_FIELD, RecoveryPolicy
from temoto.drivers.sim import Simulator
from temoto.errors import (
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverUnavailableError,
    DynamixelHardwareError,
    MotorFaultError,
    StateError,
)

__all__ = [
    "Driver",
    "DriverState",
    "Health",
    "HealthListener",
    "detect_links",
    "device_text",
    "live_drivers",
    "make_all_safe",
]

logger = logging.getLogger(__name__)


class DriverState(enum.Enum):
    """Where a driver is in its lifecycle."""

    UNCONFIGURED = "UNCONFIGURED"
    INACTIVE = "INACTIVE"
    ACTIVE = "ACTIVE"
    FINALIZED = "FINALIZED"
    FAULT = "FAULT"


_S = DriverState

#: (from, verb) → to. ``shutdown`` is allowed from everywhere (and is idempotent).
_TRANSITIONS: Final[Mapping[tuple[DriverState, str], DriverState]] = {
    (_S.UNCONFIGURED, "configure"): _S.INACTIVE,
    (_S.INACTIVE, "activate"): _S.ACTIVE,
    (_S.ACTIVE, "deactivate"): _S.INACTIVE,
    (_S.FAULT, "recover"): _S.INACTIVE,
}


@dataclass(frozen=True, slots=True)
class Health:
    """A driver's health, stamped with its clock.

    Attributes:
        driver: The driver's name.
        state: Its lifecycle state.
        ok: False in ``FAULT`` (and before ``configure``).
        message: Why it is not ok, or what it recovered from.
        stamp: Clock seconds of this report.
        error: The error behind a fault, if any.
    """

    driver: str
    state: DriverState
    ok: bool
    message: str
    stamp: float
    error: DriverError | None = None


#: Called with every new health report (on the thread that made it; keep it short).
HealthListener = Callable[[Health], None]


class Driver(ABC):
    """Base of every device driver: lifecycle, health, listeners (see the module docstring).

    Args:
        name: The device's name in its profile.
        clock: Where time is read (state stamps, poll periods, timeouts).

    Raises:
        ValueError: ``name`` is empty.
    """

    #: The profile's ``driver`` value that selects this class.
    kind: ClassVar[str] = ""

    #: The safe states this driver can leave its device in (``safe_state:`` in a profile);
    #: the first is the default. Each driver documents what each one sends.
    safe_states: ClassVar[tuple[str, ...]] = ("idle",)

    #: The keys of a profile entry besides ``driver`` and ``safe_state``
    #: (:mod:`temoto.drivers.profile`); :meth:`from_profile` reads them.
    profile_fields: ClassVar[Mapping[str, Field[Any]]] = {}

    #: Real seconds :meth:`make_safe` waits for a transition running on another thread before
    #: it sends anyway (a driver stuck in ``configure`` must not delay the safe state).
    SAFE_LOCK_WAIT: ClassVar[float] = 0.05

    def __init__(self, name: str, *, clock: Clock | None = None) -> None:
        if not isinstance(name, str) or not name:
            raise ValueError(f"a driver needs a name, got {name!r}")
        self.name = name
        self.clock: Clock = clock or MonotonicClock()
        self._lifecycle = threading.RLock()  # one transition at a time
        self._lock = threading.Lock()
        self._state = DriverState.UNCONFIGURED
        self._before_fault = DriverState.INACTIVE
        self._health = Health(name, self._state, False, "not configured", self.clock.monotonic())
        self._listeners: list[HealthListener] = []
        self._safe_state = type(self).safe_states[0]
        #: What the Robot Manager does after a fault (``recovery:`` in a profile).
        self.recovery = RecoveryPolicy()
        self._made_safe: str | None = None  # what make_safe did, until the next activate

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r} {self.state.value}>"

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.shutdown()

    def __del__(self) -> None:
        state = getattr(self, "_state", DriverState.FINALIZED)
        if state not in (DriverState.FINALIZED, DriverState.UNCONFIGURED):
            warnings.warn(
                f"driver {getattr(self, 'name', '?')!r} was not shut down ({state.value})",
                ResourceWarning,
                stacklevel=1,
            )

    # ---- state -----------------------------------------------------------------------------

    @property
    def state(self) -> DriverState:
        """The lifecycle state."""
        with self._lock:
            return self._state

    def health(self) -> Health:
        """The newest health report.

        Returns:
            The report.
        """
        with self._lock:
            return self._health

    def add_health_listener(self, listener: HealthListener) -> Callable[[], None]:
        """Be told of every health change (faults, recoveries, transitions).

        Args:
            listener: Called with each new :class:`Health`, on the reporting thread.

        Returns:
            A function that removes the listener.
        """
        with self._lock:
            self._listeners.append(listener)

        def remove() -> None:
            with self._lock:
                if listener in self._listeners:
                    self._listeners.remove(listener)

        return remove

    @property
    def safe_state(self) -> str:
        """The state :meth:`make_safe` leaves the device in (one of :attr:`safe_states`)."""
        return self._safe_state

    @safe_state.setter
    def safe_state(self, value: str) -> None:
        if value not in type(self).safe_states:
            known = ", ".join(type(self).safe_states)
            raise ValueError(f"{self.name}: safe_state must be one of {known}, got {value!r}")
        self._safe_state = value

    @classmethod
    def safe_state_from(cls, config: Mapping[str, Any], where: str) -> str:
        """The ``safe_state`` of a profile entry, checked (the default when it is absent).

        Args:
            config: The device's profile entry.
            where: The entry's key path, for messages.

        Returns:
            One of :attr:`safe_states`.

        Raises:
            ProfileError: The value is not one of them (the message names the key path).
        """
        field = cls.profile_schema()["safe_state"]
        return str(ProfileReader.at(where).field(config, "safe_state", field))

    # ---- profiles --------------------------------------------------------------------------

    @classmethod
    def profile_schema(cls) -> dict[str, Field[Any]]:
        """Every key a profile entry of this driver may have, with how it is read.

        :attr:`profile_fields` plus ``safe_state`` (one of :attr:`safe_states`, the first by
        default) and ``recovery`` (:mod:`temoto.drivers.recovery`). ``driver`` is always
        allowed too (it must name this driver).

        Returns:
            key → :class:`~temoto.drivers.profile.Field`.
        """
        safe = choice(cls.safe_states, cls.safe_states[0], init=False)
        return {**cls.profile_fields, "safe_state": safe, "recovery": RECOVERY_FIELD}

    @classmethod
    def read_profile(cls, config: Mapping[str, Any], where: str) -> dict[str, Any]:
        """Check a profile entry against :meth:`profile_schema` (without building a driver).

        Args:
            config: The entry (``driver``, when present, must name this driver).
            where: The entry's place for messages (``robot.yaml: devices.base``).

        Returns:
            Every declared key with its checked value or its default.

        Raises:
            ProfileError: The first problem; the message names the file and the key path.
        """
        return ProfileReader.at(where).entry(config, cls.profile_schema(), cls.kind)

    @classmethod
    def profile_settings(cls, values: Mapping[str, Any], where: str) -> dict[str, Any]:
        """The constructor's keyword arguments from checked profile values.

        The default passes every field declared with ``init=True`` as it is; a driver
        overrides it to convert values (a list of mappings into its node type) or to check
        keys against each other, raising through ``ProfileReader.at(where)``.

        Args:
            values: What :meth:`read_profile` returned.
            where: The entry's place for messages.

        Returns:
            Keyword arguments for ``cls(name, clock=..., **kwargs)``.

        Raises:
            ProfileError: Keys that are fine alone but not together.
        """
        schema = cls.profile_schema()
        return {k: v for k, v in values.items() if k in schema and schema[k].init}

    @classmethod
    def from_profile(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock, where: str
    ) -> Self:
        """Build the driver from its profile entry, without touching the device.

        The template: :meth:`read_profile` checks the entry, :meth:`profile_settings` turns it
        into constructor arguments, the constructor runs (a ``ValueError`` it raises becomes a
        :class:`~temoto.errors.ProfileError` naming the key its message starts with), and
        ``safe_state`` is set.

        Args:
            name: The device's name.
            config: Its profile entry (see the driver's ``docs/driver-*.md``).
            clock: The robot's clock.
            where: The entry's place for messages (``robot.yaml: devices.base``).

        Returns:
            The driver (``UNCONFIGURED``).

        Raises:
            ProfileError: A missing, unknown or bad key; the message names its path.
        """
        values = cls.read_profile(config, where)
        kwargs = cls.profile_settings(values, where)
        try:
            driver = cls(name, clock=clock, **kwargs)
        except ValueError as err:
            key = next((k for k in kwargs if str(err).startswith(k)), "")
            raise ProfileReader.at(where).error(key, str(err)) from None
        driver.safe_state = values["safe_state"]
        driver.recovery = values["recovery"]
        return driver

    @classmethod
    def simulate(
        cls, name: str, config: Mapping[str, Any], *, clock: Clock
    ) -> tuple[Simulator, dict[str, Any]]:
        """A simulator (not started) serving this profile entry, and the entry to drive it.

        Start the simulator (or enter it as a context manager) before configuring the driver
        built from the returned entry, and close it after shutting the driver down.

        Args:
            name: The device's name.
            config: Its profile entry (checked as :meth:`from_profile` checks it).
            clock: The clock the simulator steps on.

        Returns:
            ``(simulator, entry)``: the entry's ``link`` reaches the simulator.

        Raises:
            ProfileError: A bad entry.
            DriverUnavailableError: The driver has no simulator (the default).
        """
        raise DriverUnavailableError(
            f"{name}: driver {cls.kind or cls.__name__!r} has no simulator (sim: true needs one)"
        )

    # ---- transitions -----------------------------------------------------------------------

    def configure(self) -> None:
        """Open the link and check the device (``UNCONFIGURED → INACTIVE``).

        Raises:
            StateError: Not ``UNCONFIGURED``.
            DriverInitError: The device did not answer or refused its settings (the link is
                closed again; the driver stays ``UNCONFIGURED``).
            DriverUnavailableError: A library or port is missing.
        """
        with self._lifecycle:
            self._check("configure")
            try:
                self.on_configure()
            except BaseException as err:
                self._quietly(self.on_shutdown)
                raise _as_driver_error(err, DriverInitError, f"{self.name}: configure") from err
            self._set(DriverState.INACTIVE, "configured")
            _LIVE.add(self)

    def activate(self) -> None:
        """Make the device ready to act (``INACTIVE → ACTIVE``).

        Raises:
            StateError: Not ``INACTIVE``.
            DriverError: The device refused (the driver goes to ``FAULT``).
        """
        with self._lifecycle:
            self._check("activate")
            try:
                self.on_activate()
            except BaseException as err:
                error = _as_driver_error(err, DriverOperationError, f"{self.name}: activate")
                self.report_fault(error)
                raise error from err
            self._made_safe = None
            self._set(DriverState.ACTIVE, "active")

    def deactivate(self) -> None:
        """Stop acting, keep the link (``ACTIVE → INACTIVE``).

        Raises:
            StateError: Not ``ACTIVE``.
            DriverError: The device refused (the driver goes to ``FAULT``).
        """
        with self._lifecycle:
            self._check("deactivate")
            try:
                self.on_deactivate()
            except BaseException as err:
                error = _as_driver_error(err, DriverOperationError, f"{self.name}: deactivate")
                self.report_fault(error)
                raise error from err
            self._set(DriverState.INACTIVE, "inactive")

    def recover(self) -> None:
        """Reconnect after a fault (``FAULT → INACTIVE``); activate again to act.

        Raises:
            StateError: Not in ``FAULT``.
            DriverError: The device still does not answer (the driver stays in ``FAULT``).
        """
        with self._lifecycle:
            self._check("recover")
            try:
                self.on_recover()
            except BaseException as err:
                raise _as_driver_error(err, DriverOperationError, f"{self.name}: recover") from err
            self._set(DriverState.INACTIVE, "recovered")

    def shutdown(self) -> None:
        """Make the device safe, close the link and finish (any state → ``FINALIZED``).

        Idempotent; never raises for the device (a failing close is logged).
        """
        with self._lifecycle:
            if self.state is DriverState.FINALIZED:
                return
            if self.state is not DriverState.UNCONFIGURED:
                self._quietly(lambda: self.make_safe("shutdown"), "make safe at shutdown")
                self._quietly(self.on_shutdown)
            self._set(DriverState.FINALIZED, "shut down")
            _LIVE.discard(self)

    def make_safe(self, reason: str = "") -> str | None:
        """Put the device in its declared :attr:`safe_state`, now.

        Works from ``INACTIVE``, ``ACTIVE`` and ``FAULT`` (to a device that stopped answering the
        commands are still sent, best effort); an ``ACTIVE`` driver becomes ``INACTIVE``, and a
        driver in ``FAULT`` recovers to ``INACTIVE`` (activate it again to act).
        Callable from any thread, also while another transition runs (after
        :attr:`SAFE_LOCK_WAIT` it sends anyway); calling it again sends again.

        Args:
            reason: Why (for the log line).

        Returns:
            What was done, for people (``"left wheel IDLE, right wheel IDLE"``), or None when
            the driver holds no link (``UNCONFIGURED`` or ``FINALIZED``).

        Raises:
            DriverError: Sending failed (the device may not be safe; the driver goes to
                ``FAULT``).
        """
        locked = self._lifecycle.acquire(timeout=self.SAFE_LOCK_WAIT)
        try:
            state = self.state
            if state in (DriverState.UNCONFIGURED, DriverState.FINALIZED):
                return None
            try:
                done = self.on_make_safe()
            except BaseException as err:
                error = _as_driver_error(err, DriverOperationError, f"{self.name}: make safe")
                self.report_fault(error)
                raise error from err
            with self._lock:
                now = self._state
                if now is DriverState.FAULT:
                    self._before_fault = DriverState.INACTIVE  # recovery finds it safe, not acting
            self._made_safe = done
            if now is DriverState.ACTIVE:
                self._set(DriverState.INACTIVE, f"safe: {done}")
            logger.info("driver %s: safe (%s): %s", self.name, reason or "asked", done)
            return done
        finally:
            if locked:
                self._lifecycle.release()

    # ---- reports from the driver's own threads ---------------------------------------------

    def report_fault(self, error: DriverError) -> None:
        """The device failed while configured: go to ``FAULT`` and tell the listeners.

        Args:
            error: What happened (a typed :class:`~temoto.errors.DriverError`).
        """
        with self._lock:
            if self._state in (DriverState.FINALIZED, DriverState.UNCONFIGURED):
                return
            if self._state is DriverState.FAULT and self._health.error is not None:
                if str(self._health.error) == str(error):
                    return  # the same fault again: no new report
            else:
                self._before_fault = self._state
        logger.warning("driver %s: fault: %s", self.name, device_text(self.name, str(error)))
        self._set(DriverState.FAULT, str(error), error)

    def report_recovered(self, message: str = "the device answers again") -> None:
        """The device came back by itself: return to the state before the fault.

        Args:
            message: What recovered.
        """
        with self._lock:
            if self._state is not DriverState.FAULT:
                return
            back = self._before_fault
        logger.info("driver %s: recovered: %s", self.name, device_text(self.name, message))
        self._set(back, message)

    # ---- discovery -------------------------------------------------------------------------

    @classmethod
    def detect(
        cls, links: Sequence[Any] | None = None, *, timeout: float = 1.0
    ) -> list[dict[str, Any]]:
        """The devices this driver can reach, as profile device entries (docs/development.md §6).

        Looking must not move anything: a driver only listens, or asks questions the device
        answers without acting (a ping, a heartbeat). Each entry has ``driver`` and the keys
        :meth:`from_profile` needs, with placeholder joint names (``joint_<id>``) to rename, so
        it can be pasted into a profile as it is (``temoto drivers detect`` prints them).

        Args:
            links: Where to look, each in the form of the profile's ``link`` value (a URL
                string, or a python-can ``{interface, channel}`` mapping for CAN). None: the
                driver's own candidates (for example every serial port).
            timeout: Seconds to listen or wait for answers on each link (and baud rate).

        Returns:
            One entry per link where devices answered, in the order looked at.

        Raises:
            ValueError: ``timeout`` is not positive, or a link is not in the driver's form.

        The default finds nothing: a driver whose devices cannot be found without commanding
        them (MIT-mode CAN motors move on every frame) keeps it.
        """
        detect_links(links, timeout, list)
        return []

    # ---- hooks -----------------------------------------------------------------------------

    @abstractmethod
    def on_configure(self) -> None:
        """Open the link and check that the device answers (raise if not)."""

    def on_activate(self) -> None:  # noqa: B027  # optional hook: nothing to do by default
        """Make the device act (enable torque, closed loop, arm-ready)."""

    def on_deactivate(self) -> None:  # noqa: B027  # optional hook: nothing to do by default
        """Stop acting but keep the link (hold or disable torque)."""

    def on_make_safe(self) -> str:
        """Put the device in :attr:`safe_state` and say what was done (see :meth:`make_safe`).

        Called in ``INACTIVE``, ``ACTIVE`` or ``FAULT``, possibly from a signal's thread while
        another thread uses the link: send, wait briefly (a bounded time) if the protocol
        confirms, never block on the device. The default runs :meth:`on_deactivate` when
        ``ACTIVE``; drivers override it.

        Returns:
            What was done, for people.
        """
        if self.state is DriverState.ACTIVE:
            self.on_deactivate()
        return self.safe_state

    def needs_hands(self, error: BaseException | None) -> str:
        """Why a fault must not be cleared without a person looking ("": it may be).

        The Robot Manager's recovery (``recovery:`` in a profile) does not clear a device's
        own hardware error (a servo overheating or overloaded, a motor controller's error
        bits): re-arming it could harm the hardware. A driver allows the errors it knows to be
        harmless to clear (an ODrive axis whose watchdog expired while its host paused).

        Args:
            error: The fault's error (or what a recovery try raised).

        Returns:
            The reason for people, or "" when the manager may recover the device.
        """
        if isinstance(error, DynamixelHardwareError | MotorFaultError):
            return "the device reports a hardware error"
        return ""

    def on_recover(self) -> None:
        """Reconnect after a fault (default: configure again from scratch)."""
        self._quietly(self.on_shutdown)
        self.on_configure()

    @abstractmethod
    def on_shutdown(self) -> None:
        """Close the link and stop the driver's threads (must not raise for a dead device)."""

    # ---- helpers ---------------------------------------------------------------------------

    def require_active(self, verb: str) -> None:
        """Raise unless ``ACTIVE`` (for capability verbs).

        Args:
            verb: What was asked, for the message.

        Raises:
            StateError: The driver is not active (the message says its state and last fault).
        """
        with self._lock:
            state, health = self._state, self._health
        if state is not DriverState.ACTIVE:
            fault = state is DriverState.FAULT
            why = f": {device_text(self.name, health.message)}" if fault else ""
            raise StateError(f"{self.name}: cannot {verb} while {state.value}{why}")

    def _check(self, verb: str) -> None:
        with self._lock:
            state = self._state
        if (state, verb) not in _TRANSITIONS:
            raise StateError(f"{self.name}: cannot {verb} while {state.value}")

    def _set(self, state: DriverState, message: str, error: DriverError | None = None) -> None:
        ok = state in (DriverState.INACTIVE, DriverState.ACTIVE)
        health = Health(self.name, state, ok, message, self.clock.monotonic(), error)
        with self._lock:
            self._state = state
            self._health = health
            listeners = list(self._listeners)
        for listener in listeners:
            try:
                listener(health)
            except Exception:
                logger.exception("driver %s: a health listener raised", self.name)

    def _quietly(self, hook: Callable[[], Any], what: str = "") -> None:
        """Run a shutdown step that must not stop the shutdown.

        A device's error (a :class:`DriverError`, e.g. a silent link that cannot confirm the
        safe state) is one warning line; anything else is a bug in the driver and is logged
        with its traceback.
        """
        what = what or getattr(hook, "__name__", repr(hook))
        try:
            hook()
        except DriverError as err:
            logger.warning("driver %s: %s failed: %s", self.name, what, err)
        except Exception:
            logger.exception("driver %s: %s failed", self.name, what)


#: Every driver configured and not yet shut down in this process (weakly held), for
#: :func:`make_all_safe`: the one process-wide registry, for paths that cannot reach the
#: drivers' owners (signals, interpreter exit).
_LIVE: weakref.WeakSet[Driver] = weakref.WeakSet()


def live_drivers() -> list[Driver]:
    """Every driver of this process that is configured and not yet shut down.

    Returns:
        The drivers, in no particular order.
    """
    return list(_LIVE)


#: Real seconds :func:`make_all_safe` waits for the devices' confirmations, all together
#: (``docs/safety.md``: every device safe within 200 ms of a signal).
SAFE_ALL_WAIT: Final = 0.2


def make_all_safe(
    reason: str = "", *, drivers: Sequence[Driver] | None = None, wait: float = SAFE_ALL_WAIT
) -> list[tuple[Driver, str]]:
    """Put every configured driver of this process in its safe state, all at once.

    Each driver's :meth:`~Driver.make_safe` runs on a thread of its own
    (``temoto-safe-<name>``), so every device is sent its safe state at once; their
    confirmations are awaited together, for at most ``wait`` real seconds. A device that has
    not confirmed by then is listed as such (its thread goes on and logs what it did). Never
    raises: a driver that fails is logged and listed with the error's text, unless it was made
    safe and not activated since, before or meanwhile by another thread (its shutdown, say):
    then its line says what was done, not ``NOT SAFE``.

    Args:
        reason: Why (for the log lines).
        drivers: The drivers (default: every live driver of the process, by name).
        wait: Real seconds to wait for the confirmations, all together.

    Returns:
        ``(driver, what was done)`` for each driver that holds a link, in the drivers' order.
    """
    chosen = sorted(live_drivers(), key=lambda d: d.name) if drivers is None else list(drivers)
    results: dict[int, str | None] = {}
    lock = threading.Lock()

    def safe_one(index: int, driver: Driver) -> None:
        try:
            what = driver.make_safe(reason)
        except Exception as err:  # one device's failure never stops the others' safe state
            # a transition on another thread (a shutdown) may be making it safe: let it end
            if driver._lifecycle.acquire(timeout=wait):
                driver._lifecycle.release()
            before = driver._made_safe  # made safe since its last activation, by any thread
            if before is not None:
                again = device_text(driver.name, str(err))
                what = f"{before} (sending it again failed: {again})"
                logger.warning("driver %s: safe before; sending again failed: %s", driver.name, err)
            else:
                logger.error("driver %s: could not make it safe: %s", driver.name, err)
                what = f"NOT SAFE: {device_text(driver.name, str(err))}"
        with lock:
            results[index] = what

    threads = [
        threading.Thread(target=safe_one, args=(i, d), name=f"temoto-safe-{d.name}", daemon=True)
        for i, d in enumerate(chosen)
    ]
    for index, thread in enumerate(threads):
        try:
            thread.start()
        except RuntimeError:  # no new threads (interpreter shutdown): this one, here
            safe_one(index, chosen[index])
    deadline = time.monotonic() + wait
    for thread in threads:
        if thread.ident is not None:
            thread.join(max(deadline - time.monotonic(), 0.0))
    done: list[tuple[Driver, str]] = []
    with lock:
        finished = dict(results)
    for i, driver in enumerate(chosen):
        if i in finished:
            what = finished[i]
            if what is None and driver._made_safe is not None:
                what = driver._made_safe  # shut down meanwhile, which made it safe
            if what is not None:
                done.append((driver, what))
            continue
        if driver.state in (DriverState.UNCONFIGURED, DriverState.FINALIZED):
            continue
        health = driver.health()
        why = health.message if health.state is DriverState.FAULT else "no answer yet"
        why = device_text(driver.name, why)
        done.append(
            (
                driver,
                f"safe state {driver.safe_state} sent, not confirmed within {wait:g} s ({why})",
            )
        )
    return done


def device_text(device: str, text: str) -> str:
    """``text`` without the ``<device>: `` prefixes a driver's messages start with.

    A driver's errors name their device first (``base: node 1 (left_wheel): ...``); a line that
    names the device itself (``driver base: fault: ...``, ``robot r, device base: ...``) drops
    them, so no line reads ``base: base:``.

    Args:
        device: The device's name.
        text: A driver's message.

    Returns:
        The message without leading ``<device>: `` (all of them).
    """
    prefix = f"{device}: "
    while text.startswith(prefix):
        text = text[len(prefix) :]
    return text


atexit.register(make_all_safe, "interpreter exit")


def _as_driver_error(err: BaseException, category: type[DriverError], what: str) -> DriverError:
    """``err`` if it is a DriverError already, else a ``category`` naming ``what``."""
    if isinstance(err, DriverError):
        return err
    if isinstance(err, KeyboardInterrupt | SystemExit):
        raise err
    return category(f"{what}: {type(err).__name__}: {err}")


def detect_links(
    links: Sequence[Any] | None, timeout: float, candidates: Callable[[], list[Any]]
) -> list[Any]:
    """The links a :meth:`Driver.detect` looks at, after checking its arguments.

    Args:
        links: What the caller passed: None, one link URL string, or a sequence of links.
        timeout: What the caller passed as the timeout.
        candidates: The driver's own candidates, called only when ``links`` is None.

    Returns:
        The links, in order (not checked further: each driver knows its link forms).

    Raises:
        ValueError: ``timeout`` is not a positive, finite number of seconds.
    """
    number = isinstance(timeout, int | float) and not isinstance(timeout, bool)
    if not (number and timeout > 0 and math.isfinite(timeout)):
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout!r}")
    if links is None:
        return candidates()
    if isinstance(links, str):
        return [links]
    return list(links)
