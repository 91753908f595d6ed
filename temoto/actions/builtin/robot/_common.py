"""What the built-in robot actions share: the robot, one motion at a time, pause = hold."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from temoto.core.action import Action
from temoto.errors import StateError
from temoto.managers.robot.client import RobotHandle, RobotManagerClient, follow
from temoto.managers.robot.features import Motion

__all__ = ["RobotAction"]


class RobotAction(Action):
    """Base of the robot actions: ``robot`` input, a motion held while the graph is paused."""

    _motion: Motion | None = None
    _paused_during = False

    def robot(self) -> RobotHandle:
        """The robot named by the optional ``robot`` input (default: the manager's robot)."""
        name = self.inputs.get("robot", "")
        return RobotManagerClient.for_action(self).acquire(self, str(name))

    def timeout(self) -> float | None:
        """The optional ``timeout`` input (clock seconds; 0 or absent: none)."""
        value = self.inputs.get("timeout", 0)
        return float(value) if value else None

    def run_motion(self, start: Callable[[], Motion]) -> bool:
        """Start a motion and follow it to its end; False on timeout.

        While the graph is paused another graph may take the robot (a newer goal supersedes
        this one); on resume the goal is started again.

        Args:
            start: Starts the motion (called again after such a take-over).

        Returns:
            True when the goal was reached.
        """
        while True:
            motion = start()
            self._motion, self._paused_during = motion, False
            try:
                reached = follow(self, motion, self.timeout())
            except StateError:
                if motion.superseded and self._paused_during:
                    self.log(f"{motion.what}: the robot was used meanwhile; going on")
                    continue
                raise
            finally:
                self._motion = None
            if not reached:
                self.log(f"{motion.what}: not done within {self.timeout():g} s")
            return reached

    def on_pause(self) -> None:
        """Hold the robot where it is."""
        self._paused_during = True
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
