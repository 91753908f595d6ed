"""The survey mission on the simulated quad in an imperfect world (issue 30, item 3).

hw_profiles/sim_quad.yaml with the simulator's ``realism`` set: at ``typical`` (noise, jitter,
lost and late frames at the documented rates) the mission ends TRUE with no fault; at ``harsh`` it
ends TRUE or ERROR with a clear fault, never a hang. The Robot Manager and the engine run on a
clock ten times faster; each test takes some 10-25 s real time.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml
from _robots import robot_manager

from temoto import ActionEngine, Result, ScaledClock
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import parse_profile
from temoto.core.registrar import Registrar
from temoto.drivers.mavlink import SimVehicle
from temoto.managers.robot import RobotManager, RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "hw_profiles" / "sim_quad.yaml"
MISSION = json.loads((ROOT / "examples" / "missions" / "quad_survey.graph.json").read_text())
WAIT = 200.0  # real seconds: far beyond the mission's ~10 s, a hang's bound only


@contextmanager
def _quad(realism: str, seed: int) -> Iterator[tuple[Registrar, RobotManager, ScaledClock]]:
    doc = yaml.safe_load(PROFILE.read_text())
    doc["devices"]["quad"]["sim"].update(realism=realism, seed=seed)
    clock = ScaledClock(10)
    profile = parse_profile(doc, file="sim_quad.yaml", clock=clock)
    with robot_manager(f"test-quad-{realism}", profile, clock) as (registrar, manager):
        yield registrar, manager, clock


def test_the_survey_ends_true_at_typical() -> None:
    with _quad("typical", 30) as (registrar, manager, clock):
        watcher = RobotManagerClient(registrar).request(client="watcher")  # loads the quad
        sim = manager.simulator("quad")
        assert isinstance(sim, SimVehicle)
        assert sim.realism.describe() == "realism typical, seed 30"
        with ActionEngine(
            "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
        ) as engine:
            outcome = engine.run(MISSION, timeout=WAIT)
        assert outcome.result is Result.TRUE, outcome.errors
        assert watcher.healthy()  # a fault on the way would have ended a goal: not TRUE
        # at typical's 0.2 % a short mission may lose no frame: the quad stays on until one
        # was lost (about 500 frames: a few real seconds), and none may be seen as a fault
        deadline = time.monotonic() + 60.0
        while sum(sim.telemetry.lost.values()) == 0:
            assert time.monotonic() < deadline, "no telemetry frame lost in 60 s at typical"
            time.sleep(0.05)
        time.sleep(clock.real_seconds(3.0))  # three 1 Hz heartbeat periods past the loss
        assert watcher.healthy()
        registrar.release(watcher.resource.id)


@pytest.mark.parametrize("seed", [7, 8])
def test_the_survey_ends_true_or_with_a_clear_fault_at_harsh(seed: int) -> None:
    with _quad("harsh", seed) as (registrar, _, clock):
        with ActionEngine(
            "sim_quad", actions=[ROBOT_ACTIONS], registrar=registrar, clock=clock
        ) as engine:
            outcome = engine.run(MISSION, timeout=WAIT)
        assert outcome.result in (Result.TRUE, Result.ERROR)
        if outcome.result is Result.ERROR:
            text = " ".join(str(e) for e in outcome.errors)
            assert "quad" in text, outcome.errors
            assert "stale" in text or "heartbeat" in text, outcome.errors
