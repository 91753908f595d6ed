"""TaTimer: counts seconds in 0.1 s ticks until ``count_until`` (0: until stopped).

Elapsed time is measured from the start of the run, so a pause lengthens the reported count.
``final_count`` is the elapsed time in seconds; the result is true, also when stopped.
"""

from temoto import Action

TICK = 0.1


class TaTimer(Action):
    def on_run(self) -> bool:
        count_until = self.inputs.get_number("count_until")
        start = self.clock.monotonic()
        while count_until <= 0 or self.clock.monotonic() - start < count_until:
            if self.wait_until_stopped(TICK):
                break
            while self.paused and not self.stop_requested:
                self.wait_until_stopped(TICK)
        self.outputs["final_count"] = self.clock.monotonic() - start
        return True
