"""The Robot Manager: robots from hardware profiles, as registrar resources (docs/design.md §6).

Two servers on the registrar:

* ``"driver"`` (:class:`DriverRequest`): one device of the profile, opened, configured and
  activated (its simulator started first when the profile says ``sim: true``). The driver's
  health reports become statuses of the resource: a fault is ``WARNING`` while the recovery
  will bring the device back and ``FATAL`` when nothing will (with the driver's typed error as
  the message), a recovery ``OK``.
* ``"robot"`` (:class:`RobotRequest`): the robot. Loading it requests a ``"driver"`` for every
  device — dependencies, so a driver's status reaches every consumer of the robot, and the
  drivers are closed when the last consumer releases the robot — and builds the features
  (:mod:`temoto.managers.robot.features`), stepped by one control thread on the robot's clock.

Consumers use :class:`~temoto.managers.robot.client.RobotManagerClient`, never the drivers.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

from temoto.clock import Clock, MonotonicClock
from temoto.config import Profile
from temoto.core.registrar import LoadContext, Registrar, ResourceInfo, ResourceServer, Status
from temoto.drivers import (
    Actuator,
    Driver,
    DriverState,
    Health,
    JointState,
    Vehicle,
    driver_class,
    make_all_safe,
)
from temoto.drivers.base import device_text
from temoto.drivers.realism import Realism
from temoto.drivers.sim import Simulator
from temoto.errors import (
    ConfigError,
    DriverInitError,
    ResourceBrokenError,
    ResourceLoadError,
    ResourceNotFoundError,
    StateError,
)
from temoto.managers.robot.features import (
    ArmController,
    DriveController,
    FlightController,
    controllers_step,
)

if TYPE_CHECKING:
    from temoto.ros2.robot import RobotRos2Link

__all__ = [
    "DriverRequest",
    "DriverResponse",
    "Robot",
    "RobotManager",
    "RobotRequest",
    "RobotResponse",
    "SimulatedDevice",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriverRequest:
    """One device of a robot.

    Attributes:
        robot: The robot's name.
        device: The device's name in the profile.
    """

    robot: str
    device: str


@dataclass(frozen=True)
class DriverResponse:
    """A loaded device.

    Attributes:
        driver: The driver's registry name.
        joints: The joints it moves.
        simulated: Whether its simulator runs in this process.
    """

    driver: str
    joints: tuple[str, ...]
    simulated: bool

    def __post_init__(self) -> None:
        object.__setattr__(self, "joints", tuple(self.joints))  # JSON gives lists back


@dataclass(frozen=True)
class RobotRequest:
    """A robot of the profile.

    Attributes:
        robot: Its name (empty: the manager's robot).
    """

    robot: str = ""


@dataclass(frozen=True)
class RobotResponse:
    """A loaded robot.

    Attributes:
        robot: Its name.
        features: ``navigation``, ``manipulation``, ``flight`` (those it has).
        devices: Its devices.
    """

    robot: str
    features: tuple[str, ...]
    devices: tuple[str, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "features", tuple(self.features))
        object.__setattr__(self, "devices", tuple(self.devices))


@dataclass(frozen=True)
class SimulatedDevice:
    """A loaded device whose simulator runs in this process.

    Attributes:
        name: The device's name in the profile.
        driver: The driver's profile name.
        simulator: The started simulator.
        settings: The entry the driver was built from: its ``link`` reaches the simulator.
    """

    name: str
    driver: str
    simulator: Simulator
    settings: Mapping[str, Any]


@runtime_checkable
class _StreamsToGcs(Protocol):
    """A simulated vehicle that streams to ground stations (``SimVehicle.add_gcs``)."""

    def add_gcs(self, host: str, port: int) -> None: ...


@dataclass(eq=False)
class _Device:
    """An open device of the manager, and its recovery after a fault (``docs/safety.md``)."""

    driver: Driver
    sim: Simulator | None
    remove_listener: Callable[[], None] | None = None
    settings: Mapping[str, Any] | None = None  # the entry the driver got (simulated devices)
    resource_id: str = ""
    #: The recovery's condition: ``answered``, ``closing``, ``recovering`` and ``note`` change
    #: under it.
    cond: threading.Condition = field(default_factory=threading.Condition)
    recovering: bool = False  # a recovery thread runs
    answered: bool = False  # the driver said the device answers again (wakes the recovery)
    closing: bool = False
    gave_up: str = ""  # why the recovery gave up (the device stays out of service)
    note: str = ""  # the recovery's state, for the live view
    thread: threading.Thread | None = None

    @property
    def name(self) -> str:
        """The device's name in the profile."""
        return self.driver.name

    def closed(self) -> bool:
        """Whether the device is being closed (released, the manager shutting down)."""
        with self.cond:
            return self.closing

    def close(self) -> None:
        """Stop the recovery, stop listening, shut the driver down (its safe state first)."""
        with self.cond:
            self.closing = True
            self.cond.notify_all()
        if self.remove_listener is not None:
            self.remove_listener()
        try:
            self.driver.shutdown()
        finally:
            if self.sim is not None:
                self.sim.close()
            thread = self.thread  # one not started yet ends at once: it sees ``closing``
            mine = thread is threading.current_thread()
            if thread is not None and thread.ident is not None and not mine:
                thread.join(5.0)


class Robot:
    """A loaded robot: its features and the thread that steps them.

    Created by the manager; consumers reach it through the client.
    """

    def __init__(
        self,
        profile: Profile,
        devices: Mapping[str, Driver],
        clock: Clock,
        rate_hz: float,
        annotate: Callable[[Health], Health] | None = None,
    ) -> None:
        self.name = profile.robot
        self._annotate = annotate
        self.profile = profile
        self.clock = clock
        self.period = 1.0 / rate_hz
        self._devices = dict(devices)
        self.drive: DriveController | None = None
        self.arm: ArmController | None = None
        self.flight: FlightController | None = None
        #: The controllers that command each device (their goals end when it faults).
        self._commanders: list[tuple[DriveController | ArmController, frozenset[str]]] = []
        #: Every controller with the devices it needs (stepped only while they are all active).
        self._steps: list[tuple[DriveController | ArmController | FlightController, frozenset[str]]]
        if profile.navigation is not None:
            nav = profile.navigation
            wheels = (profile.joint_device(nav.left_wheel), profile.joint_device(nav.right_wheel))
            left, right = self._actuator(wheels[0]), self._actuator(wheels[1])
            self.drive = DriveController(nav, (left, right), clock)
            self._commanders.append((self.drive, frozenset(wheels)))
        if profile.manipulation is not None:
            arm = profile.manipulation
            self.arm = ArmController(arm, self._actuator(arm.device))
            self._commanders.append((self.arm, frozenset({arm.device})))
        self._steps = list(self._commanders)
        if profile.flight is not None:
            vehicle = self._devices[profile.flight.device]
            assert isinstance(vehicle, Vehicle)
            self.flight = FlightController(profile.flight, vehicle)
            self._steps.append((self.flight, frozenset({profile.flight.device})))
        #: The robot's link to ROS 2 (a profile's ``ros2:`` block), set by the manager.
        self.ros2: RobotRos2Link | None = None
        self._cond = threading.Condition()
        self._stopping = False
        self._errors_logged = 0
        self._thread = threading.Thread(
            target=self._loop, name=f"temoto-robot-{self.name}", daemon=True
        )
        self._thread.start()

    def _actuator(self, device: str) -> Actuator:
        driver = self._devices[device]
        if not isinstance(driver, Actuator):
            raise StateError(f"device '{device}' has no joints")
        return driver

    @property
    def features(self) -> tuple[str, ...]:
        """The features it has."""
        return self.profile.features

    def joint_states(self) -> list[JointState]:
        """The state of every joint of the robot's ACTIVE devices, in profile order.

        Returns:
            One per joint.
        """
        out: list[JointState] = []
        for driver in self._devices.values():
            if isinstance(driver, Actuator) and driver.state is DriverState.ACTIVE:
                out.extend(driver.read_state().joints.values())
        return out

    def navigation_devices(self) -> tuple[str, ...]:
        """The devices the drive moves (none without a navigation feature)."""
        nav = self.profile.navigation
        if nav is None:
            return ()
        left = self.profile.joint_device(nav.left_wheel)
        right = self.profile.joint_device(nav.right_wheel)
        return (left,) if left == right else (left, right)

    def healthy(self) -> bool:
        """Whether every device is active (configured, not in FAULT, not made safe)."""
        return all(d.state is DriverState.ACTIVE for d in self._devices.values())

    def health(self) -> dict[str, Health]:
        """Each device's health, with its recovery's state (a try to come, given up).

        Returns:
            Device name → its health.
        """
        annotate = self._annotate or (lambda h: h)
        return {name: annotate(d.health()) for name, d in self._devices.items()}

    def device_faulted(self, device: str, error: BaseException | None = None) -> bool:
        """End the goals of the features that command ``device`` (it faulted).

        A recovered device then holds where it is: the control loop does not take up a goal
        set before the fault. The motions of those goals end with ``error`` (the action that
        follows one fails with the device's reason); the goals of features that do not use
        the device go on.

        Args:
            device: The device's name.
            error: What the ended motions fail with (None: "cancelled").

        Returns:
            Whether the robot ended every goal that commands the device itself: False for the
            vehicle of the flight feature (its actions learn of the fault from ``FATAL``).
        """
        for controller, devices in self._commanders:
            if device in devices:
                controller.stop(error)
        return self.profile.flight is None or self.profile.flight.device != device

    def close(self) -> None:
        """Stop the control thread (the drivers are closed by their resources)."""
        if self.ros2 is not None:  # first: no cmd_vel reaches the drive after this
            self.ros2.close()
            self.ros2 = None
        for controller in (self.drive, self.arm):
            if controller is not None:
                controller.stop()
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if threading.current_thread() is not self._thread:
            self._thread.join(5.0)

    def _loop(self) -> None:
        next_step = self.clock.monotonic()
        while True:
            with self._cond:
                while not self._stopping:
                    remaining = next_step - self.clock.monotonic()
                    if remaining <= 0:
                        break
                    self.clock.wait(self._cond, remaining)
                if self._stopping:
                    return
            next_step += self.period
            now = self.clock.monotonic()
            if next_step < now - self.period:  # fell behind (a slow step): do not catch up
                next_step = now + self.period
            # A controller whose devices are not all active commands nothing (their consumers
            # were told); the others go on (a faulted arm does not stop the base's goal).
            controllers = [
                c
                for c, needs in self._steps
                if all(self._devices[d].state is DriverState.ACTIVE for d in needs)
            ]
            for err in controllers_step(controllers, self.period):
                self._errors_logged += 1
                if self._errors_logged <= 10 or self._errors_logged % 1000 == 0:
                    logger.warning("robot %s: control step failed: %s", self.name, err)


class RobotManager(ResourceServer[RobotRequest, RobotResponse]):
    """Serves the robot of one profile (``"robot"``) and its devices (``"driver"``).

    Args:
        registrar: The registrar to serve on (both servers are registered here).
        profile: The robot's checked profile.
        clock: The robot's clock (drivers, simulators, control loop).
        rate_hz: The control loop's rate.
        sim_gcs: With ``sim: true``: more UDP addresses every simulated vehicle streams to
            (ground stations watching the robot's own vehicle, the robot command's
            ``--sim-out``).
        realism: With ``sim: true``: the simulators' realism level (``off``, the default:
            the exact figures; ``typical``; ``harsh``: :mod:`temoto.drivers.realism`). A
            device entry's own ``sim.realism`` / ``sim.seed`` win over it.
        seed: The realism's top-level seed (None: a fresh one at a level other than off;
            :attr:`seed` holds it, to be printed so the run can be replayed).

    Raises:
        ValueError: ``rate_hz`` is not positive, an unknown realism level, a seed that is not
            a non-negative integer, or the servers exist already.
    """

    name: ClassVar[str] = "robot"
    request_type: ClassVar[type[Any]] = RobotRequest
    response_type: ClassVar[type[Any]] = RobotResponse

    def __init__(
        self,
        registrar: Registrar,
        profile: Profile,
        *,
        clock: Clock | None = None,
        rate_hz: float = 50.0,
        sim_gcs: Sequence[tuple[str, int]] = (),
        realism: str = "off",
        seed: int | None = None,
    ) -> None:
        if not rate_hz > 0:
            raise ValueError("rate_hz must be positive")
        #: The simulators' realism (``realism.describe()``: the line to print).
        self.realism = Realism(realism, seed=seed, device=profile.robot)
        #: The realism's top-level seed (None at ``off``).
        self.seed = self.realism.seed
        self.sim_gcs = tuple(sim_gcs)
        self.registrar = registrar
        self.profile = profile
        self.clock: Clock = clock or MonotonicClock()
        self.rate_hz = rate_hz
        self._lock = threading.Lock()
        self._devices: dict[str, _Device] = {}
        self._robots: dict[str, Robot] = {}
        self._drivers = _DriverServer(self)
        registrar.register(self._drivers)
        registrar.register(self)

    # ---- consumers' access -------------------------------------------------------------------

    def robot(self, name: str = "") -> Robot:
        """A loaded robot.

        Args:
            name: Its name (empty: this manager's robot).

        Returns:
            The robot.

        Raises:
            StateError: It is not loaded (request it through the registrar first).
        """
        name = name or self.profile.robot
        with self._lock:
            robot = self._robots.get(name)
        if robot is None:
            raise StateError(f"robot '{name}' is not loaded")
        return robot

    def simulator(self, device: str) -> Simulator:
        """The simulator of a loaded device (to inject faults in demos and tests).

        Args:
            device: The device's name.

        Returns:
            Its simulator.

        Raises:
            StateError: The device is not loaded, or not simulated.
        """
        with self._lock:
            loaded = self._devices.get(device)
        if loaded is None or loaded.sim is None:
            state = "not simulated" if loaded is not None else "not loaded"
            raise StateError(f"device '{device}' is {state}")
        return loaded.sim

    def simulated(self) -> list[SimulatedDevice]:
        """The loaded devices whose simulators run in this process, in profile order.

        Returns:
            One per simulated device (none when the profile says ``sim: false``).
        """
        with self._lock:
            loaded = dict(self._devices)
        found: list[SimulatedDevice] = []
        for name, spec in self.profile.devices.items():
            device = loaded.get(name)
            if device is not None and device.sim is not None:
                settings = device.settings or spec.config
                found.append(SimulatedDevice(name, spec.driver, device.sim, settings))
        return found

    # ---- the "robot" server ------------------------------------------------------------------

    def on_load(self, request: RobotRequest, ctx: LoadContext) -> RobotResponse:
        """Load every device (as dependencies), then build the robot."""
        name = request.robot or self.profile.robot
        if name != self.profile.robot:
            raise ResourceNotFoundError(
                f"this manager serves robot '{self.profile.robot}', not '{name}'"
            )
        drivers: dict[str, Driver] = {}
        for device in self.profile.devices:
            try:
                ctx.call("driver", DriverRequest(name, device))
            except ResourceLoadError as err:
                raise self._start_error(device, err) from err
            with self._lock:
                drivers[device] = self._devices[device].driver
        robot = Robot(self.profile, drivers, self.clock, self.rate_hz, self._annotate)
        if self.profile.ros2 is not None:  # the robot on ROS 2 (docs/ros2.md)
            from temoto.ros2.robot import RobotRos2Link

            link = RobotRos2Link(self.registrar, robot, self.profile.ros2, self.profile.source)
            try:
                link.start()
            except BaseException:
                robot.close()
                raise
            robot.ros2 = link
        with self._lock:
            self._robots[name] = robot
        logger.info("robot %s ready (%s)", name, ", ".join(self.profile.features) or "no features")
        return RobotResponse(name, self.profile.features, tuple(self.profile.devices))

    def _start_error(self, device: str, err: ResourceLoadError) -> Exception:
        """What a device that could not start says: robot, device, the driver's own reason.

        The registrar wraps the driver's error in ``server 'driver' could not load {...}``
        (the request as JSON); people get a :class:`~temoto.errors.DriverInitError`
        ``robot <r>, device <d>: could not start: <why>`` instead (a profile error stays one:
        exit 2).
        """
        inner: BaseException = err
        while isinstance(inner, ResourceLoadError) and inner.__cause__ is not None:
            inner = inner.__cause__
        if isinstance(inner, ConfigError):
            return inner
        text = f"{self._where(device)}: could not start: {device_text(device, str(inner))}"
        return DriverInitError(text)

    def on_unload(self, request: RobotRequest, response: RobotResponse) -> None:
        """Stop the robot's control loop (its drivers are released as dependencies)."""
        with self._lock:
            robot = self._robots.pop(response.robot, None)
        if robot is not None:
            robot.close()

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """After a restart from the catalog: the robot's control loop died with its process."""
        return Status.FATAL, _GONE

    def shutdown(self) -> None:
        """Close every robot and device still open (e.g. the registrar is closing)."""
        with self._lock:
            robots = list(self._robots.values())
            devices = list(self._devices.values())
            self._robots.clear()
            self._devices.clear()
        for robot in robots:
            robot.close()
        for device in devices:
            device.close()

    # ---- devices (called by the "driver" server) ---------------------------------------------

    def _open_device(self, request: DriverRequest, ctx: LoadContext) -> DriverResponse:
        if request.robot != self.profile.robot or request.device not in self.profile.devices:
            raise ResourceNotFoundError(f"robot '{request.robot}' has no device '{request.device}'")
        spec = self.profile.devices[request.device]
        cls = driver_class(spec.driver)
        where = f"{self.profile.source}: devices.{spec.name}"
        config: Mapping[str, Any] = spec.config
        sim: Simulator | None = None
        if self.profile.sim:
            own = config.get("sim")
            if own is None or isinstance(own, Mapping):  # the entry's own keys win
                level: dict[str, Any] = {"realism": self.realism.level.name}
                if self.seed is not None:
                    level["seed"] = self.seed
                config = {**config, "sim": {**level, **(own or {})}}
            sim, config = cls.simulate(spec.name, config, clock=self.clock)
            if isinstance(sim, _StreamsToGcs):
                for host, port in self.sim_gcs:
                    sim.add_gcs(host, port)
            sim.start()
        driver: Driver | None = None
        try:
            driver = cls.from_profile(spec.name, config, clock=self.clock, where=where)
            device = _Device(
                driver,
                sim,
                settings=dict(config) if sim is not None else None,
                resource_id=ctx.resource_id,
            )
            driver.configure()
            driver.activate()
            device.remove_listener = driver.add_health_listener(
                lambda health: self._on_health(device, health)
            )
        except BaseException:
            if driver is not None:
                driver.shutdown()
            if sim is not None:
                sim.close()
            raise
        with self._lock:
            self._devices[spec.name] = device
        return DriverResponse(spec.driver, spec.joints, sim is not None)

    def _close_device(self, request: DriverRequest) -> None:
        with self._lock:
            device = self._devices.pop(request.device, None)
        if device is not None:
            device.close()

    def make_safe(self, reason: str = "") -> list[str]:
        """Put every open device of this manager in its safe state now (``docs/safety.md``).

        All at once (:func:`~temoto.drivers.make_all_safe`): one thread per device, the
        confirmations awaited together for at most ``SAFE_ALL_WAIT`` seconds. Never raises.

        Args:
            reason: Why (for the log).

        Returns:
            One line per device, ``"<device>: <what was done>"`` (also for a device that could
            not be made safe or did not confirm in time: it says so, with the reason).
        """
        with self._lock:
            drivers = [d.driver for d in self._devices.values()]
        return [f"{d.name}: {what}" for d, what in make_all_safe(reason, drivers=drivers)]

    # ---- faults and their recovery -----------------------------------------------------------

    def _where(self, device: str) -> str:
        """``robot <name>, device <device>``: how statuses name a device."""
        return f"robot {self.profile.robot}, device {device}"

    def _status(self, device: _Device, status: Status, text: str) -> None:
        with contextlib.suppress(ResourceNotFoundError):  # released meanwhile
            self.registrar.send_status(
                device.resource_id,
                status,
                f"{self._where(device.name)}: {device_text(device.name, text)}",
            )

    def _on_health(self, device: _Device, health: Health) -> None:
        """A driver's report: a fault ends the device's goals, is told, starts the recovery.

        Every consumer is told (WARNING when the recovery will run, else FATAL). Runs on the
        driver's thread: the safe state and the recovery's tries (which may wait for the
        device) run on a thread of their own, ``temoto-recover-<device>``, one per fault; a
        fault while it runs (a failed try) is logged, not sent again.
        """
        if health.state is DriverState.FAULT:
            with device.cond:
                if device.closing:
                    return
                start = not device.recovering and not device.gave_up
                if start:
                    device.recovering = True
                    device.answered = False
                    device.thread = threading.Thread(
                        target=self._recover,
                        args=(device, health.message, health.error),
                        name=f"temoto-recover-{device.name}",
                        daemon=True,
                    )
            if start and device.thread is not None:  # once per fault: later reports are logged
                with self._lock:
                    robots = list(self._robots.values())
                why = device_text(device.name, health.message)
                error = ResourceBrokenError(f"{self._where(device.name)}: {why}")
                ended = [robot.device_faulted(device.name, error) for robot in robots]
                driver = device.driver
                # A fault the recovery will take on is a WARNING: the motions that command the
                # device ended above with its reason, the robot's other features go on, and an
                # action that needs the device while it is out fails at once (require()). FATAL
                # (every consumer of the robot fails) only when nothing will bring it back.
                comes_back = driver.recovery.enabled and not driver.needs_hands(health.error)
                status = Status.WARNING if comes_back and all(ended) else Status.FATAL
                self._status(device, status, health.message)
                device.thread.start()
        elif health.ok:
            with device.cond:
                if device.recovering:
                    device.answered = True
                    device.cond.notify_all()

    def _recover(self, device: _Device, reason: str, fault: BaseException | None) -> None:
        """Make a faulted device safe, then bring it back as its policy says (or give up)."""
        driver = device.driver
        policy = driver.recovery
        name = driver.name
        if device.closed():  # released before this thread ran: its shutdown made it safe
            with device.cond:
                device.recovering = False
            return
        try:
            what = driver.make_safe("fault")
        except Exception as err:
            logger.error("%s: not safe after its fault: %s", self._where(name), err)
        else:
            if what is not None:
                logger.warning("%s made safe after its fault: %s", self._where(name), what)
        hands = driver.needs_hands(fault)
        if not policy.enabled or hands:
            why = "recovery off" if not policy.enabled else f"not recovered automatically ({hands})"
            logger.warning(
                "%s: FAULT: %s; %s: it stays out of service until the robot is loaded again",
                self._where(name),
                device_text(name, reason),
                why,
            )
            with device.cond:
                device.gave_up = f"{why}: {device_text(name, reason)}"
                device.recovering = False
            return
        for attempt in range(1, policy.tries + 1):
            delay = policy.delay(attempt)
            with device.cond:
                device.note = f"recovery try {attempt}/{policy.tries} in {delay:g} s"
                deadline = self.clock.monotonic() + delay
                while not device.closing and not device.answered:
                    left = deadline - self.clock.monotonic()
                    if left <= 0:
                        break
                    self.clock.wait(device.cond, left)
                if device.closing:
                    device.recovering = False
                    return
                answered, device.answered = device.answered, False
                device.note = f"recovery try {attempt}/{policy.tries} running"
            logger.warning(
                "%s: recovery try %d/%d (%s): recover() and activate() (fault: %s)",
                self._where(name),
                attempt,
                policy.tries,
                "the device answers again" if answered else f"after {delay:g} s",
                device_text(name, reason),
            )
            error = ""
            try:
                if driver.state is DriverState.FAULT:
                    driver.recover()
                if driver.state is DriverState.INACTIVE and not device.closed():
                    driver.activate()
            except Exception as err:  # logged below; the next try comes after its wait
                error = str(err)
                hands = driver.needs_hands(err)
                if hands:  # the device reports a hardware error now: no more tries
                    gave_up = f"not recovered automatically ({hands}): {device_text(name, error)}"
                    self._give_up(device, gave_up)
                    return
            if device.closed():  # released meanwhile: its shutdown makes it safe
                with device.cond:
                    device.recovering = False
                return
            if driver.state is DriverState.ACTIVE:
                with device.cond:
                    device.recovering = False
                    device.note = ""
                logger.warning(
                    "%s: recovered on try %d/%d: active again",
                    self._where(name),
                    attempt,
                    policy.tries,
                )
                self._status(device, Status.OK, f"recovered on try {attempt}/{policy.tries}")
                return
            if driver.state is DriverState.FINALIZED:
                with device.cond:
                    device.recovering = False
                return
            reason = error or driver.health().message
            logger.warning(
                "%s: recovery try %d/%d failed: %s",
                self._where(name),
                attempt,
                policy.tries,
                device_text(name, reason),
            )
        self._give_up(device, f"gave up after {policy.tries} tries: {device_text(name, reason)}")

    def _give_up(self, device: _Device, gave_up: str) -> None:
        """The recovery ends without the device: say so loudly (log and consumers)."""
        with device.cond:
            device.gave_up = gave_up
            device.recovering = False
            device.note = ""
        logger.error("%s: %s; it stays out of service", self._where(device.name), gave_up)
        self._status(device, Status.FATAL, gave_up)

    def _annotate(self, health: Health) -> Health:
        """A device's health as the live view shows it: with its recovery's state."""
        with self._lock:
            device = self._devices.get(health.driver)
        if device is None:
            return health
        with device.cond:
            gave_up, note = device.gave_up, device.note
        if gave_up:  # out of service until loaded again, whatever the driver says now
            return replace(health, state=DriverState.FAULT, ok=False, message=gave_up)
        if note and not health.ok:
            return replace(health, message=f"{health.message} ({note})")
        return health


#: What the consumers of a robot or device restored from the catalog are told.
_GONE = (
    "the Robot Manager that drove it stopped (its drivers ran in that process); request the"
    " robot again to load it afresh"
)


class _DriverServer(ResourceServer[DriverRequest, DriverResponse]):
    """The ``"driver"`` server of a :class:`RobotManager`."""

    name: ClassVar[str] = "driver"
    request_type: ClassVar[type[Any]] = DriverRequest
    response_type: ClassVar[type[Any]] = DriverResponse

    def __init__(self, manager: RobotManager) -> None:
        self._manager = manager

    def on_load(self, request: DriverRequest, ctx: LoadContext) -> DriverResponse:
        """Open, configure and activate one device."""
        return self._manager._open_device(request, ctx)

    def on_unload(self, request: DriverRequest, response: DriverResponse) -> None:
        """Shut the device down (and its simulator)."""
        self._manager._close_device(request)

    def on_restore(self, resource: ResourceInfo) -> tuple[Status, str] | None:
        """After a restart from the catalog: the driver's threads died with its process."""
        return Status.FATAL, _GONE
