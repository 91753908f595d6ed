"""The Dynamixel simulator at a realism level, and the driver living with it.

Noise on Present Position / Velocity / Current / Temperature (never on the model's state), and
the status packets of a poll (SYNC_READ and the like) lost now and then: a timeout for the
driver, which faults only after ``timeout_polls`` polls in a row fail and asks a one-shot read
again once.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from dxl_polled import follow

from temoto.clock import ManualClock
from temoto.drivers import DriverState
from temoto.drivers.capabilities import ControlMode, JointCommand
from temoto.drivers.dynamixel import control_table as ct
from temoto.drivers.dynamixel.driver import SIM_REPLY_TIMEOUT, DynamixelDriver
from temoto.drivers.dynamixel.sim import SimDynamixelChain
from temoto.drivers.realism import Realism, RealismLevel
from temoto.errors import ProfileError


def _address(name: str) -> int:
    for reg in ct.MODELS["XM430-W350"].registers:
        if reg.name == name:
            return reg.address
    raise KeyError(name)


def readings(sim: SimDynamixelChain, clock: ManualClock, name: str, n: int = 200) -> list[int]:
    out = []
    for _ in range(n):
        clock.advance(0.01)
        out.append(sim.read_register(1, _address(name)))
    return out


@pytest.fixture
def sims() -> Iterator[Any]:
    made: list[SimDynamixelChain] = []

    def make(**kwargs: Any) -> tuple[SimDynamixelChain, ManualClock]:
        clock = ManualClock()
        sim = SimDynamixelChain({1: "XM430-W350"}, clock=clock, name="arm", **kwargs)
        made.append(sim)
        return sim, clock

    yield make
    for sim in made:
        sim.close()


def test_at_off_the_present_registers_are_the_model_s(sims: Any) -> None:
    sim, clock = sims()
    for name in ("Present Position", "Present Velocity", "Present Temperature"):
        assert len(set(readings(sim, clock, name))) == 1, name


def test_at_typical_they_are_noisy_and_replay_from_the_seed(sims: Any) -> None:
    sim, clock = sims(realism="typical", seed=9)
    position = readings(sim, clock, "Present Position")
    current = readings(sim, clock, "Present Current")
    temperature = readings(sim, clock, "Present Temperature")
    assert len(set(position)) > 1  # sigma 0.0005 rad is a third of a tick: now and then one
    assert max(abs(v - position[0]) for v in position) <= 4
    assert len(set(current)) > 5  # 0.1 A in 2.69 mA units
    assert {29, 30, 31} & set(temperature)
    assert len(set(temperature)) > 1
    sim2, clock2 = sims(realism="typical", seed=9)
    assert readings(sim2, clock2, "Present Position") == position
    # the model itself is untouched: at rest, still at rest
    assert sim.read_register(1, _address("Moving")) == 0


def config(**extra: Any) -> dict[str, Any]:
    servos = [{"id": i, "joint": f"j{i}", "model": "XM430-W350"} for i in (1, 2)]
    return {"link": "/dev/null", "poll_rate": 100, "servos": servos, **extra}


def test_a_lost_reply_to_the_first_syncread_does_not_fail_configure() -> None:
    # seed 2 on the device "arm" at a 50 % loss: the first poll's replies are lost, the second's
    # come (found by drawing Realism(...).lost() in turn); the driver asks once more
    clock = ManualClock()
    realism = Realism(RealismLevel("lossy", drop=0.5), seed=2, device="arm")
    sim = SimDynamixelChain({1: "XM430-W350", 2: "XM430-W350"}, clock=clock, name="arm")
    sim.realism = realism
    cfg = config(link=f"serial:{sim.path}", reply_timeout=SIM_REPLY_TIMEOUT)
    with sim, DynamixelDriver.from_profile("arm", cfg, clock=clock, where="arm") as driver:
        driver.configure()
        assert sim.replies_lost >= 1
        assert driver.state is DriverState.INACTIVE


@pytest.mark.parametrize("seed", [3, 4])
def test_a_driven_chain_at_typical_does_not_fault(seed: int) -> None:
    clock = ManualClock()
    sim, cfg = DynamixelDriver.simulate(
        "arm", config(sim={"realism": "typical", "seed": seed}), clock=clock
    )
    assert isinstance(sim, SimDynamixelChain)
    assert sim.realism.describe() == f"realism typical, seed {seed}"
    with sim, DynamixelDriver.from_profile("arm", cfg, clock=clock, where="arm") as driver:
        driver.configure()
        driver.activate()
        driver.command([JointCommand("j1", ControlMode.POSITION, 0.5)])
        t0 = clock.monotonic()
        follow(driver, clock, lambda: clock.monotonic() - t0 >= 6.0, 7.0, real_timeout=60.0)
        assert driver.state is DriverState.ACTIVE, driver.health().error
        assert abs(driver.read_state().joints["j1"].position - 0.5) < 0.01


@pytest.mark.parametrize(
    ("sim", "key", "words"),
    [
        ({"realism": "rough"}, "sim.realism", "off, typical, harsh"),
        ({"seed": 1.5}, "sim.seed", "non-negative integer"),
        ({"noise": 1}, "sim.noise", "realism, seed"),
        ("typical", "sim", "mapping"),
    ],
)
def test_bad_sim_keys_are_refused_in_one_line(sim: Any, key: str, words: str) -> None:
    with pytest.raises(ProfileError, match=words) as err:
        DynamixelDriver.from_profile("arm", config(sim=sim), clock=ManualClock(), where="arm")
    assert f"arm.{key}:" in str(err.value)
