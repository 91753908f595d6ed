"""Run ros2_tour.graph.json on an engine with the ROS 2 servers (docs/ros2.md).

Start the peer first, with the Python that has rclpy::

    python examples/ros2/peer.py &
    python examples/ros2/run.py

With the ROS wheels in another environment, set ``TEMOTO_ROS2_PYTHON`` to its python (the
bridge runs there) and start the peer with it. Prints the goal's result; exit 0 when the graph
ended on_true.
"""

from __future__ import annotations

import sys
from pathlib import Path

from temoto import ActionEngine, Result, load_graph
from temoto.actions.builtin import ROS2_ACTIONS
from temoto.core.registrar import Registrar
from temoto.managers.process import ProcessManager
from temoto.ros2.lifecycle import Ros2LifecycleManager
from temoto.ros2.manager import Ros2Manager

GRAPH = Path(__file__).with_name("ros2_tour.graph.json")


def main() -> int:
    registrar = Registrar("ros2-tour")
    processes = ProcessManager(registrar)
    ros2 = Ros2Manager(registrar)
    Ros2LifecycleManager(registrar)
    try:
        with ActionEngine("robot", actions=[ROS2_ACTIONS], registrar=registrar) as engine:
            outcome = engine.run(load_graph(GRAPH), timeout=120)
    finally:
        processes.shutdown()
        ros2.shutdown()
        registrar.close()
    if outcome.result is not Result.TRUE:
        print(f"ros2_tour: {outcome.result.value}: {'; '.join(map(str, outcome.errors))}")
        return 1
    print(f"ros2_tour: goal {outcome.outputs['status']}: {outcome.outputs['result']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
