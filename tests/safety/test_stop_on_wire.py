"""Motions end on the wire as they should, seen from the simulator's own process.

A stopped arm is held where it is; a vehicle whose GCS failsafe switched it to RTL ends the
flight action with the reason, and is left in RTL.

The arm's simulator runs in a process of its own (:mod:`temoto.testing.simhost`, over its
pseudo-terminal); this process runs the Robot Manager (control loop at 2 Hz, so that a hold left
to the control thread's next step would come up to half a second late) and a graph holding
MoveJoints, stopped 20 ms after the simulator reports the arm moving. The simulator's state lines
(its Goal Position and Moving registers, read every 2 ms) must show the hold before the engine
reported STOPPED, and the arm still soon after, not at the goal.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import yaml

from temoto import ActionEngine, Result
from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.config import parse_profile
from temoto.core.registrar import Registrar
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.testing.exitpaths import SimHost


def _close(host: SimHost) -> None:
    host.close()  # the host ends at the end of its input
    host._reader.join(5)
    for pipe in (host.proc.stdout, host.proc.stderr):
        if pipe is not None:
            pipe.close()


ROOT = Path(__file__).resolve().parents[2]
#: shoulder_pan (servo 1) from 0 to 2.5 rad: ~0.55 s at the XM430-W350's velocity limit.
TARGET = 2.5
#: Seconds between the wire and the host's report of it (it reads the registers every 2 ms;
#: lenient: a loaded machine can hold either process back; a hold left to the 2 Hz control
#: step, or never sent, comes later than this or not at all).
REPORT = 0.2

GRAPH = {
    "graph_name": "pan",
    "graph_entry": [{"name": "MoveJoints", "instance_id": 0}],
    "graph_exit": [{"name": "MoveJoints", "instance_id": 0}],
    "actions": [
        {
            "name": "MoveJoints",
            "instance_id": 0,
            "type": "sync",
            "input_parameters": {
                "joints": {"pvf_type": "strings", "pvf_value": ["shoulder_pan"]},
                "positions": {"pvf_type": "numbers", "pvf_value": [TARGET]},
            },
        }
    ],
}


def _moving(line: dict[str, Any]) -> bool:
    return any(line["state"]["moving"].values())


def test_a_stopped_move_is_held_on_the_wire_before_the_graph_is_stopped() -> None:
    doc = yaml.safe_load((ROOT / "hw_profiles" / "sim_arm.yaml").read_text())
    host = SimHost(doc["devices"]["arm"], {})
    registrar = Registrar("test-stop-wire")
    try:
        doc["sim"] = False
        doc["devices"]["arm"] = dict(host.config)
        profile = parse_profile(doc, file="sim_arm.yaml")
        manager = RobotManager(registrar, profile, rate_hz=2)
        try:
            watcher = RobotManagerClient(registrar).request(client="watcher")
            start_goal = host.states[-1]["state"]["goal"]["1"]
            with ActionEngine("arm", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
                t_start = time.monotonic()
                engine.start(GRAPH)
                deadline = t_start + 10
                while not any(_moving(s) for s in host.states if s["t"] >= t_start):
                    assert time.monotonic() < deadline, "the arm did not move"
                    time.sleep(0.002)
                goal = next(
                    s["state"]["goal"]["1"]
                    for s in host.states
                    if s["t"] >= t_start and s["state"]["goal"]["1"] != start_goal
                )
                time.sleep(0.02)
                t_stop = time.monotonic()
                assert engine.stop("pan", 10) is Result.STOPPED
                t_stopped = time.monotonic()
            time.sleep(0.5)
            after = [s for s in host.states if s["t"] >= t_stop]
            held = [s for s in after if s["state"]["goal"]["1"] != goal]
            assert held, f"the goal stayed {goal} (the move's) after the stop: {after[-1:]}"
            # on the wire before STOPPED was reported (the host sees it within REPORT)
            assert held[0]["t"] <= t_stopped + REPORT, (held[0]["t"] - t_stopped, t_stopped)
            last = host.states[-1]
            assert not _moving(last), last
            # held near where it was, far from the goal (2.5 rad is ~1630 ticks from the start)
            assert abs(last["state"]["goal"]["1"] - goal) > 300, (last, goal)
            registrar.release(watcher.resource.id)
        finally:
            manager.shutdown()
    finally:
        registrar.close()
        _close(host)


def test_a_failsafe_rtl_after_a_link_outage_ends_the_flight_with_the_reason() -> None:
    doc = yaml.safe_load((ROOT / "hw_profiles" / "sim_quad.yaml").read_text())
    entry = doc["devices"]["quad"]
    # ArduCopter's GCS failsafe after 2 s without our heartbeat (FS_GCS_TIMEOUT's minimum); the
    # outage below is of the uplink only (the vehicle's telemetry still reaches us), so the
    # driver sees no fault of the link: only the vehicle's own switch to RTL can end the flight
    entry.update(gcs_failsafe={"enable": 1, "timeout": 2}, heartbeat_timeout=2.0)
    host = SimHost(entry, {})
    registrar = Registrar("test-failsafe-wire")
    try:
        doc["sim"] = False
        doc["devices"]["quad"] = dict(host.config)
        manager = RobotManager(registrar, parse_profile(doc, file="sim_quad.yaml"))
        try:
            watcher = RobotManagerClient(registrar).request(client="watcher")
            motion = watcher.takeoff(3.0)
            assert motion.wait(30)
            assert motion.error is None, motion.error
            lat, lon = watcher.telemetry().position.lat, watcher.telemetry().position.lon
            graph = {
                "graph_name": "fly",
                "graph_entry": [{"name": "FlyTo", "instance_id": 0}],
                "graph_exit": [{"name": "FlyTo", "instance_id": 0}],
                "actions": [
                    {
                        "name": "FlyTo",
                        "instance_id": 0,
                        "type": "sync",
                        "input_parameters": {
                            "lat": {"pvf_type": "number", "pvf_value": lat + 0.01},
                            "lon": {"pvf_type": "number", "pvf_value": lon},
                            "alt": {"pvf_type": "number", "pvf_value": 3.0},
                        },
                    }
                ],
            }
            with ActionEngine("quad", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
                engine.start(graph)
                time.sleep(0.3)
                host.command("inject uplink_loss")
                host.wait("safe", since=time.monotonic(), timeout=10)  # RTL, seen by the host
                host.command("clear uplink_loss")
                t_back = time.monotonic()
                result = engine.wait("fly", 10)  # not RUNNING until killed
                took = time.monotonic() - t_back
                errors = [str(e) for e in engine.outcome("fly").errors]
            assert result is Result.ERROR, errors
            assert any("the vehicle switched to RTL (not commanded)" in e for e in errors), errors
            assert took < 3.0, took  # a heartbeat period (1 s) or two after the link is back
            assert host.states[-1]["state"]["mode"] in ("RTL", "LAND"), host.states[-1]
            registrar.release(watcher.resource.id)
        finally:
            manager.shutdown()
    finally:
        registrar.close()
        _close(host)
