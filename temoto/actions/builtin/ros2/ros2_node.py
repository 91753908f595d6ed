"""Ros2Node: hold a ROS 2 node's program (a Python node file or an executable) for the run."""

from __future__ import annotations

import shlex

from temoto.actions.builtin.ros2._common import acquire
from temoto.core.action import Action
from temoto.managers.process import ProcessResponse
from temoto.ros2.manager import program_request


class Ros2Node(Action):
    """Start the ROS 2 program ``program`` through the Process Manager and hold it.

    ``program``: shell-like words, the program and its arguments; a ``.py`` file runs with the
    interpreter that has rclpy (``$TEMOTO_ROS2_PYTHON``, else this one), anything else as an
    executable; both with this process's environment (the user's ROS variables), and
    ``ROS_DOMAIN_ID`` set to ``domain_id`` if given. The process is shared with equal requests
    and stopped when the last holder releases it: this run's reference goes when the run ends,
    or after ``duration`` seconds if given (the action then returns; while it holds, the
    program's exit fails it). Output ``pid``. True once started (the node's entities may take
    a moment to be discovered: give the next action a ``timeout``).
    """

    def on_run(self) -> bool:
        """Start and hold it; True once started (and, with a duration, stopped again)."""
        request = program_request(
            tuple(shlex.split(self.inputs.get_string("program"))),
            domain_id=int(self.inputs.get("domain_id", -1)),
        )
        resource = acquire(self, "process", request)
        response = resource.response
        assert isinstance(response, ProcessResponse)
        self.outputs["pid"] = response.pid
        command = shlex.join((request.executable, *request.args))
        self.log(f"ROS 2 program {command} is pid {response.pid}")
        if "duration" in self.inputs:
            self.sleep(self.inputs.get_number("duration"))
            self.release(resource)
        return True
