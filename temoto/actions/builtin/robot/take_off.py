"""TakeOff: arm the robot's vehicle and climb to an altitude."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction


class TakeOff(RobotAction):
    """Input ``altitude`` (m above home); ``robot``, ``timeout``."""

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        altitude = self.inputs.get_number("altitude")
        self.log(f"{robot.name}: taking off to {altitude:g} m")
        return self.run_motion(lambda: robot.takeoff(altitude))
