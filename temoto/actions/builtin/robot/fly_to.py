"""FlyTo: fly the robot's vehicle to a position."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction


class FlyTo(RobotAction):
    """Inputs ``lat``, ``lon`` (degrees), ``alt`` (m above home); ``robot``, ``timeout``."""

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        lat, lon = self.inputs.get_number("lat"), self.inputs.get_number("lon")
        alt = self.inputs.get_number("alt")
        self.log(f"{robot.name}: flying to ({lat:.6f}, {lon:.6f}) at {alt:g} m")
        return self.run_motion(lambda: robot.fly_to(lat, lon, alt))
