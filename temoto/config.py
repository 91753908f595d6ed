"""Hardware profiles: which robot this is, its devices, and the features built from them.

A profile is a YAML file (``hw_profiles/*.yaml``, schema in ``hw_profiles/README.md``)::

    robot: sim_rover            # the robot's name: the engine's actor and the fleet sender
    sim: true                   # start each device's simulator in-process (default false)
    devices:                    # name -> the driver and its settings (validated by the driver)
      base:
        driver: odrive_can
        ...
    features:                   # what the robot can do, built from the devices' joints
      navigation: {type: differential_drive, left_wheel: left, right_wheel: right,
                   wheel_radius: 0.1, wheel_separation: 0.5}
      manipulation: {type: arm, device: arm, poses: {home: {shoulder: 0.0}}}
      flight: {type: vehicle, device: quad}
    ros2:                       # optional: the robot's state on ROS 2 (docs/ros2.md)
      publish: {odom: 20, joint_states: 20, fix: 5, diagnostics: 1}   # Hz, 0: off
      cmd_vel: false            # true: geometry_msgs/Twist on /<robot>/cmd_vel drives the base

:func:`load_profile` reads and checks everything without touching hardware (drivers are
constructed, never configured); every problem is a :class:`~temoto.errors.ProfileError` whose
message names the file and the key path (``sim_rover.yaml: features.navigation.left_wheel:
no device has a joint 'left'``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import yaml

from temoto._files import read_regular_text
from temoto._yaml import safe_load_strict
from temoto.clock import Clock, MonotonicClock
from temoto.drivers import Actuator, Vehicle, driver_class
from temoto.drivers import profile as fields
from temoto.drivers.profile import Field, ProfileReader, custom, flag, integer, number, text
from temoto.errors import PluginError, ProfileError

__all__ = [
    "ArmFeature",
    "DeviceSpec",
    "DriveFeature",
    "FlightFeature",
    "Profile",
    "Ros2Settings",
    "load_profile",
    "parse_profile",
]

#: The keys of a profile document.
_TOP_FIELDS: Final[Mapping[str, Field[Any]]] = {
    "robot": fields.name(),
    "description": text("", empty=True),
    "sim": flag(False),
    "devices": custom(lambda p, value, key: value, {}),
    "features": custom(lambda p, value, key: value, {}),
    "ros2": custom(lambda p, value, key: value, None),
}
_DRIVER: Final = text(hint="name the driver (e.g. odrive_can, dynamixel)")
#: A device key read here, not by its driver: ``true`` accepts ``safe_state: hold`` on a device
#: whose own watchdog is off (the device then stays powered and holding after TeMoto dies).
HOLD_WITHOUT_WATCHDOG: Final = "hold_without_watchdog"

logger = logging.getLogger(__name__)
_POSITION: Final = number(low=None)  # a joint position in a pose (rad)


@dataclass(frozen=True, slots=True)
class DeviceSpec:
    """One device of a profile.

    Attributes:
        name: The device's name.
        driver: The driver's registry name.
        config: The device's settings as written (the driver validated them).
        joints: The joints it moves (empty for a vehicle).
        vehicle: Whether it is a vehicle.
        limits: (min, max) position (rad) of the joints whose driver declares limits (its
            ``joint_limits`` mapping); named poses are checked against them.
        velocity_limits: The largest speed (rad/s) of the joints whose driver declares one (its
            ``joint_velocity_limits`` mapping); navigation speeds are checked against them.
    """

    name: str
    driver: str
    config: Mapping[str, Any]
    joints: tuple[str, ...]
    vehicle: bool
    limits: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    velocity_limits: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class DriveFeature:
    """A differential-drive base from two wheel joints.

    Attributes:
        left_wheel: The left wheel's joint.
        right_wheel: The right wheel's joint.
        wheel_radius: Metres.
        wheel_separation: Metres between the wheels' contact points.
        max_speed: m/s.
        max_turn_rate: rad/s.
        tolerance: Metres within which a goal counts as reached.
    """

    left_wheel: str
    right_wheel: str
    wheel_radius: float
    wheel_separation: float
    max_speed: float = 0.5
    max_turn_rate: float = 1.5
    tolerance: float = 0.05


@dataclass(frozen=True, slots=True)
class ArmFeature:
    """An arm from the joints of one device.

    Attributes:
        device: The device.
        joints: Its joints, in order.
        poses: Named joint positions (rad).
        tolerance: Radians within which a joint counts as arrived.
    """

    device: str
    joints: tuple[str, ...]
    poses: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    tolerance: float = 0.02


@dataclass(frozen=True, slots=True)
class FlightFeature:
    """A vehicle that flies.

    Attributes:
        device: The vehicle device.
        tolerance: Metres within which a position counts as reached.
    """

    device: str
    tolerance: float = 1.0


@dataclass(frozen=True, slots=True)
class Ros2Settings:
    """The robot's state on ROS 2 (the profile's ``ros2:`` block, ``docs/ros2.md``).

    Attributes:
        rates: Topic (``odom``, ``joint_states``, ``fix``, ``diagnostics``) -> Hz; only those
            published (a rate of 0 in the file leaves the topic out).
        cmd_vel: Whether ``geometry_msgs/Twist`` on ``/<robot>/cmd_vel`` drives the base.
        cmd_vel_timeout: Seconds without a new ``cmd_vel`` after which the base is stopped.
        domain_id: The ``ROS_DOMAIN_ID`` (-1: the environment's).
        frame_prefix: Put before the frame ids ``odom`` and ``base_link``.
    """

    rates: Mapping[str, float]
    cmd_vel: bool = False
    cmd_vel_timeout: float = 0.5
    domain_id: int = -1
    frame_prefix: str = ""


@dataclass(frozen=True, slots=True)
class Profile:
    """A checked hardware profile.

    Attributes:
        robot: The robot's name.
        description: Free text.
        sim: Whether the simulators run in-process.
        devices: The devices by name, in file order.
        navigation: The drive feature, if any.
        manipulation: The arm feature, if any.
        flight: The flight feature, if any.
        source: The file it came from.
        ros2: The ``ros2:`` block, if any.
    """

    robot: str
    description: str
    sim: bool
    devices: Mapping[str, DeviceSpec]
    navigation: DriveFeature | None = None
    manipulation: ArmFeature | None = None
    flight: FlightFeature | None = None
    source: str = ""
    ros2: Ros2Settings | None = None

    @property
    def features(self) -> tuple[str, ...]:
        """The names of the features it has."""
        named = (
            ("navigation", self.navigation),
            ("manipulation", self.manipulation),
            ("flight", self.flight),
        )
        return tuple(n for n, f in named if f is not None)

    def joint_device(self, joint: str) -> str:
        """The device that moves ``joint``.

        Raises:
            KeyError: No device has it.
        """
        for spec in self.devices.values():
            if joint in spec.joints:
                return spec.name
        raise KeyError(joint)


def load_profile(path: str | Path, *, clock: Clock | None = None) -> Profile:
    """Read and check a profile file.

    Args:
        path: The YAML file.
        clock: Passed to the drivers that check their settings.

    Returns:
        The profile.

    Raises:
        ProfileError: The file cannot be read, is not YAML, or is not a valid profile. A YAML
            syntax error is one line: ``<file>:<line>:<column>: not valid YAML: <problem>``
            (line and column counted from 1).
    """
    file = str(path)
    try:
        text = read_regular_text(path)
    except OSError as err:
        raise ProfileError(f"cannot read: {err.strerror or err}", file=file) from None
    try:
        raw = safe_load_strict(text)
    except yaml.YAMLError as err:
        raise _yaml_error(err, file) from None
    return parse_profile(raw, file=file, clock=clock)


def _yaml_error(err: yaml.YAMLError, file: str) -> ProfileError:
    """One line naming the file, line and column of a YAML error."""
    mark = getattr(err, "problem_mark", None)
    where = file if mark is None else f"{file}:{mark.line + 1}:{mark.column + 1}"
    problem = getattr(err, "problem", None)
    context = getattr(err, "context", None)
    what = str(err) if not problem else f"{context}: {problem}" if context else str(problem)
    return ProfileError(f"not valid YAML: {' '.join(what.split())}", file=where)


def parse_profile(raw: object, *, file: str = "", clock: Clock | None = None) -> Profile:
    """Check a decoded profile document.

    Args:
        raw: The document (a mapping).
        file: Where it came from (for messages).
        clock: Passed to the drivers that check their settings.

    Returns:
        The profile.

    Raises:
        ProfileError: Anything is wrong (the message names the key path).
    """
    p = ProfileReader(file=file or None)
    doc = p.mapping(raw)
    top = p.fields(doc, _TOP_FIELDS)
    robot, description, sim = top["robot"], top["description"], top["sim"]
    devices = _devices(p, top["devices"], clock or MonotonicClock())
    features = p.mapping(top["features"], "features")
    p.known(features, ("navigation", "manipulation", "flight"), "features")
    nav = arm = flight = None
    if "navigation" in features:
        nav = _drive(p, features["navigation"], devices)
    if "manipulation" in features:
        arm = _arm(p, features["manipulation"], devices)
    if "flight" in features:
        flight = _flight(p, features["flight"], devices)
    ros2 = None
    if top["ros2"] is not None:
        ros2 = _ros2(p, top["ros2"], devices, nav, flight)
    return Profile(robot, description, sim, devices, nav, arm, flight, file, ros2)


#: What the ``ros2:`` block publishes when it has no ``publish`` key (Hz; each only where the
#: robot has it).
ROS2_DEFAULT_RATES: Final[Mapping[str, float]] = {
    "odom": 20.0,
    "joint_states": 20.0,
    "fix": 5.0,
    "diagnostics": 1.0,
}


def _ros2(
    p: ProfileReader,
    raw: object,
    devices: Mapping[str, DeviceSpec],
    nav: DriveFeature | None,
    flight: FlightFeature | None,
) -> Ros2Settings:
    path = "ros2"
    cfg = p.mapping(raw, path)
    keys = ("publish", "cmd_vel", "cmd_vel_timeout", "domain_id", "frame_prefix")
    p.known(cfg, keys, path)
    has = {
        "odom": nav is not None,
        "joint_states": any(spec.joints for spec in devices.values()),
        "fix": flight is not None,
        "diagnostics": True,
    }
    why = {
        "odom": "the robot has no navigation feature",
        "joint_states": "no device of the robot has joints",
        "fix": "the robot has no flight feature",
    }
    rates: dict[str, float] = {}
    if cfg.get("publish") is None:
        rates = {k: v for k, v in ROS2_DEFAULT_RATES.items() if has[k]}
    else:
        given = p.mapping(cfg["publish"], f"{path}.publish")
        p.known(given, tuple(ROS2_DEFAULT_RATES), f"{path}.publish")
        for topic in given:
            rate = p.field(
                given,
                topic,
                number(0.0, low=0.0, low_open=False, high=1000.0, unit="Hz"),
                f"{path}.publish",
            )
            if rate > 0 and not has[topic]:
                p.fail(f"{path}.publish.{topic}", why[topic])
            if rate > 0:
                rates[topic] = rate
    cmd_vel = p.field(cfg, "cmd_vel", flag(False), path)
    if cmd_vel and nav is None:
        p.fail(f"{path}.cmd_vel", "the robot has no navigation feature to drive")
    timeout = p.field(cfg, "cmd_vel_timeout", number(0.5, high=10.0, unit="s"), path)
    domain = p.field(cfg, "domain_id", integer(-1, low=0, high=232), path)
    prefix = p.field(cfg, "frame_prefix", text("", empty=True), path)
    return Ros2Settings(rates, cmd_vel, timeout, domain, prefix)


def _devices(p: ProfileReader, raw: object, clock: Clock) -> dict[str, DeviceSpec]:
    devices = p.mapping(raw, "devices")
    out: dict[str, DeviceSpec] = {}
    owner: dict[str, str] = {}
    for name, value in devices.items():
        path = f"devices.{name}"
        p.name(name, path)
        config = p.mapping(value, path)
        kind = p.field(config, "driver", _DRIVER, path)
        try:
            cls = driver_class(kind)
        except PluginError as err:
            raise p.error(f"{path}.driver", str(err)) from err
        if "safe_state" in config and config["safe_state"] is None:
            p.fail(
                f"{path}.safe_state",
                f"is null: write one of {', '.join(cls.safe_states)}, or leave the key out for"
                f" the default ({cls.safe_states[0]})",
            )
        unwatched = p.field(config, HOLD_WITHOUT_WATCHDOG, flag(False), path)
        skip = {"driver", HOLD_WITHOUT_WATCHDOG}
        settings = {k: v for k, v in config.items() if k not in skip}
        where = f"{p.file}: {path}" if p.file else path
        driver = cls.from_profile(name, settings, clock=clock, where=where)
        try:
            joints = tuple(driver.joint_names) if isinstance(driver, Actuator) else ()
            limits = dict(getattr(driver, "joint_limits", {}))
            speeds = dict(getattr(driver, "joint_velocity_limits", {}))
            watchdog = getattr(driver, "device_watchdog", None)
            safe_state = driver.safe_state
        finally:
            driver.shutdown()  # never configured: nothing to close, but it is finished
        if safe_state == "hold" and watchdog is not None and not watchdog > 0:
            if not unwatched:
                p.fail(
                    f"{path}.safe_state",
                    "hold needs the device's own watchdog (it is off here): if TeMoto dies,"
                    " the device stays powered on its last set-point; switch the watchdog on"
                    " (dynamixel: bus_watchdog; odrive_can: watchdog_timeout), or set"
                    f" {HOLD_WITHOUT_WATCHDOG}: true to accept that",
                )
            logger.warning(
                "%s.safe_state: hold without the device's watchdog (%s: true)",
                where,
                HOLD_WITHOUT_WATCHDOG,
            )
        for joint in joints:
            if joint in owner:
                p.fail(path, f"joint '{joint}' is also on device '{owner[joint]}'")
            owner[joint] = name
        vehicle = isinstance(driver, Vehicle)
        out[name] = DeviceSpec(name, kind, settings, joints, vehicle, limits, speeds)
    return out


def _joint(p: ProfileReader, value: object, path: str, devices: Mapping[str, DeviceSpec]) -> str:
    if not isinstance(value, str) or not any(value in d.joints for d in devices.values()):
        known = sorted(j for d in devices.values() for j in d.joints)
        p.fail(path, f"no device has a joint {value!r} (joints: {', '.join(known) or 'none'})")
    return str(value)


def _device(
    p: ProfileReader, value: object, path: str, devices: Mapping[str, DeviceSpec]
) -> DeviceSpec:
    if not isinstance(value, str) or value not in devices:
        p.fail(path, f"no device {value!r} (devices: {', '.join(devices) or 'none'})")
    return devices[str(value)]


def _drive(p: ProfileReader, raw: object, devices: Mapping[str, DeviceSpec]) -> DriveFeature:
    path = "features.navigation"
    cfg = p.mapping(raw, path)
    keys = {"type", "left_wheel", "right_wheel", "wheel_radius", "wheel_separation"}
    keys |= {"max_speed", "max_turn_rate", "tolerance"}
    p.known(cfg, frozenset(keys), path)
    if cfg.get("type") != "differential_drive":
        p.fail(f"{path}.type", "must be differential_drive")
    left = _joint(p, cfg.get("left_wheel"), f"{path}.left_wheel", devices)
    right = _joint(p, cfg.get("right_wheel"), f"{path}.right_wheel", devices)
    if left == right:
        p.fail(f"{path}.right_wheel", "must differ from left_wheel")
    feature = DriveFeature(
        left,
        right,
        p.field(cfg, "wheel_radius", number(), path),
        p.field(cfg, "wheel_separation", number(), path),
        p.field(cfg, "max_speed", number(0.5), path),
        p.field(cfg, "max_turn_rate", number(1.5), path),
        p.field(cfg, "tolerance", number(0.05), path),
    )
    _check_wheel_speeds(p, feature, devices, path)
    return feature


def _check_wheel_speeds(
    p: ProfileReader, f: DriveFeature, devices: Mapping[str, DeviceSpec], path: str
) -> None:
    """Refuse navigation speeds the wheels' velocity limits cannot give.

    A wheel turning at ``w`` rad/s moves its side at ``w x wheel_radius`` m/s; the controller
    drives at up to ``max_speed`` while it steers at up to ``max_turn_rate`` (the outer wheel
    then needs ``max_speed + max_turn_rate x wheel_separation / 2``). A command beyond a
    wheel's limit is refused by its driver, and the motion never ends.

    Raises:
        ProfileError: ``max_speed`` or ``max_turn_rate`` beyond the slower wheel's limit.
    """
    limits: list[tuple[float, str]] = []
    for joint in (f.left_wheel, f.right_wheel):
        for spec in devices.values():
            limit = spec.velocity_limits.get(joint, math.inf)
            if joint in spec.joints and math.isfinite(limit):
                limits.append((limit, f"devices.{spec.name} joint {joint}"))
    if not limits:
        return
    wheel, source = min(limits)
    top = wheel * f.wheel_radius
    half = f.wheel_separation / 2
    said = f"{wheel:g} rad/s x wheel_radius {f.wheel_radius:g} m = {top:.3g} m/s ({source})"
    if f.max_speed > top:
        p.fail(f"{path}.max_speed", f"{f.max_speed:g} m/s is beyond the wheels' {said}")
    if f.max_turn_rate * half > top:
        p.fail(
            f"{path}.max_turn_rate",
            f"{f.max_turn_rate:g} rad/s needs {f.max_turn_rate * half:.3g} m/s at each wheel,"
            f" beyond the wheels' {said}",
        )
    if f.max_speed + f.max_turn_rate * half > top:
        p.fail(
            f"{path}.max_speed",
            f"{f.max_speed:g} m/s while turning at max_turn_rate {f.max_turn_rate:g} rad/s needs"
            f" {f.max_speed + f.max_turn_rate * half:.3g} m/s at the outer wheel, beyond the"
            f" wheels' {said}",
        )


def _arm(p: ProfileReader, raw: object, devices: Mapping[str, DeviceSpec]) -> ArmFeature:
    path = "features.manipulation"
    cfg = p.mapping(raw, path)
    p.known(cfg, frozenset({"type", "device", "joints", "poses", "tolerance"}), path)
    if cfg.get("type") != "arm":
        p.fail(f"{path}.type", "must be arm")
    device = _device(p, cfg.get("device"), f"{path}.device", devices)
    joints = cfg.get("joints", list(device.joints))
    if not isinstance(joints, list) or not joints:
        p.fail(f"{path}.joints", "must be a non-empty list of the device's joints")
    for i, joint in enumerate(joints):
        if joint not in device.joints:
            p.fail(f"{path}.joints[{i}]", f"device '{device.name}' has no joint {joint!r}")
    poses: dict[str, dict[str, float]] = {}
    for pose, values in p.mapping(cfg.get("poses", {}), f"{path}.poses").items():
        where = f"{path}.poses.{pose}"
        p.name(pose, where)
        table: dict[str, float] = {}
        given = p.mapping(values, where)
        for joint in given:
            if joint not in joints:
                p.fail(f"{where}.{joint}", f"not a joint of the arm ({', '.join(joints)})")
            table[joint] = position = p.field(given, joint, _POSITION, where)
            if joint in device.limits:
                low, high = device.limits[joint]
                if not low <= position <= high:
                    p.fail(
                        f"{where}.{joint}",
                        f"{position:g} rad is outside the joint's limits"
                        f" [{low:.4g}, {high:.4g}] (devices.{device.name})",
                    )
        poses[pose] = table
    tolerance = p.field(cfg, "tolerance", number(0.02), path)
    return ArmFeature(device.name, tuple(joints), poses, tolerance)


def _flight(p: ProfileReader, raw: object, devices: Mapping[str, DeviceSpec]) -> FlightFeature:
    path = "features.flight"
    cfg = p.mapping(raw, path)
    p.known(cfg, frozenset({"type", "device", "tolerance"}), path)
    if cfg.get("type") != "vehicle":
        p.fail(f"{path}.type", "must be vehicle")
    device = _device(p, cfg.get("device"), f"{path}.device", devices)
    if not device.vehicle:
        p.fail(f"{path}.device", f"device '{device.name}' ({device.driver}) is not a vehicle")
    return FlightFeature(device.name, p.field(cfg, "tolerance", number(1.0), path))
