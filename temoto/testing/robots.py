"""A stand-in for a loaded robot, for tests of code that samples one (recorders, views).

:class:`FakeRobot` answers what :class:`~temoto.managers.robot.client.RobotHandle` answers to
a reader: a rover with an arm that also flies. Each :meth:`~FakeRobot.pose` call moves it
``step`` metres along x, so samples can be told apart and counted.
"""

from __future__ import annotations

import math

from temoto.drivers import GeoPoint, VehicleTelemetry

__all__ = ["FakeRobot"]


class FakeRobot:
    """A robot handle's read side: pose, joints, vehicle telemetry and health.

    Args:
        step: Metres the rover moves along x at each :meth:`pose` call.
        y: Its constant y, metres.
        attitude: The vehicle's (roll, pitch, yaw), radians.
    """

    name = "bot"
    features = ("navigation", "manipulation", "flight")

    def __init__(
        self,
        *,
        step: float = 0.1,
        y: float = 0.5,
        attitude: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        self.step = step
        self.y = y
        self.attitude = attitude
        self.x = 0.0

    def pose(self) -> tuple[float, float, float]:
        """The next pose: ``step`` further along x, facing +y."""
        self.x += self.step
        return self.x, self.y, math.pi / 2

    def joint_positions(self) -> dict[str, float]:
        """Two arm joints, radians."""
        return {"shoulder": 0.25, "elbow": -0.5}

    def telemetry(self) -> VehicleTelemetry:
        """A vehicle armed in GUIDED at 10 m, battery 87 %."""
        return VehicleTelemetry(
            stamp=1.0,
            armed=True,
            mode="GUIDED",
            position=GeoPoint(47.39, 8.54, 10.0),
            attitude=self.attitude,
            battery_voltage=12.4,
            battery_remaining=87,
            status_texts=(),
            heartbeat_age=0.1,
        )

    def healthy(self) -> bool:
        """Always healthy."""
        return True
