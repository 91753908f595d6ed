"""A faulted device stops only the features that move it: the base drives on while the arm is out.

Before, the robot's control thread stepped no feature at all while any device was not active, so
a NavigateTo with only the arm in fault stood still until its deadline, and its error named
neither the arm nor the reason.
"""

from __future__ import annotations

import time
from pathlib import Path

from _robots import robot_manager

from temoto.config import load_profile
from temoto.managers.robot import RobotManagerClient

PROFILES = Path(__file__).resolve().parents[2] / "hw_profiles"


def test_the_base_reaches_its_goal_while_the_arm_is_in_fault() -> None:
    profile = load_profile(PROFILES / "sim_mobile_manipulator.yaml")
    with robot_manager("test-partial-fault", profile) as (registrar, manager):
        handle = RobotManagerClient(registrar).request(client="watcher")
        manager.simulator("arm").inject("silence")
        deadline = time.monotonic() + 10
        while handle.healthy():
            assert time.monotonic() < deadline, "the arm's silence was not noticed"
            time.sleep(0.01)
        motion = handle.navigate_to(0.3, 0.0)
        assert motion.wait(20), "the base did not move while the arm was in fault"
        assert motion.error is None, motion.error
        x, y, _ = handle.pose()
        assert abs(x - 0.3) < 0.1, (x, y)
        assert abs(y) < 0.1, (x, y)
        registrar.release(handle.resource.id)
