"""WaitForRobot: wait until the robot is in a condition (healthy, landed, airborne)."""

from __future__ import annotations

from collections.abc import Callable

from temoto.actions.builtin.robot._common import RobotAction
from temoto.managers.robot.client import RobotHandle


class WaitForRobot(RobotAction):
    """Input ``condition``: ``healthy``, ``landed`` or ``airborne``; ``robot``, ``timeout``.

    Checked every ``period`` seconds of clock time (default 0.1); returns false on timeout.
    """

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        condition = self.inputs.get_string("condition")
        check = _CONDITIONS.get(condition)
        if check is None:
            raise ValueError(
                f"unknown condition {condition!r} (known: {', '.join(sorted(_CONDITIONS))})"
            )
        period = self.inputs.get_number("period") if "period" in self.inputs else 0.1
        timeout = self.timeout()
        waited = 0.0
        while not check(robot):
            if timeout is not None and waited >= timeout:
                self.log(f"{robot.name}: not {condition} within {timeout:g} s")
                return False
            self.sleep(period)  # stop- and pause-aware
            waited += period
        self.log(f"{robot.name}: {condition}")
        return True


def _landed(robot: RobotHandle) -> bool:
    return bool(robot.telemetry().position.alt <= 0.3)


def _airborne(robot: RobotHandle) -> bool:
    return bool(robot.telemetry().position.alt > 0.3)


_CONDITIONS: dict[str, Callable[[RobotHandle], bool]] = {
    "healthy": RobotHandle.healthy,
    "landed": _landed,
    "airborne": _airborne,
}
