"""Land: land the robot's vehicle where it is."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction


class Land(RobotAction):
    """Inputs ``robot``, ``timeout`` (both optional)."""

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        self.log(f"{robot.name}: landing")
        return self.run_motion(robot.land)
