"""Add: ``sum = a + b``."""

from temoto import Action


class Add(Action):
    blocking = False  # never waits: runs inline, on the thread evolving the graph

    def on_run(self) -> bool:
        self.outputs["sum"] = self.inputs.get_number("a") + self.inputs.get_number("b")
        return True
