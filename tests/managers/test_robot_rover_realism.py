"""The rover's and the mobile manipulator's missions at ``--realism harsh``: on_true or a fault.

The robot command (``python -m temoto.managers.robot``) runs the shipped simulated profile and its
mission with the CAN simulators at ``harsh`` (noise, lost cyclic frames, jitter and late frames:
``docs/simulators.md``, "Realism"): the mission ends ``on_true`` (exit 0) or with a clear fault
naming the device (exit 1), never a hang. On the profiles' ``virtual`` bus the driver gives a
simulator in its own process 0.2 s of silence; over ``udp_multicast`` (inside ``unshare -n``, as
root), as on a real bus, the encoder estimates are stale after 3 periods (30 ms), which harsh's
late frames reach now and then. Process tests: each runs a mission of some 15 s in real time.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
DEADLINE = 120.0  # real seconds: far beyond the missions' ~15 s, a hang's bound only


def _no_netns() -> str | None:
    if os.geteuid() != 0:
        return "needs root for unshare -n"
    if not (shutil.which("unshare") and shutil.which("ip")):
        return "needs unshare and ip (iproute2)"
    return None


def run_mission(
    profile: Path, mission: str, seed: int, *, netns: bool = False
) -> subprocess.CompletedProcess[str]:
    argv = [
        sys.executable,
        "-m",
        "temoto.managers.robot",
        "--profile",
        str(profile),
        "--mission",
        str(ROOT / "examples" / "missions" / f"{mission}.graph.json"),
        "--local",
        "--realism",
        "harsh",
        "--seed",
        str(seed),
    ]
    if netns:  # multicast routed on the namespace's loopback, as temoto.testing.exitpaths does
        script = "ip link set lo up && ip route add 224.0.0.0/4 dev lo && exec " + " ".join(argv)
        argv = ["unshare", "-n", "sh", "-c", script]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        argv, capture_output=True, text=True, timeout=DEADLINE, env=env, cwd=ROOT, check=False
    )


def ends_true_or_with_a_fault(proc: subprocess.CompletedProcess[str], mission: str) -> None:
    assert proc.stderr.splitlines()[0].startswith("realism harsh, seed "), proc.stderr
    if proc.returncode == 0:
        assert f"{mission}: on_true in " in proc.stdout
        return
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert f"{mission}: on_error in " in proc.stdout, proc.stdout[-2000:]
    errors = [line for line in proc.stderr.splitlines() if line.startswith("  error: ")]
    assert errors, proc.stderr[-2000:]
    # one line naming the device (at harsh: mostly "node 1 (left_wheel) encoder estimates
    # stale: none for 0.033 s (expected every 0.01 s)"); an action that starts while the base
    # recovers fails at once with "device 'base' is FAULT: ..."
    assert any("device base: " in line or "device 'base' is " in line for line in errors), errors
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize(
    ("profile", "mission", "seed"),
    [
        ("sim_rover.yaml", "rover_route", 3),
        ("sim_mobile_manipulator.yaml", "mobile_manipulation", 5),
    ],
)
def test_a_mission_at_harsh_ends_true_or_with_a_fault(
    profile: str, mission: str, seed: int
) -> None:
    proc = run_mission(ROOT / "hw_profiles" / profile, mission, seed)
    ends_true_or_with_a_fault(proc, mission)


@pytest.mark.skipif(_no_netns() is not None, reason=str(_no_netns()))
@pytest.mark.parametrize("seed", [4, 6])
def test_the_rover_over_a_real_bus_at_harsh_ends_true_or_with_a_fault(
    seed: int, tmp_path: Path
) -> None:
    doc = yaml.safe_load((ROOT / "hw_profiles" / "sim_rover.yaml").read_text())
    doc["devices"]["base"]["link"] = {
        "interface": "udp_multicast",
        "channel": "239.74.163.19",
        "fd": False,
    }
    profile = tmp_path / "rover_udp.yaml"
    profile.write_text(yaml.safe_dump(doc))
    proc = run_mission(profile, "rover_route", seed, netns=True)
    ends_true_or_with_a_fault(proc, "rover_route")
