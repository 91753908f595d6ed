"""NavigateTo: drive the robot's base to a position (odometry frame)."""

from __future__ import annotations

import math

from temoto.actions.builtin.robot._common import RobotAction
from temoto.managers.robot.client import RobotHandle
from temoto.managers.robot.features import Motion


class NavigateTo(RobotAction):
    """Inputs ``x``, ``y`` (m), optional ``yaw`` (rad), ``robot``, ``timeout``.

    Outputs ``pose_x``, ``pose_y``, ``pose_yaw``: where it stopped. Progress: ``rover: to
    (2, 0.5): 1.2 m left``.
    """

    feature = "navigation"
    _goal: tuple[RobotHandle, float, float] | None = None

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        x, y = self.inputs.get_number("x"), self.inputs.get_number("y")
        yaw = self.inputs.get_number("yaw") if "yaw" in self.inputs else None
        self.log(f"{robot.name}: navigating to ({x:g}, {y:g})")
        self._goal = (robot, x, y)
        reached = self.run_motion(
            lambda: robot.navigate_to(x, y, yaw), lambda: robot.estimate_navigate(x, y, yaw)
        )
        px, py, pyaw = robot.pose()
        self.outputs["pose_x"], self.outputs["pose_y"], self.outputs["pose_yaw"] = px, py, pyaw
        if reached:
            self.log(f"{robot.name}: at ({px:.2f}, {py:.2f})")
        return reached

    def missed(self, motion: Motion) -> tuple[str, str]:
        """``at (2, 0.5)`` and ``1.2 m left``."""
        if self._goal is None:
            return super().missed(motion)
        robot, x, y = self._goal
        px, py, _ = robot.pose()
        return f"at ({x:g}, {y:g})", f"{math.hypot(x - px, y - py):.1f} m left"

    def progress(self, motion: Motion) -> str:
        """The distance left to the goal."""
        if self._goal is None:
            return motion.progress
        robot, x, y = self._goal
        px, py, _ = robot.pose()
        return f"{robot.name}: to ({x:g}, {y:g}): {math.hypot(x - px, y - py):.1f} m left"
