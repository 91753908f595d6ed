"""DemoNavigate: drives a simulated base to a waypoint, reporting progress in its log.

Speed 2 m/s of clock time, progress every second, so the demo stays short.
"""

from temoto import Action

SPEED = 2.0  # m/s
STEP = 1.0  # s between progress reports


class DemoNavigate(Action):
    def on_run(self) -> bool:
        location = self.inputs.get_string("location")
        distance = self.inputs.get_number("distance")
        self.log(f"driving to {location} ({distance:.1f} m)")
        travelled = 0.0
        while travelled < distance:
            self.sleep(min(STEP, (distance - travelled) / SPEED))
            travelled = min(distance, travelled + SPEED * STEP)
            self.logger.info("%s: %.1f / %.1f m", location, travelled, distance)
        self.log(f"arrived at {location}")
        self.outputs["location"] = location
        return True
