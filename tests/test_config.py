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
    from temoto.managers.robot.__main__ import main

    doc = variant(sim=False)
    doc["devices"]["arm"]["link"] = "serial:/dev/nonexistent-temoto-tty?baud=1000000"
    doc["features"]["manipulation"]["poses"]["reach"]["elbow"] = 9.0
    path = tmp_path / "arm.yaml"
    path.write_text(yaml.safe_dump(doc))
    assert main(["--profile", str(path), "--local"]) == 2
