"""NavigateTo: drive the robot's base to a position (odometry frame)."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction


class NavigateTo(RobotAction):
    """Inputs ``x``, ``y`` (m), optional ``yaw`` (rad), ``robot``, ``timeout``.

    Outputs ``pose_x``, ``pose_y``, ``pose_yaw``: where it stopped.
    """

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        x, y = self.inputs.get_number("x"), self.inputs.get_number("y")
        yaw = self.inputs.get_number("yaw") if "yaw" in self.inputs else None
        self.log(f"{robot.name}: navigating to ({x:g}, {y:g})")
        reached = self.run_motion(lambda: robot.navigate_to(x, y, yaw))
        px, py, pyaw = robot.pose()
        self.outputs["pose_x"], self.outputs["pose_y"], self.outputs["pose_yaw"] = px, py, pyaw
        if reached:
            self.log(f"{robot.name}: at ({px:.2f}, {py:.2f})")
        return reached
