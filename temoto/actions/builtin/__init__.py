"""Actions shipped with TeMoto, in folders an engine's catalog can scan.

* :data:`ROBOT_ACTIONS`: the robot verbs (navigate, move joints, take off, fly, land, wait),
  which need a Robot Manager on the engine's registrar (``python -m temoto.managers.robot``
  adds the folder to its catalog).
* :data:`COMPONENT_ACTIONS`: request a component or a pipeline, wait for its data (a Component
  Manager on the registrar).
* :data:`CONTEXT_ACTIONS`: add, move, get, remove and find items of the shared world model (a
  Context Manager on the registrar).
* :data:`VISUALIZATION_ACTIONS`: show a display (a Visualization Manager on the registrar).
* :data:`ROS2_ACTIONS`: publish, wait for a message, call a service, send a goal, hold a
  lifecycle node on ROS 2 (the ``"ros2"`` and ``"ros2_lifecycle"`` servers on the registrar,
  :mod:`temoto.ros2`, and the ``temoto[ros2]`` extra; ``docs/ros2.md``). Not in
  :data:`BUILTIN_ACTIONS`.
* :data:`BUILTIN_ACTIONS`: every folder above but the ROS 2 one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

__all__ = [
    "BUILTIN_ACTIONS",
    "COMPONENT_ACTIONS",
    "CONTEXT_ACTIONS",
    "ROBOT_ACTIONS",
    "ROS2_ACTIONS",
    "VISUALIZATION_ACTIONS",
]

_HERE: Final = Path(__file__).resolve().parent
#: The folder of the built-in robot actions.
ROBOT_ACTIONS: Final = _HERE / "robot"
#: The folder of the built-in component actions.
COMPONENT_ACTIONS: Final = _HERE / "component"
#: The folder of the built-in context (world model) actions.
CONTEXT_ACTIONS: Final = _HERE / "context"
#: The folder of the built-in visualization actions.
VISUALIZATION_ACTIONS: Final = _HERE / "visualization"
#: The folder of the built-in ROS 2 actions.
ROS2_ACTIONS: Final = _HERE / "ros2"
#: Every folder of built-in actions (but the ROS 2 one).
BUILTIN_ACTIONS: Final = (ROBOT_ACTIONS, COMPONENT_ACTIONS, CONTEXT_ACTIONS, VISUALIZATION_ACTIONS)
