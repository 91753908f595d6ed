"""ROS 2 peers: a bridge process that runs rclpy, and the resource server that starts it.

rclpy never runs in a TeMoto process: a wrong ``RMW_IMPLEMENTATION`` makes ``import rclpy`` exit
the process (code 102), an executor thread that is not joined aborts the interpreter at exit,
and rclpy installs its own signal handlers. The bridge (``python -m temoto.ros2.bridge``, see
:mod:`temoto.ros2.bridge`) owns those pitfalls in a process of its own; the Process Manager
starts and watches it as a resource (:class:`~temoto.ros2.manager.Ros2Manager`, the ``"ros2"``
server), and the built-in ROS 2 actions talk to it over a Unix socket in length-prefixed JSON
frames (:mod:`temoto.ros2.protocol`, :class:`~temoto.ros2.client.BridgeClient`).

Only the bridge imports rclpy, from the optional extra ``temoto[ros2]`` (or a sourced system
ROS 2). See ``docs/ros2.md``.
"""

from __future__ import annotations

import importlib.util
from typing import Final

from temoto.errors import ConfigError

__all__ = ["INSTALL_HINT", "require_rclpy"]

#: How the extra is installed (named in the one-line error when rclpy is missing).
INSTALL_HINT: Final = "pip install 'temoto[ros2]' (or source a ROS 2 installation)"


def require_rclpy() -> None:
    """Check that rclpy can be imported, without importing it (that may exit the process).

    Raises:
        ConfigError: rclpy is not installed (one line naming the extra).
    """
    if importlib.util.find_spec("rclpy") is None:
        raise ConfigError(f"the ROS 2 actions need rclpy: {INSTALL_HINT}")
