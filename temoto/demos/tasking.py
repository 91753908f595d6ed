"""Demonstration 4, source-agnostic tasking (thesis §8).

A task in words — "go to the workshop, pick up the object, then go to the lobby" — is turned
into a UMRF graph by a task source (:class:`~temoto.tasking.RuleBasedTaskSource`, offline; a
language-model source would plug into the same :class:`~temoto.tasking.TaskSource` interface),
the graph is checked by the engine (validation and planning: every action must resolve) and run
on the simulated mobile manipulator. A second task naming a place the robot does not know is
refused before anything moves, with the reason.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Final

from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.clock import Clock, MonotonicClock, ScaledClock
from temoto.config import load_profile
from temoto.core.documents import graph_from_document
from temoto.core.engine import ActionEngine
from temoto.core.instrument import Instrument
from temoto.core.registrar import Registrar
from temoto.core.states import NodeState, Result
from temoto.core.validation import validate_graph
from temoto.demos._timeline import DemoReport, Timeline
from temoto.errors import TaskParseError
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.tasking import RuleBasedTaskSource

__all__ = ["PLACES", "TASK", "run"]

PROFILE: Final = Path(__file__).resolve().parent / "data" / "demo_mobile_manipulator.yaml"
#: The places the robot knows, in its odometry frame (metres).
PLACES: Final = {"workshop": (2.0, 0.5), "lobby": (-1.0, 1.0), "dock": (0.0, 0.0)}
#: The task the demonstration runs.
TASK: Final = "Go to the workshop, pick up the object, then go to the lobby and put it down."
#: A task it must refuse.
BAD_TASK: Final = "go to the kitchen and pick up the mug"


class _Steps(Instrument):
    def __init__(self, timeline: Timeline, labels: dict[str, str]) -> None:
        self.timeline = timeline
        self.labels = labels

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        if new in (NodeState.RUNNING, NodeState.FINISHED, NodeState.ERROR):
            what = "started" if new is NodeState.RUNNING else new.value.lower()
            self.timeline.say("robot", f"{node} ({self.labels.get(node, '')}) {what}")


def run(
    timeline: Timeline, *, speed: float = 1.0, realism: str = "off", seed: int | None = None
) -> DemoReport:
    """Run the demonstration.

    Args:
        timeline: Where events are printed.
        speed: Clock speed-up of the robot (1: real time).

        realism: The robots' simulators' realism level (``off``, ``typical``, ``harsh``).
        seed: The realism's seed (None: a fresh one at a level other than off).

    Returns:
        The report (facts: the steps understood, the result, where the robot ended, the
        refusal of the second task).
    """
    report = DemoReport()
    clock: Clock = MonotonicClock() if speed == 1 else ScaledClock(speed)
    source = RuleBasedTaskSource(PLACES)
    timeline.say("operator", f"task: {TASK!r}")
    doc = source.graph(TASK, graph_name="spoken_task")
    steps = [f"{a['name']}_{a['instance_id']}: {a['description']}" for a in doc["actions"]]
    for step in steps:
        timeline.say(source.name, step)
    report.facts["steps"] = [a["name"] for a in doc["actions"]]
    graph = graph_from_document(doc)
    report_v = validate_graph(graph)
    report_v.raise_for_errors()
    timeline.say("engine", f"graph '{graph.name}' valid ({len(graph.actions)} actions)")
    registrar = Registrar("demo4")
    manager = RobotManager(
        registrar, load_profile(PROFILE, clock=clock), clock=clock, realism=realism, seed=seed
    )
    try:
        robot = RobotManagerClient(registrar).request(client="demo")
        timeline.say("robot", f"ready ({', '.join(robot.features)}; simulated)")
        labels = {f"{a['name']}_{a['instance_id']}": a["description"] for a in doc["actions"]}
        with ActionEngine(
            "robot",
            actions=[ROBOT_ACTIONS],
            registrar=registrar,
            clock=clock,
            instruments=[_Steps(timeline, labels)],
        ) as engine:
            engine.plan(graph)  # every action resolves, or this says which does not
            outcome = engine.run(graph, timeout=120)
            timeline.say("engine", f"'{graph.name}' ended: {report_result(outcome.result)}")
            report.facts["result"] = report_result(outcome.result)
            x, y, _ = robot.pose()
            report.facts["robot_at"] = (round(x, 2), round(y, 2))
            timeline.say("operator", f"task: {BAD_TASK!r}")
            try:
                source.graph(BAD_TASK)
            except TaskParseError as err:
                timeline.say(source.name, f"refused: {err}")
                report.facts["refused"] = str(err)
        registrar.release(robot.resource.id)
    finally:
        manager.shutdown()
        registrar.close()
    lobby = PLACES["lobby"]
    report.ok = (
        report.facts.get("result") == Result.TRUE.value
        and math.dist(report.facts["robot_at"], lobby) < 0.2
        and "kitchen" in report.facts.get("refused", "")
    )
    return report


def report_result(result: Result | None) -> str:
    """``on_true`` etc., or ``none`` while a run has no result."""
    return result.value if result is not None else "none"
