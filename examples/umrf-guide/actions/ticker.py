"""Ticker: a reactive (``spontaneous``) action: each run waits ``period`` s and emits the next
``tick`` (1, 2, 3, ...). The engine runs it again as soon as it returns, until it is stopped."""

from temoto import Action


class Ticker(Action):
    count = 0  # the instance lives as long as the graph run: it counts across runs

    def on_run(self) -> bool:
        self.sleep(self.inputs.get_number("period"))  # returns early (raises) on a stop
        self.count += 1
        self.outputs["tick"] = float(self.count)
        return True
