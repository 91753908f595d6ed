"""MoveJoints: move the robot's arm to a named pose or to joint positions."""

from __future__ import annotations

from temoto.actions.builtin.robot._common import RobotAction


class MoveJoints(RobotAction):
    """Input ``pose`` (a profile pose) or ``joints`` + ``positions`` (rad).

    Optional: ``robot``, ``timeout``.
    """

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        if "pose" in self.inputs and self.inputs.get_string("pose"):
            pose = self.inputs.get_string("pose")
            self.log(f"{robot.name}: arm to pose '{pose}'")
            reached = self.run_motion(lambda: robot.move_to_pose(pose))
        else:
            joints = self.inputs.get_strings("joints") if "joints" in self.inputs else []
            positions = self.inputs.get_numbers("positions") if "positions" in self.inputs else []
            if not joints or len(joints) != len(positions):
                raise ValueError("give a pose, or joints and positions of the same length")
            targets = dict(zip(joints, positions, strict=True))
            self.log(f"{robot.name}: arm to {targets}")
            reached = self.run_motion(lambda: robot.move_joints(targets))
        now = robot.joint_positions()
        self.outputs["arm_joints"] = list(now)
        self.outputs["arm_positions"] = list(now.values())
        return reached
