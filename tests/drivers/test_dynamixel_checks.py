"""Dynamixel checks before anything is written: identity, duplicates, model limits, every bad
status packet counted, and messages that name the servo and the register.

The simulated chain runs on its pseudo-terminal; what reaches it is watched by wrapping its
packet handler (the instructions on the wire), and registers are read back from it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import pytest
from contract import eventually

from temoto.clock import ManualClock, MonotonicClock
from temoto.drivers import DriverState
from temoto.drivers.dynamixel import protocol as p
from temoto.drivers.dynamixel.driver import SIM_REPLY_TIMEOUT, DynamixelDriver
from temoto.drivers.dynamixel.sim import SimDynamixelChain
from temoto.errors import DriverInitError, DriverOperationError, ProfileError

pytest.importorskip("dynamixel_sdk")

ID, RETURN_DELAY, MAX_POSITION, MIN_POSITION, TORQUE = 7, 9, 48, 52, 64
WRITES = frozenset(
    {
        p.Instruction.WRITE,
        p.Instruction.REG_WRITE,
        p.Instruction.SYNC_WRITE,
        p.Instruction.BULK_WRITE,
        p.Instruction.REBOOT,
        p.Instruction.FACTORY_RESET,
    }
)


def entry(n: int, **extra: Any) -> dict[str, Any]:
    servos = [
        {
            "id": i,
            "joint": f"j{i}",
            "model": "XM430-W350",
            "min_position": -2.5,
            "max_position": 2.5,
        }
        for i in range(1, n + 1)
    ]
    return {"link": "/dev/null", "baud": 1_000_000, "poll_rate": 50, "servos": servos, **extra}


def watch(sim: SimDynamixelChain) -> list[int]:
    """The instruction of every packet that reaches the chain, in order."""
    heard: list[int] = []
    handle = sim._handle

    def recording(packet: p.Packet, line: int | None = None) -> list[bytes]:
        heard.append(packet.instruction)
        return handle(packet, line)

    sim._handle = recording  # type: ignore[method-assign]
    return heard


def eeprom(sim: SimDynamixelChain) -> dict[int, tuple[int, int, int]]:
    return {
        i: tuple(sim.read_register(i, a) for a in (RETURN_DELAY, MIN_POSITION, MAX_POSITION))
        for i in sim.ids
    }  # type: ignore[misc]


@contextlib.contextmanager
def on_chain(
    servos: dict[int, str], config: dict[str, Any], clock: Any = None
) -> Iterator[tuple[SimDynamixelChain, DynamixelDriver]]:
    clock = clock or MonotonicClock()
    sim = SimDynamixelChain(servos, clock=clock)
    config = {**config, "link": f"serial:{sim.path}", "reply_timeout": SIM_REPLY_TIMEOUT}
    with sim, DynamixelDriver.from_profile("arm", config, clock=clock, where="arm") as driver:
        yield sim, driver


# ---- 1. nothing written before every servo is checked -------------------------------------------


def test_a_wrong_model_on_the_last_servo_leaves_every_servo_untouched() -> None:
    servos = dict.fromkeys(range(1, 7), "XM430-W350")
    servos[6] = "XL430-W250"  # the profile says XM430-W350
    with on_chain(servos, entry(6, return_delay_time=0)) as (sim, driver):
        heard = watch(sim)
        before = eeprom(sim)
        with pytest.raises(DriverInitError) as err:
            driver.configure()
        message = str(err.value)
        assert "servo 6 (j6) is XL430-W250 (model number 1060)" in message, message
        assert "the profile says XM430-W350 (1020)" in message, message
        assert "nothing was written to any servo" in message
        assert "\n" not in message
        assert eeprom(sim) == before  # limits and return delay of servos 1-5 as they were
        assert sim.stats["eeprom_writes"] == 0
        assert not WRITES & set(heard), heard  # only PING and READ went out
        assert p.Instruction.PING in heard
        assert driver.state is DriverState.UNCONFIGURED


def test_a_good_chain_is_written_after_the_checks() -> None:
    with on_chain({1: "XM430-W350", 2: "XM430-W350"}, entry(2, return_delay_time=0)) as (
        sim,
        driver,
    ):
        heard = watch(sim)
        driver.configure()
        first_write = next(i for i, inst in enumerate(heard) if inst in WRITES)
        assert heard.count(p.Instruction.PING) >= 2
        assert max(i for i, inst in enumerate(heard) if inst == p.Instruction.PING) < first_write
        assert sim.read_register(2, RETURN_DELAY) == 0
        assert sim.read_register(2, MIN_POSITION) > 0
        driver.shutdown()


# ---- 2. limits against the model's table --------------------------------------------------------


@pytest.mark.parametrize(
    ("servo", "key", "what"),
    [
        # XM430-W350: Velocity Limit (44) 0..1023 x 0.229 rev/min = 24.53 rad/s
        ({"mode": "velocity", "velocity_limit": 30.0}, "velocity_limit", "24.53 rad/s"),
        # ... through a 2:1 gear the joint gets half
        ({"velocity_limit": 13.0, "gear": 2.0}, "velocity_limit", "12.27 rad/s"),
        # Current Limit (38) 0..1193 x 2.69 mA x 1.78 N·m/A = 5.72 N·m
        ({"mode": "current", "effort_limit": 6.0}, "effort_limit", "5.721 N·m"),
        # XL430-W250: no current sensor; stall torque 1.5 N·m
        ({"model": "XL430-W250", "effort_limit": 2.0}, "effort_limit", "1.5 N·m"),
        # XL330-M288: Current Limit 0..1750 x 1 mA
        ({"model": "XL330-M288", "mode": "current", "effort_limit": 1.0}, "effort_limit", "0.619"),
    ],
)
def test_limits_beyond_the_model_are_refused(servo: dict[str, Any], key: str, what: str) -> None:
    config = entry(1)
    config["servos"][0] = {"id": 1, "joint": "j1", "model": "XM430-W350", **servo}
    with pytest.raises(ProfileError) as err:
        DynamixelDriver.from_profile("arm", config, clock=MonotonicClock(), where="a.yaml: d")
    message = str(err.value)
    assert message.startswith(f"a.yaml: d.servos[0].{key}: "), message
    assert what in message, message


def test_limits_within_the_model_load() -> None:
    config = entry(1)
    config["servos"][0] = {
        "id": 1,
        "joint": "j1",
        "model": "XM430-W350",
        "mode": "velocity",
        "velocity_limit": 24.5,
    }
    driver = DynamixelDriver.from_profile("arm", config, clock=MonotonicClock(), where="d")
    assert driver.joint_velocity_limits == {"j1": 24.5}
    driver.shutdown()


def test_a_velocity_limit_above_the_servo_register_is_refused_before_writing() -> None:
    config = entry(1)
    config["servos"][0] = {
        "id": 1,
        "joint": "j1",
        "model": "XM430-W350",
        "mode": "velocity",
        "velocity_limit": 10.0,  # the register's factory 200 units are 4.8 rad/s
    }
    with on_chain({1: "XM430-W350"}, config) as (sim, driver):
        with pytest.raises(DriverInitError, match=r"servo 1 \(j1\): velocity_limit 10 rad/s"):
            driver.configure()
        assert sim.read_register(1, 11) == 3  # Operating Mode still position: nothing written


# ---- 3. duplicates and bad packets --------------------------------------------------------------


def test_two_servos_on_one_id_are_found_before_torque_on() -> None:
    with on_chain({1: "XM430-W350", 2: "XM430-W350", 3: "XL430-W250"}, entry(2)) as (sim, driver):
        sim.write_register(3, ID, 2)  # now two servos answer id 2
        heard = watch(sim)
        with pytest.raises(DriverInitError) as err:
            driver.configure()
        message = str(err.value)
        assert "duplicate servo id 2 (j2)" in message, message
        assert "2 status packets answered one PING" in message, message
        assert not WRITES & set(heard)
        assert all(sim.read_register(i, TORQUE) == 0 for i in (1, 2))


def test_replies_to_ping_garbled_every_time_say_duplicate() -> None:
    with on_chain({1: "XM430-W350"}, entry(1)) as (sim, driver):
        sim.inject("corrupt")  # as two servos answering at once look on a real bus
        with pytest.raises(DriverInitError, match=r"duplicate servo id 1 \(j1\)\? its replies"):
            driver.configure()


def test_each_bad_packet_counts_not_each_poll() -> None:
    """8 corrupt status packets within two polls (40 ms) are a fault: the limit is 5 in 1 s."""
    clock = ManualClock()
    with on_chain(dict.fromkeys(range(1, 7), "XM430-W350"), entry(6), clock) as (sim, driver):
        driver.configure()
        driver.activate()
        sim.inject("corrupt", replies=8)
        eventually(lambda: sim.fault("corrupt") is None, 1.0, clock)
        eventually(lambda: driver.state is DriverState.FAULT, 0.1, clock)
        error = driver.health().error
        assert isinstance(error, DriverOperationError)
        assert "bad status packets within 1 s" in str(error)
        # the first poll's 6 replies were enough (the fault then says so again with 8)
        assert ": corrupt status packet reading Present Current" in str(error)
        assert driver.health().message.startswith("arm: ")


# ---- 4. messages name the servo and the register ------------------------------------------------


def test_a_silent_servo_is_named_with_the_register() -> None:
    with on_chain({1: "XM430-W350", 2: "XM430-W350", 3: "XM430-W350"}, entry(3)) as (sim, driver):
        driver.configure()
        driver.activate()
        sim.inject("silence", device=3)
        eventually(lambda: driver.state is DriverState.FAULT, 5.0, MonotonicClock())
        message = driver.health().message
        assert message.startswith("arm: "), message
        assert "arm: arm:" not in message
        assert (
            "servo 3: no status packet reading Present Current, Present Velocity,"
            " Present Position (126..135)" in message
        ), message
        assert "TxRxResult" not in message


def test_a_silent_servo_at_configure_is_named() -> None:
    with on_chain({1: "XM430-W350", 2: "XM430-W350"}, entry(2)) as (sim, driver):
        sim.inject("silence", device=2)
        with pytest.raises(DriverInitError) as err:
            driver.configure()
        message = str(err.value)
        assert "servo 2 (j2): no status packet to PING on /dev/pts/" in message, message
        assert "TxRxResult" not in message


def test_a_refused_write_names_the_servo_register_and_value() -> None:
    with on_chain({1: "XM430-W350"}, entry(1)) as (sim, driver):
        driver.configure()
        assert sim.read_register(1, 0) == 1020
        with pytest.raises(DriverOperationError) as err, driver._bus:
            driver._write(1, next(r for r in _registers() if r.name == "Model Number"), 5)
        message = str(err.value)
        assert message == "arm: servo 1 refused writing Model Number (0) = 5: ACCESS error", message


def _registers() -> Any:
    from temoto.drivers.dynamixel import control_table as ct

    return ct.REGISTERS
