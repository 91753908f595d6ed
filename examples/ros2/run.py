"""Run ros2_tour.graph.json on an engine with the ROS 2 servers (docs/ros2.md).

Start the peer first, with the Python that has rclpy::

    python examples/ros2/peer.py &
    python examples/ros2/run.py [--order N]

With the ROS wheels in another environment, set ``TEMOTO_ROS2_PYTHON`` to its python (the
bridge runs there) and start the peer with it. Prints the goal's result; exit 0 when the graph
ended on_true, 1 otherwise, 130 after Ctrl-C (the goal is cancelled, the bridge stopped).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from temoto import ActionEngine, Result
from temoto.actions.builtin import ROS2_ACTIONS
from temoto.core.registrar import Registrar
from temoto.managers.process import ProcessManager
from temoto.ros2.lifecycle import Ros2LifecycleManager
from temoto.ros2.manager import Ros2Manager

GRAPH = Path(__file__).with_name("ros2_tour.graph.json")


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--order", type=int, default=6, help="the Fibonacci goal's order")
    args = parser.parse_args()
    graph = json.loads(GRAPH.read_text())
    for action in graph["actions"]:
        if action["name"] == "Ros2SendGoal":
            action["input_parameters"]["goal"]["pvf_value"] = json.dumps({"order": args.order})
    interrupted = threading.Event()
    signal.signal(signal.SIGINT, lambda _s, _f: interrupted.set())
    registrar = Registrar("ros2-tour")
    processes = ProcessManager(registrar)
    ros2 = Ros2Manager(registrar)
    Ros2LifecycleManager(registrar)
    try:
        with ActionEngine("robot", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
            name = engine.start(graph)
            while not interrupted.is_set():
                try:
                    engine.wait(name, timeout=0.1)
                    break
                except TimeoutError:
                    continue
            if interrupted.is_set():
                engine.stop(name, timeout=30)
            outcome = engine.outcome(name)
    finally:
        processes.shutdown()
        ros2.shutdown()
        registrar.close()
    if interrupted.is_set():
        print(f"ros2_tour: interrupted ({outcome.result.value})")
        return 130
    if outcome.result is not Result.TRUE:
        print(f"ros2_tour: {outcome.result.value}: {'; '.join(map(str, outcome.errors))}")
        return 1
    print(f"ros2_tour: goal {outcome.outputs['status']}: {outcome.outputs['result']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
