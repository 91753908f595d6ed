"""Every way out of the robot command leaves every device family in its safe state.

Each case runs :mod:`temoto.testing.exitpaths`: the device's simulator in a process of its own,
the robot command in another one talking to it over the real link (CAN over python-can's
``udp_multicast`` inside ``unshare -n``, the Dynamixel pseudo-terminal, MAVLink over UDP), and
the device's state as the simulator sees it on the wire. Bounds (docs/safety.md):
safe within 200 ms of SIGINT or SIGTERM; safe before the command exits at a mission's end, after
an action's exception or a driver fault; a second SIGINT exits at once; no process of the
command is left behind, and no traceback is printed.
"""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Any

import pytest

from temoto.testing.exitpaths import FAMILIES, why_not_netns

pytestmark = pytest.mark.slow

#: Milliseconds from a signal to every device safe, seen on the wire.
SIGNAL_BOUND_MS = 200.0
#: Exit codes per path.
RC = {"end": 0, "fault": 1, "exception": 1, "sigint": 130, "sigterm": 143, "double_sigint": 130}


needs_netns = pytest.mark.skipif(bool(why_not_netns()), reason=why_not_netns() or "ok")


def run(
    family: str,
    path: str,
    entry: dict[str, Any] | None = None,
    silent: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One exit path, in a private network namespace."""
    argv = [sys.executable, "-m", "temoto.testing.exitpaths", family, path, "--netns"]
    if entry is not None:
        argv += ["--entry", json.dumps(entry)]
    if silent is not None:
        argv += ["--silent", json.dumps(silent)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=90, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    return result


def _story(result: dict[str, Any]) -> str:
    states = [(round((s["t"] - result["event_t"]) * 1000, 1), s["state"]) for s in result["states"]]
    return (
        f"rc={result['rc']} safe_ms={result['safe_ms']} safe_at_exit={result['safe_at_exit']}\n"
        f"states (ms after the event): {states[:8]}\n"
        f"stdout:\n{result['stdout']}\nstderr:\n{result['stderr'][-2000:]}"
    )


@needs_netns
@pytest.mark.parametrize("path", list(RC))
@pytest.mark.parametrize("family", list(FAMILIES))
def test_every_exit_path_leaves_the_device_safe(family: str, path: str) -> None:
    result = run(family, path)
    story = _story(result)
    assert result["rc"] == RC[path], story
    assert not result["traceback"], story
    assert result["leftovers"] == [], story
    assert result["safe_at_exit"], story
    assert result["safe_t"] is not None, story
    if path in ("sigint", "sigterm", "double_sigint"):
        assert result["safe_ms"] <= SIGNAL_BOUND_MS, story
        assert ("SIGTERM" if path == "sigterm" else "SIGINT") in result["stderr"], story
        assert "device: " in result["stderr"], story  # one line per device
    else:  # safe before the command had exited
        assert result["safe_t"] <= result["exit_t"], story
    if path == "double_sigint":  # the second signal does not wait for the stuck action
        assert result["exit_t"] - result["second_t"] < 1.0, story


#: Seconds beyond a watchdog's bound for the simulator host's reads (every 2 ms) and scheduling.
WATCHDOG_SLACK_S = 0.03


@needs_netns
@pytest.mark.parametrize("family", list(FAMILIES))
def test_after_a_sigkill_the_devices_watchdog_makes_it_safe(family: str) -> None:
    # nothing of the robot command runs: only the watchdog the driver kept fed can help
    bound = FAMILIES[family]["sigkill_bound_s"]
    result = run(family, "sigkill")
    story = _story(result)
    assert result["rc"] == -9, story
    assert result["leftovers"] == [], story
    assert result["safe_t"] is not None, story
    assert result["safe_ms"] <= (bound + WATCHDOG_SLACK_S) * 1000.0, story
    assert result["safe_ms"] >= 0.0, story


def _six_servo_arm() -> dict[str, Any]:
    """The Dynamixel family's arm with six servos (each unanswered torque-off costs a reply)."""
    entry = json.loads(json.dumps(FAMILIES["dynamixel"]["device"]))
    servo = entry["servos"][0]
    entry["servos"] = [{**servo, "id": i, "joint": f"joint{i}"} for i in range(1, 7)]
    return entry


@needs_netns
def test_sigterm_makes_every_device_safe_at_once_with_two_links_silent() -> None:
    # the rover's ODrive acts; the arm's and the quad's links are cut just before SIGTERM:
    # their safe states wait for replies that never come, which must not delay the base
    silent = {"arm": _six_servo_arm(), "quad": dict(FAMILIES["mavlink"]["device"])}
    result = run("odrive", "sigterm", silent=silent)
    story = _story(result)
    assert result["rc"] == 143, story
    assert not result["traceback"], story
    assert result["leftovers"] == [], story
    assert result["safe_t"] is not None, story
    assert result["safe_ms"] <= SIGNAL_BOUND_MS, story
    lines = [line.strip() for line in result["stderr"].splitlines() if line.startswith("  ")]
    named = {line.partition(": ")[0]: line for line in lines}
    assert set(named) >= {"arm", "device", "quad"}, story  # one line per device, always
    assert named["device"].startswith("device: left_wheel IDLE"), story
    assert "NOT SAFE" not in result["stderr"], story
