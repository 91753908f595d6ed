"""DemoInspect: takes a (simulated, deterministic) gauge reading at a location."""

import zlib

from temoto import Action


class DemoInspect(Action):
    def on_run(self) -> bool:
        location = self.inputs.get_string("location")
        self.sleep(0.5)
        reading = zlib.crc32(location.encode()) % 100 / 10.0  # the same place reads the same
        limit = self.inputs.get_number("max_reading")
        self.log(f"gauge at {location} reads {reading:.1f} (limit {limit:.1f})")
        return reading <= limit
