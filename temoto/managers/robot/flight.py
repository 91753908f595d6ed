"""The flight feature: :class:`FlightController` (stop, hold and modes: see :mod:`.features`)."""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from temoto.config import FlightFeature
from temoto.drivers import GeoPoint, MissionItem, MissionVehicle, Vehicle
from temoto.errors import StateError
from temoto.managers.robot.motion import Motion

__all__ = ["FlightController"]

logger = logging.getLogger(__name__)

_EARTH_RADIUS = 6_371_000.0  # m


def _distance(a: GeoPoint, b: GeoPoint) -> float:
    """Metres between two points (haversine over the ground, plus the altitude difference)."""
    p1, p2 = math.radians(a.lat), math.radians(b.lat)
    dp, dl = p2 - p1, math.radians(b.lon - a.lon)
    h = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    ground = 2 * _EARTH_RADIUS * math.asin(min(1.0, math.sqrt(h)))
    return math.hypot(ground, b.alt - a.alt)


class FlightController:
    """A flying vehicle: take off, fly to, land, fly a mission; arrival checked on every step.

    A held motion makes the vehicle LOITER; resumed, it goes on in GUIDED (a mission: in AUTO,
    from the item it was at). A motion cancelled (a stopped graph, a missed deadline) leaves
    the vehicle in LOITER, holding where it is, not flying on (or the rest of a mission) on its
    own. A mode the controller did not command (a failsafe's RTL or LAND, a pilot's switch)
    ends the motion with an error naming it, and the vehicle is left in that mode.

    Args:
        feature: The profile's flight settings.
        vehicle: The vehicle driver.
    """

    #: Altitude (m) below which a landing vehicle counts as down.
    LANDED_ALT = 0.3
    #: The mode a stop or a hold sets: ArduCopter LOITER brakes to a stop and holds the
    #: position (BRAKE holds too, but the vehicle cannot be sent on from it by GUIDED commands
    #: without a mode change either; LOITER is what ``safe_state: loiter`` uses).
    HOLD_MODE = "LOITER"
    #: ArduCopter's defaults (cm/s) when the vehicle cannot tell its own (copter.ardupilot.org
    #: parameter list: WPNAV_SPEED 1000, WPNAV_SPEED_UP 250, WPNAV_SPEED_DN 150, LAND_SPEED 50,
    #: LAND_ALT_LOW 1000 cm).
    DEFAULT_SPEEDS: Mapping[str, float] = {
        "WPNAV_SPEED": 1000.0,
        "WPNAV_SPEED_UP": 250.0,
        "WPNAV_SPEED_DN": 150.0,
        "LAND_SPEED": 50.0,
        "LAND_ALT_LOW": 1000.0,
    }

    def __init__(self, feature: FlightFeature, vehicle: Vehicle) -> None:
        self.feature = feature
        self._vehicle = vehicle
        self._lock = threading.Lock()
        self._motion: Motion | None = None
        self._check: Callable[[Any], bool] | None = None
        self._resend: Callable[[], None] | None = None
        self._resume_mode = "GUIDED"
        self._describe: Callable[[Any], str] | None = None
        self._modes: frozenset[str] = frozenset()  # the modes this motion commands
        self._seen_mode = ""  # the mode the telemetry showed at the last step
        #: Modes a stop, hold or resume asked for that the telemetry has not shown since (by
        #: count: a mode asked twice is owed two changes into it).
        self._asked: dict[str, int] = {}
        self._speeds: dict[str, float] | None = None

    def telemetry(self) -> Any:
        """The vehicle's newest telemetry."""
        return self._vehicle.telemetry()

    # ---- estimates --------------------------------------------------------------------------

    def speeds(self) -> Mapping[str, float]:
        """The vehicle's navigation speeds (m/s; ``LAND_ALT_LOW`` in m), read once.

        Read from the vehicle's parameters when it has them (``get_param``), else
        :attr:`DEFAULT_SPEEDS`; after one parameter that could not be read, the others are not
        asked for (a vehicle that does not answer would hold up the first flight action for
        every parameter's timeout).
        """
        if self._speeds is None:
            get = getattr(self._vehicle, "get_param", None)
            speeds: dict[str, float] = {}
            for name, default in self.DEFAULT_SPEEDS.items():
                value = default
                if get is not None:
                    try:
                        value = float(get(name))
                    except Exception as err:
                        logger.info("flight: %s not read (%s); ArduCopter's defaults", name, err)
                        get = None
                speeds[name] = max(value, 10.0) / 100.0
            self._speeds = speeds
        return self._speeds

    def estimate_takeoff(self, altitude: float) -> float:
        """Seconds to climb from here to ``altitude`` m at ``WPNAV_SPEED_UP``."""
        alt = float(self.telemetry().position.alt)
        return max(0.0, altitude - max(alt, 0.0)) / self.speeds()["WPNAV_SPEED_UP"]

    def estimate_fly_to(self, target: GeoPoint) -> float:
        """Seconds to fly from here to ``target`` (horizontal and vertical legs together)."""
        return self._leg(self.telemetry().position, target, self.speeds()["WPNAV_SPEED"])

    def estimate_land(self) -> float:
        """Seconds to land from here: WPNAV_SPEED_DN above LAND_ALT_LOW, LAND_SPEED below."""
        return self._descent(self.telemetry().position.alt)

    def estimate_mission(self, items: Sequence[MissionItem]) -> float:
        """Seconds to fly a mission from here: every leg, hold and landing in turn."""
        s = self.speeds()
        here = self.telemetry().position
        speed = s["WPNAV_SPEED"]
        total = 0.0
        for item in items:
            if item.kind == "speed" and item.speed > 0:
                speed = item.speed
            elif item.kind == "takeoff" and item.alt is not None:
                total += max(0.0, item.alt - here.alt) / s["WPNAV_SPEED_UP"]
                here = GeoPoint(here.lat, here.lon, max(here.alt, item.alt))
            elif item.kind in ("waypoint", "loiter_time"):
                lat = here.lat if item.lat is None else item.lat
                lon = here.lon if item.lon is None else item.lon
                there = GeoPoint(lat, lon, here.alt if item.alt is None else item.alt)
                total += self._leg(here, there, speed) + item.seconds
                here = there
            elif item.kind == "land":
                if item.lat is not None and item.lon is not None:
                    there = GeoPoint(item.lat, item.lon, here.alt)
                    total += self._leg(here, there, speed)
                total += self._descent(here.alt)
            elif item.kind == "rtl":
                home = getattr(self._vehicle, "home", lambda: None)()
                if home is not None:
                    total += self._leg(here, GeoPoint(home.lat, home.lon, here.alt), speed)
                total += self._descent(here.alt)
        return total

    def _leg(self, a: GeoPoint, b: GeoPoint, speed: float) -> float:
        s = self.speeds()
        ground = _distance(GeoPoint(a.lat, a.lon, 0.0), GeoPoint(b.lat, b.lon, 0.0))
        climb = b.alt - a.alt
        vertical = climb / s["WPNAV_SPEED_UP"] if climb > 0 else -climb / s["WPNAV_SPEED_DN"]
        return max(ground / speed, vertical)

    def _descent(self, alt: float) -> float:
        s = self.speeds()
        low = s["LAND_ALT_LOW"]
        return max(0.0, alt - low) / s["WPNAV_SPEED_DN"] + min(max(alt, 0.0), low) / s["LAND_SPEED"]

    # ---- verbs ------------------------------------------------------------------------------

    def takeoff(self, altitude: float, mode: str = "GUIDED") -> Motion:
        """Switch to ``mode``, arm and climb to ``altitude`` m above home.

        Raises:
            ValueError: ``altitude`` is not positive.
            DriverError: The vehicle refused (MavlinkCommandError) or did not answer.
        """
        if not (math.isfinite(altitude) and altitude > 0):
            raise ValueError(f"a take-off altitude must be positive, got {altitude}")
        seen = self._vehicle.telemetry().mode
        self._vehicle.set_mode(mode)
        if not self._vehicle.telemetry().armed:
            self._vehicle.arm()
        self._vehicle.takeoff(altitude)
        target = altitude - self.feature.tolerance
        return self._start(
            f"take off to {altitude:g} m",
            lambda t: t.position.alt >= target,
            lambda: self._vehicle.takeoff(altitude),
            modes={mode},
            seen=seen,
            resume_mode=mode,
        )

    def fly_to(self, target: GeoPoint) -> Motion:
        """Fly to a position.

        Raises:
            DriverError: The vehicle refused or did not answer.
        """
        seen = self._vehicle.telemetry().mode
        self._vehicle.goto(target)
        tol = self.feature.tolerance
        return self._start(
            f"fly to ({target.lat:.6f}, {target.lon:.6f}, {target.alt:g} m)",
            lambda t: _distance(t.position, target) <= tol,
            lambda: self._vehicle.goto(target),
            modes={"GUIDED"},
            seen=seen,
        )

    def land(self) -> Motion:
        """Land where it is.

        Raises:
            DriverError: The vehicle refused or did not answer.
        """
        seen = self._vehicle.telemetry().mode
        self._vehicle.land()
        return self._start(
            "land",
            lambda t: t.position.alt <= self.LANDED_ALT,
            self._vehicle.land,
            modes={"LAND"},
            seen=seen,
            resume_mode="LAND",
        )

    def fly_mission(self, items: Sequence[MissionItem]) -> Motion:
        """Upload a mission, start it (arming and taking off as the vehicle needs) and follow it.

        The motion is reached when the vehicle reports its last item done (a mission that ends
        with ``land`` or ``rtl``: also down, within :attr:`LANDED_ALT`); its progress says
        ``item 2/5 (waypoint), alt 9.8 m``. Cancelled (stopped, timed out), it sets the vehicle
        to LOITER before :meth:`Motion.cancel` returns.

        Args:
            items: The mission.

        Raises:
            StateError: The vehicle cannot fly missions.
            ValueError: No items.
            DriverError: The vehicle refused the mission or its start, or did not answer.
        """
        vehicle = self._vehicle
        if not isinstance(vehicle, MissionVehicle):
            raise StateError(
                f"the flight feature's vehicle ({type(vehicle).__name__}) cannot fly missions"
            )
        mission = list(items)
        if not mission:
            raise ValueError("a mission needs at least one item")
        seen = vehicle.telemetry().mode
        vehicle.upload_mission(mission)
        vehicle.start_mission()
        total = len(mission)
        lands = mission[-1].kind in ("land", "rtl")

        def done(telemetry: Any) -> bool:
            progress = vehicle.mission_progress
            down = telemetry.position.alt <= self.LANDED_ALT
            if lands and progress.current >= total and down and not telemetry.armed:
                return True  # landed at the end and disarmed, as ArduCopter does
            return progress.finished and (not lands or down)

        def describe(telemetry: Any) -> str:
            at = vehicle.mission_progress.current
            kind = f" ({mission[at - 1].kind})" if 1 <= at <= total else ""
            return f"item {at}/{total}{kind}, alt {telemetry.position.alt:.1f} m"

        return self._start(
            f"fly a mission of {total} items",
            done,
            None,
            resume_mode="AUTO",
            describe=describe,
            modes={"GUIDED", "AUTO"},  # start_mission arms in GUIDED, then AUTO
            seen=seen,
        )

    def _start(
        self,
        what: str,
        check: Callable[[Any], bool],
        resend: Callable[[], None] | None,
        *,
        modes: set[str],
        seen: str,
        resume_mode: str = "GUIDED",
        describe: Callable[[Any], str] | None = None,
    ) -> Motion:
        motion = Motion(what, self)
        with self._lock:
            old, self._motion, self._check, self._resend = self._motion, motion, check, resend
            self._resume_mode, self._describe = resume_mode, describe
            self._modes = frozenset(modes | {resume_mode})
            self._seen_mode = seen
            if self._asked.get(seen):  # shown while no motion was stepped: no longer owed
                self._asked[seen] -= 1
        if old is not None:
            old.supersede()
        return motion

    # ---- stop, hold, resume (on the caller's thread, under the lock) ------------------------

    def _ask(self, mode: str) -> None:
        """Lock held: note that ``mode`` is asked for, before it is (see :meth:`step`).

        Kept across motions: the LOITER of a stop may show after the next motion started.
        No change is owed when the vehicle shows that mode already and no other asked change
        is still to show (it stays in it), so nothing is owed for ever.
        """
        if not any(self._asked.values()):
            try:
                if str(self._vehicle.telemetry().mode) == mode:
                    return
            except Exception as err:  # no telemetry yet: owe it
                logger.debug("flight: no telemetry for the mode asked: %s", err)
        self._asked[mode] = self._asked.get(mode, 0) + 1

    def _loiter(self, motion: Motion, why: str) -> None:
        """Lock held: the vehicle LOITERs (the acknowledgement awaited).

        Noted as asked even when the acknowledgement does not come: the vehicle may have
        switched all the same, and its LOITER is then still this controller's.
        """
        self._ask(self.HOLD_MODE)
        try:
            self._vehicle.set_mode(self.HOLD_MODE)
        except Exception as err:
            logger.warning("%s: %s: %s refused: %s", motion.what, why, self.HOLD_MODE, err)
        else:
            logger.info("%s: %s: vehicle %s", motion.what, why, self.HOLD_MODE)

    def _switched(self, mode: str) -> StateError:
        """The error for a change into ``mode`` that this controller did not ask for.

        The vehicle's own (a failsafe, a pilot) unless its driver says it asked for that mode
        itself (the safe state it sent after a fault, e.g. LOITER or BRAKE): that is not the
        vehicle's own switch, and the error says so.
        """
        name = getattr(self._vehicle, "name", "vehicle")
        change = getattr(self._vehicle, "last_mode_change", None)
        if change is not None and change.new == mode and change.commanded:
            return StateError(
                f"{name}: the vehicle was switched to {mode} by its driver (its safe state),"
                " not by this flight"
            )
        return StateError(f"{name}: the vehicle switched to {mode} (not commanded)")

    def _halt(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is not motion:
                return
            self._motion = None
            self._loiter(motion, "stopped")

    def _hold(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is motion:
                self._loiter(motion, "held")

    def _resume(self, motion: Motion) -> None:
        with self._lock:
            if self._motion is not motion:
                return
            self._ask(self._resume_mode)
            try:
                self._vehicle.set_mode(self._resume_mode)
                if self._resend is not None:
                    self._resend()
            except Exception as err:  # a refused mode change ends the motion with the reason
                self._motion = None
                error: BaseException = err
            else:
                return
        motion.finish(error)

    def step(self, dt: float) -> None:
        """Control thread: check arrival and the vehicle's mode.

        Never waits for a stop, hold or resume that is talking to the vehicle (it holds the
        lock while the mode change is acknowledged): that step is skipped, so the robot's other
        features are still stepped.

        A mode is judged when the telemetry shows a change into it: the vehicle's own (the
        motion ends with an error naming it) unless this motion commands it, or a hold
        holds in it, or a stop, hold or resume asked for it and that change was still owed.
        The telemetry's mode comes from the HEARTBEAT, up to a period after the vehicle
        acknowledged a mode (and read here before the lock is taken, so a pause or resume may
        come between the reading and the check): a hold's LOITER may show only after the
        resume was acknowledged, and is still commanded. Only changes are judged, so a reading
        from before an ask cannot use it up.
        """
        if not self._lock.acquire(blocking=False):
            return
        try:
            motion, check = self._motion, self._check
            describe = self._describe
            if motion is not None and motion.done:
                self._motion = None
                return
        finally:
            self._lock.release()
        if motion is None or check is None:
            return
        telemetry = self._vehicle.telemetry()
        error: StateError | None = None
        if not self._lock.acquire(blocking=False):
            return
        try:
            if self._motion is not motion:
                return
            mode = str(telemetry.mode)
            if mode and mode != self._seen_mode:
                self._seen_mode = mode
                owed = self._asked.get(mode, 0)
                if owed:
                    self._asked[mode] = owed - 1  # the change a stop, hold or resume asked for
                elif mode not in self._modes and not (motion.held and mode == self.HOLD_MODE):
                    self._motion = None
                    error = self._switched(mode)
            reached = error is None and not motion.held and check(telemetry)
            if reached:
                self._motion = None
        finally:
            self._lock.release()
        if error is not None:
            logger.warning("%s: %s", motion.what, error)
            motion.finish(error)
            return
        motion.progress = (
            describe(telemetry) if describe is not None else f"alt {telemetry.position.alt:.1f} m"
        )
        if reached:
            motion.finish()
