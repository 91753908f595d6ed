"""TakeOff: arm the robot's vehicle and climb to an altitude."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction
from temoto.managers.robot.client import RobotHandle
from temoto.managers.robot.features import Motion


class TakeOff(RobotAction):
    """Input ``altitude`` (m above home); ``robot``, ``timeout``. Progress: ``quad: 8.5/10 m``."""

    feature = "flight"
    _goal: tuple[RobotHandle, float] | None = None

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        altitude = self.inputs.get_number("altitude")
        self.log(f"{robot.name}: taking off to {altitude:g} m")
        self._goal = (robot, altitude)
        return self.run_motion(
            lambda: robot.takeoff(altitude), lambda: robot.estimate_takeoff(altitude)
        )

    def missed(self, motion: Motion) -> tuple[str, str]:
        """``at 10 m`` and ``alt 4.2 m``."""
        if self._goal is None:
            return super().missed(motion)
        robot, altitude = self._goal
        return f"at {altitude:g} m", f"alt {robot.telemetry().position.alt:.1f} m"

    def progress(self, motion: Motion) -> str:
        """The altitude against the goal's."""
        if self._goal is None:
            return motion.progress
        robot, altitude = self._goal
        return f"{robot.name}: {robot.telemetry().position.alt:.1f}/{altitude:g} m"
