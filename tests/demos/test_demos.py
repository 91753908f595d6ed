"""The thesis' demonstrations end to end, on faster clocks (each prints its timeline), at
``typical`` realism as ``temoto demo`` runs them; the seed is printed for a replay
(``temoto demo N --seed S``)."""

from __future__ import annotations

import io
import random
import subprocess
import sys

import pytest

from temoto.demos import run_demo


@pytest.fixture
def seed() -> int:
    """A fresh realism seed per test, printed (pytest shows it with a failure's output)."""
    value = random.randrange(2**32)
    print(f"realism typical, seed {value}")
    return value


def test_demo_1_sensor_redundancy() -> None:
    out = io.StringIO()
    report = run_demo(1, out)  # its sensors are processes, not simulated devices: no realism
    assert report.ok, out.getvalue()
    facts = report.facts
    assert facts["fed_the_display"] == ["lidar_3d", "depth_camera", "lidar_2d"]
    assert len(facts["switch_over_ms"]) == 2
    assert all(0 < ms < 1000 for ms in facts["switch_over_ms"])
    assert facts["sensor_processes_max"] == 1  # never more than the one in use
    assert facts["if_all_started"] == 3
    assert "display: switched to depth_camera" in out.getvalue()


def test_demo_2_multi_robot_escort(seed: int) -> None:
    out = io.StringIO()
    report = run_demo(2, out, speed=3, realism="typical", seed=seed)
    assert report.ok, out.getvalue()
    facts = report.facts
    assert facts["shown"] == ["worker_camera", "escort_camera"]
    assert facts["camera_robot"] == "escort"  # a remote resource, found through RIS
    assert facts["switch_over_ms"] < 1000
    assert facts["escort_gap_m"] < 1.2  # it followed the worker


def test_demo_3_mission_adaptiveness(seed: int) -> None:
    out = io.StringIO()
    report = run_demo(3, out, speed=3, realism="typical", seed=seed)
    assert report.ok, out.getvalue()
    facts = report.facts
    assert facts["delivery"] == {"rover": "on_true", "arm_station": "on_true"}
    assert facts["paused_at_s"] < facts["resumed_at_s"]
    assert facts["patrol_legs"] == ["NavigateTo_0", "NavigateTo_1", "NavigateTo_2"]
    text = out.getvalue()
    # the patrol pauses before the delivery starts and resumes after it ended on both robots
    order = [
        "operator: pause surveillance",
        "operator: start delivery",
        "arm_station: delivery: MoveJoints_20 (load the parcel) started",
        "rover: delivery ended: on_true",
        "operator: resume surveillance",
        "rover: surveillance: NavigateTo_2 (warehouse) resumed",
        "rover: surveillance ended: on_stopped",
    ]
    positions = [text.index(line) for line in order]
    assert positions == sorted(positions), text


def test_demo_4_source_agnostic_tasking(seed: int) -> None:
    out = io.StringIO()
    report = run_demo(4, out, speed=3, realism="typical", seed=seed)
    assert report.ok, out.getvalue()
    assert report.facts["steps"] == ["NavigateTo", "MoveJoints", "NavigateTo", "MoveJoints"]
    assert report.facts["result"] == "on_true"
    assert "unknown place 'kitchen'" in report.facts["refused"]


def test_demo_5_multi_robot_knowledge_sharing(seed: int) -> None:
    out = io.StringIO()
    report = run_demo(5, out, speed=3, realism="typical", seed=seed)
    assert report.ok, out.getvalue()
    facts = report.facts
    assert facts["trees_equal"]
    assert facts["found_by"] == {"trash": "scout_1", "chair": "scout_2"}
    assert all(p == ["map", "bin", "trash"] for p in facts["trash_path"].values())
    assert "worker: its world model learnt trash from scout_1" in out.getvalue()


def test_the_command_line_runs_a_demo() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "temoto", "demo", "4", "--speed", "4"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("== demo 4: Source-agnostic tasking")
    assert "== done in" in proc.stdout


def test_a_demo_that_does_not_exist() -> None:
    with pytest.raises(ValueError, match="no demonstration 9"):
        run_demo(9)
