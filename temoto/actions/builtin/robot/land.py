"""Land: land the robot's vehicle where it is."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction
from temoto.managers.robot.client import RobotHandle
from temoto.managers.robot.features import Motion


class Land(RobotAction):
    """Inputs ``robot``, ``timeout`` (both optional). Progress: ``quad: alt 4.2 m``."""

    feature = "flight"
    _robot: RobotHandle | None = None

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        self.log(f"{robot.name}: landing")
        self._robot = robot
        return self.run_motion(robot.land, robot.estimate_land)

    def missed(self, motion: Motion) -> tuple[str, str]:
        """``landed`` and ``alt 4.2 m``."""
        if self._robot is None:
            return super().missed(motion)
        return "landed", f"alt {self._robot.telemetry().position.alt:.1f} m"

    def progress(self, motion: Motion) -> str:
        """The altitude."""
        if self._robot is None:
            return motion.progress
        return f"{self._robot.name}: alt {self._robot.telemetry().position.alt:.1f} m"
