"""AtLeast: true if ``value >= limit``, false otherwise (a condition to branch on)."""

from temoto import Action


class AtLeast(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        value, limit = self.inputs.get_number("value"), self.inputs.get_number("limit")
        self.log(f"{value:g} {'>=' if value >= limit else '<'} {limit:g}")
        return value >= limit
