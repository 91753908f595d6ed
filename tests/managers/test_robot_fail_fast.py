"""An action that needs a faulted device fails at once with the device's reason.

The base's wheels are commanded only by the robot's control thread, which does not step while a
device is in FAULT: NavigateTo must not wait RUNNING there, with no error. The fault
happens before the action starts: the robot's consumers were told of it when it
happened, so the action (which holds no reference yet) is never told; it must see it itself
when it acquires the robot or starts its motion, instead of waiting for a device that does not
move.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from _robots import robot_manager

from temoto import ActionEngine, Result
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import load_profile
from temoto.core.registrar import Registrar
from temoto.managers.robot import RobotManager, RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
PROFILES = ROOT / "hw_profiles"

GRAPH = {
    "graph_name": "drive",
    "graph_entry": [{"name": "NavigateTo", "instance_id": 0}],
    "graph_exit": [{"name": "NavigateTo", "instance_id": 0}],
    "actions": [
        {
            "name": "NavigateTo",
            "instance_id": 0,
            "type": "sync",
            "input_parameters": {
                "x": {"pvf_type": "number", "pvf_value": 1.0},
                "y": {"pvf_type": "number", "pvf_value": 0.0},
            },
        }
    ],
}


@pytest.fixture
def rover() -> Iterator[tuple[Registrar, RobotManager]]:
    with robot_manager("test-fail-fast", load_profile(PROFILES / "sim_rover.yaml")) as pair:
        yield pair


def test_a_drive_after_the_bases_fault_fails_at_once_with_the_devices_reason(
    rover: tuple[Registrar, RobotManager],
) -> None:
    registrar, manager = rover
    watcher = RobotManagerClient(registrar).request(client="watcher")
    manager.simulator("base").inject("silence")
    deadline = time.monotonic() + 10
    while watcher.healthy():
        assert time.monotonic() < deadline, "the arm's silence was not noticed"
        time.sleep(0.01)
    with ActionEngine("sim_rover", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
        t0 = time.monotonic()
        engine.start(GRAPH)
        try:
            result = engine.wait("drive", 5)  # not RUNNING, with no error, for ever
        finally:
            took = time.monotonic() - t0
            errors = [str(e) for e in engine.outcome("drive").errors]
            engine.stop("drive", 10)
    assert result is Result.ERROR, errors
    assert any("device 'base' is FAULT" in e for e in errors), errors
    assert took < 4, took  # at once, not after its deadline (1.5 x ~2.3 s + 5 s)
    registrar.release(watcher.resource.id)
