"""Robot Manager: start-to-ready time and idle memory of a robot instance; stop to still.

Each round starts ``python -m temoto.managers.robot --profile <profile> --local`` (serving, no
mission) as a fresh process, measures from ``Popen`` to its "robot '<name>' ready" line (profile
load, instance, simulators, drivers configured and activated, robot loaded), reads its VmRSS
after it has idled for a second (half a second in quick mode), and stops it with SIGTERM.

``stop_to_still_ms``, a graph's stop command -> every commanded device still.

For each robot of the shipped simulated profiles (the rover's ODrive base, the Dynamixel arm,
the MAVLink quadcopter in the air), a Robot Manager with its simulators in this process (real
time, the control loop at 50 Hz) runs a one-node graph (NavigateTo 3 m, MoveJoints to pose
'reach', FlyTo 2 km). While the device moves (the wheels above 5 rad/s, the arm 20 ms into its
move, the vehicle above 5 m/s), ``engine.stop`` is called on another thread; this thread reads
the simulator's state every 1 ms and takes the time from the stop call to the first reading
in which every device of the robot is still:

* base: every wheel below 0.24 rad/s (the Dynamixel Moving Threshold's default speed; 2 cm/s at
  the rover's 8 cm wheel);
* arm: every servo's Moving register 0 (the servo's own flag: under its Moving Threshold,
  0.24 rad/s by default, ROBOTIS e-Manual, address 122);
* vehicle: horizontal speed below 0.1 m/s.

``stop_to_rest_command_ms`` is the part of it until the simulator holds the rest set-point
(the wheels' input velocity 0, the arm's goal positions no longer the pose's, the vehicle in
LOITER); the rest is the device slowing down (the simulated ODrive axes and servos are driven
by their controllers' torque, bounded by their current limits, against inertia and friction).
``stop_decel_min_base_ms`` is the least of that slowing down the base's torque limit allows
from the speed its wheels had when the zero reached them (the whole limit braking all the way);
``stop_decel_min_vehicle_ms`` the least the vehicle's lean limit allows (g·tan ``ANGLE_MAX``)
from its speed when it entered LOITER.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench.common import Results, median

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "hw_profiles" / "sim_mobile_manipulator.yaml"


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError(f"no VmRSS for {pid}")


def _one(profile: Path, idle_s: float) -> tuple[float, float]:
    env = {k: v for k, v in os.environ.items() if k != "TEMOTO_FLEET_KEY"}
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-m", "temoto.managers.robot", "--profile", str(profile), "--local"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        ready = time.perf_counter() - t0
        if "ready" not in line:
            raise RuntimeError(f"the robot did not get ready: {line!r} (exit {proc.poll()})")
        time.sleep(idle_s)  # idle: the control loop and the drivers' threads keep running
        rss = _rss_mb(proc.pid)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return ready, rss


def bench_robot(quick: bool) -> Results:
    out = Results()
    if not PROFILE.is_file():
        out.notes.append(f"{PROFILE.name} not found: robot_manager_* skipped")
        return out
    rounds = 2 if quick else 10
    idle_s = 0.5 if quick else 1.0
    samples = [_one(PROFILE, idle_s) for _ in range(rounds)]
    ready = [s[0] for s in samples]
    rss = [s[1] for s in samples]
    how = f"{PROFILE.name} (simulators in-process), --local, {rounds} fresh processes"
    idle = f"VmRSS after {idle_s:g} s idle"
    out.add(
        "robot_manager_ready_s",
        median(ready),
        "s",
        f"{how}: Popen -> 'ready' line; min {min(ready):.2f}, max {max(ready):.2f}",
        ("<=", 1.5),
    )
    out.add(
        "robot_manager_idle_rss_mb",
        median(rss),
        "MB",
        f"{how}: {idle}; min {min(rss):.1f}, max {max(rss):.1f}",
        ("<=", 60.0),
    )
    stops = bench_stop_to_still(quick)
    out.metrics.extend(stops.metrics)
    out.notes.extend(stops.notes)
    return out


PROFILES = ROOT / "hw_profiles"

#: The goal: every commanded device still within 100 ms of the stop command.
GOAL_MS = 100.0

#: X-series control table (ROBOTIS e-Manual): Goal Position 116, Moving 122, Present Position
#: 132.
_GOAL, _MOVING, _PRESENT = 116, 122, 132


def _graph(action: str, inputs: dict[str, Any]) -> dict[str, Any]:
    node = {"name": action, "instance_id": 0}
    params = {
        k: {"pvf_type": "string" if isinstance(v, str) else "number", "pvf_value": v}
        for k, v in inputs.items()
    }
    return {
        "graph_name": "motion",
        "graph_entry": [node],
        "graph_exit": [node],
        "actions": [{**node, "type": "sync", "input_parameters": params}],
    }


#: rad/s: "still" for a wheel (the Dynamixel Moving Threshold's default speed).
_STILL_RAD_S = 0.24


def _decel_min_s(axis: Any, speed: float) -> float:
    """Seconds the axis needs at the least from ``speed`` (turn/s) to still, at its torque limit.

    The whole torque limit ``T`` braking, helped by the load's viscous friction ``d``, against
    the inertia ``J`` (turn units): ``J dv/dt = -(T + d v)``, so ``t = J/d ln((T + d v0) /
    (T + d v_still))``. No controller stops quicker (its PI leaves the limit near zero speed).
    """
    inertia = 2 * math.pi * (axis.inertia + axis.load_inertia)  # N·m per turn/s²
    top, damping = axis.torque_limit, axis.damping
    still = _STILL_RAD_S / (2 * math.pi)
    if speed <= still:
        return 0.0
    if damping <= 0:
        return inertia * (speed - still) / top
    return inertia / damping * math.log((top + damping * speed) / (top + damping * still))


class _Base:
    """The wheels' readings; the least deceleration time noted when the zero set-point lands."""

    def __init__(self) -> None:
        self.moved = False
        #: ms: the current-limited minimum from the speed the wheels had when the zero reached
        #: them (None until it did).
        self.decel_min_ms: float | None = None
        #: rad/s: that speed (the fastest wheel).
        self.speed_at_rest: float | None = None

    def __call__(self, sim: Any) -> tuple[bool, bool, bool]:
        axes = list(sim.axes.values())
        vels = [abs(a.vel) * 2 * math.pi for a in axes]  # ODrive: rev/s; here rad/s
        moving = max(vels) > 5.0
        self.moved = self.moved or moving
        rest = all(a.input_vel == 0 for a in axes)
        if rest and self.moved and self.decel_min_ms is None:
            # the model was stepped to each zero's arrival (the simulator steps an axis on
            # every frame): these are the speeds the stop starts from
            self.speed_at_rest = max(vels)
            self.decel_min_ms = 1000 * max(_decel_min_s(a, abs(a.vel)) for a in axes)
        return moving, rest, max(vels) < _STILL_RAD_S


class _Arm:
    """The arm's readings; the pose's goal of shoulder_lift (servo 2) noted while it moves."""

    def __init__(self) -> None:
        self.pose_goal: int | None = None

    def __call__(self, sim: Any) -> tuple[bool, bool, bool]:
        flags = [sim.read_register(i, _MOVING) for i in sim.ids]
        goal = sim.read_register(2, _GOAL)
        if self.pose_goal is None and any(flags):
            self.pose_goal = goal
        rest = self.pose_goal is not None and goal != self.pose_goal  # the hold arrived
        return any(flags), rest, not any(flags)


#: m/s: "still" for the vehicle (horizontal speed).
_STILL_M_S = 0.1


class _Vehicle:
    """The vehicle's readings; the least braking time noted when it is in LOITER."""

    def __init__(self) -> None:
        self.moved = False
        #: ms: the least time the lean limit (``ANGLE_MAX``: g·tan) needs from the speed the
        #: vehicle had when it entered LOITER to still (None until it did).
        self.decel_min_ms: float | None = None
        #: m/s: that speed.
        self.speed_at_rest: float | None = None

    def __call__(self, sim: Any) -> tuple[bool, bool, bool]:
        speed = math.hypot(sim.vel[0], sim.vel[1])
        moving = speed > 5.0
        self.moved = self.moved or moving
        rest = sim.mode == "LOITER"
        if rest and self.moved and self.decel_min_ms is None:
            self.speed_at_rest = speed
            top = sim.state.max_accel()  # m/s²
            self.decel_min_ms = 1000 * max(0.0, speed - _STILL_M_S) / top
        return moving, rest, speed < _STILL_M_S


def _stop_once(
    profile: str, device: str, graph: dict[str, Any], read: Callable[..., Any]
) -> tuple[float, float]:
    from temoto import ActionEngine
    from temoto.actions.builtin import ROBOT_ACTIONS
    from temoto.config import load_profile
    from temoto.core.registrar import Registrar
    from temoto.managers.robot import RobotManager, RobotManagerClient

    registrar = Registrar(f"bench-{device}")
    manager = RobotManager(registrar, load_profile(PROFILES / profile))
    try:
        watcher = RobotManagerClient(registrar).request(client="bench")
        sim = manager.simulator(device)
        if device == "quad":
            motion = watcher.takeoff(5.0)
            if not motion.wait(30) or motion.error is not None:
                raise RuntimeError(f"the quad did not take off: {motion.error}")
            lat, lon, _ = sim.home
            graph = _graph("FlyTo", {"lat": lat + 2000 / 111_195.0, "lon": lon, "alt": 5.0})
        with ActionEngine("bench", actions=[ROBOT_ACTIONS], registrar=registrar) as engine:
            engine.start(graph)
            deadline = time.monotonic() + 30
            while not read(sim)[0]:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{device} did not move")
                time.sleep(0.001)
            if device == "arm":
                time.sleep(0.02)
            stopper = threading.Thread(
                target=engine.stop, args=("motion", 30), name="temoto-bench-stop"
            )
            t0 = time.perf_counter()
            stopper.start()
            rest_at = still_at = None
            while still_at is None or rest_at is None:
                _, rest, still = read(sim)
                now = time.perf_counter()
                if rest and rest_at is None:
                    rest_at = now
                if still and still_at is None:
                    still_at = now
                if now - t0 > 10:
                    raise RuntimeError(f"{device} not still 10 s after the stop")
                time.sleep(0.001)
            stopper.join()
        registrar.release(watcher.resource.id)
        return (still_at - t0) * 1000, (rest_at - t0) * 1000
    finally:
        manager.shutdown()
        registrar.close()


def bench_stop_to_still(quick: bool) -> Results:
    """``stop_to_still_ms`` (the slowest robot's median) and per robot ``..._<robot>_ms``."""
    out = Results()
    cases = {
        "base": (
            "sim_rover.yaml",
            "base",
            _graph("NavigateTo", {"x": 3.0, "y": 0.0}),
            _Base,
        ),
        "arm": ("sim_arm.yaml", "arm", _graph("MoveJoints", {"pose": "reach"}), _Arm),
        "vehicle": ("sim_quad.yaml", "quad", {}, _Vehicle),
    }
    rounds = 1 if quick else 7
    still: dict[str, list[float]] = {k: [] for k in cases}
    rest: dict[str, list[float]] = {k: [] for k in cases}
    failed: dict[str, list[str]] = {k: [] for k in cases}
    # per robot with a deceleration bound: (the least deceleration ms, the speed) per stop
    decel: dict[str, list[tuple[float, float]]] = {"base": [], "vehicle": []}
    for _ in range(rounds):
        for name, (profile, device, graph, read) in cases.items():
            for _attempt in range(3):  # a device that faulted under load: that round again
                reader = read()
                try:
                    s, r = _stop_once(profile, device, graph, reader)
                except RuntimeError as err:
                    failed[name].append(str(err))
                    continue
                still[name].append(s)
                rest[name].append(r)
                if isinstance(reader, (_Base, _Vehicle)) and reader.decel_min_ms is not None:
                    decel[name].append((reader.decel_min_ms, reader.speed_at_rest or 0.0))
                break
    for name, errors in failed.items():
        if errors:
            out.notes.append(f"{name}: {len(errors)} round(s) again after: {errors[-1]}")
    if not all(still.values()):
        out.notes.append("stop_to_still_ms: a robot never completed a round; not measured")
        return out
    how = f"in-process simulators, real time, control loop 50 Hz, {rounds} stops each"
    worst = max(median(v) for v in still.values())
    out.add(
        "stop_to_still_ms",
        worst,
        "ms",
        f"engine.stop -> every device still (the slowest robot's median; {how})",
        ("<=", GOAL_MS),
    )
    for name in cases:
        s, r = still[name], rest[name]
        out.add(
            f"stop_to_still_{name}_ms",
            median(s),
            "ms",
            f"min {min(s):.1f}, max {max(s):.1f}; rest set-point held after {median(r):.1f} ms"
            f" (max {max(r):.1f})",
        )
        out.add(f"stop_to_rest_command_{name}_ms", median(r), "ms", f"max {max(r):.1f}")
    bounds = {
        "base": ("the wheels' torque limit", "the zero reached them", "rad/s"),
        "vehicle": ("the lean limit (g·tan ANGLE_MAX)", "it entered LOITER", "m/s"),
    }
    for name, (what, when, unit) in bounds.items():
        if decel[name]:
            speeds = [v for _, v in decel[name]]
            out.add(
                f"stop_decel_min_{name}_ms",
                median([d for d, _ in decel[name]]),
                "ms",
                f"the least time {what} needs from the speed at which {when}"
                f" ({min(speeds):.2f} - {max(speeds):.2f} {unit}) to still; a physical bound,"
                f" part of stop_to_still_{name}_ms",
            )
    return out
