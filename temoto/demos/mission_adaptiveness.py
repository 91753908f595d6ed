"""Demonstration 3, mission adaptiveness (thesis §8).

A rover patrols three locations in a loop (a cyclic graph, ``data/surveillance.graph.json``).
Mid-mission the operator, from another process's point of view (a
:class:`~temoto.fleet.control.GraphCommander` on the fleet bus), pauses the patrol and starts a
delivery shared by the rover and an arm station (``data/delivery.graph.json``: the rover drives
to the station, the arm loads the parcel, the rover delivers it). When the delivery has ended
on both robots the patrol resumes where it was — the goal it was driving to when it was paused
is driven to again, since the delivery used the rover meanwhile — and is stopped after it has
reached its next location.

Both robots are whole instances (:class:`~temoto.instance.Instance` with a Robot Manager on
their simulators: two ODrive wheel axes on a virtual CAN bus, a Dynamixel arm on a
pseudo-terminal) joined by an authenticated in-process fleet bus.
"""

from __future__ import annotations

import json
import secrets
import threading
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Final

from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.clock import Clock, MonotonicClock, ScaledClock
from temoto.config import load_profile
from temoto.core.instrument import Instrument
from temoto.core.states import NodeState, Result
from temoto.demos._timeline import DemoReport, Timeline
from temoto.fleet.control import GraphCommander
from temoto.instance import Instance
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.transport import FleetAuth, FleetLink, InProcessTransport

__all__ = ["run"]

DATA: Final = Path(__file__).resolve().parent / "data"
ROBOTS: Final = (("rover", "demo_rover.yaml"), ("arm_station", "demo_arm_station.yaml"))
WAIT: Final = 60.0  # real seconds any single step may take


class _Steps(Instrument):
    """Prints the starts and ends of one robot's own actions; lets the demo wait for them.

    Args:
        actor: The robot.
        timeline: Where to print.
        wake: Notified on every end.
        remote: Per graph, the nodes another actor runs (their mirrors here are not printed).
        labels: Per node, what it does (the action's description), printed beside its name.
    """

    def __init__(
        self,
        actor: str,
        timeline: Timeline,
        wake: threading.Condition,
        remote: dict[str, set[str]],
        labels: dict[str, str],
    ) -> None:
        self.actor = actor
        self.timeline = timeline
        self.wake = wake
        self.remote = remote
        self.labels = labels
        self.finished: list[tuple[str, str]] = []  # (graph, node), in order

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Print starts, pauses and ends; remember ends."""
        if node in self.remote.get(graph, ()):
            return
        label = self.labels.get(f"{graph}/{node}")
        shown = f"{node} ({label})" if label else node
        if new is NodeState.RUNNING:
            verb = "resumed" if old is NodeState.PAUSED else "started"
            self.timeline.say(self.actor, f"{graph}: {shown} {verb}")
        elif new is NodeState.PAUSED:
            self.timeline.say(self.actor, f"{graph}: {shown} paused")
        elif new in (NodeState.FINISHED, NodeState.ERROR):
            self.timeline.say(self.actor, f"{graph}: {shown} {new.value.lower()}")
            with self.wake:
                self.finished.append((graph, node))
                self.wake.notify_all()

    def graph_finished(self, graph: str, result: Result, t: float) -> None:
        """Print the end of a run."""
        self.timeline.say(self.actor, f"{graph} ended: {result.value}")


def run(
    timeline: Timeline, *, speed: float = 1.0, realism: str = "off", seed: int | None = None
) -> DemoReport:
    """Run the demonstration.

    Args:
        timeline: Where events are printed.
        speed: Clock speed-up of the robots (1: real time).

        realism: The robots' simulators' realism level (``off``, ``typical``, ``harsh``).
        seed: The realism's seed (None: a fresh one at a level other than off).

    Returns:
        The report (facts: pause/resume times, delivery results, patrol legs).
    """
    report = DemoReport()
    clock: Clock = MonotonicClock() if speed == 1 else ScaledClock(speed)
    bus = f"demo3-{secrets.token_hex(4)}"
    key = secrets.token_bytes(32)
    wake = threading.Condition()
    surveillance = json.loads((DATA / "surveillance.graph.json").read_text())
    delivery = json.loads((DATA / "delivery.graph.json").read_text())
    with ExitStack() as stack:
        instances: dict[str, Instance] = {}
        steps: dict[str, _Steps] = {}
        for actor, profile_file in ROBOTS:
            instance = stack.enter_context(
                Instance(
                    actor,
                    transport=InProcessTransport(bus),
                    key=key,
                    actions=[ROBOT_ACTIONS],
                    clock=clock,
                    feedback_period_s=0.5,
                )
            )
            manager = RobotManager(
                instance.registrar,
                load_profile(DATA / profile_file, clock=clock),
                clock=clock,
                realism=realism,
                seed=seed,
            )
            instance.add_manager(manager)
            robot = RobotManagerClient(instance.registrar).request(client="demo")
            timeline.say(actor, f"ready ({', '.join(robot.features)}; simulated)")
            remote = {"delivery": _nodes_of_others(delivery, actor)}
            labels = {
                f"{g['graph_name']}/{a['name']}_{a['instance_id']}": a.get("description", "")
                for g in (surveillance, delivery)
                for a in g["actions"]
            }
            steps[actor] = _Steps(actor, timeline, wake, remote, labels)
            instance.engine.add_instrument(steps[actor])
            instances[actor] = instance
        operator_bus = stack.enter_context(InProcessTransport(bus))
        commander = stack.enter_context(
            GraphCommander(FleetLink(operator_bus, FleetAuth("temoto", "operator", key)))
        )
        rover = steps["rover"]

        def command(verb: str, targets: list[str], **kwargs: Any) -> None:
            timeline.say(
                "operator", f"{verb} {kwargs.get('graph') or 'graph'} on {', '.join(targets)}"
            )
            out = commander.command(verb, targets, timeout=WAIT, **kwargs)
            if not out.ok:
                raise RuntimeError(f"{verb}: {out}")

        def wait_finished(graph: str, node: str, after: int = 0) -> int:
            with wake:
                ok = wake.wait_for(
                    lambda: (graph, node) in rover.finished[after:], clock.real_seconds(WAIT)
                )
            if not ok:
                raise TimeoutError(f"{graph}: {node} did not finish")
            return rover.finished.index((graph, node), after) + 1

        command("start", ["rover"], graph="surveillance", graph_json=surveillance)
        wait_finished("surveillance", "NavigateTo_1")  # the yard, on the first lap
        command("pause", ["rover"], graph="surveillance")
        report.facts["paused_at_s"] = round(timeline.now(), 2)
        command("start", ["rover", "arm_station"], graph="delivery", graph_json=delivery)
        results = {a: instances[a].engine.wait("delivery", WAIT) for a in instances}
        report.facts["delivery"] = {a: r.value for a, r in results.items()}
        report.facts["delivery_s"] = round(timeline.now() - report.facts["paused_at_s"], 2)
        mark = len(rover.finished)
        command("resume", ["rover"], graph="surveillance")
        report.facts["resumed_at_s"] = round(timeline.now(), 2)
        wait_finished("surveillance", "NavigateTo_2", after=mark)  # the warehouse, again
        patrol = [n for g, n in rover.finished if g == "surveillance"]
        command("stop", ["rover"], graph="surveillance")
        report.facts["patrol_legs"] = patrol
        x, y, _ = RobotManagerClient(instances["rover"].registrar).request(client="demo").pose()
        report.facts["rover_at_stop"] = (round(x, 2), round(y, 2))
        report.ok = (
            all(r is Result.TRUE for r in results.values())
            and patrol == ["NavigateTo_0", "NavigateTo_1", "NavigateTo_2"]
            and instances["rover"].engine.outcome("surveillance").result is Result.STOPPED
        )
    return report


def _nodes_of_others(graph: dict[str, Any], actor: str) -> set[str]:
    """The full names of a graph's actions that another actor runs."""
    return {
        f"{a['name']}_{a['instance_id']}"
        for a in graph["actions"]
        if a.get("actor") not in (None, "", actor)
    }
