"""Demonstration 5, multi-robot knowledge sharing (thesis §8).

Three robots — two scouts and a worker (a rover carrying an arm) — are whole instances on one
authenticated fleet bus; each has a Context Manager, and their world models are kept the same
over the fleet. The worker puts the map, the bin and itself into the model. The scouts search
(``data/scout_*_search.graph.json``) and report what they find with the built-in ``AddItem``
action: one finds the trash, the other a chair. The worker's graph
(``data/take_out_the_trash.graph.json``) waits with ``GetItem`` until the trash is known, drives
to it, picks it up and re-parents it to itself (map → worker), drives to the bin, drops it and
re-parents it to the bin (worker → bin). At the end every robot holds the same tree.
"""

from __future__ import annotations

import contextlib
import json
import secrets
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import Final

from temoto.actions.builtin import ROBOT_ACTIONS
from temoto.clock import Clock, MonotonicClock, ScaledClock
from temoto.config import load_profile
from temoto.core.instrument import Instrument
from temoto.core.states import NodeState, Result
from temoto.demos._timeline import DemoReport, Timeline
from temoto.instance import Instance
from temoto.managers.context import Change, ContextManager, Pose
from temoto.managers.robot import RobotManager, RobotManagerClient
from temoto.transport import InProcessTransport

__all__ = ["run"]

DATA: Final = Path(__file__).resolve().parent / "data"
ROBOTS: Final = (
    ("scout_1", "demo_scout_1.yaml", "scout_1_search.graph.json"),
    ("scout_2", "demo_scout_2.yaml", "scout_2_search.graph.json"),
    ("worker", "demo_worker_mm.yaml", "take_out_the_trash.graph.json"),
)
BIN_AT: Final = (3.3, 0.0)
WAIT: Final = 60.0


class _Steps(Instrument):
    """Prints the starts and ends of one robot's actions, with what each is for."""

    def __init__(self, actor: str, timeline: Timeline, labels: dict[str, str]) -> None:
        self.actor = actor
        self.timeline = timeline
        self.labels = labels

    def node_transition(
        self, graph: str, node: str, old: NodeState, new: NodeState, t: float
    ) -> None:
        """Print it."""
        if new in (NodeState.RUNNING, NodeState.FINISHED, NodeState.ERROR):
            what = "started" if new is NodeState.RUNNING else new.value.lower()
            self.timeline.say(self.actor, f"{node} ({self.labels.get(node, '')}) {what}")


def _tree_lines(context: ContextManager, name: str = "", depth: int = 0) -> list[str]:
    lines = []
    for item in context.children(name):
        lines.append(f"{'  ' * depth}{item.name} ({item.type}, by {item.maintainer})")
        lines.extend(_tree_lines(context, item.name, depth + 1))
    return lines


def _until(check: Callable[[], bool], what: str, timeout: float = 10.0) -> None:
    """Wait (polling every 10 ms, bounded) for something another thread brings about."""
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out waiting until {what}")
        time.sleep(0.01)


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
        The report (facts: who found what, the trash's path in each robot's tree, whether the
        trees are equal).
    """
    report = DemoReport()
    clock: Clock = MonotonicClock() if speed == 1 else ScaledClock(speed)
    bus = f"demo5-{secrets.token_hex(4)}"
    key = secrets.token_bytes(32)
    with ExitStack() as stack:
        instances: dict[str, Instance] = {}
        graphs: dict[str, dict[str, object]] = {}
        for actor, profile_file, graph_file in ROBOTS:
            instance = stack.enter_context(
                Instance(
                    actor,
                    transport=InProcessTransport(bus),
                    key=key,
                    actions=[ROBOT_ACTIONS],
                    clock=clock,
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
            graph = json.loads((DATA / graph_file).read_text())
            labels = {f"{a['name']}_{a['instance_id']}": a["description"] for a in graph["actions"]}
            instance.engine.add_instrument(_Steps(actor, timeline, labels))
            instances[actor], graphs[actor] = instance, graph
            timeline.say(actor, f"ready ({', '.join(robot.features)})")
        worker = instances["worker"].context

        def seen(change: Change) -> None:
            if change.robot != "worker":
                timeline.say(
                    "worker",
                    f"its world model learnt {', '.join(change.names)} from {change.robot}",
                )

        worker.listen(seen)
        worker.add("map", "map")
        worker.add("bin", "bin", "map", Pose(BIN_AT[0], BIN_AT[1], 0.0, 0.0, 0.0, 0.0, 1.0))
        worker.add("worker", "robot", "map")
        for scout in ("scout_1", "scout_2"):
            _until(lambda s=scout: "map" in instances[s].context, f"{scout} learns the map")  # type: ignore[misc]
            instances[scout].context.add(scout, "robot", "map")
        timeline.say("worker", "put the map, the bin and itself into the world model")
        for actor, _, _ in ROBOTS:
            instances[actor].engine.start(graphs[actor])
        results = {
            actor: instances[actor].engine.wait(str(graphs[actor]["graph_name"]), WAIT)
            for actor, _, _ in ROBOTS
        }
        report.facts["results"] = {a: r.value for a, r in results.items()}

        def equal() -> bool:
            return len({i.context.digest() for i in instances.values()}) == 1

        with contextlib.suppress(TimeoutError):  # reported as trees_equal: False
            _until(equal, "every robot holds the same tree")
        report.facts["trees_equal"] = equal()
        report.facts["trash_path"] = {a: i.context.path("trash") for a, i in instances.items()}
        report.facts["found_by"] = {
            name: worker.get(name).maintainer for name in ("trash", "chair") if name in worker
        }
        for line in _tree_lines(worker):
            timeline.say("world model", line)
        trash_xy = worker.world_pose("trash")
        report.facts["trash_at"] = (round(trash_xy.x, 2), round(trash_xy.y, 2))
        report.ok = (
            all(r is Result.TRUE for r in results.values())
            and report.facts["trees_equal"]
            and all(p == ["map", "bin", "trash"] for p in report.facts["trash_path"].values())
        )
    return report
