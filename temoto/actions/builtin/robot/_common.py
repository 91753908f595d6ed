"""What the built-in robot actions share: the robot, one motion at a time, pause = hold."""

from __future__ import annotations

from typing import Any

from temoto.core.action import Action
from temoto.managers.robot.client import RobotHandle, RobotManagerClient, follow
from temoto.managers.robot.features import Motion

__all__ = ["RobotAction"]


class RobotAction(Action):
    """Base of the robot actions: ``robot`` input, a motion held while the graph is paused."""

    _motion: Motion | None = None

    def robot(self) -> RobotHandle:
        """The robot named by the optional ``robot`` input (default: the manager's robot)."""
        name = self.inputs.get("robot", "")
        return RobotManagerClient.for_action(self).acquire(self, str(name))

    def timeout(self) -> float | None:
        """The optional ``timeout`` input (clock seconds; 0 or absent: none)."""
        value = self.inputs.get("timeout", 0)
        return float(value) if value else None

    def run_motion(self, motion: Motion) -> bool:
        """Follow ``motion`` to its end; False on timeout."""
        self._motion = motion
        try:
            reached = follow(self, motion, self.timeout())
        finally:
            self._motion = None
        if not reached:
            self.log(f"{motion.what}: not done within {self.timeout():g} s")
        return reached

    def on_pause(self) -> None:
        """Hold the robot where it is."""
        motion = self._motion
        if motion is not None:
            motion.hold()

    def on_resume(self) -> None:
        """Go on."""
        motion = self._motion
        if motion is not None:
            motion.resume()

    def on_stop(self) -> None:
        """Stop moving at once."""
        motion = self._motion
        if motion is not None:
            motion.cancel("stopped")

    @staticmethod
    def number(value: Any) -> float:
        """An input number as a float."""
        return float(value)
