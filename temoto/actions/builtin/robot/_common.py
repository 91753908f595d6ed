"""What the built-in robot actions share: the robot, one motion at a time, pause = hold.

While a motion goes on, the action writes a progress line to its log (``self.log``: the node's
runtime messages, the live view, ``temoto run --progress``, logger
``temoto.action.<graph>.<node>`` at INFO) every :data:`PROGRESS_PERIOD` seconds of clock time,
when it changed: ``rover: to (2, 0.5): 1.2 m left``, ``quad: 8.5/10 m``. A subclass says what
by :meth:`RobotAction.progress`.

**Stop and pause.** ``on_stop`` cancels the motion and ``on_pause`` holds it; both return only
after the robot's devices were told to be still (:class:`~temoto.managers.robot.features.Motion`),
and the engine reports the node PAUSED only after ``on_pause`` returned, and STOPPED only after
``on_run`` returned (which cancels the motion on its way out, waiting for the devices too).

**Fail fast.** The robot is checked when the action acquires it and when a motion starts: a
device the action's feature moves that is not ACTIVE (FAULT, INACTIVE) fails the action at
once with the device's reason (:meth:`~temoto.managers.robot.client.RobotHandle.require`).

**Deadlines.** Without a ``timeout`` input, every motion has a deadline::

    deadline = DEADLINE_FACTOR * estimate + DEADLINE_SLACK      (clock seconds)

where ``estimate`` is the controller's time for the motion at the robot's limits (distance and
turns at ``max_speed``/``max_turn_rate`` for NavigateTo; the farthest joint's travel at its
speed limit for MoveJoints; the climb, descent and legs at the vehicle's WPNAV/LAND speeds for
TakeOff, Land, FlyTo and FlyMission, see :mod:`temoto.managers.robot.features`). The margin
(x1.5, +5 s) covers acceleration, the controllers' slow final approach and command latency. A
missed deadline stops the motion (the devices are made still) and ends the action on_error:
``NavigateTo: not at (2, 0.5) within 14.2 s (1.2 m left)``. An explicit ``timeout`` input wins:
then the action ends on_false at the timeout. Paused time is not counted.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from temoto.core.action import Action
from temoto.errors import ActionError, StateError, StopRequested
from temoto.managers.robot.client import RobotHandle, RobotManagerClient
from temoto.managers.robot.features import Motion

__all__ = ["DEADLINE_FACTOR", "DEADLINE_SLACK", "PROGRESS_PERIOD", "RobotAction"]

#: Clock seconds between two progress lines of a motion (the first comes after one period:
#: a motion that ends sooner has none).
PROGRESS_PERIOD = 1.0

#: A motion's deadline is ``DEADLINE_FACTOR * estimate + DEADLINE_SLACK`` clock seconds.
DEADLINE_FACTOR = 1.5
DEADLINE_SLACK = 5.0


class RobotAction(Action):
    """Base of the robot actions: ``robot`` input, a motion held while the graph is paused."""

    _motion: Motion | None = None
    _paused_during = False
    #: The feature the action moves (``navigation``, ``manipulation``, ``flight``; "" none):
    #: its devices are checked when the robot is acquired.
    feature = ""

    def robot(self) -> RobotHandle:
        """The robot named by the optional ``robot`` input (default: the manager's robot).

        Raises:
            ResourceBrokenError: A device of :attr:`feature` is not ACTIVE (its reason).
        """
        name = self.inputs.get("robot", "")
        handle = RobotManagerClient.for_action(self).acquire(self, str(name))
        if self.feature:
            handle.require(self.feature)
        return handle

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

    def missed(self, motion: Motion) -> tuple[str, str]:
        """For a missed deadline: the goal, and how far from it the robot is.

        E.g. ``("at (2, 0.5)", "1.2 m left")``; the default: the motion and its progress.

        Args:
            motion: The motion.

        Returns:
            The goal's words and the shortfall's (may be "").
        """
        return motion.what, motion.progress

    def run_motion(
        self, start: Callable[[], Motion], estimate: Callable[[], float] | None = None
    ) -> bool:
        """Start a motion and follow it to its end, logging its progress; False on timeout.

        While the graph is paused another graph may take the robot (a newer goal supersedes
        this one); on resume the goal is started again.

        Args:
            start: Starts the motion (called again after such a take-over).
            estimate: Clock seconds the motion takes at the robot's limits, for its deadline
                when there is no ``timeout`` input (see the module).

        Returns:
            True when the goal was reached; False when the ``timeout`` input ran out.

        Raises:
            ActionError: The deadline passed (the motion was stopped).
        """
        while True:
            timeout, deadline = self.timeout(), None
            if timeout is None and estimate is not None:
                deadline = DEADLINE_FACTOR * estimate() + DEADLINE_SLACK
            motion = start()
            self._motion, self._paused_during = motion, False
            if self.paused:  # paused while it was starting: on_pause did not see it
                motion.hold()
            try:
                reached = self._follow(motion, timeout if deadline is None else deadline)
            except StateError:
                if motion.superseded and self._paused_during:
                    self.log(f"{motion.what}: the robot was used meanwhile; going on")
                    continue
                raise
            finally:
                self._motion = None
            if not reached and deadline is not None:
                goal, left = self.missed(motion)
                left = f" ({left})" if left else ""
                raise ActionError(
                    f"{type(self).__name__}: not {goal} within {deadline:.1f} s{left}",
                    graph=self.graph_name,
                    node=self.name,
                )
            if not reached:
                self.log(f"{motion.what}: not done within {timeout:g} s")
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
