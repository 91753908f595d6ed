"""MoveJoints: move the robot's arm to a named pose or to joint positions."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction
from temoto.managers.robot.client import RobotHandle
from temoto.managers.robot.features import Motion


class MoveJoints(RobotAction):
    """Input ``pose`` (a profile pose) or ``joints`` + ``positions`` (rad).

    Optional: ``robot``, ``timeout``. Progress: ``mm: arm to pose 'reach': 0.120 rad to go``
    (the joint farthest from its goal), then ``mm: joints reached (pose 'reach')``.
    """

    feature = "manipulation"
    _robot_name = ""
    _left: tuple[RobotHandle, dict[str, float]] | None = None
    _goal = ""  # "pose 'reach'" or "j1 0.5, j2 -1"

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        if "pose" in self.inputs and self.inputs.get_string("pose"):
            pose = self.inputs.get_string("pose")
            self.log(f"{robot.name}: arm to pose '{pose}'")
            self._robot_name, self._goal = robot.name, f"pose '{pose}'"
            targets = robot.pose_targets(pose)
            self._left = (robot, targets)
            reached = self.run_motion(
                lambda: robot.move_to_pose(pose), lambda: robot.estimate_joints(targets)
            )
        else:
            joints = self.inputs.get_strings("joints") if "joints" in self.inputs else []
            positions = self.inputs.get_numbers("positions") if "positions" in self.inputs else []
            if not joints or len(joints) != len(positions):
                raise ValueError("give a pose, or joints and positions of the same length")
            targets = dict(zip(joints, positions, strict=True))
            self.log(f"{robot.name}: arm to {targets}")
            self._robot_name = robot.name
            self._goal = ", ".join(f"{j} {v:g}" for j, v in targets.items())
            self._left = (robot, targets)
            reached = self.run_motion(
                lambda: robot.move_joints(targets), lambda: robot.estimate_joints(targets)
            )
        if reached:
            self.log(f"{robot.name}: joints reached ({self._goal})")
        now = robot.joint_positions()
        self.outputs["arm_joints"] = list(now)
        self.outputs["arm_positions"] = list(now.values())
        return reached

    def missed(self, motion: Motion) -> tuple[str, str]:
        """``at pose 'reach'`` and ``0.120 rad left`` (the farthest joint)."""
        if self._left is None:
            return super().missed(motion)
        robot, targets = self._left
        now = robot.joint_positions()
        worst = max((abs(now[j] - v) for j, v in targets.items() if j in now), default=0.0)
        return f"at {self._goal}", f"{worst:.3f} rad left"

    def progress(self, motion: Motion) -> str:
        """The goal and how far the farthest joint is from it."""
        if not motion.progress:
            return ""
        return f"{self._robot_name}: arm to {self._goal}: {motion.progress}"
