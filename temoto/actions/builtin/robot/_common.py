"""What the built-in robot actions share: the robot, one motion at a time, pause = hold.

While a motion goes on, the action writes a progress line to its log (``self.log``: the node's
runtime messages, the live view, ``temoto run --progress``, logger
``temoto.action.<graph>.<node>`` at INFO) every :data:`PROGRESS_PERIOD` seconds of clock time,
when it changed: ``rover: to (2, 0.5): 1.2 m left``, ``quad: 8.5/10 m``. A subclass says what
by :meth:`RobotAction.progress`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from temoto.core.action import Action
from temoto.errors import StateError, StopRequested
from temoto.managers.robot.client import RobotHandle, RobotManagerClient
from temoto.managers.robot.features import Motion

__all__ = ["PROGRESS_PERIOD", "RobotAction"]

#: Clock seconds between two progress lines of a motion (the first comes after one period:
#: a motion that ends sooner has none).
PROGRESS_PERIOD = 1.0


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

    def progress(self, motion: Motion) -> str:
        """How the motion is going, for a person (empty: nothing to say).

        Called every :data:`PROGRESS_PERIOD` while the motion goes on; the default is what
        the robot's controller says (``at (1.20, 0.31)``, ``0.120 rad to go``, ``alt 8.5 m``).

        Args:
            motion: The motion.

        Returns:
            One line, or "".
        """
        return motion.progress

    def run_motion(self, start: Callable[[], Motion]) -> bool:
        """Start a motion and follow it to its end, logging its progress; False on timeout.

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
                reached = self._follow(motion, self.timeout())
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

    def _follow(self, motion: Motion, timeout: float | None) -> bool:
        """Wait for a motion (paused time does not count), logging its progress.

        A stop cancels the motion (and raises StopRequested); a fault of the robot raises
        ResourceBrokenError (and cancels it); a timeout cancels it and returns False.
        """
        motion.add_listener(self.wake)
        left = timeout
        said = ""
        try:
            while True:
                step = PROGRESS_PERIOD if left is None else min(PROGRESS_PERIOD, left)
                if self.wait_for(lambda: motion.done, step):
                    break
                if left is not None:
                    left -= step
                    if left <= 0:
                        motion.cancel("timed out")
                        return False
                text = self.progress(motion)
                if text and text != said:
                    self.log(text)
                    said = text
        except (StopRequested, Exception):
            motion.cancel("the action ended")
            raise
        if motion.error is not None:
            raise motion.error
        return True

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
