"""FlyTo: fly the robot's vehicle to a position."""

from __future__ import annotations

import math

from temoto.actions.builtin.robot._common import RobotAction
from temoto.managers.robot.client import RobotHandle
from temoto.managers.robot.features import Motion

#: Mean Earth radius (m), for the distance left (an equirectangular estimate: fine over a
#: flight's few kilometres).
_EARTH_RADIUS = 6_371_000.0


class FlyTo(RobotAction):
    """Inputs ``lat``, ``lon`` (degrees), ``alt`` (m above home); ``robot``, ``timeout``.

    Progress: ``quad: 120 m left, alt 9.8/10 m``.
    """

    feature = "flight"
    _goal: tuple[RobotHandle, float, float, float] | None = None

    def on_run(self) -> bool:
        """Do it; True when the goal was reached."""
        robot = self.robot()
        lat, lon = self.inputs.get_number("lat"), self.inputs.get_number("lon")
        alt = self.inputs.get_number("alt")
        self.log(f"{robot.name}: flying to ({lat:.6f}, {lon:.6f}) at {alt:g} m")
        self._goal = (robot, lat, lon, alt)
        return self.run_motion(
            lambda: robot.fly_to(lat, lon, alt), lambda: robot.estimate_fly_to(lat, lon, alt)
        )

    def missed(self, motion: Motion) -> tuple[str, str]:
        """``at (47.397742, 8.545594, 10 m)`` and ``120 m left, alt 9.8 m``."""
        if self._goal is None:
            return super().missed(motion)
        _, lat, lon, alt = self._goal
        left, here = self._left()
        return f"at ({lat:.6f}, {lon:.6f}, {alt:g} m)", f"{left:.0f} m left, alt {here:.1f} m"

    def _left(self) -> tuple[float, float]:
        assert self._goal is not None
        robot, lat, lon, _ = self._goal
        here = robot.telemetry().position
        north = math.radians(lat - here.lat) * _EARTH_RADIUS
        east = math.radians(lon - here.lon) * _EARTH_RADIUS * math.cos(math.radians(lat))
        return math.hypot(north, east), here.alt

    def progress(self, motion: Motion) -> str:
        """The horizontal distance left and the altitude against the goal's."""
        if self._goal is None:
            return motion.progress
        robot, _, _, alt = self._goal
        left, here = self._left()
        return f"{robot.name}: {left:.0f} m left, alt {here:.1f}/{alt:g} m"
