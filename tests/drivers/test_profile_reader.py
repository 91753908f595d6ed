"""The one profile reader: field kinds, messages naming file and key path, Driver.from_profile."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, ClassVar

import pytest

from temoto.clock import ManualClock
from temoto.drivers.base import Driver
from temoto.drivers.profile import (
    Field,
    ProfileReader,
    choice,
    custom,
    flag,
    integer,
    name,
    number,
    text,
)
from temoto.errors import DriverUnavailableError, ProfileError


def error(spec: Mapping[str, Field[Any]], config: object, where: str = "p.yaml: devices.d") -> str:
    with pytest.raises(ProfileError) as info:
        ProfileReader.at(where).entry(config, spec, "pump")
    return str(info.value)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        (number(1.0), 0, "must be a positive number, got 0"),
        (number(1.0), True, "must be a positive number, got True"),
        (number(1.0), "1", "must be a positive number, got '1'"),
        (number(1.0), float("inf"), "must be a positive number, got inf"),
        (number(1.0, low=None), float("nan"), "must be a finite number, got nan"),
        (number(50.0, low=0, high=1000, unit="Hz"), 1001, "must be a number in (0, 1000] Hz"),
        (number(0.0, low=0, low_open=False), -1, "must be a number >= 0, got -1"),
        (number(0.0, low=0, low_open=False, describe="0 (off) or positive"), -1, "0 (off) or"),
        (integer(3, low=1), 0, "must be an integer >= 1, got 0"),
        (integer(3, low=0, high=63), 64, "must be an integer 0..63, got 64"),
        (integer(3, low=0, high=63), 1.0, "must be an integer 0..63, got 1.0"),
        (integer(3), False, "must be an integer, got False"),
        (text("x"), "", "must be non-empty text, got ''"),
        (text("x", empty=True), 3, "must be text, got 3"),
        (name(), "1st", "must be a name (a letter, then letters"),
        (flag(False), "yes", "must be true or false, got 'yes'"),
        (choice(("idle", "hold")), "coast", "must be one of idle, hold, got 'coast'"),
    ],
)
def test_each_field_kind_says_what_it_must_be_and_what_it_got(
    field: Field[Any], value: object, message: str
) -> None:
    text_ = error({"rate": field}, {"rate": value})
    assert text_.startswith("p.yaml: devices.d.rate: "), text_
    assert message in text_, text_


def test_values_defaults_and_absent_optional_keys() -> None:
    spec: dict[str, Field[Any]] = {
        "rate": number(50.0, low=0, high=1000),
        "retries": integer(3, low=0),
        "id": integer(None, low=1, high=255),
        "mode": choice(("a", "b"), "a"),
        "on": flag(True),
    }
    got = ProfileReader.at("d").entry({"rate": 200, "driver": "pump", "id": None}, spec, "pump")
    assert got == {"rate": 200.0, "retries": 3, "id": None, "mode": "a", "on": True}
    assert isinstance(got["rate"], float)


def test_missing_unknown_and_foreign_keys_are_named() -> None:
    spec = {"link": custom(lambda r, v, k: v, hint="e.g. serial:/dev/ttyUSB0")}
    assert error(spec, {}) == "p.yaml: devices.d.link: missing: e.g. serial:/dev/ttyUSB0"
    assert error(spec, {"link": "x", "colour": 1}).startswith(
        "p.yaml: devices.d.colour: unknown key (known: driver, link)"
    )
    assert error(spec, {"link": "x", "driver": "valve"}) == (
        "p.yaml: devices.d.driver: must be 'pump' for this driver, got 'valve'"
    )
    assert error(spec, ["link"]).startswith("p.yaml: devices.d: must be a mapping with text keys")


def test_where_is_split_into_the_file_and_the_key_path() -> None:
    reader = ProfileReader.at("robots/arm.yaml: devices.arm")
    err = reader.error("servos[1].id", "duplicate id 1")
    assert (err.file, err.path, err.reason) == (
        "robots/arm.yaml",
        "devices.arm.servos[1].id",
        "duplicate id 1",
    )
    assert str(err) == "robots/arm.yaml: devices.arm.servos[1].id: duplicate id 1"
    bare = ProfileReader.at("arm").error("poll_rate", "bad")
    assert (bare.file, str(bare)) == (None, "arm.poll_rate: bad")
    assert str(ProfileReader().error("", "must be a mapping")) == "must be a mapping"
    items = ProfileReader("d")
    with pytest.raises(ProfileError, match=r"^d\.nodes\[1\]: must be a mapping"):
        items.items([{"a": 1}, 3], "nodes")
    with pytest.raises(ProfileError, match=r"^d\.nodes: must be a non-empty list, got \[\]"):
        items.items([], "nodes")


class Pump(Driver):
    """A driver built by the base class's from_profile from the fields it declares."""

    kind = "pump"
    safe_states = ("off", "drain")
    profile_fields: ClassVar[Mapping[str, Field[Any]]] = {
        "port": text(hint="e.g. /dev/ttyUSB0"),
        "rate": number(10.0, low=0, high=100, unit="Hz"),
        "burst": integer(2, low=1),
        "sim": custom(lambda r, v, k: v, None, init=False),
    }

    def __init__(self, name: str, *, port: str, rate: float, burst: int, clock: Any = None) -> None:
        super().__init__(name, clock=clock)
        if burst > rate:
            raise ValueError(f"burst {burst} must not exceed the rate {rate:g}")
        self.port, self.rate, self.burst = port, rate, burst

    def on_configure(self) -> None:
        """Nothing to open."""

    def on_shutdown(self) -> None:
        """Nothing to close."""


def test_from_profile_builds_a_driver_from_its_declared_fields() -> None:
    config = {"port": "/dev/pump", "rate": 20, "safe_state": "drain", "sim": {"flow": 1}}
    pump = Pump.from_profile("p", config, clock=ManualClock(), where="r.yaml: devices.p")
    assert (pump.port, pump.rate, pump.burst, pump.safe_state) == ("/dev/pump", 20.0, 2, "drain")
    assert pump.name == "p"
    pump.shutdown()


def test_from_profile_names_the_key_of_a_bad_value_and_of_a_refusing_constructor() -> None:
    clock = ManualClock()
    with pytest.raises(ProfileError, match=r"^r\.yaml: devices\.p\.port: missing: e\.g\. /dev/tty"):
        Pump.from_profile("p", {}, clock=clock, where="r.yaml: devices.p")
    with pytest.raises(ProfileError, match=r"^r\.yaml: devices\.p\.safe_state: must be one of off"):
        Pump.from_profile(
            "p", {"port": "x", "safe_state": "on"}, clock=clock, where="r.yaml: devices.p"
        )
    with pytest.raises(ProfileError, match=r"^r\.yaml: devices\.p\.burst: burst 5 must not"):
        Pump.from_profile(
            "p", {"port": "x", "rate": 4, "burst": 5}, clock=clock, where="r.yaml: devices.p"
        )


def test_a_driver_without_a_simulator_says_so() -> None:
    with pytest.raises(DriverUnavailableError, match="driver 'pump' has no simulator"):
        Pump.simulate("p", {"port": "x"}, clock=ManualClock())
