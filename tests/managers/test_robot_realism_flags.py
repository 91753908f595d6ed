"""``--realism``/``--seed`` reach every simulated device: the Robot Manager and the commands."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from temoto.clock import MonotonicClock
from temoto.config import parse_profile
from temoto.core.registrar import Registrar
from temoto.managers.robot import RobotManager
from temoto.managers.robot.client import RobotManagerClient

ROOT = Path(__file__).resolve().parents[2]
MM = ROOT / "hw_profiles" / "sim_mobile_manipulator.yaml"
ARM = ROOT / "hw_profiles" / "sim_arm.yaml"
MISSION = ROOT / "examples" / "missions" / "arm_poses.graph.json"


def loaded(
    doc: dict[str, Any], realism: str = "off", seed: int | None = None
) -> tuple[Registrar, RobotManager]:
    clock = MonotonicClock()
    registrar = Registrar(f"realism-{os.getpid()}-{id(doc)}")
    profile = parse_profile(doc, file="mm.yaml", clock=clock)
    manager = RobotManager(registrar, profile, clock=clock, realism=realism, seed=seed)
    RobotManagerClient(registrar).request(client="test")
    return registrar, manager


def close(registrar: Registrar, manager: RobotManager) -> None:
    for ref in registrar.references():
        registrar.release(ref.id)
    manager.shutdown()
    registrar.close()


def test_the_manager_gives_each_simulator_its_level_and_seed_and_an_entry_s_own_wins() -> None:
    doc = yaml.safe_load(MM.read_text())
    own = copy.deepcopy(doc)
    own["devices"]["arm"]["sim"] = {"realism": "harsh", "seed": 3}
    registrar, manager = loaded(own, realism="typical", seed=77)
    try:
        assert manager.seed == 77
        base, arm = manager.simulator("base").realism, manager.simulator("arm").realism
        assert (base.level.name, base.seed) == ("typical", 77)
        assert (arm.level.name, arm.seed) == ("harsh", 3)
    finally:
        close(registrar, manager)
    registrar, manager = loaded(doc)  # the class default: the exact figures
    try:
        assert manager.seed is None
        assert not manager.simulator("base").realism.enabled
        assert not manager.simulator("arm").realism.enabled
    finally:
        close(registrar, manager)
    with pytest.raises(ValueError, match="realism must be one of off, typical, harsh"):
        RobotManager(Registrar("realism-bad"), parse_profile(doc, file="mm.yaml"), realism="wild")


def robot(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [sys.executable, "-m", "temoto.managers.robot", *args],
        capture_output=True,
        text=True,
        timeout=90,
        env=env,
        cwd=ROOT,
    )


def test_the_robot_command_prints_its_level_and_seed_once() -> None:
    # a process test (about 5 s): the default is typical with a fresh seed, printed first
    proc = robot("--profile", str(ARM), "--mission", str(MISSION), "--local", "--seed", "12345")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines()[0] == "realism typical, seed 12345"
    assert proc.stderr.count("realism ") == 1
    proc = robot("--profile", str(ARM), "--mission", str(MISSION), "--local", "--realism", "off")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.splitlines()[0] == "realism off"
    proc = robot("--profile", str(ARM), "--local", "--realism", "wild")
    assert proc.returncode == 2
    assert "invalid choice: 'wild'" in proc.stderr
