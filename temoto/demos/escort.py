"""Demonstration 2, multi-robot escort (thesis §8).

Two rovers — a worker and an escort — are whole instances on an authenticated fleet bus, each
with a Robot Manager on its simulators and a Component Manager reading the same camera
descriptions (``data/cameras.yaml``: each camera's ``robot`` says who hosts it). The operator's
display is a Visualization Manager display (``docs/visualization.md``) of the worker's
``camera`` component: the worker's own camera feeds it. The worker's camera fails; the
Component Manager finds, through RIS, that the escort offers a camera, and asks the escort's
manager for it (a remote resource): the escort starts its camera, which now feeds the same
display (the display stays; its messages name the new camera). The escort then follows the
worker (0.7 m behind it) while the worker drives on.
"""

from __future__ import annotations

import json
import math
import os
import secrets
import signal
import threading
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Final

from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.clock import Clock, MonotonicClock, ScaledClock
from temoto.config import load_profile
from temoto.core.registrar import StatusUpdate
from temoto.demos._timeline import DemoReport, Timeline
from temoto.instance import Instance
from temoto.managers.robot import RobotHandle, RobotManager, RobotManagerClient
from temoto.managers.visualization import DisplayRequest, VisualizationManager
from temoto.transport import InProcessTransport

__all__ = ["run"]

DATA: Final = Path(__file__).resolve().parent / "data"
#: Where each robot's odometry frame starts in the world (the escort waits behind the worker).
ORIGIN: Final = {"worker": (0.0, 0.0), "escort": (-1.5, 0.0)}
FOLLOW_GAP: Final = 0.7  # metres behind the worker
WAIT: Final = 30.0


def _world(robot: RobotHandle) -> tuple[float, float]:
    x, y, _ = robot.pose()
    ox, oy = ORIGIN[robot.name]
    return x + ox, y + oy


class _Follower:
    """Keeps the escort ``FOLLOW_GAP`` behind the worker, re-aiming every 0.2 s of clock."""

    def __init__(self, escort: RobotHandle, worker: RobotHandle, clock: Clock) -> None:
        self.escort = escort
        self.worker = worker
        self.clock = clock
        self.cond = threading.Condition()
        self.stop = False
        self.thread = threading.Thread(target=self._follow, name="demo2-follow", daemon=True)
        self.thread.start()

    def _follow(self) -> None:
        while True:
            with self.cond:
                if self.stopping():
                    return
                self.clock.wait(self.cond, 0.2)
                if self.stopping():  # woken by close()
                    return
            wx, wy = _world(self.worker)
            ex, ey = _world(self.escort)
            gap = math.hypot(wx - ex, wy - ey)
            if gap <= FOLLOW_GAP + 0.15:
                continue
            k = (gap - FOLLOW_GAP) / gap  # a point on the line to the worker, GAP short of it
            tx, ty = ex + (wx - ex) * k, ey + (wy - ey) * k
            ox, oy = ORIGIN["escort"]
            self.escort.navigate_to(tx - ox, ty - oy)

    def stopping(self) -> bool:
        """Whether :meth:`close` was called (read afresh: another thread sets it)."""
        return self.stop

    def close(self) -> None:
        with self.cond:
            self.stop = True
            self.cond.notify_all()
        self.thread.join(5.0)


class _Shown:
    """Watches the operator's display: prints the first message of each camera."""

    def __init__(self, timeline: Timeline) -> None:
        self.timeline = timeline
        self.cond = threading.Condition()
        self.first: dict[str, float] = {}  # camera -> monotonic time of its first message

    def __call__(self, message: dict[str, Any]) -> None:
        camera = str(message.get("data", "")).split(" ", 1)[0]
        with self.cond:
            if camera and camera not in self.first:
                self.first[camera] = time.monotonic()
                self.timeline.say("display", f"showing {camera}")
                self.cond.notify_all()

    def wait_for(self, camera: str, timeout: float) -> float:
        """When ``camera``'s first message was shown (waiting up to ``timeout`` s)."""
        with self.cond:
            if not self.cond.wait_for(lambda: camera in self.first, timeout):
                raise TimeoutError(f"the display showed nothing from {camera} in {timeout:g} s")
            return self.first[camera]

    def order(self) -> list[str]:
        """The cameras in the order the display first showed them."""
        with self.cond:
            return sorted(self.first, key=self.first.__getitem__)


def run(
    timeline: Timeline,
    *,
    speed: float = 1.0,
    foxglove: tuple[str, int] | None = None,
    realism: str = "off",
    seed: int | None = None,
) -> DemoReport:
    """Run the demonstration.

    Args:
        timeline: Where events are printed.
        speed: Clock speed-up of the rovers (the cameras are real processes).
        foxglove: Serve the display live to Foxglove on this (host, port), or None.

        realism: The robots' simulators' realism level (``off``, ``typical``, ``harsh``).
        seed: The realism's seed (None: a fresh one at a level other than off).

    Returns:
        The report (facts: which camera fed the display, the switch-over time, the escort's
        gap to the worker at the end).
    """
    report = DemoReport()
    clock: Clock = MonotonicClock() if speed == 1 else ScaledClock(speed)
    bus = f"demo2-{secrets.token_hex(4)}"
    key = secrets.token_bytes(32)
    with ExitStack() as stack:
        instances: dict[str, Instance] = {}
        robots: dict[str, RobotHandle] = {}
        for actor in ("worker", "escort"):
            instance = stack.enter_context(
                Instance(
                    actor,
                    transport=InProcessTransport(bus),
                    key=key,
                    actions=[ROBOT_ACTIONS],
                    clock=clock,
                    advert_period_s=0.2,
                )
            )
            profile = load_profile(DATA / f"demo_{actor}.yaml", clock=clock)
            robot_manager = RobotManager(
                instance.registrar, profile, clock=clock, realism=realism, seed=seed
            )
            instance.add_manager(robot_manager)
            instance.components.add_file(DATA / "cameras.yaml")
            robots[actor] = RobotManagerClient(instance.registrar).request(client="demo")
            instances[actor] = instance
            timeline.say(actor, f"ready at {ORIGIN[actor]} (navigation; camera)")
        deadline = time.monotonic() + WAIT
        while "escort" not in instances["worker"].ris.providers("component"):
            if time.monotonic() > deadline:
                raise TimeoutError("the worker never heard the escort's Component Manager")
            time.sleep(0.02)
        timeline.say("worker", "RIS: the escort offers components")
        server = None
        if foxglove is not None:
            from temoto.managers.visualization.foxglove import FoxgloveServer

            server = FoxgloveServer(*foxglove, name="temoto demo 2")
            stack.callback(server.close)  # after the display's release (LIFO)
            timeline.say("foxglove", f"serving the display on {server.url}")
        displays = VisualizationManager(instances["worker"].registrar, server)
        stack.callback(displays.shutdown)
        shown = _Shown(timeline)

        def on_status(update: StatusUpdate) -> None:
            timeline.say("display", f"told: {update.status.value} {update.message}")

        request = DisplayRequest("component", target="camera", name="camera")
        ref = instances["worker"].registrar.call(
            "display", request, client="operator", on_status=on_status
        )
        displays.displays()["camera"].watch(shown)
        (component,) = instances["worker"].registrar.dependencies(ref.resource_id)
        shown.wait_for("worker_camera", WAIT)
        mission = json.loads((DATA / "worker_route.graph.json").read_text())
        instances["worker"].engine.start(mission)
        timeline.say("worker", "driving its route")
        time.sleep(clock.real_seconds(1.0))
        pid = component.response.pid
        timeline.say("operator", f"the worker's camera fails (process {pid} killed)")
        t_kill = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        t_escort = shown.wait_for("escort_camera", WAIT)
        report.facts["switch_over_ms"] = round((t_escort - t_kill) * 1000, 1)
        report.facts["camera_robot"] = (
            instances["worker"].registrar.info(component.id).response.robot
        )
        timeline.say("escort", "camera on; following the worker")
        follower = _Follower(robots["escort"], robots["worker"], clock)
        stack.callback(follower.close)
        result = instances["worker"].engine.wait(mission["graph_name"], WAIT * 2)
        timeline.say("worker", f"route ended: {result.value}")
        time.sleep(clock.real_seconds(3.0))  # the escort catches up
        follower.close()
        wx, wy = _world(robots["worker"])
        ex, ey = _world(robots["escort"])
        report.facts["escort_gap_m"] = round(math.hypot(wx - ex, wy - ey), 2)
        report.facts["worker_at"] = (round(wx, 2), round(wy, 2))
        report.facts["escort_at"] = (round(ex, 2), round(ey, 2))
        report.facts["shown"] = shown.order()
        instances["worker"].registrar.release(ref.id)
        report.ok = (
            report.facts["shown"] == ["worker_camera", "escort_camera"]
            and report.facts["camera_robot"] == "escort"
            and report.facts["escort_gap_m"] < FOLLOW_GAP + 0.5
            and result.value == "on_true"
        )
    return report
