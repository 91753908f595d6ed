"""Hardware profiles: every shipped profile loads; bad ones fail naming the file and key path."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from temoto.config import load_profile, parse_profile
from temoto.errors import ProfileError

ROOT = Path(__file__).resolve().parents[1]
PROFILES = sorted((ROOT / "hw_profiles").glob("*.yaml"))
ARM = yaml.safe_load((ROOT / "hw_profiles" / "sim_arm.yaml").read_text())


@pytest.mark.parametrize("path", PROFILES, ids=[p.stem for p in PROFILES])
def test_every_shipped_profile_loads(path: Path) -> None:
    profile = load_profile(path)
    assert profile.robot
    assert profile.devices
    assert profile.features


def variant(**changes: Any) -> dict[str, Any]:
    doc: dict[str, Any] = yaml.safe_load(yaml.safe_dump(ARM))
    for dotted, value in changes.items():
        *parents, last = dotted.split("__")
        node = doc
        for part in parents:
            node = node[int(part)] if isinstance(node, list) else node[part]
        if value is ...:
            del node[last]
        else:
            node[last] = value
    return doc


@pytest.mark.parametrize(
    ("changes", "where", "what"),
    [
        ({"robot": ""}, "robot", "must be a name"),
        ({"colour": "red"}, "colour", "unknown key"),
        ({"sim": "yes"}, "sim", "true or false"),
        ({"devices__arm__driver": "warp_drive"}, "devices.arm.driver", "no driver named"),
        ({"devices__arm__driver": ...}, "devices.arm.driver", "missing"),
        ({"devices__arm__servos__1__id": 1}, "devices.arm.servos", "1"),
        ({"features__manipulation__device": "leg"}, "features.manipulation.device", "no device"),
        ({"features__manipulation__type": "leg"}, "features.manipulation.type", "must be arm"),
        ({"features__manipulation__poses__home__knee": 0.1}, "poses.home.knee", "not a joint"),
        ({"features__manipulation__tolerance": -1}, "tolerance", "positive"),
        ({"features__flight": {"type": "vehicle", "device": "arm"}}, "flight.device", "vehicle"),
        (
            {
                "features__navigation": {
                    "type": "differential_drive",
                    "left_wheel": "elbow",
                    "right_wheel": "nope",
                    "wheel_radius": 0.1,
                    "wheel_separation": 0.4,
                }
            },
            "navigation.right_wheel",
            "no device has a joint 'nope'",
        ),
    ],
)
def test_bad_profiles_name_the_key(changes: dict[str, Any], where: str, what: str) -> None:
    with pytest.raises(ProfileError) as err:
        parse_profile(variant(**changes), file="arm.yaml")
    message = str(err.value)
    assert message.startswith("arm.yaml: "), message
    assert where in message, message
    assert what in message, message


def test_a_file_that_is_not_yaml_or_missing(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("robot: [unclosed")
    with pytest.raises(ProfileError, match=r"bad\.yaml:1:17: not valid YAML"):
        load_profile(bad)
    with pytest.raises(ProfileError, match="cannot read"):
        load_profile(tmp_path / "missing.yaml")
    with pytest.raises(ProfileError, match="must be a mapping"):
        parse_profile(["a", "list"], file="x.yaml")


def test_a_joint_on_two_devices_is_refused() -> None:
    doc = variant()
    doc["devices"]["arm2"] = doc["devices"]["arm"]
    with pytest.raises(ProfileError, match=r"devices\.arm2: joint 'shoulder_pan' is also on"):
        parse_profile(doc, file="arm.yaml")


def test_a_yaml_error_is_one_line_with_file_line_and_column(tmp_path: Path) -> None:
    bad = tmp_path / "arm.yaml"
    bad.write_text("robot: arm\ndevices:\n  arm: {driver: dynamixel\nfeatures: {}\n")
    with pytest.raises(ProfileError) as err:
        load_profile(bad)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"{bad}:4:9: not valid YAML: "), message
    assert "<unicode string>" not in message


def test_a_minimal_servo_entry_loads() -> None:
    doc = variant()
    doc["devices"]["arm"]["servos"] = [{"id": 1, "joint": "j1", "model": "XM430-W350"}]
    doc["features"]["manipulation"]["poses"] = {"home": {"j1": 0.0}}
    profile = parse_profile(doc, file="arm.yaml")
    low, high = profile.devices["arm"].limits["j1"]
    assert low == pytest.approx(-3.14159, abs=1e-4)  # tick 0
    assert high == pytest.approx(3.14006, abs=1e-4)  # tick 4095: inside the single turn


@pytest.mark.parametrize(("joint", "value"), [("elbow", 2.5), ("gripper", -0.6)])
def test_a_pose_outside_the_joint_limits_is_refused_before_any_port_opens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, joint: str, value: float
) -> None:
    from temoto.drivers.dynamixel import _sdk

    opened: list[str] = []
    monkeypatch.setattr(_sdk.SdkPort, "open", lambda self: opened.append(self.path))
    doc = variant(sim=False)
    doc["features"]["manipulation"]["poses"]["reach"][joint] = value
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ProfileError) as err:
        load_profile(path)
    message = str(err.value)
    assert message.startswith(f"{path}: features.manipulation.poses.reach.{joint}: "), message
    assert "outside the joint's limits" in message
    assert opened == []


def test_the_robot_command_exits_2_on_a_pose_beyond_the_limits(tmp_path: Path) -> None:
    from temoto.cli.robot import main

    doc = variant(sim=False)
    doc["devices"]["arm"]["link"] = "serial:/dev/nonexistent-temoto-tty?baud=1000000"
    doc["features"]["manipulation"]["poses"]["reach"]["elbow"] = 9.0
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert main(["--profile", str(path), "--local"]) == 2


# ---- profile-wide rules ----------------------------------------------------------------------

ROVER = yaml.safe_load((ROOT / "hw_profiles" / "sim_rover.yaml").read_text())


def rover(**nav: Any) -> dict[str, Any]:
    doc: dict[str, Any] = yaml.safe_load(yaml.safe_dump(ROVER))
    doc["features"]["navigation"].update(nav)
    return doc


@pytest.mark.parametrize(
    ("nav", "key", "what"),
    [
        # the wheels: 20 rad/s x 0.08 m = 1.6 m/s; half the separation 0.21 m
        ({"max_speed": 2.0}, "max_speed", "2 m/s is beyond the wheels' 20 rad/s"),
        ({"max_turn_rate": 8.0}, "max_turn_rate", "needs 1.68 m/s at each wheel"),
        ({"max_speed": 1.5}, "max_speed", "needs 1.92 m/s at the outer wheel"),
    ],
)
def test_navigation_faster_than_the_wheels_is_refused(
    nav: dict[str, Any], key: str, what: str
) -> None:
    with pytest.raises(ProfileError) as err:
        parse_profile(rover(**nav), file="rover.yaml")
    message = str(err.value)
    assert message.startswith(f"rover.yaml: features.navigation.{key}: "), message
    assert what in message, message
    assert "devices.base joint left_wheel" in message, message
    assert "\n" not in message


def test_navigation_within_the_wheels_loads() -> None:
    profile = parse_profile(rover(max_speed=1.15, max_turn_rate=2.0), file="rover.yaml")
    assert profile.navigation is not None
    assert profile.devices["base"].velocity_limits == {"left_wheel": 20.0, "right_wheel": 20.0}


def test_dynamixel_wheels_are_checked_against_their_model() -> None:
    # no velocity_limit: the XM430-W350's Velocity Limit (44) can be set to at most
    # 1023 x 0.229 rev/min = 24.53 rad/s, so 2.45 m/s on 0.1 m wheels
    servos = [
        {"id": 1, "joint": "left", "model": "XM430-W350", "mode": "velocity"},
        {"id": 2, "joint": "right", "model": "XM430-W350", "mode": "velocity"},
    ]
    doc = {
        "robot": "dxl_rover",
        "devices": {"base": {"driver": "dynamixel", "link": "/dev/null", "servos": servos}},
        "features": {
            "navigation": {
                "type": "differential_drive",
                "left_wheel": "left",
                "right_wheel": "right",
                "wheel_radius": 0.1,
                "wheel_separation": 0.3,
                "max_speed": 2.5,
                "max_turn_rate": 1.0,
            }
        },
    }
    with pytest.raises(ProfileError, match=r"navigation\.max_speed: 2\.5 m/s is beyond .*2\.45"):
        parse_profile(doc, file="dxl.yaml")
    doc["features"]["navigation"]["max_speed"] = 2.0
    assert parse_profile(doc, file="dxl.yaml").navigation is not None


def test_a_null_safe_state_is_refused_not_defaulted() -> None:
    with pytest.raises(ProfileError) as err:
        parse_profile(variant(devices__arm__safe_state=None), file="arm.yaml")
    message = str(err.value)
    assert message.startswith("arm.yaml: devices.arm.safe_state: is null"), message
    assert "torque_off, hold" in message


@pytest.mark.parametrize(
    ("doc", "device"),
    [
        (variant(devices__arm__safe_state="hold", devices__arm__bus_watchdog=0), "arm"),
        (
            {
                **rover(),
                "devices": {
                    "base": {
                        **ROVER["devices"]["base"],
                        "safe_state": "hold",
                        "watchdog_timeout": 0,
                    }
                },
            },
            "base",
        ),
    ],
    ids=["dynamixel", "odrive"],
)
def test_hold_without_a_device_watchdog_must_be_acknowledged(
    doc: dict[str, Any], device: str
) -> None:
    with pytest.raises(ProfileError) as err:
        parse_profile(doc, file="p.yaml")
    message = str(err.value)
    assert message.startswith(f"p.yaml: devices.{device}.safe_state: hold needs"), message
    assert "hold_without_watchdog: true" in message
    doc["devices"][device]["hold_without_watchdog"] = True
    profile = parse_profile(doc, file="p.yaml")
    assert "hold_without_watchdog" not in profile.devices[device].config  # not the driver's key
    doc["devices"][device]["hold_without_watchdog"] = "yes"
    with pytest.raises(ProfileError, match=rf"devices\.{device}\.hold_without_watchdog: "):
        parse_profile(doc, file="p.yaml")


def test_hold_with_the_watchdog_on_loads() -> None:
    profile = parse_profile(variant(devices__arm__safe_state="hold"), file="arm.yaml")
    assert profile.devices["arm"].config["safe_state"] == "hold"


@pytest.mark.parametrize(
    ("doc", "key"),
    [
        (rover(max_speed=3.0), "features.navigation.max_speed"),
        (variant(devices__arm__safe_state=None), "devices.arm.safe_state"),
        (variant(devices__arm__safe_state="hold", devices__arm__bus_watchdog=0), "safe_state"),
        (variant(devices__arm__servos__0__velocity_limit=30.0), "servos[0].velocity_limit"),
    ],
    ids=["speed", "null", "hold", "model_limit"],
)
def test_the_robot_command_exits_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], doc: dict[str, Any], key: str
) -> None:
    from temoto.cli.robot import main

    doc["sim"] = False
    path = tmp_path / "robot.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert main(["--profile", str(path), "--local"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"temoto-robot: error: {path}: "), err
    assert key in err, err
    assert "\n" not in err, err
