"""`python -m temoto.managers.robot`: a robot's instance from a profile, with a mission."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from temoto.record.reader import read_messages

ROOT = Path(__file__).resolve().parents[2]
ARM = ROOT / "hw_profiles" / "sim_arm.yaml"
MISSION = ROOT / "examples" / "missions" / "arm_poses.graph.json"


def robot(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    return subprocess.run(
        [sys.executable, "-m", "temoto.managers.robot", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        check=False,
    )


def test_a_mission_on_the_simulated_arm_ends_on_true() -> None:
    proc = robot("--profile", str(ARM), "--mission", str(MISSION), "--local")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("robot 'sim_arm' ready in ")
    assert "(simulated; manipulation; fleet off)" in lines[0]
    assert any("MoveJoints_2 FINISHED" in line for line in lines)
    assert lines[-1].startswith("arm_poses: on_true in ")


def test_a_bad_profile_is_invalid_input_naming_the_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(ARM.read_text().replace("model: XM430-W210", "model: XM999"))
    proc = robot("--profile", str(bad), "--mission", str(MISSION), "--local")
    assert proc.returncode == 2
    assert "devices.arm.servos[3].model" in proc.stderr


def test_joining_a_fleet_needs_a_key_or_insecure() -> None:
    proc = robot("--profile", str(ARM))
    assert proc.returncode == 2
    assert "a fleet key is needed" in proc.stderr


def test_a_restart_with_a_state_dir_loads_the_robot_afresh(tmp_path: Path) -> None:
    # The first run's robot resource is in the registrar's journal when the process ends; the
    # second run restores it (FATAL: its drivers ran in the first process), lets the first
    # run's references go and loads the robot again.
    state = tmp_path / "state"
    for run in (1, 2, 3):
        proc = robot(
            "--profile", str(ARM), "--mission", str(MISSION), "--local", "--state-dir", str(state)
        )
        assert proc.returncode == 0, f"run {run}: {proc.stderr}"
        assert proc.stdout.splitlines()[-1].startswith("arm_poses: on_true in ")
    assert sorted(p.name for p in state.iterdir()) == ["registrar.journal", "world.journal"]


def test_a_device_that_cannot_start_is_named_without_internal_json(tmp_path: Path) -> None:
    dead = tmp_path / "dead_arm.yaml"
    text = ARM.read_text().replace("sim: true", "sim: false")
    dead.write_text(text.replace("/dev/ttyUSB0?", "/dev/null?"))
    proc = robot("--profile", str(dead), "--mission", str(MISSION), "--local")
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(
        "temoto-robot: error: robot sim_arm, device arm: could not start: cannot open /dev/null: "
    ), lines[0]
    assert "{" not in lines[0]
    assert "could not load" not in lines[0]


MOBILE = ROOT / "hw_profiles" / "sim_mobile_manipulator.yaml"


def test_after_a_pause_of_the_process_every_device_comes_back(tmp_path: Path) -> None:
    # SIGSTOP/SIGCONT of a serving robot (its simulators pause with it): the ODrive axes'
    # watchdogs (1 s) expire and the Dynamixel chain goes stale; the recovery brings both back
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    record = tmp_path / "run.mcap"
    argv = ["--profile", str(MOBILE), "--local", "--record", str(record)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto.managers.robot", *argv],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    lines: list[str] = []
    seen = threading.Condition()

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            with seen:
                lines.append(line.rstrip("\n"))
                seen.notify_all()

    reader = threading.Thread(target=read, name="test-robot-stderr")
    reader.start()

    def wait_for(text: str, timeout: float = 30.0) -> None:
        with seen:
            assert seen.wait_for(lambda: any(text in line for line in lines), timeout), (
                f"no line with {text!r}:\n" + "\n".join(lines)
            )

    try:
        wait_for("serving; Ctrl-C stops it")
        time.sleep(0.5)
        proc.send_signal(signal.SIGSTOP)
        time.sleep(1.5)
        proc.send_signal(signal.SIGCONT)
        wait_for("device base: recovered on try")
        wait_for("device arm: recovered on try")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        reader.join(10)
        if proc.stderr is not None:
            proc.stderr.close()
    text = "\n".join(lines)
    assert "gave up" not in text
    assert "  base: left_wheel IDLE, right_wheel IDLE" in lines
    assert "  arm: 6 servos torque off" in lines
    # the recording has the recovery's lines too
    messages, complete = read_messages(record, {"/temoto/log"})
    assert complete
    logged = [m.data["message"] for m in messages]
    for device in ("base", "arm"):
        assert any(
            t.startswith(f"robot sim_mobile_manipulator, device {device}: recovered on try")
            for t in logged
        ), logged
