"""Arm missions through the robot command at ``--realism harsh`` (issue 30, item 3).

``python -m temoto.managers.robot --profile <arm profile> --mission <graph> --local --realism
harsh --seed N``, run in-process (:func:`temoto.cli.robot.main`, its simulators in-process too):
lost poll replies, status packets late past dynamixel-sdk's timeout, noise on every present
register. The mission must end ``on_true`` (exit 0) or with one clear fault line naming the
robot and the device (exit 1), never hang and never print a traceback; ``--timeout`` bounds a
hang only. Each test takes some 10-20 s real time (the arm moves through its poses at its own
speed).
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from temoto.cli.robot import main

ROOT = Path(__file__).resolve().parents[2]
MISSIONS = ROOT / "examples" / "missions"
HANG = 90.0  # real seconds: far beyond the missions' 5-15 s, a hang's bound only


def _run(profile: str, mission: str, seed: int, capfd: pytest.CaptureFixture[str]) -> None:
    argv = ["--profile", str(ROOT / "hw_profiles" / profile), "--mission", str(MISSIONS / mission)]
    argv += ["--local", "--realism", "harsh", "--seed", str(seed), "--timeout", str(HANG)]
    t0 = time.monotonic()
    code = main(argv)
    took = time.monotonic() - t0
    out, err = capfd.readouterr()
    text = out + err
    assert err.splitlines()[0] == f"realism harsh, seed {seed}", err
    assert "Traceback" not in text, text
    assert took < HANG - 10.0, f"the mission ran into --timeout: {text}"
    graph = mission.split(".")[0]
    if code == 0:
        assert f"{graph}: on_true" in text, text
        return
    assert code == 1, text
    errors = [line for line in text.splitlines() if line.startswith("  error: ")]
    assert errors, text  # the summary names the failing node and why, one line each
    robot = profile.removesuffix(".yaml")
    assert any(f"robot {robot}, device arm: " in line for line in errors), errors


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_arm_s_poses_end_on_true_or_with_a_clear_fault_at_harsh(
    seed: int, capfd: pytest.CaptureFixture[str]
) -> None:
    _run("sim_arm.yaml", "arm_poses.graph.json", seed, capfd)


def test_the_mobile_manipulator_s_arm_poses_end_on_true_or_with_a_clear_fault_at_harsh(
    capfd: pytest.CaptureFixture[str],
) -> None:
    _run("sim_mobile_manipulator.yaml", "arm_poses.graph.json", 4, capfd)
